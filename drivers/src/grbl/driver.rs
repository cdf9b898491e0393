//! GRBL machine driver: owns the serial port and the timing (ack timeouts, status polling,
//! rate limiting) and implements `Machine` on top of the sans-I/O codec.

use std::collections::{BTreeMap, VecDeque};
use std::time::Duration;

use async_trait::async_trait;
use serde::{Deserialize, Serialize};
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::time::Instant;

use super::codec::{
    alarm_text, error_text, format_dwell, format_move, parse_controller_line, ControllerLine,
    Framed, GrblState, LineFramer, PosFrame, StatusReport, MAX_LINE_BYTES, SOFT_RESET,
    STATUS_QUERY,
};
use crate::serial::check_seconds;
use crate::traits::{AxisPositions, DeviceError, LinkFault, Machine, MachineState};

/// G-code axis letters in the order GRBL reports positions: X, Y, Z (metres), then the rotary
/// axes A, B, C (radians inside, degrees on the wire) of controllers with more axes.
const LETTERS: [char; 6] = ['X', 'Y', 'Z', 'A', 'B', 'C'];
/// Axes a driver tracks (linear then rotary).
const N_AXES: usize = LETTERS.len();

/// How a GRBL controller is reached and judged. Lives in the machine's TOML config.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GrblConfig {
    #[serde(default = "default_id")]
    pub id: String,
    /// Serial device path, e.g. `/dev/ttyUSB0`.
    pub port: String,
    #[serde(default = "default_baud")]
    pub baud: u32,
    /// Longest wait for the `ok` of one line, seconds. A line is acknowledged once planned,
    /// but a full planner (or a dwell) delays it, so this is generous.
    #[serde(default = "default_ack_timeout_s")]
    pub ack_timeout_s: f64,
    /// Longest wait for the answer to `?`, seconds.
    #[serde(default = "default_status_timeout_s")]
    pub status_timeout_s: f64,
    /// Minimum time between two `?` queries, seconds; `state()` returns the last report
    /// in between so that a tight polling loop does not flood the controller.
    #[serde(default = "default_status_interval_s")]
    pub status_interval_s: f64,
    /// Feed of every commanded move, m/s.
    #[serde(default = "default_feed_m_s")]
    pub feed_m_s: f64,
    /// The machine counts as arrived when Idle within this distance of the target on every
    /// commanded axis, metres.
    #[serde(default = "default_tolerance_m")]
    pub position_tolerance_m: f64,
    /// The same for rotary axes (A, B, C), radians (default 2e-5 rad, about GRBL's 0.001°).
    #[serde(default = "default_tolerance_rad")]
    pub position_tolerance_rad: f64,
    /// geocal axis name -> GRBL axis letter (`X`, `Y`, `Z`, or the rotary `A`, `B`, `C`).
    #[serde(default = "default_axis_letters")]
    pub axis_letters: BTreeMap<String, char>,
    /// After the port is lost (read/write error, hang-up), keep trying to reopen `port` for
    /// this long, seconds; 0 = do not reconnect. Only drivers opened by path reconnect.
    #[serde(default = "default_reconnect_timeout_s")]
    pub reconnect_timeout_s: f64,
}

fn default_reconnect_timeout_s() -> f64 {
    5.0
}

fn default_id() -> String {
    "grbl".into()
}
fn default_baud() -> u32 {
    115_200
}
fn default_ack_timeout_s() -> f64 {
    5.0
}
fn default_status_timeout_s() -> f64 {
    1.0
}
fn default_status_interval_s() -> f64 {
    0.05
}
fn default_feed_m_s() -> f64 {
    0.01
}
fn default_tolerance_m() -> f64 {
    1e-6
}
fn default_tolerance_rad() -> f64 {
    2e-5
}
fn default_axis_letters() -> BTreeMap<String, char> {
    [("x", 'X'), ("y", 'Y'), ("z", 'Z')]
        .into_iter()
        .map(|(n, l)| (n.to_string(), l))
        .collect()
}

