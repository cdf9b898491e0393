//! GRBL controller emulator: the device side of the protocol over a pty (or any stream),
//! reusing the codec, with values from a `MachineSink` and seeded fault injection.

use std::collections::VecDeque;
use std::io;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::task::JoinHandle;
use tokio::time::Instant;

use super::codec::{
    format_banner, format_status, parse_block, Block, Framed, GrblState, LineFramer, PosFrame,
    StatusReport, MAX_LINE_BYTES, SOFT_RESET, STATUS_QUERY,
};

/// How often the emulator looks at its clock when no byte arrives: bounds the latency of
/// the `ok` after a dwell and of accepting a queued move once the previous one ends.
const TICK: Duration = Duration::from_millis(2);

/// The machine behind the emulated controller: it is told what was commanded and asked
/// where the axes are. The core's simulated world implements it; `KinematicSink` is a
/// simple stand-in. Times are seconds since the emulator started; positions are X, Y, Z in
/// metres (machine coordinates). A machine with rotary axes (A, then B, then C) says how many
/// (`rotary_axes`) and takes and reports them in radians through the `_rotary` methods; the
/// defaults describe a 3-axis machine.
pub trait MachineSink: Send {
    /// A move to `axes_m` at `feed_m_s` was accepted at `t_s`.
    fn commanded(&mut self, axes_m: [f64; 3], feed_m_s: f64, t_s: f64);
    /// Axis positions at `t_s`, and whether the axes are still moving.
    fn position(&mut self, t_s: f64) -> ([f64; 3], bool);
    /// Rotary axes this machine has (0 to 3: A, B, C); the controller reports them after
    /// X, Y, Z and answers `error:20` to words of axes it does not have.
    fn rotary_axes(&self) -> usize {
        0
    }
    /// A move that may turn the rotary axes: `rotary_rad` has `rotary_axes()` targets.
    fn commanded_rotary(&mut self, axes_m: [f64; 3], rotary_rad: &[f64], feed_m_s: f64, t_s: f64) {
        let _ = rotary_rad;
        self.commanded(axes_m, feed_m_s, t_s);
    }
    /// Rotary axis positions at `t_s`, radians (`rotary_axes()` of them).
    fn rotary_position(&mut self, t_s: f64) -> Vec<f64> {
        let _ = t_s;
        Vec::new()
    }
}

/// Straight-line moves at constant speed (no acceleration), arriving exactly on target. With
/// rotary axes the feed applies to the combined move as in GRBL, a degree counting as a mm.
#[derive(Debug, Clone)]
pub struct KinematicSink {
    from_m: [f64; 3],
    to_m: [f64; 3],
    from_rad: Vec<f64>,
    to_rad: Vec<f64>,
    t0_s: f64,
    duration_s: f64,
}

impl KinematicSink {
    pub fn new(start_m: [f64; 3]) -> Self {
        Self::with_rotary(start_m, Vec::new())
    }

    /// A machine with rotary axes (A, B, C in order) starting at `start_rad`.
    pub fn with_rotary(start_m: [f64; 3], start_rad: Vec<f64>) -> Self {
        Self {
            from_m: start_m,
            to_m: start_m,
            from_rad: start_rad.clone(),
            to_rad: start_rad,
            t0_s: 0.0,
            duration_s: 0.0,
        }
    }

    fn fraction(&self, t_s: f64) -> Option<f64> {
        let dt = t_s - self.t0_s;
        (dt < self.duration_s).then(|| (dt / self.duration_s).max(0.0))
    }
}

impl MachineSink for KinematicSink {
    fn commanded(&mut self, axes_m: [f64; 3], feed_m_s: f64, t_s: f64) {
        let rotary = self.rotary_position(t_s);
        self.commanded_rotary(axes_m, &rotary, feed_m_s, t_s);
    }

    fn position(&mut self, t_s: f64) -> ([f64; 3], bool) {
        match self.fraction(t_s) {
            None => (self.to_m, false),
            Some(f) => (
                std::array::from_fn(|k| self.from_m[k] + f * (self.to_m[k] - self.from_m[k])),
                true,
            ),
        }
    }

    fn rotary_axes(&self) -> usize {
        self.to_rad.len()
    }

