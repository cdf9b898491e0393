//! Host driver: owns the serial port, a reader task that decodes and timestamps frames, and
//! the command path (ack, timeout, retry). Serves `Tracer`, and `Environment` through a handle.

use std::collections::{BTreeMap, VecDeque};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use async_trait::async_trait;
use serde::{Deserialize, Serialize};
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::sync::mpsc;
use tokio::task::JoinHandle;
use tokio::time::Instant;

use super::clock::StreamClock;
use super::codec::{encode_host, DeviceDecoder};
use super::frame::{DeviceFrame, HostCommand, HostFrame, Meteo};
use crate::traits::{DeviceError, EnvReading, Environment, LinkFault, Tracer, TracerReading};

/// Which device stream feeds the tracer. Only distance: a `Tracer` reports lengths, and
/// integrating the velocity stream would drift.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Hpi3dStream {
    #[default]
    Distance,
}

/// Driver configuration (lives beside the driver; `config` builds the trait objects from it).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Hpi3dConfig {
    /// Device name in errors and records.
    pub id: String,
    /// Serial port path, e.g. `/dev/ttyUSB0`.
    pub port: String,
    pub baud: u32,
    /// How long to wait for the acknowledgement of one command attempt.
    pub ack_timeout_s: f64,
    /// Extra attempts after the first before a command fails with `Timeout`.
    pub retries: u32,
    pub stream: Hpi3dStream,
    /// Ask for the meteo (environment) stream.
    pub meteo: bool,
    /// `next_sample` fails with `Timeout` after this long without a distance frame.
    pub stream_timeout_s: f64,
    /// While the beam reads broken, re-send "clear small-signal flag" this often: the device
    /// latches the flag, so without a clear the driver would never see the beam return.
    pub flag_clear_interval_s: f64,
    /// Samples buffered for a slow consumer; beyond it new samples are counted and dropped.
    pub sample_queue: usize,
    /// Frames per second of the distance stream (the device: 25 Hz). Sample times are laid
    /// on this grid by frame count (docs/protocols/hpi3d.md, "Timestamps").
    pub stream_rate_hz: f64,
}

impl Default for Hpi3dConfig {
    fn default() -> Self {
        Hpi3dConfig {
            id: "hpi3d".into(),
            port: "/dev/ttyUSB0".into(),
            baud: 3_000_000,
            ack_timeout_s: 0.2,
            retries: 3,
            stream: Hpi3dStream::Distance,
            meteo: true,
            stream_timeout_s: 1.0,
            flag_clear_interval_s: 0.5,
            sample_queue: 4096,
            stream_rate_hz: 25.0,
        }
    }
}

/// Link health counters, for the sequencer's `fault` events. Monotonic since connect.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Hpi3dCounters {
    /// Frames with a good CRC, of any kind.
    pub frames_ok: u64,
    pub distance_frames: u64,
    /// Frames dropped for a bad CRC.
    pub frames_corrupted: u64,
    /// Bytes discarded while resynchronising.
    pub bytes_skipped: u64,
    /// Command attempts after the first.
    pub retries: u64,
    /// Commands that failed after every retry.
    pub ack_timeouts: u64,
    /// Samples dropped because the consumer fell `sample_queue` behind.
    pub samples_overflowed: u64,
    /// Frames with a cmd the driver does not use (velocity, unknown).
    pub frames_ignored: u64,
}

const METEO_QUEUE: usize = 1024;

/// State shared by the reader task, the tracer and the environment handle.
#[derive(Default)]
struct Shared {
    counters: Mutex<Hpi3dCounters>,
    meteo: Mutex<VecDeque<EnvReading>>,
    /// Why the link ended, once it has.
    closed: Mutex<Option<String>>,
}

/// A poisoned lock only means another thread panicked mid-update of plain counters.
fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

fn duration(device: &str, name: &str, s: f64) -> Result<Duration, DeviceError> {
    Duration::try_from_secs_f64(s).map_err(|_| DeviceError::Rejected {
        device: device.into(),
        message: format!("{name} = {s} is not a valid duration"),
    })
}