impl Default for GrblConfig {
    fn default() -> Self {
        Self {
            id: default_id(),
            port: String::new(),
            baud: default_baud(),
            ack_timeout_s: default_ack_timeout_s(),
            status_timeout_s: default_status_timeout_s(),
            status_interval_s: default_status_interval_s(),
            feed_m_s: default_feed_m_s(),
            position_tolerance_m: default_tolerance_m(),
            position_tolerance_rad: default_tolerance_rad(),
            axis_letters: default_axis_letters(),
            reconnect_timeout_s: default_reconnect_timeout_s(),
        }
    }
}

impl GrblConfig {
    /// Reject values the driver cannot work with.
    pub fn validate(&self) -> Result<(), DeviceError> {
        check_seconds(&self.id, "ack_timeout_s", self.ack_timeout_s)?;
        check_seconds(&self.id, "status_timeout_s", self.status_timeout_s)?;
        check_seconds(&self.id, "status_interval_s", self.status_interval_s)?;
        check_seconds(&self.id, "reconnect_timeout_s", self.reconnect_timeout_s)?;
        let bad = |message: String| DeviceError::Protocol {
            device: self.id.clone(),
            message,
        };
        if !(self.feed_m_s.is_finite() && self.feed_m_s > 0.0) {
            return Err(bad(format!(
                "feed_m_s must be positive, got {}",
                self.feed_m_s
            )));
        }
        if !(self.position_tolerance_m.is_finite() && self.position_tolerance_m >= 0.0) {
            return Err(bad(format!(
                "position_tolerance_m must be >= 0, got {}",
                self.position_tolerance_m
            )));
        }
        if !(self.position_tolerance_rad.is_finite() && self.position_tolerance_rad >= 0.0) {
            return Err(bad(format!(
                "position_tolerance_rad must be >= 0, got {}",
                self.position_tolerance_rad
            )));
        }
        Ok(())
    }
}

/// GRBL's `error:9`: G-code locked out during alarm or jog state.
const ERROR_LOCKED_BY_ALARM: u16 = 9;

/// A GRBL-style controller driven line by line (`ok`/`error:` per line, `?` status).
pub struct GrblMachine<S> {
    cfg: GrblConfig,
    io: S,
    framer: LineFramer,
    lines: VecDeque<String>,
    /// geocal axis name -> index into `LETTERS`.
    axis_index: BTreeMap<String, usize>,
    /// Last commanded absolute target per GRBL axis in `LETTERS` order, metres or radians
    /// (work coordinates).
    commanded: [Option<f64>; N_AXES],
    /// Work coordinate offset, metres; GRBL sends it only now and then.
    wco_m: [f64; 3],
    /// Its rotary part (A, B, C), radians.
    wco_rotary_rad: Vec<f64>,
    last_status: Option<StatusReport>,
    last_query: Option<Instant>,
    version: Option<String>,
    status_queries: u64,
    garbled_lines: u64,
    /// Heard an `ok`, `error:`, alarm or status since the last banner.
    talked: bool,
    /// Code of the last `ALARM:N` heard (a status in `Alarm` does not say which).
    last_alarm: Option<u16>,
    /// An `ALARM:N` that arrived between commands (e.g. just after a move ended): the next
    /// move reports it instead of being sent into a locked controller.
    alarm_pending: Option<u16>,
    /// The last move line sent, re-sent after a reconnect (the controller reset).
    last_move: Option<String>,
    /// Reopens the port by path (drivers made by `open`).
    reopen: Option<Reopen<S>>,
    link_faults: Vec<LinkFault>,
}

type Reopen<S> = Box<dyn Fn() -> Result<S, DeviceError> + Send + Sync>;