    fn commanded_rotary(&mut self, axes_m: [f64; 3], rotary_rad: &[f64], feed_m_s: f64, t_s: f64) {
        let (here, _) = self.position(t_s);
        let here_rad = self.rotary_position(t_s);
        // GRBL's feed is along the vector of all axes in wire units: mm and degrees.
        let linear_mm2: f64 = (0..3).map(|k| ((axes_m[k] - here[k]) * 1e3).powi(2)).sum();
        let rotary_deg2: f64 = here_rad
            .iter()
            .zip(rotary_rad)
            .map(|(a, b)| (b - a).to_degrees().powi(2))
            .sum();
        let dist_mm = (linear_mm2 + rotary_deg2).sqrt();
        self.from_m = here;
        self.to_m = axes_m;
        self.to_rad = here_rad
            .iter()
            .enumerate()
            .map(|(k, &r)| rotary_rad.get(k).copied().unwrap_or(r))
            .collect();
        self.from_rad = here_rad;
        self.t0_s = t_s;
        self.duration_s = if feed_m_s > 0.0 {
            dist_mm * 1e-3 / feed_m_s
        } else {
            0.0
        };
    }

    fn rotary_position(&mut self, t_s: f64) -> Vec<f64> {
        match self.fraction(t_s) {
            None => self.to_rad.clone(),
            Some(f) => self
                .from_rad
                .iter()
                .zip(&self.to_rad)
                .map(|(a, b)| a + f * (b - a))
                .collect(),
        }
    }
}

/// Faults the emulator injects; line numbers count G-code lines received, from 1.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GrblFaults {
    /// Seed of the generator behind the probabilities.
    pub seed: u64,
    /// Probability that an accepted line's `ok` is never sent.
    pub drop_ok_probability: f64,
    /// Lines whose `ok` is never sent (the line still runs).
    pub drop_ok_at_lines: Vec<u64>,
    /// Probability that a line is answered `error:{error_code}` and not run.
    pub error_probability: f64,
    /// Lines answered `error:{error_code}` and not run (once: a resend is a new line).
    pub error_at_lines: Vec<u64>,
    pub error_code: u16,
    /// From this line on the controller is silent for `silence_s`: input (including `?`) is
    /// dropped and nothing is sent; motion already under way continues.
    pub silence_at_line: Option<u64>,
    pub silence_s: f64,
    /// At this line the controller closes the port (the pty master), as a pulled cable.
    pub disconnect_at_line: Option<u64>,
    /// After a disconnect, plug back in after this many seconds: a new pty behind the same
    /// link path (`GrblEmulator::spawn_pty_linked`), as a USB adapter re-enumerating behind
    /// its /dev/serial/by-id link; the controller resets (banner) as on a DTR reset.
    pub reconnect_after_s: Option<f64>,
    /// The move of this line starts, then `alarm_after_s` later the controller aborts it
    /// with `ALARM:{alarm_code}` (as a limit switch would) and locks until `$X`.
    pub alarm_at_line: Option<u64>,
    /// From this time (seconds since start) on, the next move in progress is aborted the same way.
    pub alarm_at_s: Option<f64>,
    pub alarm_after_s: f64,
    pub alarm_code: u16,
}

impl Default for GrblFaults {
    fn default() -> Self {
        Self {
            seed: 0,
            drop_ok_probability: 0.0,
            drop_ok_at_lines: Vec::new(),
            error_probability: 0.0,
            error_at_lines: Vec::new(),
            error_code: 20,
            silence_at_line: None,
            silence_s: 0.0,
            disconnect_at_line: None,
            reconnect_after_s: None,
            alarm_at_line: None,
            alarm_at_s: None,
            alarm_after_s: 0.02,
            alarm_code: 1,
        }
    }
}

/// The emulated controller's settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GrblEmulatorConfig {
    /// Version shown in the banner.
    pub version: String,
    /// Soft limits (machine travel), metres per X, Y, Z.
    pub travel_min_m: [f64; 3],
    pub travel_max_m: [f64; 3],
    /// Real GRBL raises ALARM:2 on a move beyond travel; by default the emulator answers
    /// `error:15` instead so the line is rejected without locking the controller.
    pub soft_limit_alarm: bool,
    /// Speed of G0 moves, m/s.
    pub rapid_m_s: f64,
    pub faults: GrblFaults,
}

impl Default for GrblEmulatorConfig {
    fn default() -> Self {
        Self {
            version: "1.1h".into(),
            travel_min_m: [-1.0; 3],
            travel_max_m: [1.0; 3],
            soft_limit_alarm: false,
            rapid_m_s: 0.1,
            faults: GrblFaults::default(),
        }
    }
}