/// The HPI-3D as a `Tracer`. Dropping it stops the reader task.
pub struct Hpi3dTracer {
    id: String,
    ack_timeout: Duration,
    retries: u32,
    stream_timeout: Duration,
    flag_clear_interval: Duration,
    writer: Box<dyn AsyncWrite + Send + Unpin>,
    samples: mpsc::Receiver<TracerReading>,
    acks: mpsc::UnboundedReceiver<HostCommand>,
    shared: Arc<Shared>,
    reader: JoinHandle<()>,
    last_flag_clear: Option<Instant>,
    /// Counters as last reported by `take_link_faults`.
    reported: Hpi3dCounters,
    stream: Hpi3dStream,
    meteo: bool,
}

impl Hpi3dTracer {
    /// Open `config.port` (8N1, no flow control) and start the streams.
    pub async fn open(config: Hpi3dConfig) -> Result<Self, DeviceError> {
        let port = crate::serial::open_8n1(&config.id, &config.port, config.baud)?;
        Self::from_io(port, config).await
    }

    /// Run over any byte stream (a pty, a socket, an in-memory duplex); `config.port` and
    /// `config.baud` are unused. Must be called inside a tokio runtime.
    pub async fn from_io<S>(io: S, config: Hpi3dConfig) -> Result<Self, DeviceError>
    where
        S: AsyncRead + AsyncWrite + Unpin + Send + 'static,
    {
        let id = config.id.clone();
        let ack_timeout = duration(&id, "ack_timeout_s", config.ack_timeout_s)?;
        let stream_timeout = duration(&id, "stream_timeout_s", config.stream_timeout_s)?;
        let flag_clear_interval =
            duration(&id, "flag_clear_interval_s", config.flag_clear_interval_s)?;
        let clock =
            StreamClock::new(config.stream_rate_hz).ok_or_else(|| DeviceError::Rejected {
                device: id.clone(),
                message: format!(
                    "stream_rate_hz = {} is not a valid rate: expected a positive number of frames per second",
                    config.stream_rate_hz
                ),
            })?;
        let (rd, wr) = tokio::io::split(io);
        let (sample_tx, samples) = mpsc::channel(config.sample_queue.max(1));
        let (ack_tx, acks) = mpsc::unbounded_channel();
        let shared = Arc::new(Shared::default());
        let reader = tokio::spawn(reader_task(
            rd,
            Instant::now(),
            clock,
            sample_tx,
            ack_tx,
            shared.clone(),
        ));
        let mut tracer = Hpi3dTracer {
            id,
            ack_timeout,
            retries: config.retries,
            stream_timeout,
            flag_clear_interval,
            writer: Box::new(wr),
            samples,
            acks,
            shared,
            reader,
            last_flag_clear: None,
            reported: Hpi3dCounters::default(),
            stream: config.stream,
            meteo: config.meteo,
        };
        tracer.start_streams().await?;
        Ok(tracer)
    }

    /// Start the streams from a known state whatever the previous session left running.
    /// Samples queued before the restart are discarded: a caller that kept the driver open
    /// between runs gets only samples measured after this call.
    pub async fn start_streams(&mut self) -> Result<(), DeviceError> {
        self.command(HostCommand::StopAll).await?;
        // Every distance frame sent before the stop was read before its acknowledgement.
        while self.samples.try_recv().is_ok() {}
        lock(&self.shared.meteo).clear();
        self.last_flag_clear = None;
        self.command(HostCommand::ClearSmallSignal).await?;
        match self.stream {
            Hpi3dStream::Distance => self.command(HostCommand::DistanceOn).await?,
        }
        let meteo = if self.meteo {
            HostCommand::MeteoOn
        } else {
            HostCommand::MeteoOff
        };
        self.command(meteo).await
    }

    /// Stop the streams (the device stays connected and idle).
    pub async fn stop_streams(&mut self) -> Result<(), DeviceError> {
        self.command(HostCommand::StopAll).await
    }

    /// An `Environment` fed by this driver's meteo frames (any number of handles).
    pub fn environment(&self) -> Hpi3dEnvironment {
        Hpi3dEnvironment {
            id: format!("{}-meteo", self.id),
            shared: self.shared.clone(),
        }
    }

