//! Device traits: what the sequencer may ask of a tracer, an environment sensor, a machine,
//! a rotary table and whoever moves the tracer between stations. Real, simulated and replay
//! drivers implement them.

use std::collections::BTreeMap;

use async_trait::async_trait;

/// Commanded or reported axis positions by axis name (`"x"`, `"y"`, `"z"`), metres.
pub type AxisPositions = BTreeMap<String, f64>;

#[derive(Debug, thiserror::Error)]
pub enum DeviceError {
    #[error("{device}: timed out after {after_s} s waiting for {what}")]
    Timeout {
        device: String,
        what: String,
        after_s: f64,
    },
    #[error("{device}: protocol error: {message}")]
    Protocol { device: String, message: String },
    #[error("{device}: disconnected: {message}")]
    Disconnected { device: String, message: String },
    #[error("{device}: {message}")]
    Rejected { device: String, message: String },
    #[error("{device}: stream ended")]
    EndOfStream { device: String },
    /// The machine controller raised an alarm (GRBL `ALARM:N`, state `Alarm`): motion was
    /// aborted and the controller is locked until `Machine::unlock`.
    #[error("{device}: ALARM:{code} ({message})")]
    Alarm {
        device: String,
        code: u16,
        message: String,
    },
}

impl DeviceError {
    /// What happened, without the device's name (and for a disconnection without
    /// `disconnected:`), for a new error of the same device that embeds this one: no
    /// "mill: disconnected: mill: disconnected: …".
    pub fn detail(&self) -> String {
        match self {
            DeviceError::Disconnected { message, .. } => message.clone(),
            other => {
                let text = other.to_string();
                let device = match other {
                    DeviceError::Timeout { device, .. }
                    | DeviceError::Protocol { device, .. }
                    | DeviceError::Disconnected { device, .. }
                    | DeviceError::Rejected { device, .. }
                    | DeviceError::EndOfStream { device }
                    | DeviceError::Alarm { device, .. } => device,
                };
                text.strip_prefix(&format!("{device}: "))
                    .map(str::to_owned)
                    .unwrap_or(text)
            }
        }
    }
}

/// Something a driver detected and recovered from by itself (a frame that failed its CRC,
/// a link it lost and reopened), for the session's `fault` events (`code`: `crc`, `resync`,
/// `disconnect`, `reconnect`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LinkFault {
    pub code: String,
    pub message: String,
}

/// One raw interferometer sample, as the device (or its driver) reports it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TracerReading {
    /// Frame counter; a gap shows lost frames.
    pub seq: u64,
    /// Device time since device start, seconds.
    pub t_s: f64,
    /// Relative interferometric length since the last homing, metres.
    pub length_m: f64,
    /// Beam signal level, 0..1.
    pub signal: f64,
    /// False while the beam is broken.
    pub tracking: bool,
    /// Increments at every re-homing after a beam break.
    pub beam_segment: u32,
}

/// One environment sample.
#[derive(Debug, Clone, PartialEq)]
pub struct EnvReading {
    pub t_s: f64,
    pub air_temp_k: f64,
    pub pressure_pa: f64,
    pub humidity_pct: f64,
    pub material_temp_k: Vec<f64>,
}

/// A tracking interferometer: a continuous stream of relative lengths.
#[async_trait]
pub trait Tracer: Send {
    fn id(&self) -> &str;
    /// Wait for the next sample of the stream.
    async fn next_sample(&mut self) -> Result<TracerReading, DeviceError>;
    /// Zero the length counter at the current target position.
    async fn home(&mut self) -> Result<(), DeviceError>;
    /// Faults recovered inside the driver since the last call (none by default).
    fn take_link_faults(&mut self) -> Vec<LinkFault> {
        Vec::new()
    }
}

/// Air and material temperature, pressure and humidity sensors.
#[async_trait]
pub trait Environment: Send {
    fn id(&self) -> &str;
    /// Samples that became available since the last call (possibly none); never blocks long.
    async fn poll(&mut self) -> Result<Vec<EnvReading>, DeviceError>;
}

#[derive(Debug, Clone, PartialEq)]
pub enum MachineState {
    Moving,
    /// At rest at the reported position (metres, by axis name).
    Idle {
        position: AxisPositions,
    },
}

/// A machine whose axes geocal commands.
#[async_trait]
pub trait Machine: Send {
    fn id(&self) -> &str;
    /// Start a move to the given axis positions (returns once the command is accepted).
    async fn start_move(&mut self, target: &AxisPositions) -> Result<(), DeviceError>;
    /// Current motion state; cheap to call often (drivers rate-limit their own queries).
    async fn state(&mut self) -> Result<MachineState, DeviceError>;
    /// Leave the alarm state after `DeviceError::Alarm` (GRBL: `$X`, or `$H` where the
    /// controller requires homing); the interrupted move must be commanded again.
    async fn unlock(&mut self) -> Result<(), DeviceError> {
        Err(DeviceError::Rejected {
            device: self.id().to_string(),
            message: "this machine driver cannot clear an alarm".into(),
        })
    }
    /// Faults recovered inside the driver since the last call (none by default).
    fn take_link_faults(&mut self) -> Vec<LinkFault> {
        Vec::new()
    }
    /// The compensation trims the controller applies now, per joint, where they can be read
    /// (LinuxCNC's HAL pins in a real-controller HIL run); none by default.
    fn controller_trims(&mut self) -> Vec<ControllerTrim> {
        Vec::new()
    }
    /// The run is over (done or stopped): leave the controller's modes as the run found them
    /// (nothing to do by default).
    async fn finish(&mut self) -> Result<(), DeviceError> {
        Ok(())
    }
}