/// Counters of what the emulator saw and did (tests read them).
#[derive(Debug, Default)]
pub struct GrblEmulatorStats {
    pub lines: AtomicU64,
    pub status_queries: AtomicU64,
    pub oks_sent: AtomicU64,
    pub errors_sent: AtomicU64,
    pub moves: AtomicU64,
    pub resets: AtomicU64,
    pub alarms: AtomicU64,
    pub unlocks: AtomicU64,
    pub disconnects: AtomicU64,
    /// Connections served (1 + reconnections).
    pub connections: AtomicU64,
}

impl GrblEmulatorStats {
    fn bump(counter: &AtomicU64) {
        counter.fetch_add(1, Ordering::Relaxed);
    }
}

struct Queued {
    line: String,
    drop_ok: bool,
    line_no: u64,
}

/// What the controller loop should do after a step.
enum Action {
    Continue,
    Disconnect,
}

/// The controller's state machine; no I/O: fed bytes and a clock, it appends output bytes.
struct Controller {
    cfg: GrblEmulatorConfig,
    sink: Box<dyn MachineSink>,
    framer: LineFramer,
    queue: VecDeque<Queued>,
    feed_m_s: Option<f64>,
    alarm: Option<u16>,
    /// End of the current dwell and whether its `ok` is dropped.
    dwell: Option<(f64, bool)>,
    silent_until_s: Option<f64>,
    line_no: u64,
    /// When the move under way is aborted by the injected alarm.
    alarm_pending_s: Option<f64>,
    /// The time-based alarm already struck.
    timed_alarm_done: bool,
    rng: ChaCha8Rng,
    stats: Arc<GrblEmulatorStats>,
    out: Vec<u8>,
}

impl Controller {
    fn new(
        cfg: GrblEmulatorConfig,
        sink: Box<dyn MachineSink>,
        stats: Arc<GrblEmulatorStats>,
    ) -> Self {
        let rng = ChaCha8Rng::seed_from_u64(cfg.faults.seed);
        Self {
            cfg,
            sink,
            framer: LineFramer::with_realtime(MAX_LINE_BYTES),
            queue: VecDeque::new(),
            feed_m_s: None,
            alarm: None,
            dwell: None,
            silent_until_s: None,
            line_no: 0,
            alarm_pending_s: None,
            timed_alarm_done: false,
            rng,
            stats,
            out: Vec::new(),
        }
    }

    fn say(&mut self, s: &str) {
        self.out.extend_from_slice(s.as_bytes());
    }

    fn ok(&mut self, drop: bool) {
        if !drop {
            self.say("ok\r\n");
            GrblEmulatorStats::bump(&self.stats.oks_sent);
        }
    }

    fn error(&mut self, code: u16) {
        self.say(&format!("error:{code}\r\n"));
        GrblEmulatorStats::bump(&self.stats.errors_sent);
    }

    fn silent(&mut self, t_s: f64) -> bool {
        match self.silent_until_s {
            Some(end) if t_s < end => true,
            Some(_) => {
                self.silent_until_s = None;
                false
            }
            None => false,
        }
    }

    fn chance(&mut self, p: f64) -> bool {
        p > 0.0 && self.rng.random::<f64>() < p
    }

    fn status(&mut self, t_s: f64) {
        let (pos, moving) = self.sink.position(t_s);
        let state = if self.alarm.is_some() {
            GrblState::Alarm
        } else if moving || self.dwell.is_some() {
            GrblState::Run
        } else {
            GrblState::Idle
        };
        let rotary_rad = self.sink.rotary_position(t_s);
        let report = StatusReport {
            state,
            substate: None,
            position_m: pos,
            rotary_rad,
            frame: PosFrame::Machine,
            wco_m: None,
            wco_rotary_rad: Vec::new(),
            feed_m_s: Some(if moving {
                self.feed_m_s.unwrap_or(0.0)
            } else {
                0.0
            }),
        };
        let s = format_status(&report);
        self.say(&s);
    }