    pub fn counters(&self) -> Hpi3dCounters {
        *lock(&self.shared.counters)
    }

    fn disconnected(&self) -> DeviceError {
        DeviceError::Disconnected {
            device: self.id.clone(),
            message: lock(&self.shared.closed)
                .clone()
                .unwrap_or_else(|| "reader stopped".into()),
        }
    }

    async fn write(&mut self, command: HostCommand) -> Result<(), DeviceError> {
        let bytes = encode_host(&HostFrame::new(command));
        let written = async {
            self.writer.write_all(&bytes).await?;
            self.writer.flush().await
        }
        .await;
        written.map_err(|e| DeviceError::Disconnected {
            device: self.id.clone(),
            message: format!("write failed: {e}"),
        })
    }

    /// Send a command and wait for its acknowledgement, retrying `retries` times.
    pub async fn command(&mut self, command: HostCommand) -> Result<(), DeviceError> {
        // Late acks of earlier commands must not answer this one.
        while self.acks.try_recv().is_ok() {}
        for attempt in 0..=self.retries {
            if attempt > 0 {
                lock(&self.shared.counters).retries += 1;
            }
            self.write(command).await?;
            let deadline = Instant::now() + self.ack_timeout;
            loop {
                match tokio::time::timeout_at(deadline, self.acks.recv()).await {
                    Ok(Some(acked)) if acked == command => return Ok(()),
                    Ok(Some(_)) => continue,
                    Ok(None) => return Err(self.disconnected()),
                    Err(_) => break,
                }
            }
        }
        lock(&self.shared.counters).ack_timeouts += 1;
        Err(DeviceError::Timeout {
            device: self.id.clone(),
            what: format!("acknowledgement of {command:?} ({:#06x})", command.code()),
            after_s: self.ack_timeout.as_secs_f64() * f64::from(self.retries + 1),
        })
    }
}

impl Drop for Hpi3dTracer {
    fn drop(&mut self) {
        self.reader.abort();
        lock(&self.shared.closed).get_or_insert_with(|| "driver dropped".into());
    }
}

#[async_trait]
impl Tracer for Hpi3dTracer {
    fn id(&self) -> &str {
        &self.id
    }

    async fn next_sample(&mut self) -> Result<TracerReading, DeviceError> {
        let reading = match tokio::time::timeout(self.stream_timeout, self.samples.recv()).await {
            Ok(Some(r)) => r,
            Ok(None) => return Err(self.disconnected()),
            Err(_) => {
                return Err(DeviceError::Timeout {
                    device: self.id.clone(),
                    what: "distance frame".into(),
                    after_s: self.stream_timeout.as_secs_f64(),
                })
            }
        };
        if !reading.tracking
            && self
                .last_flag_clear
                .is_none_or(|t| t.elapsed() >= self.flag_clear_interval)
        {
            // Fire and forget: its ack is discarded by the next command.
            self.last_flag_clear = Some(Instant::now());
            self.write(HostCommand::ClearSmallSignal).await?;
        }
        Ok(reading)
    }

    /// Clear the (latched) small-signal flag, then zero the counter. After a beam break the
    /// next sample with tracking starts a new `beam_segment`.
    async fn home(&mut self) -> Result<(), DeviceError> {
        self.command(HostCommand::ClearSmallSignal).await?;
        self.command(HostCommand::Home).await
    }

    /// Frames dropped for a bad CRC (`crc`) and garbage skipped to resynchronise
    /// (`resync`) since the last call; a lost distance frame also shows as a `seq` gap.
    fn take_link_faults(&mut self) -> Vec<LinkFault> {
        let now = self.counters();
        let mut faults = Vec::new();
        let crc = now
            .frames_corrupted
            .saturating_sub(self.reported.frames_corrupted);
        if crc > 0 {
            faults.push(LinkFault {
                code: "crc".into(),
                message: format!(
                    "{crc} frame(s) failed their CRC and were dropped ({} so far)",
                    now.frames_corrupted
                ),
            });
        }
        let skipped = now
            .bytes_skipped
            .saturating_sub(self.reported.bytes_skipped);
        if skipped > 0 {
            faults.push(LinkFault {
                code: "resync".into(),
                message: format!("{skipped} byte(s) of garbage skipped to resynchronise"),
            });
        }
        self.reported = now;
        faults
    }
}