impl GrblMachine<tokio_serial::SerialStream> {
    /// Open the serial port named in the config.
    pub fn open(cfg: GrblConfig) -> Result<Self, DeviceError> {
        let port = crate::serial::open_8n1(&cfg.id, &cfg.port, cfg.baud)?;
        let (id, path, baud) = (cfg.id.clone(), cfg.port.clone(), cfg.baud);
        let mut machine = Self::from_stream(port, cfg)?;
        machine.reopen = Some(Box::new(move || crate::serial::open_8n1(&id, &path, baud)));
        Ok(machine)
    }
}

impl<S: AsyncRead + AsyncWrite + Unpin + Send> GrblMachine<S> {
    /// Drive a controller over any byte stream (a pty, a socket, an in-memory duplex).
    pub fn from_stream(io: S, cfg: GrblConfig) -> Result<Self, DeviceError> {
        cfg.validate()?;
        let mut axis_index = BTreeMap::new();
        let mut used = [false; N_AXES];
        for (name, letter) in &cfg.axis_letters {
            let k = LETTERS
                .iter()
                .position(|l| l.eq_ignore_ascii_case(letter))
                .ok_or_else(|| DeviceError::Protocol {
                    device: cfg.id.clone(),
                    message: format!("axis {name:?}: letter {letter:?} is not X, Y, Z, A, B or C"),
                })?;
            if used[k] {
                return Err(DeviceError::Protocol {
                    device: cfg.id.clone(),
                    message: format!("axis letter {letter:?} mapped twice"),
                });
            }
            used[k] = true;
            axis_index.insert(name.clone(), k);
        }
        Ok(Self {
            cfg,
            io,
            framer: LineFramer::new(MAX_LINE_BYTES),
            lines: VecDeque::new(),
            axis_index,
            commanded: [None; N_AXES],
            wco_m: [0.0; 3],
            wco_rotary_rad: Vec::new(),
            last_status: None,
            last_query: None,
            version: None,
            status_queries: 0,
            garbled_lines: 0,
            talked: false,
            last_alarm: None,
            alarm_pending: None,
            last_move: None,
            reopen: None,
            link_faults: Vec::new(),
        })
    }

    pub fn config(&self) -> &GrblConfig {
        &self.cfg
    }

    /// Controller version from the last banner seen (`1.1h`), if any.
    pub fn controller_version(&self) -> Option<&str> {
        self.version.as_deref()
    }

    /// `?` queries sent so far (for tests of the rate limit and for diagnostics).
    pub fn status_queries(&self) -> u64 {
        self.status_queries
    }

    /// Lines from the controller that could not be decoded (noise on the line).
    pub fn garbled_lines(&self) -> u64 {
        self.garbled_lines
    }

    /// Last status report received, if any.
    pub fn last_status(&self) -> Option<&StatusReport> {
        self.last_status.as_ref()
    }

    fn disconnected(&self, message: String) -> DeviceError {
        DeviceError::Disconnected {
            device: self.cfg.id.clone(),
            message,
        }
    }

    async fn write_all(&mut self, bytes: &[u8]) -> Result<(), DeviceError> {
        let r = async {
            self.io.write_all(bytes).await?;
            self.io.flush().await
        }
        .await;
        r.map_err(|e| self.disconnected(format!("write failed: {e}")))
    }

    /// Feed bytes read from the port into the framer.
    fn take_bytes(&mut self, bytes: &[u8]) {
        for f in self.framer.push(bytes) {
            match f {
                Framed::Line(l) => self.lines.push_back(l),
                Framed::Overlong => self.garbled_lines += 1,
                Framed::Realtime(_) => {}
            }
        }
    }