/// One joint's compensation as the controller applies it, metres.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ControllerTrim {
    pub joint: usize,
    /// The position commanded to the drive: the nominal position plus the applied trim.
    pub motor_pos_cmd_m: f64,
    /// The table's value at the position (LinuxCNC `joint.N.backlash-corr`).
    pub table_m: f64,
    /// The trim applied (LinuxCNC `joint.N.backlash-filt`, after its rate limiter).
    pub applied_m: f64,
}

/// Whoever changes the set-up between measurements: puts the tracer on the next station (an
/// operator at a prompt, a rotary table the tracer stands on, the simulated world) and mounts
/// a reflector at another offset on the tool. Either interrupts the beam.
#[async_trait]
pub trait Operator: Send {
    /// Place the tracer at station `index` (named `id`, near `hint_m` if given).
    async fn place_station(
        &mut self,
        index: usize,
        id: &str,
        hint_m: Option<[f64; 3]>,
    ) -> Result<(), DeviceError>;
    /// Mount the reflector `target` at `offset_m` from the tool point.
    async fn mount_target(&mut self, target: &str, offset_m: [f64; 3]) -> Result<(), DeviceError>;
}

/// One reading of a displacement probe.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProbeReading {
    /// Host time of the reading, seconds since the driver was opened (midpoint of request
    /// and reply, since the device stamps nothing).
    pub t_s: f64,
    /// Measured displacement, metres.
    pub value_m: f64,
}

/// A displacement probe read on request (laser triangulation sensor, dial gauge readout).
#[async_trait]
pub trait Probe: Send {
    fn id(&self) -> &str;
    /// Request one reading and wait for it.
    async fn read(&mut self) -> Result<ProbeReading, DeviceError>;
}

/// Motion state of a rotary table.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum RotaryState {
    /// Rotating, or not yet settled inside the in-position window.
    Moving,
    /// At rest inside the in-position window, at the angle its encoder reports (radians).
    InPosition { encoder_rad: f64 },
}

/// A rotary table (an axis such as C) whose angle geocal commands, e.g. over Modbus.
#[async_trait]
pub trait RotaryTable: Send {
    fn id(&self) -> &str;
    /// Start a rotation to the absolute commanded angle, radians (returns once accepted).
    async fn start_rotation(&mut self, commanded_rad: f64) -> Result<(), DeviceError>;
    /// Current motion state; cheap to call often (drivers rate-limit their own queries).
    async fn state(&mut self) -> Result<RotaryState, DeviceError>;
    /// Faults recovered inside the driver since the last call (none by default).
    fn take_link_faults(&mut self) -> Vec<LinkFault> {
        Vec::new()
    }
}

/// A platform pose: x_fixed = R(rotation_vector_rad) · x_platform + translation_m.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlatformPose {
    /// Rotation vector (axis × angle), radians.
    pub rotation_vector_rad: [f64; 3],
    pub translation_m: [f64; 3],
}

/// One reading of the six leg encoders of a hexapod.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LegReading {
    /// Device (or host) time, seconds since the driver was opened.
    pub t_s: f64,
    /// Leg lengths as the incremental encoders count them (an unknown constant per leg), metres.
    pub lengths_m: [f64; 6],
}

/// Motion state of a hexapod.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum HexapodState {
    Moving,
    /// At rest at the commanded pose (as its controller believes).
    Idle,
}

/// A six-leg parallel machine: commanded in platform poses, read through its leg encoders.
#[async_trait]
pub trait Hexapod: Send {
    fn id(&self) -> &str;
    /// Start a move to a platform pose (returns once the command is accepted).
    async fn start_move(&mut self, pose: &PlatformPose) -> Result<(), DeviceError>;
    /// Current motion state; cheap to call often.
    async fn state(&mut self) -> Result<HexapodState, DeviceError>;
    /// Read the six leg encoders.
    async fn read_legs(&mut self) -> Result<LegReading, DeviceError>;
    /// Faults recovered inside the driver since the last call (none by default).
    fn take_link_faults(&mut self) -> Vec<LinkFault> {
        Vec::new()
    }
}

/// One measured platform pose (a tracer or tracker measuring the platform, or given values).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseReading {
    pub t_s: f64,
    pub pose: PlatformPose,
}

/// An instrument that measures the platform pose of a hexapod.
#[async_trait]
pub trait PoseSensor: Send {
    fn id(&self) -> &str;
    /// Measure the platform pose now (the platform at rest).
    async fn measure(&mut self) -> Result<PoseReading, DeviceError>;
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_embedded_error_does_not_repeat_its_prefix() {
        let lost = DeviceError::Disconnected {
            device: "mill".into(),
            message: "read failed: EOF".into(),
        };
        let again = DeviceError::Disconnected {
            device: "mill".into(),
            message: "cannot open /dev/ttyUSB0: no such file".into(),
        };
        let gave_up = DeviceError::Disconnected {
            device: "mill".into(),
            message: format!("{}; could not reopen: {}", lost.detail(), again.detail()),
        };
        assert_eq!(
            gave_up.to_string(),
            "mill: disconnected: read failed: EOF; could not reopen: cannot open \
             /dev/ttyUSB0: no such file"
        );
        let timeout = DeviceError::Timeout {
            device: "mill".into(),
            what: "ok".into(),
            after_s: 2.0,
        };
        assert_eq!(timeout.detail(), "timed out after 2 s waiting for ok");
    }
}
