//! HPI-3D frames as plain data: host commands (8 bytes on the wire) and device frames (16).
//! Fields keep the exact integer encodings so that encode(decode(x)) == x; methods give SI units.

/// First byte of every frame in both directions.
pub const START: u8 = 0xAA;
/// Host-to-device frame length: start, cmd (2), data (4), crc.
pub const HOST_FRAME_LEN: usize = 8;
/// Device-to-host frame length: start, cmd (2), data (12), crc.
pub const DEVICE_FRAME_LEN: usize = 16;

/// Length unit of the distance frame: 100 pm.
pub const POSITION_UNIT_M: f64 = 1e-10;
/// Velocity unit of the velocity frame: 100 nm/s.
pub const VELOCITY_UNIT_M_PER_S: f64 = 1e-7;
/// Temperature unit of the meteo frame: 0.01 K (sent as °C).
pub const TEMPERATURE_UNIT_K: f64 = 0.01;
/// Pressure unit of the meteo frame: 10 Pa.
pub const PRESSURE_UNIT_PA: f64 = 10.0;
const ZERO_CELSIUS_K: f64 = 273.15;
/// The position field is 56 bits wide (bytes 0-6).
pub const POSITION_MAX_COUNTS: i64 = (1 << 55) - 1;
pub const POSITION_MIN_COUNTS: i64 = -(1 << 55);

/// Device frame cmd codes.
pub const CMD_DISTANCE: u16 = 0xB015;
pub const CMD_VELOCITY: u16 = 0xB016;
pub const CMD_METEO: u16 = 0xB00A;

/// A host command. Codes outside the documented table are kept as `Other` so that a
/// device-side decoder can still acknowledge (or log) them.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum HostCommand {
    DistanceOn,
    DistanceOff,
    VelocityOn,
    VelocityOff,
    StopAll,
    ClearSmallSignal,
    ClearVelocityOverflow,
    ClearExternalCapture,
    MeteoOn,
    MeteoOff,
    /// Clear measurement results: the current position becomes the origin.
    Home,
    Other(u16),
}

impl HostCommand {
    pub const KNOWN: [HostCommand; 11] = [
        HostCommand::DistanceOn,
        HostCommand::DistanceOff,
        HostCommand::VelocityOn,
        HostCommand::VelocityOff,
        HostCommand::StopAll,
        HostCommand::ClearSmallSignal,
        HostCommand::ClearVelocityOverflow,
        HostCommand::ClearExternalCapture,
        HostCommand::MeteoOn,
        HostCommand::MeteoOff,
        HostCommand::Home,
    ];

    pub fn code(self) -> u16 {
        match self {
            HostCommand::DistanceOn => 0xB032,
            HostCommand::DistanceOff => 0xB033,
            HostCommand::VelocityOn => 0xB034,
            HostCommand::VelocityOff => 0xB035,
            HostCommand::StopAll => 0xB03C,
            HostCommand::ClearSmallSignal => 0xB03D,
            HostCommand::ClearVelocityOverflow => 0xB03F,
            HostCommand::ClearExternalCapture => 0xB040,
            HostCommand::MeteoOn => 0xB079,
            HostCommand::MeteoOff => 0xB07A,
            HostCommand::Home => 0xB048,
            HostCommand::Other(code) => code,
        }
    }

    /// The documented command with this code, if any.
    pub fn known(code: u16) -> Option<HostCommand> {
        Self::KNOWN.into_iter().find(|c| c.code() == code)
    }

    /// Never fails: unknown codes become `Other`.
    pub fn from_code(code: u16) -> HostCommand {
        Self::known(code).unwrap_or(HostCommand::Other(code))
    }
}

/// One host-to-device frame. `data` is zero for every documented command.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct HostFrame {
    pub command: HostCommand,
    pub data: [u8; 4],
}

impl HostFrame {
    pub fn new(command: HostCommand) -> Self {
        HostFrame {
            command,
            data: [0; 4],
        }
    }
}

/// Status bits and signal level shared by the distance and velocity frames (data bytes 9-11).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Status {
    /// Byte 9 bit 3.
    pub velocity_overflow: bool,
    /// Byte 10 bit 0.
    pub laser_ready: bool,
    /// Byte 10 bit 3 CLEAR: the beam is weak or broken (the wire bit means "signal ok").
    pub small_signal: bool,
    /// Byte 11, 0..=255.
    pub signal_level: u8,
    /// Undocumented bits of bytes 9 and 10, kept verbatim (the known bits are zero here).
    pub other_bits: [u8; 2],
}

const B9_VELOCITY_OVERFLOW: u8 = 1 << 3;
const B10_LASER_READY: u8 = 1 << 0;
const B10_SIGNAL_OK: u8 = 1 << 3;

impl Status {
    /// A healthy beam: laser ready, signal ok, at the given level.
    pub fn ok(signal_level: u8) -> Self {
        Status {
            laser_ready: true,
            signal_level,
            ..Status::default()
        }
    }

    /// Signal level as a fraction, 0..1.
    pub fn signal(&self) -> f64 {
        f64::from(self.signal_level) / 255.0
    }