    /// Decode a line and remember what it tells about the controller.
    fn observe(&mut self, line: &str) -> Option<ControllerLine> {
        match parse_controller_line(line) {
            Ok(msg) => {
                match &msg {
                    ControllerLine::Status(s) => {
                        if let Some(w) = s.wco_m {
                            self.wco_m = w;
                            self.wco_rotary_rad = s.wco_rotary_rad.clone();
                        }
                        self.last_status = Some(s.clone());
                    }
                    ControllerLine::Banner { version } => {
                        self.version = Some(version.clone());
                        // The power-up banner (or one before any exchange) is no news; after
                        // an exchange it means the controller reset and forgot its motion.
                        if !std::mem::replace(&mut self.talked, false) {
                            return Some(ControllerLine::Other(line.to_string()));
                        }
                        return Some(msg);
                    }
                    ControllerLine::Other(_) | ControllerLine::Feedback(_) => return Some(msg),
                    ControllerLine::Ok | ControllerLine::Error(_) | ControllerLine::Alarm(_) => {}
                }
                self.talked = true;
                Some(msg)
            }
            Err(_) => {
                self.garbled_lines += 1;
                None
            }
        }
    }

    /// Next decoded controller line, waiting until `deadline`.
    async fn next_line(
        &mut self,
        deadline: Instant,
        what: &str,
        timeout_s: f64,
    ) -> Result<ControllerLine, DeviceError> {
        let mut buf = [0u8; 256];
        loop {
            while let Some(l) = self.lines.pop_front() {
                if let Some(msg) = self.observe(&l) {
                    return Ok(msg);
                }
            }
            match tokio::time::timeout_at(deadline, self.io.read(&mut buf)).await {
                Err(_) => {
                    return Err(DeviceError::Timeout {
                        device: self.cfg.id.clone(),
                        what: what.to_string(),
                        after_s: timeout_s,
                    })
                }
                Ok(Ok(0)) => return Err(self.disconnected("port closed by the controller".into())),
                Ok(Ok(n)) => self.take_bytes(&buf[..n]),
                Ok(Err(e)) => return Err(self.disconnected(format!("read failed: {e}"))),
            }
        }
    }

    /// Consume whatever has already arrived (late `ok`s of timed-out lines, stray reports),
    /// so that it is not mistaken for the answer to the next command.
    async fn drain(&mut self) -> Result<(), DeviceError> {
        let mut buf = [0u8; 256];
        loop {
            // A zero timeout still polls the read once: it returns only bytes already here.
            match tokio::time::timeout(Duration::ZERO, self.io.read(&mut buf)).await {
                Err(_) => break,
                Ok(Ok(0)) => return Err(self.disconnected("port closed by the controller".into())),
                Ok(Ok(n)) => self.take_bytes(&buf[..n]),
                Ok(Err(e)) => return Err(self.disconnected(format!("read failed: {e}"))),
            }
        }
        while let Some(l) = self.lines.pop_front() {
            if let Some(ControllerLine::Alarm(code)) = self.observe(&l) {
                self.last_alarm = Some(code);
                self.alarm_pending = Some(code);
            }
        }
        Ok(())
    }

    /// An alarm: motion aborted, controller locked until `unlock`.
    fn alarm(&mut self, code: u16, context: &str) -> DeviceError {
        self.last_alarm = Some(code);
        DeviceError::Alarm {
            device: self.cfg.id.clone(),
            code,
            message: format!(
                "{}{context}; unlock with $X and command the move again",
                alarm_text(code)
            ),
        }
    }