/// The meteo side of an `Hpi3dTracer`: drains the readings its reader task assembled.
pub struct Hpi3dEnvironment {
    id: String,
    shared: Arc<Shared>,
}

#[async_trait]
impl Environment for Hpi3dEnvironment {
    fn id(&self) -> &str {
        &self.id
    }

    async fn poll(&mut self) -> Result<Vec<EnvReading>, DeviceError> {
        let readings: Vec<EnvReading> = lock(&self.shared.meteo).drain(..).collect();
        if readings.is_empty() {
            if let Some(message) = lock(&self.shared.closed).clone() {
                return Err(DeviceError::Disconnected {
                    device: self.id.clone(),
                    message,
                });
            }
        }
        Ok(readings)
    }
}

/// Beam bookkeeping in stream order, so a homing ack falls between the right frames.
#[derive(Default)]
struct Beam {
    seq: u64,
    segment: u32,
    /// A break was seen since the last valid homing.
    broken: bool,
    /// A homing was acknowledged while broken; the next frame decides whether it counts.
    rehomed: bool,
}

/// Turns per-sensor meteo frames into `EnvReading`s: one per air-sensor frame, with the
/// latest value of every material sensor seen so far (so these may lag by one period).
#[derive(Default)]
struct MeteoAssembler {
    material_k: BTreeMap<u8, f64>,
}

impl MeteoAssembler {
    fn push(&mut self, m: &Meteo, t_s: f64) -> Option<EnvReading> {
        if m.sensor != 0 {
            self.material_k.insert(m.sensor, m.temperature_k());
            return None;
        }
        Some(EnvReading {
            t_s,
            air_temp_k: m.temperature_k(),
            pressure_pa: m.pressure_pa(),
            humidity_pct: f64::from(m.humidity_pct),
            material_temp_k: self.material_k.values().copied().collect(),
        })
    }
}

