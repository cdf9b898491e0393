//! ASCII probe emulator: the sensor side of the request/response protocol over a pty (or
//! any stream), with values from a `ProbeSource` and seeded fault injection.

use std::io;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::task::JoinHandle;
use tokio::time::Instant;

use super::codec::{format_reply, Framed, LineFramer, MAX_REPLY_BYTES};

/// What the sensor reads now: displacement in metres at `t_s` (seconds since the emulator
/// started), or `None` when out of range (the emulator answers its error reply). The
/// core's simulated world implements it; any `FnMut(f64) -> Option<f64>` does too.
pub trait ProbeSource: Send {
    fn value_m(&mut self, t_s: f64) -> Option<f64>;
}

impl<F: FnMut(f64) -> Option<f64> + Send> ProbeSource for F {
    fn value_m(&mut self, t_s: f64) -> Option<f64> {
        self(t_s)
    }
}

/// Faults the emulator injects; request numbers count requests received, from 1.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ProbeFaults {
    pub seed: u64,
    /// Probability that a request is answered with a garbage line.
    pub garbage_probability: f64,
    pub garbage_at_requests: Vec<u64>,
    /// Probability that a request gets no answer at all.
    pub no_answer_probability: f64,
    pub no_answer_at_requests: Vec<u64>,
}

/// The emulated sensor's dialect; must agree with the driver's `ProbeConfig`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ProbeEmulatorConfig {
    /// Request it answers (compared without surrounding whitespace).
    pub command: String,
    /// Reply with `{value}` where the number goes.
    pub reply_template: String,
    pub value_decimals: usize,
    /// Always sign the number (`+00.1234`), as many sensors do.
    pub plus_sign: bool,
    /// Metres per device unit.
    pub scale_to_m: f64,
    /// Reply when the source is out of range.
    pub out_of_range_reply: String,
    /// Reply to any other request.
    pub unknown_command_reply: String,
    /// Line terminator of replies.
    pub terminator: String,
    pub faults: ProbeFaults,
}

impl Default for ProbeEmulatorConfig {
    fn default() -> Self {
        Self {
            command: "M0".into(),
            reply_template: "M0,{value}".into(),
            value_decimals: 4,
            plus_sign: true,
            scale_to_m: 1e-3,
            out_of_range_reply: "ER,M0,01".into(),
            unknown_command_reply: "ER,??,02".into(),
            terminator: "\r".into(),
            faults: ProbeFaults::default(),
        }
    }
}

/// Counters of what the emulator saw and did.
#[derive(Debug, Default)]
pub struct ProbeEmulatorStats {
    pub requests: AtomicU64,
    pub replies: AtomicU64,
}

struct Sensor {
    cfg: ProbeEmulatorConfig,
    source: Box<dyn ProbeSource>,
    framer: LineFramer,
    rng: ChaCha8Rng,
    n: u64,
    stats: Arc<ProbeEmulatorStats>,
}

impl Sensor {
    fn chance(&mut self, p: f64) -> bool {
        p > 0.0 && self.rng.random::<f64>() < p
    }

    /// A line no pattern should accept: starts with `#`, then printable noise.
    fn garbage(&mut self) -> String {
        let len = self.rng.random_range(4..16);
        let mut s = String::from("#");
        for _ in 0..len {
            s.push(char::from(self.rng.random_range(b'!'..=b'~')));
        }
        s
    }

    /// Replies to the bytes received (sans-I/O: returns what to write).
    fn input(&mut self, bytes: &[u8], t_s: f64) -> Vec<u8> {
        let mut out = String::new();
        for f in self.framer.push(bytes) {
            let Framed::Line(line) = f else { continue };
            self.n += 1;
            self.stats.requests.fetch_add(1, Ordering::Relaxed);
            let n = self.n;
            let faults = self.cfg.faults.clone();
            let reply = if faults.no_answer_at_requests.contains(&n)
                || self.chance(faults.no_answer_probability)
            {
                continue;
            } else if faults.garbage_at_requests.contains(&n)
                || self.chance(faults.garbage_probability)
            {
                self.garbage()
            } else if line.trim() != self.cfg.command.trim() {
                self.cfg.unknown_command_reply.clone()
            } else {
                match self.source.value_m(t_s) {
                    Some(v) if v.is_finite() => format_reply(
                        &self.cfg.reply_template,
                        v / self.cfg.scale_to_m,
                        self.cfg.value_decimals,
                        self.cfg.plus_sign,
                    ),
                    _ => self.cfg.out_of_range_reply.clone(),
                }
            };
            self.stats.replies.fetch_add(1, Ordering::Relaxed);
            out.push_str(&reply);
            out.push_str(&self.cfg.terminator);
        }
        out.into_bytes()
    }
}

async fn run<S: AsyncRead + AsyncWrite + Unpin>(mut io: S, mut sensor: Sensor) -> io::Result<()> {
    let t0 = Instant::now();
    let mut buf = [0u8; 128];
    loop {
        let n = io.read(&mut buf).await?;
        if n == 0 {
            return Ok(());
        }
        let out = sensor.input(&buf[..n], t0.elapsed().as_secs_f64());
        if !out.is_empty() {
            io.write_all(&out).await?;
            io.flush().await?;
        }
    }
}

/// A running emulated sensor. Dropping it stops the emulator.
pub struct ProbeEmulator {
    task: JoinHandle<io::Result<()>>,
    stats: Arc<ProbeEmulatorStats>,
    pty: crate::serial::PtySlave,
}

impl ProbeEmulator {
    /// Serve the sensor side on any stream.
    pub fn spawn<S>(io: S, cfg: ProbeEmulatorConfig, source: Box<dyn ProbeSource>) -> Self
    where
        S: AsyncRead + AsyncWrite + Unpin + Send + 'static,
    {
        let stats = Arc::new(ProbeEmulatorStats::default());
        let sensor = Sensor {
            rng: ChaCha8Rng::seed_from_u64(cfg.faults.seed),
            cfg,
            source,
            framer: LineFramer::new(MAX_REPLY_BYTES),
            n: 0,
            stats: stats.clone(),
        };
        Self {
            task: tokio::spawn(run(io, sensor)),
            stats,
            pty: crate::serial::PtySlave::default(),
        }
    }

    /// Serve on a new pseudo-terminal; the slave end stays open until taken, so another
    /// process can open `slave_path()`.
    pub fn spawn_pty(cfg: ProbeEmulatorConfig, source: Box<dyn ProbeSource>) -> io::Result<Self> {
        let (master, pty) = crate::serial::pty_pair()?;
        let mut emu = Self::spawn(master, cfg, source);
        emu.pty = pty;
        Ok(emu)
    }

    pub fn slave_path(&self) -> Option<&str> {
        self.pty.path()
    }

    pub fn take_slave(&mut self) -> Option<tokio_serial::SerialStream> {
        self.pty.take()
    }

    pub fn stats(&self) -> &ProbeEmulatorStats {
        &self.stats
    }
}

impl Drop for ProbeEmulator {
    fn drop(&mut self) {
        self.task.abort();
    }
}