    /// After the port was lost: reopen it by path until `reconnect_timeout_s`, then wait
    /// briefly for the banner of the controller's reset. Records `disconnect` and
    /// `reconnect` link faults. Fails with the original error if it cannot reconnect.
    async fn reconnect(&mut self, lost: DeviceError) -> Result<(), DeviceError> {
        let (Some(reopen), true) = (&self.reopen, self.cfg.reconnect_timeout_s > 0.0) else {
            return Err(lost);
        };
        self.link_faults.push(LinkFault {
            code: "disconnect".into(),
            message: lost.to_string(),
        });
        let started = Instant::now();
        let deadline = started + Duration::from_secs_f64(self.cfg.reconnect_timeout_s);
        let io = loop {
            tokio::time::sleep(Duration::from_millis(20)).await;
            match reopen() {
                Ok(io) => break io,
                Err(e) if Instant::now() >= deadline => {
                    return Err(DeviceError::Disconnected {
                        device: self.cfg.id.clone(),
                        message: format!(
                            "{}; could not reopen {} within {} s: {}",
                            lost.detail(),
                            self.cfg.port,
                            self.cfg.reconnect_timeout_s,
                            e.detail()
                        ),
                    })
                }
                Err(_) => {}
            }
        };
        self.io = io;
        self.framer.clear();
        self.lines.clear();
        self.alarm_pending = None;
        self.last_status = None;
        self.last_query = None;
        // GRBL resets when its port is opened: wait for the banner, if it comes.
        let t = self.cfg.ack_timeout_s;
        let banner_deadline = Instant::now() + Duration::from_secs_f64(t);
        loop {
            match self.next_line(banner_deadline, "banner", t).await {
                Ok(ControllerLine::Banner { .. }) | Err(DeviceError::Timeout { .. }) => break,
                Ok(_) => {}
                Err(e) => return Err(e),
            }
        }
        self.link_faults.push(LinkFault {
            code: "reconnect".into(),
            message: format!(
                "reopened {} after {:.2} s",
                self.cfg.port,
                started.elapsed().as_secs_f64()
            ),
        });
        Ok(())
    }

    /// Send the last move again (after a reconnect the controller has forgotten it).
    async fn resend_last_move(&mut self) -> Result<(), DeviceError> {
        match self.last_move.clone() {
            Some(line) => self.send_line(&line, self.cfg.ack_timeout_s).await,
            None => Ok(()),
        }
    }

    async fn start_move_once(&mut self, target: &AxisPositions) -> Result<(), DeviceError> {
        self.drain().await?;
        if let Some(code) = self.alarm_pending.take() {
            return Err(self.alarm(code, " (raised after the last command)"));
        }
        let mut axes = Vec::new();
        let mut next = self.commanded;
        for (name, &pos_m) in target {
            let k = *self
                .axis_index
                .get(name)
                .ok_or_else(|| self.rejected(format!("no GRBL axis mapped to axis {name:?}")))?;
            if !pos_m.is_finite() {
                return Err(self.rejected(format!("target of axis {name:?} is not finite")));
            }
            axes.push((k, pos_m));
            next[k] = Some(pos_m);
        }
        if axes.is_empty() {
            return Ok(());
        }
        axes.sort_by_key(|&(k, _)| k);
        let words: Vec<(char, f64)> = axes.iter().map(|&(k, p)| (LETTERS[k], p)).collect();
        let line = format_move(&words, self.cfg.feed_m_s);
        let before = self.commanded;
        // Judge arrival against the new target from now on: if the `ok` is lost the line
        // most likely ran, and an old status must not count as arrival.
        self.commanded = next;
        self.last_status = None;
        self.last_move = Some(line.clone());
        match self.send_line(&line, self.cfg.ack_timeout_s).await {
            Err(e @ DeviceError::Rejected { .. }) => {
                self.commanded = before;
                Err(e)
            }
            r => r,
        }
    }

    async fn state_once(&mut self) -> Result<MachineState, DeviceError> {
        let interval = Duration::from_secs_f64(self.cfg.status_interval_s.max(0.0));
        // Inside the interval the last report stands; with none (just after a move was
        // started) the answer is Moving, which is what the controller would say anyway.
        let fresh = self.last_query.is_some_and(|t| t.elapsed() < interval);
        if !fresh {
            self.query_status().await?;
        }
        match self.last_status.clone() {
            Some(s) => self.evaluate(&s),
            None => Ok(MachineState::Moving),
        }
    }

    fn rejected(&self, message: String) -> DeviceError {
        DeviceError::Rejected {
            device: self.cfg.id.clone(),
            message,
        }
    }

