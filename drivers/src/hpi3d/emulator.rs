//! Device-side HPI-3D over a pty (or any byte stream), reusing the codec: acks commands,
//! streams distance/velocity/meteo frames from a `TracerSource`, and injects seeded faults.

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use rand::{Rng, RngCore, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::task::JoinHandle;
use tokio::time::{Instant, MissedTickBehavior};
use tokio_serial::SerialStream;

use super::codec::{encode_device, HostDecoder};
use super::frame::{
    DeviceFrame, Distance, HostCommand, HostFrame, Meteo, Status, Velocity, DEVICE_FRAME_LEN,
    VELOCITY_UNIT_M_PER_S,
};

/// What the emulated interferometer sees at one instant.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SourceReading {
    /// Absolute tracer-to-target distance, metres (any continuous length works: the
    /// emulator reports it relative to the origin set by the last homing).
    pub length_m: f64,
    /// False while the beam is interrupted (the emulator raises the small-signal flag).
    pub beam_ok: bool,
    /// Signal level, 0..1.
    pub signal: f64,
}

/// One meteo sensor's values, SI units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MeteoSensorReading {
    /// 0 = air (temperature, humidity, pressure), 1.. = material temperature sensors.
    pub sensor: u8,
    pub temperature_k: f64,
    pub humidity_pct: f64,
    pub pressure_pa: f64,
}

/// Where the emulator gets its values; the core's simulated world implements it.
pub trait TracerSource: Send {
    fn sample(&mut self, t_s: f64) -> SourceReading;
    /// The host homed at `t_s` (a notification: the emulator keeps the origin itself).
    fn home(&mut self, t_s: f64);
    fn meteo(&mut self, t_s: f64) -> Vec<MeteoSensorReading>;
}

/// A `TracerSource` from a closure of time and a fixed set of meteo readings.
pub struct FnSource<F> {
    pub sample: F,
    pub meteo: Vec<MeteoSensorReading>,
}

impl<F: FnMut(f64) -> SourceReading + Send> TracerSource for FnSource<F> {
    fn sample(&mut self, t_s: f64) -> SourceReading {
        (self.sample)(t_s)
    }
    fn home(&mut self, _t_s: f64) {}
    fn meteo(&mut self, _t_s: f64) -> Vec<MeteoSensorReading> {
        self.meteo.clone()
    }
}

/// A time window `[from_s, to_s)` since emulator start.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Window {
    pub from_s: f64,
    pub to_s: f64,
}

impl Window {
    fn contains(w: &Option<Window>, t_s: f64) -> bool {
        w.is_some_and(|w| t_s >= w.from_s && t_s < w.to_s)
    }
}

/// Seeded, deterministic fault injection (each kind draws from its own random stream, so
/// enabling one fault does not change where another strikes).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FaultConfig {
    pub seed: u64,
    /// Fraction of stream frames not sent at all.
    pub drop_fraction: f64,
    /// Fraction of stream frames sent with a wrong CRC.
    pub corrupt_fraction: f64,
    /// Fraction of stream frames preceded by 1..=16 random bytes.
    pub garbage_fraction: f64,
    /// Fraction of host commands acted on but not acknowledged.
    pub ack_drop_fraction: f64,
    /// Send nothing and ignore commands.
    pub silence: Option<Window>,
    /// Beam interrupted regardless of the source.
    pub beam_break: Option<Window>,
    /// Commands ignored entirely (no action, no ack).
    pub mute_commands: Option<Window>,
}