async fn reader_task<R: AsyncRead + Unpin>(
    mut rd: R,
    start: Instant,
    mut clock: StreamClock,
    samples: mpsc::Sender<TracerReading>,
    acks: mpsc::UnboundedSender<HostCommand>,
    shared: Arc<Shared>,
) {
    let mut decoder = DeviceDecoder::new();
    let mut buf = vec![0u8; 4096];
    let mut frames = Vec::new();
    let mut beam = Beam::default();
    let mut meteo = MeteoAssembler::default();
    let mut corrupted_seen = 0;
    let reason = loop {
        let n = match rd.read(&mut buf).await {
            Ok(0) => break "end of stream".to_string(),
            Ok(n) => n,
            Err(e) => break format!("read failed: {e}"),
        };
        // Device time is not in the frames: distance frames are timed by their count from
        // this reception time, meteo frames (not counted) keep it.
        let recv_s = start.elapsed().as_secs_f64();
        decoder.feed_into(&buf[..n], &mut frames);
        let stats = decoder.stats();
        let mut ignored = 0;
        let mut overflowed = 0;
        let mut distance = 0;
        for frame in frames.drain(..) {
            match frame {
                DeviceFrame::Distance(d) => {
                    distance += 1;
                    // A frame lost to a bad CRC was almost surely a stream frame: let it
                    // leave a gap in seq.
                    beam.seq += 1 + (stats.frames_corrupted - corrupted_seen);
                    corrupted_seen = stats.frames_corrupted;
                    let tracking = d.status.tracking();
                    if beam.rehomed {
                        beam.rehomed = false;
                        if tracking {
                            beam.segment += 1;
                            beam.broken = false;
                        }
                    }
                    if !tracking {
                        beam.broken = true;
                    }
                    let reading = TracerReading {
                        seq: beam.seq,
                        t_s: clock.stamp(beam.seq, recv_s),
                        length_m: d.position_m(),
                        signal: d.status.signal(),
                        tracking,
                        beam_segment: beam.segment,
                    };
                    match samples.try_send(reading) {
                        Ok(()) => {}
                        Err(mpsc::error::TrySendError::Full(_)) => overflowed += 1,
                        // The tracer is gone; nobody is listening.
                        Err(mpsc::error::TrySendError::Closed(_)) => return,
                    }
                }
                DeviceFrame::Ack { command, .. } => {
                    if command == HostCommand::Home && beam.broken {
                        beam.rehomed = true;
                    }
                    // A stream switched on again ticks on a grid of its own.
                    if command == HostCommand::DistanceOn {
                        clock.restart();
                    }
                    let _ = acks.send(command);
                }
                DeviceFrame::Meteo(m) => {
                    if let Some(r) = meteo.push(&m, recv_s) {
                        let mut q = lock(&shared.meteo);
                        if q.len() >= METEO_QUEUE {
                            q.pop_front();
                        }
                        q.push_back(r);
                    }
                }
                DeviceFrame::Velocity(_) | DeviceFrame::Unknown { .. } => ignored += 1,
            }
        }
        let mut c = lock(&shared.counters);
        c.frames_ok = stats.frames_ok;
        c.frames_corrupted = stats.frames_corrupted;
        c.bytes_skipped = stats.bytes_skipped;
        c.distance_frames += distance;
        c.frames_ignored += ignored;
        c.samples_overflowed += overflowed;
    };
    *lock(&shared.closed) = Some(reason);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn config_defaults_and_unknown_fields() {
        let c: Hpi3dConfig =
            serde_json::from_str(r#"{"port": "/dev/ttyACM0", "stream": "distance"}"#).unwrap();
        assert_eq!(c.baud, 3_000_000);
        assert_eq!(c.port, "/dev/ttyACM0");
        assert!(c.meteo);
        assert_eq!(c.stream_rate_hz, 25.0);
        assert!(serde_json::from_str::<Hpi3dConfig>(r#"{"baudrate": 9600}"#).is_err());
        assert!(serde_json::from_str::<Hpi3dConfig>(r#"{"stream": "velocity"}"#).is_err());
    }

    #[tokio::test]
    async fn rejects_negative_timeouts() {
        let (a, _b) = tokio::io::duplex(64);
        let config = Hpi3dConfig {
            ack_timeout_s: -1.0,
            ..Hpi3dConfig::default()
        };
        let err = Hpi3dTracer::from_io(a, config).await.err().unwrap();
        assert!(matches!(err, DeviceError::Rejected { .. }), "{err}");
    }

    #[tokio::test]
    async fn rejects_a_stream_rate_that_is_not_a_rate() {
        for rate in [0.0, -25.0, f64::NAN, f64::INFINITY] {
            let (a, _b) = tokio::io::duplex(64);
            let config = Hpi3dConfig {
                stream_rate_hz: rate,
                ..Hpi3dConfig::default()
            };
            let err = Hpi3dTracer::from_io(a, config).await.err().unwrap();
            assert!(
                matches!(&err, DeviceError::Rejected { message, .. } if message.contains("stream_rate_hz")),
                "{err}"
            );
        }
    }

    #[test]
    fn meteo_reading_on_the_air_frame() {
        let mut m = MeteoAssembler::default();
        let frame = |sensor, temperature_centi_c| Meteo {
            sensor,
            temperature_centi_c,
            humidity_pct: 40,
            battery: 100,
            link: 100,
            pressure_deca_pa: 10_000,
            spare: [0; 4],
        };
        assert!(m.push(&frame(2, 2100), 0.0).is_none());
        assert!(m.push(&frame(1, 2000), 0.0).is_none());
        let r = m.push(&frame(0, -500), 0.5).unwrap();
        assert!((r.air_temp_k - 268.15).abs() < 1e-9);
        assert!((r.pressure_pa - 100_000.0).abs() < 1e-9);
        assert_eq!(r.material_temp_k.len(), 2);
        assert!((r.material_temp_k[0] - 293.15).abs() < 1e-9);
        assert!((r.material_temp_k[1] - 294.15).abs() < 1e-9);
    }
}