    fn input(&mut self, bytes: &[u8], t_s: f64) -> Action {
        for f in self.framer.push(bytes) {
            if self.silent(t_s) {
                continue;
            }
            match f {
                Framed::Realtime(STATUS_QUERY) => {
                    GrblEmulatorStats::bump(&self.stats.status_queries);
                    self.status(t_s);
                }
                Framed::Realtime(SOFT_RESET) => self.reset(t_s),
                // Feed hold and resume are not emulated.
                Framed::Realtime(_) => {}
                Framed::Overlong => {
                    self.line_no += 1;
                    GrblEmulatorStats::bump(&self.stats.lines);
                    self.error(11);
                }
                Framed::Line(line) => {
                    self.line_no += 1;
                    GrblEmulatorStats::bump(&self.stats.lines);
                    let n = self.line_no;
                    let faults = &self.cfg.faults;
                    if faults.disconnect_at_line == Some(n) {
                        return Action::Disconnect;
                    }
                    if faults.silence_at_line == Some(n) {
                        self.silent_until_s = Some(t_s + faults.silence_s);
                        continue;
                    }
                    let forced_error = faults.error_at_lines.contains(&n);
                    let forced_drop = faults.drop_ok_at_lines.contains(&n);
                    let (p_err, p_drop, code) = (
                        faults.error_probability,
                        faults.drop_ok_probability,
                        faults.error_code,
                    );
                    if forced_error || self.chance(p_err) {
                        self.error(code);
                        continue;
                    }
                    let drop_ok = forced_drop || self.chance(p_drop);
                    self.queue.push_back(Queued {
                        line,
                        drop_ok,
                        line_no: n,
                    });
                }
            }
        }
        Action::Continue
    }

    /// Stop the axes where they are (commanding the current position).
    fn stop(&mut self, t_s: f64) {
        let (here, _) = self.sink.position(t_s);
        let rotary = self.sink.rotary_position(t_s);
        self.sink.commanded_rotary(here, &rotary, 0.0, t_s);
    }

    fn reset(&mut self, t_s: f64) {
        GrblEmulatorStats::bump(&self.stats.resets);
        self.stop(t_s);
        self.queue.clear();
        self.dwell = None;
        self.alarm = None;
        self.framer.clear();
        let banner = format_banner(&self.cfg.version);
        self.say(&banner);
    }

    /// Abort the motion under way with the injected alarm once its time has come.
    fn injected_alarm(&mut self, t_s: f64) {
        let (_, moving) = self.sink.position(t_s);
        if let Some(at) = self.cfg.faults.alarm_at_s {
            if !self.timed_alarm_done && t_s >= at && moving && self.alarm_pending_s.is_none() {
                self.timed_alarm_done = true;
                self.alarm_pending_s = Some(t_s);
            }
        }
        if self.alarm_pending_s.is_none_or(|at| t_s < at) {
            return;
        }
        self.alarm_pending_s = None;
        // A hard stop where the axes are; queued lines are discarded.
        self.stop(t_s);
        self.queue.clear();
        self.dwell = None;
        let code = self.cfg.faults.alarm_code;
        self.alarm = Some(code);
        GrblEmulatorStats::bump(&self.stats.alarms);
        self.say(&format!("ALARM:{code}\r\n"));
    }

    /// The port was reopened: the controller resets (as on DTR), motion stops, queue gone.
    fn reconnected(&mut self, t_s: f64) {
        self.stop(t_s);
        self.queue.clear();
        self.dwell = None;
        self.alarm = None;
        self.alarm_pending_s = None;
        self.silent_until_s = None;
        self.framer.clear();
        self.out.clear();
    }