    /// The beam is usable: laser ready and no small-signal flag.
    pub fn tracking(&self) -> bool {
        self.laser_ready && !self.small_signal
    }

    pub(crate) fn to_bytes(self) -> [u8; 3] {
        let mut b9 = self.other_bits[0] & !B9_VELOCITY_OVERFLOW;
        if self.velocity_overflow {
            b9 |= B9_VELOCITY_OVERFLOW;
        }
        let mut b10 = self.other_bits[1] & !(B10_LASER_READY | B10_SIGNAL_OK);
        if self.laser_ready {
            b10 |= B10_LASER_READY;
        }
        if !self.small_signal {
            b10 |= B10_SIGNAL_OK;
        }
        [b9, b10, self.signal_level]
    }

    pub(crate) fn from_bytes(b: [u8; 3]) -> Self {
        Status {
            velocity_overflow: b[0] & B9_VELOCITY_OVERFLOW != 0,
            laser_ready: b[1] & B10_LASER_READY != 0,
            small_signal: b[1] & B10_SIGNAL_OK == 0,
            signal_level: b[2],
            other_bits: [
                b[0] & !B9_VELOCITY_OVERFLOW,
                b[1] & !(B10_LASER_READY | B10_SIGNAL_OK),
            ],
        }
    }
}

/// Distance frame (B0 15): relative position since the last homing.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Distance {
    /// 56-bit signed count, unit 100 pm (`POSITION_UNIT_M`).
    pub position_counts: i64,
    /// Data bytes 7-8, undocumented, kept verbatim.
    pub spare: [u8; 2],
    pub status: Status,
}

impl Distance {
    pub fn position_m(&self) -> f64 {
        self.position_counts as f64 * POSITION_UNIT_M
    }

    /// Nearest count for a length, clamped to the 56-bit field (NaN gives 0).
    pub fn counts_from_m(length_m: f64) -> i64 {
        let counts = (length_m / POSITION_UNIT_M).round();
        if counts.is_nan() {
            0
        } else {
            // `as` saturates; the clamp keeps the value inside 56 bits.
            (counts as i64).clamp(POSITION_MIN_COUNTS, POSITION_MAX_COUNTS)
        }
    }
}

/// Velocity frame (B0 16).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Velocity {
    /// Signed count, unit 100 nm/s (`VELOCITY_UNIT_M_PER_S`).
    pub velocity_counts: i32,
    /// Data bytes 4-8, undocumented, kept verbatim.
    pub spare: [u8; 5],
    pub status: Status,
}

impl Velocity {
    pub fn velocity_m_per_s(&self) -> f64 {
        f64::from(self.velocity_counts) * VELOCITY_UNIT_M_PER_S
    }
}

/// Meteo frame (B0 0A): one sensor's reading.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Meteo {
    /// 0 = air, 1.. = material sensors.
    pub sensor: u8,
    /// Signed, unit 0.01 °C.
    pub temperature_centi_c: i16,
    pub humidity_pct: u8,
    pub battery: u8,
    pub link: u8,
    /// Unsigned, unit 10 Pa.
    pub pressure_deca_pa: u16,
    /// Data bytes 8-11, undocumented, kept verbatim.
    pub spare: [u8; 4],
}

impl Meteo {
    pub fn temperature_k(&self) -> f64 {
        f64::from(self.temperature_centi_c) * TEMPERATURE_UNIT_K + ZERO_CELSIUS_K
    }

    pub fn pressure_pa(&self) -> f64 {
        f64::from(self.pressure_deca_pa) * PRESSURE_UNIT_PA
    }

    /// Nearest encodings of SI values, saturated to the field ranges.
    pub fn encode_temperature_k(temperature_k: f64) -> i16 {
        // `as` saturates and maps NaN to 0.
        ((temperature_k - ZERO_CELSIUS_K) / TEMPERATURE_UNIT_K).round() as i16
    }

    pub fn encode_pressure_pa(pressure_pa: f64) -> u16 {
        (pressure_pa / PRESSURE_UNIT_PA).round() as u16
    }
}

/// One device-to-host frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DeviceFrame {
    /// Acknowledgement of a documented host command (the frame's cmd is the command's code).
    Ack {
        command: HostCommand,
        data: [u8; 12],
    },
    Distance(Distance),
    Velocity(Velocity),
    Meteo(Meteo),
    /// Any other cmd, kept verbatim.
    Unknown {
        cmd: u16,
        data: [u8; 12],
    },
}

impl DeviceFrame {
    pub fn ack(command: HostCommand) -> Self {
        DeviceFrame::Ack {
            command,
            data: [0; 12],
        }
    }

    pub fn cmd(&self) -> u16 {
        match self {
            DeviceFrame::Ack { command, .. } => command.code(),
            DeviceFrame::Distance(_) => CMD_DISTANCE,
            DeviceFrame::Velocity(_) => CMD_VELOCITY,
            DeviceFrame::Meteo(_) => CMD_METEO,
            DeviceFrame::Unknown { cmd, .. } => *cmd,
        }
    }
}