impl Default for FaultConfig {
    fn default() -> Self {
        FaultConfig {
            seed: 0,
            drop_fraction: 0.0,
            corrupt_fraction: 0.0,
            garbage_fraction: 0.0,
            ack_drop_fraction: 0.0,
            silence: None,
            beam_break: None,
            mute_commands: None,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EmulatorConfig {
    /// Distance/velocity stream rate (the real device: 25 Hz).
    pub rate_hz: f64,
    /// Meteo period (the real device: 1 s); one frame per sensor each period.
    pub meteo_period_s: f64,
    pub faults: FaultConfig,
}

impl Default for EmulatorConfig {
    fn default() -> Self {
        EmulatorConfig {
            rate_hz: 25.0,
            meteo_period_s: 1.0,
            faults: FaultConfig::default(),
        }
    }
}

/// What the emulator did, to compare with what the driver counted.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct EmulatorStats {
    /// Stream frames sent intact (distance, velocity, meteo).
    pub frames_sent: u64,
    pub frames_dropped: u64,
    pub frames_corrupted: u64,
    pub garbage_bytes: u64,
    pub commands_received: u64,
    /// Commands ignored (mute or silence window).
    pub commands_ignored: u64,
    pub acks_sent: u64,
    pub acks_dropped: u64,
    pub homings: u64,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// A running emulator; dropping it stops the device task.
pub struct Hpi3dEmulator {
    task: JoinHandle<()>,
    stats: Arc<Mutex<EmulatorStats>>,
    slave_path: Option<PathBuf>,
}

impl Drop for Hpi3dEmulator {
    fn drop(&mut self) {
        self.task.abort();
    }
}

fn invalid(message: String) -> std::io::Error {
    std::io::Error::new(std::io::ErrorKind::InvalidInput, message)
}

impl Hpi3dEmulator {
    /// Serve the device side on `io`. Must be called inside a tokio runtime.
    pub fn spawn<S>(
        io: S,
        config: EmulatorConfig,
        source: Box<dyn TracerSource>,
    ) -> std::io::Result<Self>
    where
        S: AsyncRead + AsyncWrite + Send + 'static,
    {
        let period = Duration::try_from_secs_f64(1.0 / config.rate_hz)
            .map_err(|_| invalid(format!("rate_hz = {}", config.rate_hz)))?;
        let meteo_period = Duration::try_from_secs_f64(config.meteo_period_s)
            .ok()
            .filter(|d| !d.is_zero())
            .ok_or_else(|| invalid(format!("meteo_period_s = {}", config.meteo_period_s)))?;
        let f = &config.faults;
        for (name, p) in [
            ("drop_fraction", f.drop_fraction),
            ("corrupt_fraction", f.corrupt_fraction),
            ("garbage_fraction", f.garbage_fraction),
            ("ack_drop_fraction", f.ack_drop_fraction),
        ] {
            if !(0.0..=1.0).contains(&p) {
                return Err(invalid(format!("{name} = {p} is not in [0, 1]")));
            }
        }
        let stats = Arc::new(Mutex::new(EmulatorStats::default()));
        let device = Device::new(config, source, stats.clone());
        let task = tokio::spawn(run(io, device, period, meteo_period));
        Ok(Hpi3dEmulator {
            task,
            stats,
            slave_path: None,
        })
    }

    /// Serve the device side on a new pty; returns the host end. Keep that end open even if
    /// an external process opens `slave_path()` instead: when every slave descriptor is
    /// closed the pty reports errors to the device side.
    pub fn spawn_pty(
        config: EmulatorConfig,
        source: Box<dyn TracerSource>,
    ) -> std::io::Result<(Self, SerialStream)> {
        let (master, mut pty) = crate::serial::pty_pair()?;
        let path = pty.path().map(PathBuf::from);
        let slave = pty
            .take()
            .ok_or_else(|| std::io::Error::other("pty without a slave end"))?;
        let mut emulator = Self::spawn(master, config, source)?;
        emulator.slave_path = path;
        Ok((emulator, slave))
    }

    /// The host-side device path of a pty emulator, for `Hpi3dTracer::open` or another process.
    pub fn slave_path(&self) -> Option<&Path> {
        self.slave_path.as_deref()
    }

    pub fn stats(&self) -> EmulatorStats {
        *lock(&self.stats)
    }
}

/// Device state: the part of the emulator that does not touch I/O.
struct Device {
    source: Box<dyn TracerSource>,
    faults: FaultConfig,
    rate_hz: f64,
    stats: Arc<Mutex<EmulatorStats>>,
    drop_rng: ChaCha8Rng,
    corrupt_rng: ChaCha8Rng,
    garbage_rng: ChaCha8Rng,
    ack_rng: ChaCha8Rng,
    distance_on: bool,
    velocity_on: bool,
    meteo_on: bool,
    /// Source length at the last homing (or the counter's re-anchor after a break).
    origin_m: f64,
    /// The counter's value when last read; frozen while the beam is broken.
    counter_m: f64,
    beam_lost: bool,
    /// The device latches small signal until the host clears it (B0 3D).
    small_signal_latched: bool,
    last_length_m: Option<f64>,
}

impl Device {
    fn new(
        config: EmulatorConfig,
        source: Box<dyn TracerSource>,
        stats: Arc<Mutex<EmulatorStats>>,
    ) -> Self {
        let rng = |stream: u64| {
            let mut r = ChaCha8Rng::seed_from_u64(config.faults.seed);
            r.set_stream(stream);
            r
        };
        Device {
            source,
            rate_hz: config.rate_hz,
            stats,
            drop_rng: rng(1),
            corrupt_rng: rng(2),
            garbage_rng: rng(3),
            ack_rng: rng(4),
            faults: config.faults,
            distance_on: false,
            velocity_on: false,
            meteo_on: false,
            origin_m: 0.0,
            counter_m: 0.0,
            beam_lost: false,
            small_signal_latched: false,
            last_length_m: None,
        }
    }

    fn stats(&self) -> MutexGuard<'_, EmulatorStats> {
        lock(&self.stats)
    }

    fn command(&mut self, frame: HostFrame, t_s: f64, out: &mut Vec<u8>) {
        self.stats().commands_received += 1;
        if Window::contains(&self.faults.silence, t_s)
            || Window::contains(&self.faults.mute_commands, t_s)
        {
            self.stats().commands_ignored += 1;
            return;
        }
        match frame.command {
            HostCommand::DistanceOn => {
                self.distance_on = true;
                self.velocity_on = false;
            }
            HostCommand::DistanceOff => self.distance_on = false,
            HostCommand::VelocityOn => {
                self.velocity_on = true;
                self.distance_on = false;
            }
            HostCommand::VelocityOff => self.velocity_on = false,
            HostCommand::StopAll => {
                self.distance_on = false;
                self.velocity_on = false;
                self.meteo_on = false;
            }
            HostCommand::ClearSmallSignal => self.small_signal_latched = false,
            HostCommand::MeteoOn => self.meteo_on = true,
            HostCommand::MeteoOff => self.meteo_on = false,
            HostCommand::Home => {
                let s = self.source.sample(t_s);
                self.origin_m = s.length_m;
                self.counter_m = 0.0;
                self.source.home(t_s);
                self.stats().homings += 1;
            }
            HostCommand::ClearVelocityOverflow
            | HostCommand::ClearExternalCapture
            | HostCommand::Other(_) => {}
        }
        if self.ack_rng.random_bool(self.faults.ack_drop_fraction) {
            self.stats().acks_dropped += 1;
            return;
        }
        // Undocumented commands are acknowledged too: the cmd echoes whatever came in.
        let ack = match frame.command {
            HostCommand::Other(cmd) => DeviceFrame::Unknown { cmd, data: [0; 12] },
            command => DeviceFrame::ack(command),
        };
        out.extend_from_slice(&encode_device(&ack));
        self.stats().acks_sent += 1;
    }

    /// Read the source and advance the fringe counter; returns the status for the frame.
    fn measure(&mut self, t_s: f64) -> (f64, Status) {
        let s = self.source.sample(t_s);
        let beam_ok = s.beam_ok && !Window::contains(&self.faults.beam_break, t_s);
        if beam_ok {
            if self.beam_lost {
                // Fringes were not counted during the break: the counter resumes from its
                // frozen value, so lengths after it no longer refer to the homing point.
                self.origin_m = s.length_m - self.counter_m;
                self.beam_lost = false;
            }
            self.counter_m = s.length_m - self.origin_m;
        } else {
            self.beam_lost = true;
            self.small_signal_latched = true;
        }
        let level = if beam_ok {
            (s.signal.clamp(0.0, 1.0) * 255.0).round() as u8
        } else {
            0
        };
        let status = Status {
            laser_ready: true,
            small_signal: self.small_signal_latched,
            signal_level: level,
            ..Status::default()
        };
        (s.length_m, status)
    }

    fn stream_frame(&mut self, t_s: f64, out: &mut Vec<u8>) {
        if Window::contains(&self.faults.silence, t_s) {
            return;
        }
        if !(self.distance_on || self.velocity_on) {
            return;
        }
        let (length_m, status) = self.measure(t_s);
        let frame = if self.distance_on {
            DeviceFrame::Distance(Distance {
                position_counts: Distance::counts_from_m(self.counter_m),
                spare: [0; 2],
                status,
            })
        } else {
            let v = self
                .last_length_m
                .map_or(0.0, |prev| (length_m - prev) * self.rate_hz);
            DeviceFrame::Velocity(Velocity {
                // `as` saturates: an overflowing speed reads as full scale.
                velocity_counts: (v / VELOCITY_UNIT_M_PER_S).round() as i32,
                spare: [0; 5],
                status,
            })
        };
        self.last_length_m = Some(length_m);
        self.emit(&frame, out);
    }

    fn meteo_frames(&mut self, t_s: f64, out: &mut Vec<u8>) {
        if !self.meteo_on || Window::contains(&self.faults.silence, t_s) {
            return;
        }
        let mut readings = self.source.meteo(t_s);
        // Material sensors first, air last: the driver emits a reading on the air frame.
        readings.sort_by_key(|r| std::cmp::Reverse(r.sensor));
        for r in readings {
            let frame = DeviceFrame::Meteo(Meteo {
                sensor: r.sensor,
                temperature_centi_c: Meteo::encode_temperature_k(r.temperature_k),
                humidity_pct: r.humidity_pct.round().clamp(0.0, 100.0) as u8,
                battery: 100,
                link: 100,
                pressure_deca_pa: Meteo::encode_pressure_pa(r.pressure_pa),
                spare: [0; 4],
            });
            self.emit(&frame, out);
        }
    }

    /// Append a stream frame, applying the frame faults.
    fn emit(&mut self, frame: &DeviceFrame, out: &mut Vec<u8>) {
        let f = &self.faults;
        let (drop, corrupt, garbage) = (
            self.drop_rng.random_bool(f.drop_fraction),
            self.corrupt_rng.random_bool(f.corrupt_fraction),
            self.garbage_rng.random_bool(f.garbage_fraction),
        );
        let mut stats = lock(&self.stats);
        if garbage {
            let n = self.garbage_rng.random_range(1..=16);
            let mut bytes = vec![0u8; n];
            self.garbage_rng.fill_bytes(&mut bytes);
            out.extend_from_slice(&bytes);
            stats.garbage_bytes += n as u64;
        }
        if drop {
            stats.frames_dropped += 1;
            return;
        }
        let mut bytes = encode_device(frame);
        if corrupt {
            bytes[DEVICE_FRAME_LEN - 1] ^= 0x5A;
            stats.frames_corrupted += 1;
        } else {
            stats.frames_sent += 1;
        }
        out.extend_from_slice(&bytes);
    }
}

async fn run<S>(io: S, mut device: Device, period: Duration, meteo_period: Duration)
where
    S: AsyncRead + AsyncWrite + Send + 'static,
{
    let (mut rd, mut wr) = tokio::io::split(io);
    let start = Instant::now();
    let mut decoder = HostDecoder::new();
    let mut stream_tick = tokio::time::interval(period);
    stream_tick.set_missed_tick_behavior(MissedTickBehavior::Skip);
    let mut meteo_tick = tokio::time::interval(meteo_period);
    meteo_tick.set_missed_tick_behavior(MissedTickBehavior::Skip);
    let mut buf = [0u8; 512];
    let mut out = Vec::new();
    let mut commands = VecDeque::new();
    loop {
        out.clear();
        tokio::select! {
            r = rd.read(&mut buf) => match r {
                Ok(0) => return,
                Ok(n) => {
                    let t_s = start.elapsed().as_secs_f64();
                    commands.extend(decoder.feed(&buf[..n]));
                    while let Some(c) = commands.pop_front() {
                        device.command(c, t_s, &mut out);
                    }
                }
                // A pty with no slave open errors until one opens again: wait and retry.
                Err(_) => tokio::time::sleep(Duration::from_millis(20)).await,
            },
            _ = stream_tick.tick() => device.stream_frame(start.elapsed().as_secs_f64(), &mut out),
            _ = meteo_tick.tick() => device.meteo_frames(start.elapsed().as_secs_f64(), &mut out),
        }
        if !out.is_empty() && wr.write_all(&out).await.is_err() {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn config_from_json_with_defaults() {
        let c: EmulatorConfig = serde_json::from_str(
            r#"{"rate_hz": 500, "faults": {"seed": 9, "beam_break": {"from_s": 1, "to_s": 2}}}"#,
        )
        .unwrap();
        assert_eq!(c.meteo_period_s, 1.0);
        assert_eq!(c.faults.seed, 9);
        assert!(Window::contains(&c.faults.beam_break, 1.5));
        assert!(!Window::contains(&c.faults.beam_break, 2.0));
        assert!(serde_json::from_str::<EmulatorConfig>(r#"{"rate": 5}"#).is_err());
        assert!(serde_json::from_str::<FaultConfig>(r#"{"drop": 0.1}"#).is_err());
    }

    #[tokio::test]
    async fn rejects_bad_fractions() {
        let (a, _b) = tokio::io::duplex(64);
        let config = EmulatorConfig {
            faults: FaultConfig {
                drop_fraction: f64::NAN,
                ..FaultConfig::default()
            },
            ..EmulatorConfig::default()
        };
        let source = FnSource {
            sample: |_| SourceReading {
                length_m: 0.0,
                beam_ok: true,
                signal: 1.0,
            },
            meteo: vec![],
        };
        assert!(Hpi3dEmulator::spawn(a, config, Box::new(source)).is_err());
    }
}