    /// Run queued lines as far as motion allows.
    fn step(&mut self, t_s: f64) {
        if self.silent(t_s) {
            return;
        }
        self.injected_alarm(t_s);
        if let Some((end_s, drop)) = self.dwell {
            if t_s < end_s {
                return;
            }
            self.dwell = None;
            self.ok(drop);
        }
        while let Some(q) = self.queue.front() {
            let drop_ok = q.drop_ok;
            let q_line_no = q.line_no;
            let block = parse_block(&q.line);
            let (here, moving) = self.sink.position(t_s);
            match block {
                Err(code) => self.error(code),
                Ok(Block::Empty) => self.ok(drop_ok),
                Ok(Block::Unlock) => {
                    GrblEmulatorStats::bump(&self.stats.unlocks);
                    self.alarm = None;
                    self.say("[MSG:Caution: Unlocked]\r\n");
                    self.ok(drop_ok);
                }
                Ok(Block::System(_)) => self.error(3),
                Ok(Block::Move { .. } | Block::Dwell { .. }) if self.alarm.is_some() => {
                    self.error(9)
                }
                // One motion at a time: the line waits (and its `ok` with it).
                Ok(Block::Move { .. } | Block::Dwell { .. }) if moving => return,
                Ok(Block::Dwell { dwell_s }) => {
                    self.queue.pop_front();
                    self.dwell = Some((t_s + dwell_s, drop_ok));
                    return;
                }
                Ok(Block::Move { target_rad, .. })
                    if target_rad[self.sink.rotary_axes().min(3)..]
                        .iter()
                        .any(Option::is_some) =>
                {
                    // A word of an axis this controller does not have.
                    self.error(20)
                }
                Ok(Block::Move {
                    rapid,
                    target_m,
                    target_rad,
                    feed_m_s,
                }) => {
                    if let Some(f) = feed_m_s {
                        self.feed_m_s = Some(f);
                    }
                    let target: [f64; 3] = std::array::from_fn(|k| target_m[k].unwrap_or(here[k]));
                    let rotary_here = self.sink.rotary_position(t_s);
                    let rotary: Vec<f64> = rotary_here
                        .iter()
                        .enumerate()
                        .map(|(k, &r)| target_rad.get(k).copied().flatten().unwrap_or(r))
                        .collect();
                    let within = (0..3).all(|k| {
                        target[k] >= self.cfg.travel_min_m[k]
                            && target[k] <= self.cfg.travel_max_m[k]
                    });
                    let feed = if rapid {
                        Some(self.cfg.rapid_m_s)
                    } else {
                        self.feed_m_s
                    };
                    match feed {
                        None => self.error(22),
                        Some(_) if !within && self.cfg.soft_limit_alarm => {
                            self.alarm = Some(2);
                            self.say("ALARM:2\r\n");
                        }
                        Some(_) if !within => self.error(15),
                        Some(f) => {
                            GrblEmulatorStats::bump(&self.stats.moves);
                            if rotary.is_empty() {
                                self.sink.commanded(target, f, t_s);
                            } else {
                                self.sink.commanded_rotary(target, &rotary, f, t_s);
                            }
                            self.ok(drop_ok);
                            if self.cfg.faults.alarm_at_line == Some(q_line_no) {
                                self.alarm_pending_s = Some(t_s + self.cfg.faults.alarm_after_s);
                            }
                        }
                    }
                }
            }
            self.queue.pop_front();
        }
    }
}

async fn run<S: AsyncRead + AsyncWrite + Unpin>(io: S, mut ctl: Controller) -> io::Result<()> {
    serve(io, &mut ctl, Instant::now()).await.map(|_| ())
}

/// Serve one connection until the peer goes, an I/O error, or an injected disconnect.
async fn serve<S: AsyncRead + AsyncWrite + Unpin>(
    mut io: S,
    ctl: &mut Controller,
    t0: Instant,
) -> io::Result<Action> {
    GrblEmulatorStats::bump(&ctl.stats.connections);
    let banner = format_banner(&ctl.cfg.version);
    io.write_all(banner.as_bytes()).await?;
    io.flush().await?;
    let mut buf = [0u8; 256];
    loop {
        let t_s = t0.elapsed().as_secs_f64();
        match tokio::time::timeout(TICK, io.read(&mut buf)).await {
            Err(_) => {}
            Ok(Ok(0)) => return Ok(Action::Continue),
            Ok(Ok(n)) => {
                if let Action::Disconnect = ctl.input(&buf[..n], t_s) {
                    GrblEmulatorStats::bump(&ctl.stats.disconnects);
                    return Ok(Action::Disconnect);
                }
            }
            // EIO on a pty master: the other side was closed.
            Ok(Err(e)) => return Err(e),
        }
        ctl.step(t0.elapsed().as_secs_f64());
        if !ctl.out.is_empty() {
            let out = std::mem::take(&mut ctl.out);
            io.write_all(&out).await?;
            io.flush().await?;
        }
    }
}

/// Serve on ptys behind the symlink `link`, starting with `first`: a new pty after every
/// injected disconnect (after `reconnect_after_s`), or stop if none is configured.
async fn serve_linked(
    mut ctl: Controller,
    link: PathBuf,
    first: (tokio_serial::SerialStream, crate::serial::PtySlave),
) -> io::Result<()> {
    let t0 = Instant::now();
    let mut next = Some(first);
    loop {
        let (master, slave) = match next.take() {
            Some(pair) => pair,
            None => linked_pty(&link)?,
        };
        // `slave` stays open while this connection is served (see `PtySlave`); dropping it
        // with the master hangs up the driver's descriptor too.
        let action = serve(master, &mut ctl, t0).await?;
        drop(slave);
        let (Action::Disconnect, Some(after_s)) = (action, ctl.cfg.faults.reconnect_after_s) else {
            return Ok(());
        };
        tokio::time::sleep(Duration::try_from_secs_f64(after_s).unwrap_or_default()).await;
        ctl.reconnected(t0.elapsed().as_secs_f64());
    }
}