    /// Send one G-code line and wait for its `ok`.
    async fn send_line(&mut self, line: &str, timeout_s: f64) -> Result<(), DeviceError> {
        self.drain().await?;
        self.write_all(line.as_bytes()).await?;
        let shown = line.trim_end();
        let what = format!(
            "`ok` to `{shown}` (reply lost or controller stalled; the line may or may not run)"
        );
        let deadline = Instant::now() + Duration::from_secs_f64(timeout_s.max(0.0));
        loop {
            match self.next_line(deadline, &what, timeout_s).await? {
                ControllerLine::Ok => return Ok(()),
                // The controller is locked by an alarm whose `ALARM:` report this driver has
                // not taken (lost, or consumed as an earlier line's garbage): the alarm path
                // (unlock, send again) is the recovery, not a rejected line.
                ControllerLine::Error(ERROR_LOCKED_BY_ALARM) => {
                    let code = self.alarm_pending.take().or(self.last_alarm).unwrap_or(0);
                    return Err(self.alarm(
                        code,
                        &format!(
                            " (error:{ERROR_LOCKED_BY_ALARM} to `{shown}`: locked by an alarm)"
                        ),
                    ));
                }
                ControllerLine::Error(code) => {
                    return Err(
                        self.rejected(format!("error:{code} ({}) to `{shown}`", error_text(code)))
                    )
                }
                ControllerLine::Alarm(code) => {
                    return Err(self.alarm(code, &format!(" after `{shown}`")))
                }
                ControllerLine::Banner { .. } => {
                    return Err(DeviceError::Protocol {
                        device: self.cfg.id.clone(),
                        message: format!("controller reset while waiting for `ok` to `{shown}`"),
                    })
                }
                _ => {}
            }
        }
    }

    /// Dwell on the controller (G4); the `ok` comes after the dwell ends.
    pub async fn dwell(&mut self, dwell_s: f64) -> Result<(), DeviceError> {
        check_seconds(&self.cfg.id, "dwell", dwell_s)?;
        let line = format_dwell(dwell_s);
        self.send_line(&line, self.cfg.ack_timeout_s + dwell_s)
            .await
    }

    /// Soft reset (Ctrl-X): aborts motion and waits for the banner. Clears the commanded
    /// target, since the controller forgets what it was doing.
    pub async fn soft_reset(&mut self) -> Result<(), DeviceError> {
        self.write_all(&[SOFT_RESET]).await?;
        self.commanded = [None; N_AXES];
        self.alarm_pending = None;
        self.last_status = None;
        self.framer.clear();
        self.lines.clear();
        let deadline = Instant::now() + Duration::from_secs_f64(self.cfg.ack_timeout_s);
        loop {
            if let ControllerLine::Banner { .. } = self
                .next_line(deadline, "banner after soft reset", self.cfg.ack_timeout_s)
                .await?
            {
                return Ok(());
            }
        }
    }

    async fn query_status(&mut self) -> Result<(), DeviceError> {
        self.last_query = Some(Instant::now());
        self.status_queries += 1;
        self.write_all(&[STATUS_QUERY]).await?;
        let t = self.cfg.status_timeout_s;
        let deadline = Instant::now() + Duration::from_secs_f64(t.max(0.0));
        loop {
            match self.next_line(deadline, "status report to `?`", t).await? {
                ControllerLine::Status(_) => return Ok(()),
                ControllerLine::Alarm(code) => return Err(self.alarm(code, "")),
                ControllerLine::Banner { .. } => {
                    return Err(DeviceError::Protocol {
                        device: self.cfg.id.clone(),
                        message: "controller reset (banner) while polling status".into(),
                    })
                }
                // Late `ok`/`error:` of an earlier line: already reported or timed out.
                _ => {}
            }
        }
    }

    fn evaluate(&mut self, s: &StatusReport) -> Result<MachineState, DeviceError> {
        if s.state == GrblState::Alarm {
            return Err(self.alarm(self.last_alarm.unwrap_or(0), " (status Alarm)"));
        }
        // Work position per axis in `LETTERS` order; None for a rotary axis not reported.
        let machine_offset = |k: usize| match s.frame {
            PosFrame::Work => 0.0,
            PosFrame::Machine if k < 3 => self.wco_m[k],
            PosFrame::Machine => self.wco_rotary_rad.get(k - 3).copied().unwrap_or(0.0),
        };
        let work: [Option<f64>; N_AXES] = std::array::from_fn(|k| {
            let reported = if k < 3 {
                Some(s.position_m[k])
            } else {
                s.rotary_rad.get(k - 3).copied()
            };
            reported.map(|v| v - machine_offset(k))
        });
        if let Some((name, &k)) = self.axis_index.iter().find(|(_, &k)| work[k].is_none()) {
            return Err(DeviceError::Protocol {
                device: self.cfg.id.clone(),
                message: format!(
                    "the status report has no axis {} (axis {name:?}): the controller reports {} axes",
                    LETTERS[k],
                    3 + s.rotary_rad.len()
                ),
            });
        }
        let tolerance = |k: usize| {
            if k < 3 {
                self.cfg.position_tolerance_m
            } else {
                self.cfg.position_tolerance_rad
            }
        };
        let arrived =
            self.commanded.iter().enumerate().all(|(k, c)| {
                c.is_none_or(|c| work[k].is_some_and(|p| (c - p).abs() <= tolerance(k)))
            });
        if s.state == GrblState::Idle && arrived {
            let position = self
                .axis_index
                .iter()
                .filter_map(|(name, &k)| work[k].map(|v| (name.clone(), v)))
                .collect();
            Ok(MachineState::Idle { position })
        } else {
            Ok(MachineState::Moving)
        }
    }
}

#[async_trait]
impl<S: AsyncRead + AsyncWrite + Unpin + Send> Machine for GrblMachine<S> {
    fn id(&self) -> &str {
        &self.cfg.id
    }

    /// Send the move; after a lost port, reconnect and send it again.
    async fn start_move(&mut self, target: &AxisPositions) -> Result<(), DeviceError> {
        match self.start_move_once(target).await {
            Err(e @ DeviceError::Disconnected { .. }) => {
                self.reconnect(e).await?;
                self.start_move_once(target).await
            }
            r => r,
        }
    }

    /// The motion state; after a lost port, reconnect, re-send the last move (the
    /// controller reset and stopped) and report Moving.
    async fn state(&mut self) -> Result<MachineState, DeviceError> {
        match self.state_once().await {
            Err(e @ DeviceError::Disconnected { .. }) => {
                self.reconnect(e).await?;
                self.resend_last_move().await?;
                Ok(MachineState::Moving)
            }
            r => r,
        }
    }

    /// `$X`: leave the alarm state (the emulator and GRBL without homing lock accept it).
    async fn unlock(&mut self) -> Result<(), DeviceError> {
        self.send_line("$X\n", self.cfg.ack_timeout_s).await?;
        self.last_alarm = None;
        self.alarm_pending = None;
        self.last_status = None;
        self.last_query = None;
        Ok(())
    }

    fn take_link_faults(&mut self) -> Vec<LinkFault> {
        std::mem::take(&mut self.link_faults)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn config_defaults_and_unknown_keys() {
        let c: GrblConfig = serde_json::from_str(r#"{"port": "/dev/ttyUSB0"}"#).expect("config");
        assert_eq!(c.baud, 115_200);
        assert_eq!(c.axis_letters["z"], 'Z');
        assert!(serde_json::from_str::<GrblConfig>(r#"{"port": "p", "feed": 1}"#).is_err());
        let bad = GrblConfig {
            ack_timeout_s: f64::INFINITY,
            ..GrblConfig::default()
        };
        assert!(bad.validate().is_err());
        let twice = GrblConfig {
            axis_letters: [("a".to_string(), 'X'), ("b".to_string(), 'x')].into(),
            ..GrblConfig::default()
        };
        assert!(GrblMachine::from_stream(tokio::io::empty(), twice).is_err());
    }
}