/// A new pty with `link` pointing at its slave end.
fn linked_pty(link: &Path) -> io::Result<(tokio_serial::SerialStream, crate::serial::PtySlave)> {
    let (master, slave) = crate::serial::pty_pair()?;
    let target = slave
        .path()
        .ok_or_else(|| io::Error::other("pty without a path"))?
        .to_string();
    point_link(link, Path::new(&target))?;
    Ok((master, slave))
}

/// Make `link` a symlink to `target`, replacing an old one atomically.
fn point_link(link: &Path, target: &Path) -> io::Result<()> {
    let tmp = link.with_extension("new");
    let _ = std::fs::remove_file(&tmp);
    std::os::unix::fs::symlink(target, &tmp)?;
    std::fs::rename(&tmp, link)
}

/// A running emulated controller. Dropping it stops the emulator.
pub struct GrblEmulator {
    task: JoinHandle<io::Result<()>>,
    stats: Arc<GrblEmulatorStats>,
    pty: crate::serial::PtySlave,
    /// The stable path of a linked emulator (removed on drop).
    link: Option<PathBuf>,
}

impl GrblEmulator {
    /// Serve the controller side on any stream (the host talks on the other end).
    pub fn spawn<S>(io: S, cfg: GrblEmulatorConfig, sink: Box<dyn MachineSink>) -> Self
    where
        S: AsyncRead + AsyncWrite + Unpin + Send + 'static,
    {
        let stats = Arc::new(GrblEmulatorStats::default());
        let ctl = Controller::new(cfg, sink, stats.clone());
        Self {
            task: tokio::spawn(run(io, ctl)),
            stats,
            pty: crate::serial::PtySlave::default(),
            link: None,
        }
    }

    /// Serve on a pty reached through the symlink `link` (a stable path, like
    /// /dev/serial/by-id/...): drivers open `link`. An injected disconnect closes the pty;
    /// with `reconnect_after_s` a new one appears behind the same link. Must be called
    /// inside a tokio runtime.
    pub fn spawn_pty_linked(
        cfg: GrblEmulatorConfig,
        sink: Box<dyn MachineSink>,
        link: PathBuf,
    ) -> io::Result<Self> {
        let stats = Arc::new(GrblEmulatorStats::default());
        let ctl = Controller::new(cfg, sink, stats.clone());
        // The first pty exists (and the link points at it) before this returns.
        let first = linked_pty(&link)?;
        let task = tokio::spawn(serve_linked(ctl, link.clone(), first));
        Ok(Self {
            task,
            stats,
            pty: crate::serial::PtySlave::default(),
            link: Some(link),
        })
    }

    /// Serve on a new pseudo-terminal. The emulator keeps the slave end open so that an
    /// external process can open `slave_path()` at any time; an in-process driver takes it
    /// with `take_slave()`.
    pub fn spawn_pty(cfg: GrblEmulatorConfig, sink: Box<dyn MachineSink>) -> io::Result<Self> {
        let (master, pty) = crate::serial::pty_pair()?;
        let mut emu = Self::spawn(master, cfg, sink);
        emu.pty = pty;
        Ok(emu)
    }

    /// Device path of the pty's slave end (`/dev/pts/N`, or the link of a linked
    /// emulator), for a driver in another process.
    pub fn slave_path(&self) -> Option<&str> {
        match &self.link {
            Some(link) => link.to_str(),
            None => self.pty.path(),
        }
    }

    /// The pty's slave end, for a driver in this process.
    pub fn take_slave(&mut self) -> Option<tokio_serial::SerialStream> {
        self.pty.take()
    }

    pub fn stats(&self) -> &GrblEmulatorStats {
        &self.stats
    }

    /// True once the emulator stopped (disconnect fault, peer gone, I/O error).
    pub fn is_finished(&self) -> bool {
        self.task.is_finished()
    }
}

impl Drop for GrblEmulator {
    fn drop(&mut self) {
        self.task.abort();
        if let Some(link) = &self.link {
            let _ = std::fs::remove_file(link);
        }
    }
}
