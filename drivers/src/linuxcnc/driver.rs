//! LinuxCNC machine driver over linuxcncrsh (TCP): owns the connection and the timing (reply
//! time-outs, status polling, rate limiting, reconnects) and implements `Machine` on top of the
//! sans-I/O codec. Moves are MDI lines in machine coordinates (`G53`); `start_move` returns
//! once linuxcncrsh acknowledged the line and `state` polls the interpreter and the position.

use std::collections::{BTreeMap, VecDeque};
use std::future::Future;
use std::io;
use std::path::{Path, PathBuf};
use std::pin::Pin;
use std::sync::Arc;
use std::time::Duration;

use async_trait::async_trait;
use serde::{Deserialize, Serialize};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio::time::Instant;

use super::codec::{
    decode_error, decode_homed, decode_linear_units_mm, decode_mode, decode_on_off,
    decode_positions, decode_program_codes, decode_program_status, format_move, parse_reply,
    ModalCodes, Mode, MoveKind, ProgramStatus, Query, Reply, Request, MAX_LINE_BYTES, MM_PER_M,
};
use crate::grbl::codec::{Framed, LineFramer};
use crate::serial::check_seconds;
use crate::traits::{AxisPositions, DeviceError, LinkFault, Machine, MachineState};

/// Axis letters in the order linuxcncrsh reports positions (`ABS_ACT_POS x y z a b c ...`).
const LETTERS: [char; 6] = ['X', 'Y', 'Z', 'A', 'B', 'C'];
const N_AXES: usize = LETTERS.len();

/// `DeviceError::Alarm` codes of this driver (LinuxCNC has no alarm numbers of its own).
pub const ALARM_ESTOP: u16 = 1;
/// The machine was turned off (a following error, an amplifier fault, the operator).
pub const ALARM_MACHINE_OFF: u16 = 2;
/// How long `set machine on` may take to show before the E-stop is cycled.
const MACHINE_ON_SETTLE: Duration = Duration::from_secs(3);
/// How long a stop caused elsewhere takes to show in full: linuxcncrsh reports another
/// client's `set estop on` as machine off first and as E-stop about 0.3 s later.
const STOP_SETTLE: Duration = Duration::from_secs(1);
/// How `stopped_state` names the two stops.
const IN_ESTOP: &str = "in E-stop";
const POWERED_OFF: &str = "powered off (machine off)";
/// LinuxCNC's joint limit (`EMCMOT_MAX_JOINTS`).
const MAX_JOINTS: usize = 16;

/// Opens a new connection to linuxcncrsh: by host and port (`tcp_connector`), or by whatever
/// the caller needs (e.g. a socket opened inside another network namespace).
pub type StreamConnector =
    Arc<dyn Fn() -> Pin<Box<dyn Future<Output = io::Result<TcpStream>> + Send>> + Send + Sync>;

/// A connector to `host:port`.
pub fn tcp_connector(host: &str, port: u16) -> StreamConnector {
    let host = host.to_string();
    Arc::new(move || {
        let host = host.clone();
        Box::pin(async move { TcpStream::connect((host.as_str(), port)).await })
    })
}

/// Whether the driver may home LinuxCNC's joints itself (`set home -1`) when they are not
/// homed: homing moves the axes to their switches, so a real machine's config must say so.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum HomePolicy {
    Allow,
    #[default]
    Refuse,
}

/// How moves are commanded.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MoveMode {
    /// `G1` at `feed_m_s`.
    #[default]
    Feed,
    /// `G0` at the machine's rapid rate (`feed_m_s` unused).
    Rapid,
}

/// How a LinuxCNC machine is reached and driven. Lives in the machine's TOML config
/// (`[devices.machine.linuxcnc]`); the passwords live in `password_file`, never here.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LinuxCncConfig {
    #[serde(default = "default_id")]
    pub id: String,
    /// Host running linuxcncrsh (its `[DISPLAY] DISPLAY = linuxcncrsh` or `loadusr linuxcncrsh`).
    #[serde(default)]
    pub host: String,
    /// linuxcncrsh's port (`--port`), 5007 by default.
    #[serde(default = "default_port")]
    pub port: u16,
    /// A TOML file with `connect = "..."` and `enable = "..."`: linuxcncrsh's connect and
    /// enable passwords (`--connectpw`, `--enablepw`). Readable by its owner only. Without it
    /// LinuxCNC's defaults (`EMC`, `EMCTOO`) are used.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub password_file: Option<PathBuf>,
    /// The client name sent in `hello` (no spaces).
    #[serde(default = "default_client_name")]
    pub client_name: String,
    /// Home the joints when they are not homed (`allow`), or refuse to run (`refuse`).
    #[serde(default)]
    pub home: HomePolicy,
    /// LinuxCNC's joint count (`[KINS] JOINTS`); joints 0..joints must be homed. linuxcncrsh
    /// reports six homed flags whatever the machine has, so without this key the driver reads
    /// `[KINS] JOINTS` from the INI file LinuxCNC names (`get inifile`), which works when
    /// geocal runs on the LinuxCNC computer; elsewhere the key is required.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub joints: Option<usize>,
    /// At the start of a run, release LinuxCNC's E-stop and turn the machine on when they are
    /// found so (false: refuse to start, the operator does it at the machine). Never during a
    /// run: an E-stop or machine-off geocal did not cause stops the run.
    #[serde(default)]
    pub power_on: bool,
    #[serde(default)]
    pub motion: MoveMode,
    /// Feed of every `G1` move, m/s (a run takes `devices.machine.feed_m_s`).
    #[serde(default = "default_feed_m_s")]
    pub feed_m_s: f64,
    /// Longest wait for the reply to one request, seconds. `set` requests are answered once
    /// LinuxCNC's task received them (a few servo-to-task cycles).
    #[serde(default = "default_reply_timeout_s")]
    pub reply_timeout_s: f64,
    /// Longest wait for homing all joints, seconds.
    #[serde(default = "default_home_timeout_s")]
    pub home_timeout_s: f64,
    /// Minimum time between two status polls, seconds; `state()` returns the last answer
    /// in between.
    #[serde(default = "default_status_interval_s")]
    pub status_interval_s: f64,
    /// The machine counts as arrived when LinuxCNC's interpreter is idle and the actual
    /// position is within this distance of the target on every commanded axis, metres.
    #[serde(default = "default_tolerance_m")]
    pub position_tolerance_m: f64,
    /// The machine counts as standing while every axis stays within this distance of where
    /// it stood: a few counts of the position feedback, so that its noise is not motion,
    /// metres.
    #[serde(default = "default_standstill_band_m")]
    pub standstill_band_m: f64,
    /// LinuxCNC idle short of the target without an error for this long is reported as a
    /// stalled move, seconds.
    #[serde(default = "default_stall_s")]
    pub stall_timeout_s: f64,
    /// After the connection is lost, keep trying to reconnect for this long, seconds;
    /// 0 = do not reconnect.
    #[serde(default = "default_reconnect_timeout_s")]
    pub reconnect_timeout_s: f64,
    /// geocal axis name -> LinuxCNC axis letter (X, Y, Z, A, B, C).
    #[serde(default = "default_axis_letters")]
    pub axis_letters: BTreeMap<String, char>,
    /// Refused: passwords do not belong in a configuration that is stored with every session.
    #[serde(default, skip_serializing)]
    pub connect_password: Option<String>,
    /// Refused, as `connect_password`.
    #[serde(default, skip_serializing)]
    pub enable_password: Option<String>,
}

fn default_id() -> String {
    "linuxcnc".into()
}
fn default_port() -> u16 {
    5007
}
fn default_client_name() -> String {
    "geocal".into()
}
fn default_feed_m_s() -> f64 {
    0.01
}
fn default_reply_timeout_s() -> f64 {
    5.0
}
fn default_home_timeout_s() -> f64 {
    120.0
}
fn default_status_interval_s() -> f64 {
    0.05
}
fn default_tolerance_m() -> f64 {
    1e-6
}
fn default_standstill_band_m() -> f64 {
    0.25e-6
}
fn default_stall_s() -> f64 {
    2.0
}
fn default_reconnect_timeout_s() -> f64 {
    10.0
}
fn default_axis_letters() -> BTreeMap<String, char> {
    [("x", 'X'), ("y", 'Y'), ("z", 'Z')]
        .into_iter()
        .map(|(n, l)| (n.to_string(), l))
        .collect()
}

impl Default for LinuxCncConfig {
    fn default() -> Self {
        Self {
            id: default_id(),
            host: String::new(),
            port: default_port(),
            password_file: None,
            client_name: default_client_name(),
            home: HomePolicy::default(),
            joints: None,
            power_on: false,
            motion: MoveMode::default(),
            feed_m_s: default_feed_m_s(),
            reply_timeout_s: default_reply_timeout_s(),
            home_timeout_s: default_home_timeout_s(),
            status_interval_s: default_status_interval_s(),
            position_tolerance_m: default_tolerance_m(),
            standstill_band_m: default_standstill_band_m(),
            stall_timeout_s: default_stall_s(),
            reconnect_timeout_s: default_reconnect_timeout_s(),
            axis_letters: default_axis_letters(),
            connect_password: None,
            enable_password: None,
        }
    }
}

impl LinuxCncConfig {
    /// Reject values the driver cannot work with (and passwords written inline).
    pub fn validate(&self) -> Result<(), DeviceError> {
        let bad = |message: String| DeviceError::Protocol {
            device: self.id.clone(),
            message,
        };
        for (key, given) in [
            ("connect_password", &self.connect_password),
            ("enable_password", &self.enable_password),
        ] {
            if given.is_some() {
                return Err(bad(format!(
                    "{key}: passwords are not written in the configuration (it is stored with \
                     every session); put `connect` and `enable` in the file named by password_file"
                )));
            }
        }
        for (name, v) in [
            ("reply_timeout_s", self.reply_timeout_s),
            ("home_timeout_s", self.home_timeout_s),
            ("status_interval_s", self.status_interval_s),
            ("stall_timeout_s", self.stall_timeout_s),
            ("reconnect_timeout_s", self.reconnect_timeout_s),
        ] {
            check_seconds(&self.id, name, v)?;
        }
        if self.motion == MoveMode::Feed && !(self.feed_m_s.is_finite() && self.feed_m_s > 0.0) {
            return Err(bad(format!(
                "feed_m_s must be positive, got {}",
                self.feed_m_s
            )));
        }
        for (name, v) in [
            ("position_tolerance_m", self.position_tolerance_m),
            ("standstill_band_m", self.standstill_band_m),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(bad(format!("{name} must be >= 0, got {v}")));
            }
        }
        if let Some(joints) = self.joints.filter(|j| !(1..=MAX_JOINTS).contains(j)) {
            return Err(bad(format!(
                "joints must be between 1 and {MAX_JOINTS}, got {joints}"
            )));
        }
        if self.client_name.is_empty() || !self.client_name.bytes().all(|b| b.is_ascii_graphic()) {
            return Err(bad(format!(
                "client_name must be printable ASCII without spaces, got {:?}",
                self.client_name
            )));
        }
        axis_index(self)?;
        Ok(())
    }
}

/// geocal axis name -> index into `LETTERS`.
fn axis_index(cfg: &LinuxCncConfig) -> Result<BTreeMap<String, usize>, DeviceError> {
    let mut index = BTreeMap::new();
    let mut used = [false; N_AXES];
    for (name, letter) in &cfg.axis_letters {
        let k = LETTERS
            .iter()
            .position(|l| l.eq_ignore_ascii_case(letter))
            .ok_or_else(|| DeviceError::Protocol {
                device: cfg.id.clone(),
                message: format!("axis {name:?}: letter {letter:?} is not X, Y, Z, A, B or C"),
            })?;
        if k >= 3 {
            return Err(DeviceError::Protocol {
                device: cfg.id.clone(),
                message: format!(
                    "axis {name:?}: rotary axis {letter:?} is not driven by this driver yet (X, Y, Z)"
                ),
            });
        }
        if std::mem::replace(&mut used[k], true) {
            return Err(DeviceError::Protocol {
                device: cfg.id.clone(),
                message: format!("axis letter {letter:?} mapped twice"),
            });
        }
        index.insert(name.clone(), k);
    }
    Ok(index)
}

/// linuxcncrsh's connect and enable passwords. Never printed.
#[derive(Clone, PartialEq, Eq)]
pub struct Passwords {
    connect: String,
    enable: String,
}

impl std::fmt::Debug for Passwords {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Passwords(***)")
    }
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct PasswordFile {
    connect: String,
    enable: String,
}

impl Passwords {
    pub fn new(connect: &str, enable: &str) -> Self {
        Self {
            connect: connect.into(),
            enable: enable.into(),
        }
    }

    /// LinuxCNC's defaults (`EMC`, `EMCTOO`): what linuxcncrsh accepts without
    /// `--connectpw`/`--enablepw`.
    pub fn linuxcnc_defaults() -> Self {
        Self::new("EMC", "EMCTOO")
    }

    /// Read a password file (TOML: `connect = "..."`, `enable = "..."`), which only its owner
    /// may read or write.
    pub fn load(device: &str, path: &Path) -> Result<Self, DeviceError> {
        let bad = |message: String| DeviceError::Rejected {
            device: device.to_string(),
            message: format!("password file {}: {message}", path.display()),
        };
        let meta = std::fs::metadata(path).map_err(|e| bad(format!("cannot read it: {e}")))?;
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let mode = meta.permissions().mode();
            if mode & 0o077 != 0 {
                return Err(bad(format!(
                    "readable or writable by others (mode {:o}): chmod 600 it",
                    mode & 0o777
                )));
            }
        }
        #[cfg(not(unix))]
        let _ = meta;
        let text =
            std::fs::read_to_string(path).map_err(|e| bad(format!("cannot read it: {e}")))?;
        // The parse error would quote the offending line, i.e. a password: say where only.
        let file: PasswordFile = toml::from_str(&text).map_err(|e| {
            let at = e
                .span()
                .map(|s| format!(" at byte {}", s.start))
                .unwrap_or_default();
            bad(format!(
                "expected TOML with the keys `connect` and `enable` (strings){at}"
            ))
        })?;
        Ok(Self::new(&file.connect, &file.enable))
    }
}

/// A LinuxCNC machine driven over linuxcncrsh.
pub struct LinuxCncMachine {
    cfg: LinuxCncConfig,
    connector: StreamConnector,
    passwords: Passwords,
    io: TcpStream,
    framer: LineFramer,
    lines: VecDeque<String>,
    axis_index: BTreeMap<String, usize>,
    /// Millimetres per LinuxCNC user unit (`get user_linear_units`).
    mm_per_unit: f64,
    /// Last commanded absolute target per axis in `LETTERS` order, metres.
    commanded: [Option<f64>; N_AXES],
    /// The last MDI move line sent (re-sent after a reconnect of `start_move`).
    last_move: Option<String>,
    /// When the last move was accepted; LinuxCNC idle short of it for `stall_timeout_s`
    /// after that is a stalled move.
    idle_short_since: Option<Instant>,
    /// When the last move was accepted (`SET MDI ACK`).
    move_accepted_at: Option<Instant>,
    /// Since when LinuxCNC reports the move running while the machine stands at its target,
    /// and where it stood (a move still creeping beyond `standstill_band_m` is not standing).
    running_at_target_since: Option<(Instant, [Option<f64>; N_AXES])>,
    last_state: Option<MachineState>,
    last_poll: Option<Instant>,
    server: String,
    requests: u64,
    status_polls: u64,
    link_faults: Vec<LinkFault>,
    /// Connected for watching only (no `set enable`).
    observer: bool,
    /// What the run found LinuxCNC in: set back at its end, on a stop and on a refusal.
    found: Option<Found>,
    /// Joints 0..joints must be homed (the config's `joints` or the INI's `[KINS] JOINTS`).
    joints: usize,
    /// A move line stated G90/G94 where the operator had G91/G93/G95: set back at arrival.
    modes_changed: bool,
    /// An exchange was abandoned between its request and its reply (its future dropped).
    reply_owed: bool,
}

/// The controller's state as a run found it.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Found {
    mode: Mode,
    codes: ModalCodes,
    estop: bool,
    machine_on: bool,
}

/// What linuxcncrsh reports of the machine (`LinuxCncMachine::status`).
#[derive(Debug, Clone, PartialEq)]
pub struct ControllerStatus {
    pub estop: bool,
    pub machine_on: bool,
    pub program: ProgramStatus,
    /// Actual position of X, Y, Z in machine coordinates, metres (nominal: without a
    /// compensation table's trim).
    pub position_m: [f64; 3],
}

impl LinuxCncMachine {
    /// Connect to `host:port` from the config, with the passwords of its `password_file`.
    pub async fn connect(cfg: LinuxCncConfig) -> Result<Self, DeviceError> {
        if cfg.host.is_empty() {
            return Err(DeviceError::Protocol {
                device: cfg.id.clone(),
                message: "host is empty: name the machine running linuxcncrsh".into(),
            });
        }
        let connector = tcp_connector(&cfg.host, cfg.port);
        Self::connect_with(cfg, connector).await
    }

    /// Connect through `connector` (host and port of the config unused), with the passwords
    /// of the config's `password_file` (LinuxCNC's defaults without one).
    pub async fn connect_with(
        cfg: LinuxCncConfig,
        connector: StreamConnector,
    ) -> Result<Self, DeviceError> {
        cfg.validate()?;
        let passwords = match &cfg.password_file {
            Some(path) => Passwords::load(&cfg.id, path)?,
            None => Passwords::linuxcnc_defaults(),
        };
        Self::connect_with_passwords(cfg, connector, passwords).await
    }

    /// Connect through `connector` with the given passwords: `hello`, enable, then the start
    /// of a run (`begin_run`).
    pub async fn connect_with_passwords(
        cfg: LinuxCncConfig,
        connector: StreamConnector,
        passwords: Passwords,
    ) -> Result<Self, DeviceError> {
        let mut machine = Self::open(cfg, connector, passwords, false).await?;
        machine.begin_run().await?;
        Ok(machine)
    }

    /// The start of a run: note the controller's state (mode, units, distance and feed mode),
    /// check everything that could refuse the run (joints homed as `home` allows, E-stop and
    /// machine power as `power_on` allows), and only then release the E-stop and power on
    /// (if allowed), home (if allowed) and enter MDI mode. A refusal leaves LinuxCNC as found.
    pub async fn begin_run(&mut self) -> Result<(), DeviceError> {
        self.found = None;
        self.modes_changed = false;
        let found = Found {
            mode: self.mode().await?,
            codes: self.program_codes().await?,
            estop: self.get_on_off(Query::Estop).await?,
            machine_on: self.get_on_off(Query::Machine).await?,
        };
        self.found = Some(found);
        let r = self.check_and_prepare().await;
        if let Err(e) = r {
            // Best effort, the first error being the one worth reporting: the mode as found,
            // and the E-stop pressed again (or the machine off) if this start released it.
            let _ = self.leave_as_found().await;
            if found.estop && !self.get_on_off(Query::Estop).await.unwrap_or(true) {
                let _ = self.set(&Request::Estop(true)).await;
            } else if !found.machine_on && self.get_on_off(Query::Machine).await.unwrap_or(false) {
                let _ = self.set(&Request::Machine(false)).await;
            }
            return Err(e);
        }
        Ok(())
    }

    async fn check_and_prepare(&mut self) -> Result<(), DeviceError> {
        self.joints = self.joint_count().await?;
        let unhomed = self.unhomed_joints().await?;
        if !unhomed.is_empty() && self.cfg.home == HomePolicy::Refuse {
            return Err(self.rejected(format!(
                "LinuxCNC's joints {unhomed:?} are not homed and home = \"refuse\": home the \
                 machine at its console, or set home = \"allow\" to let geocal home all joints"
            )));
        }
        let (estop, machine_on) = self
            .found
            .map_or((true, false), |f| (f.estop, f.machine_on));
        if (estop || !machine_on) && !self.cfg.power_on {
            let what = if estop {
                "in E-stop"
            } else {
                "powered off (machine off)"
            };
            return Err(self.rejected(format!(
                "LinuxCNC is {what}: release the E-stop and turn the machine on at the machine, \
                 then start again (geocal does so itself only with power_on = true in \
                 [devices.machine.linuxcnc])"
            )));
        }
        self.power_up().await?;
        self.ensure_homed().await?;
        self.ensure_mdi().await
    }

    /// The interpreter's units, distance and feed mode.
    async fn program_codes(&mut self) -> Result<ModalCodes, DeviceError> {
        let value = self.get(Query::ProgramCodes).await?;
        decode_program_codes(&value).map_err(|e| self.protocol(format!("`get program_codes`: {e}")))
    }

    /// The joint count: the config's `joints`, else `[KINS] JOINTS` of the INI file LinuxCNC
    /// names (linuxcncrsh itself reports six joints whatever the machine has).
    async fn joint_count(&mut self) -> Result<usize, DeviceError> {
        if let Some(joints) = self.cfg.joints {
            return Ok(joints);
        }
        let path = self.get(Query::IniFile).await?;
        let path = path.trim();
        let text = std::fs::read_to_string(path).map_err(|e| {
            self.rejected(format!(
                "the joint count: linuxcncrsh reports six joints whatever the machine has, so \
                 geocal reads [KINS] JOINTS from LinuxCNC's INI file, {path} (`get inifile`), \
                 which cannot be read here ({e}): set `joints` in [devices.machine.linuxcnc]"
            ))
        })?;
        ini_joints(&text).ok_or_else(|| {
            self.rejected(format!(
                "the joint count: LinuxCNC's INI file {path} has no [KINS] JOINTS between 1 and \
                 {MAX_JOINTS}: set `joints` in [devices.machine.linuxcnc]"
            ))
        })
    }

    /// Set back what the run changed, as found at its start: geocal's own move still under
    /// way is stopped (`set abort`: a cancelled run ends there), then the interpreter's modal
    /// codes (units, distance and feed mode, motion mode, feed rate; one MDI line) and the
    /// task mode. LinuxCNC refuses both in E-stop or with the machine off: then an error says
    /// what stays changed.
    pub async fn leave_as_found(&mut self) -> Result<(), DeviceError> {
        let Some(found) = self.found else {
            return Ok(());
        };
        if self.observer {
            return Ok(());
        }
        let stopped =
            self.get_on_off(Query::Estop).await? || !self.get_on_off(Query::Machine).await?;
        if !stopped
            && self.last_move.is_some()
            && self.program_status().await? != ProgramStatus::Idle
        {
            self.abort().await?;
            self.wait_program_idle("`set abort` to stop geocal's move")
                .await?;
        }
        let now = self.program_codes().await?;
        let restore = found.codes.words_to_restore(&now);
        let mode = self.mode().await?;
        if restore.is_none() && mode == found.mode {
            return Ok(());
        }
        if stopped {
            return Err(self.rejected(format!(
                "LinuxCNC is in E-stop or off, where it refuses mode changes and MDI: it stays \
                 in mode {mode:?}{} (found: mode {:?})",
                restore
                    .as_deref()
                    .map(|w| format!(" without `{w}`"))
                    .unwrap_or_default(),
                found.mode,
            )));
        }
        if let Some(words) = restore {
            self.restore_modal_codes(&words).await?;
        }
        if mode != found.mode || self.mode().await? != found.mode {
            self.ensure_mode(found.mode).await?;
        }
        Ok(())
    }

    async fn program_status(&mut self) -> Result<ProgramStatus, DeviceError> {
        let value = self.get(Query::ProgramStatus).await?;
        decode_program_status(&value)
            .map_err(|e| self.protocol(format!("`get program_status`: {e}")))
    }

    /// Wait (up to `reply_timeout_s`) until the interpreter is idle.
    async fn wait_program_idle(&mut self, what: &str) -> Result<(), DeviceError> {
        let deadline = Instant::now() + Duration::from_secs_f64(self.cfg.reply_timeout_s);
        while self.program_status().await? != ProgramStatus::Idle {
            if Instant::now() >= deadline {
                return Err(DeviceError::Timeout {
                    device: self.cfg.id.clone(),
                    what: what.to_string(),
                    after_s: self.cfg.reply_timeout_s,
                });
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        Ok(())
    }

    /// Send the MDI line that sets the operator's distance/feed mode again and wait until the
    /// interpreter took it.
    async fn restore_modal_codes(&mut self, words: &str) -> Result<(), DeviceError> {
        self.ensure_mdi().await?;
        self.set(&Request::Mdi(words.to_string())).await?;
        self.wait_program_idle(&format!("`set mdi {words}` to finish"))
            .await?;
        if let Some(e) = self.error_text().await? {
            return Err(self.rejected(format!("LinuxCNC refused `set mdi {words}`: {e}")));
        }
        self.modes_changed = false;
        Ok(())
    }

    /// Connect for watching only (`geocal monitor`): `hello` with the connect password, no
    /// enable, nothing commanded; `status` reads the machine. Commands are refused by
    /// linuxcncrsh (`SET ... NAK`).
    pub async fn observe_with(
        cfg: LinuxCncConfig,
        connector: StreamConnector,
    ) -> Result<Self, DeviceError> {
        cfg.validate()?;
        let passwords = match &cfg.password_file {
            Some(path) => Passwords::load(&cfg.id, path)?,
            None => Passwords::linuxcnc_defaults(),
        };
        Self::open(cfg, connector, passwords, true).await
    }

    async fn open(
        cfg: LinuxCncConfig,
        connector: StreamConnector,
        passwords: Passwords,
        observer: bool,
    ) -> Result<Self, DeviceError> {
        cfg.validate()?;
        let axis_index = axis_index(&cfg)?;
        let io = open_stream(&cfg, &connector).await?;
        let mut machine = Self {
            cfg,
            connector,
            passwords,
            io,
            framer: LineFramer::new(MAX_LINE_BYTES),
            lines: VecDeque::new(),
            axis_index,
            mm_per_unit: 1.0,
            commanded: [None; N_AXES],
            last_move: None,
            idle_short_since: None,
            move_accepted_at: None,
            running_at_target_since: None,
            last_state: None,
            last_poll: None,
            server: String::new(),
            requests: 0,
            status_polls: 0,
            link_faults: Vec::new(),
            observer,
            found: None,
            joints: 0,
            modes_changed: false,
            reply_owed: false,
        };
        machine.handshake().await?;
        if !machine.observer {
            machine.enable().await?;
        }
        Ok(machine)
    }

    pub fn config(&self) -> &LinuxCncConfig {
        &self.cfg
    }

    /// linuxcncrsh's server name and protocol version from `HELLO ACK`.
    pub fn server(&self) -> &str {
        &self.server
    }

    /// Millimetres per LinuxCNC linear user unit (1 for a mm machine, 25.4 for inch).
    pub fn mm_per_unit(&self) -> f64 {
        self.mm_per_unit
    }

    /// Requests sent so far (for tests of the rate limit and for diagnostics).
    pub fn requests(&self) -> u64 {
        self.requests
    }

    /// Status polls (`get program_status`) sent so far.
    pub fn status_polls(&self) -> u64 {
        self.status_polls
    }

    fn disconnected(&self, message: String) -> DeviceError {
        DeviceError::Disconnected {
            device: self.cfg.id.clone(),
            message,
        }
    }

    fn rejected(&self, message: String) -> DeviceError {
        DeviceError::Rejected {
            device: self.cfg.id.clone(),
            message,
        }
    }

    fn protocol(&self, message: String) -> DeviceError {
        DeviceError::Protocol {
            device: self.cfg.id.clone(),
            message,
        }
    }

    /// `hello`, verbose on (every `set` is answered), echo off, units; then the error queue is
    /// emptied (old errors are not this run's). Control (`enable`) is taken apart.
    async fn handshake(&mut self) -> Result<(), DeviceError> {
        let hello = Request::Hello {
            password: self.passwords.connect.clone(),
            client: self.cfg.client_name.clone(),
        };
        match self.exchange(&hello).await? {
            Reply::HelloAck { server, version } => self.server = format!("{server} {version}"),
            Reply::HelloNak => {
                return Err(self.rejected(
                    "linuxcncrsh refused the connect password (HELLO NAK): check `connect` in \
                     password_file against linuxcncrsh's --connectpw"
                        .into(),
                ))
            }
            other => return Err(self.unexpected(&hello, &other)),
        }
        self.set(&Request::Verbose(true)).await?;
        self.set(&Request::Echo(false)).await?;
        let units = self.get(Query::UserLinearUnits).await?;
        self.mm_per_unit = decode_linear_units_mm(&units)
            .map_err(|e| self.protocol(format!("`get user_linear_units`: {e}")))?;
        self.drain_errors().await?;
        Ok(())
    }

    /// `set enable <password>`: this connection commands the machine (taking control from
    /// any other linuxcncrsh client); then `set set_wait received`.
    async fn enable(&mut self) -> Result<(), DeviceError> {
        let enable = Request::Enable {
            password: self.passwords.enable.clone(),
        };
        match self.exchange(&enable).await? {
            Reply::SetAck(k) if k == "ENABLE" => {}
            Reply::SetNak(k) if k == "ENABLE" => {
                return Err(self.rejected(
                    "linuxcncrsh refused the enable password (SET ENABLE NAK): check `enable` in \
                     password_file against linuxcncrsh's --enablepw"
                        .into(),
                ))
            }
            other => return Err(self.unexpected(&enable, &other)),
        }
        // `start_move` must return once the move is accepted, not when it ends; the setting
        // is linuxcncrsh's, shared by all clients.
        self.set(&Request::WaitReceived).await
    }

    /// Out of E-stop, machine on (only at the start of a run, and only with `power_on`).
    async fn power_up(&mut self) -> Result<(), DeviceError> {
        if self.get_on_off(Query::Estop).await? {
            self.set(&Request::Estop(false)).await?;
            if self.settle_on_off(Query::Estop, false).await? {
                let why = self.error_text().await?.unwrap_or_default();
                return Err(self.rejected(format!(
                    "LinuxCNC stays in E-stop after `set estop off` (an external E-stop chain is \
                     open?) {why}"
                )));
            }
        }
        if !self.get_on_off(Query::Machine).await? {
            self.set(&Request::Machine(true)).await?;
            // After an E-stop in the middle of a fast move LinuxCNC 2.9 enables motion and
            // drops it at once ("Motion enabled after reaching a coordinate soft limit with
            // active external offsets"), every time; an E-stop cycle clears that.
            if !self
                .settle_on_off_within(Query::Machine, true, MACHINE_ON_SETTLE)
                .await?
            {
                let why = self.error_text().await?.unwrap_or_default();
                self.link_faults.push(LinkFault {
                    code: "machine_on".into(),
                    message: format!(
                        "LinuxCNC's machine stayed off after `set machine on` {why}; cycling \
                         E-stop (on, off) and turning it on again"
                    ),
                });
                self.set(&Request::Estop(true)).await?;
                self.settle_on_off(Query::Estop, true).await?;
                self.set(&Request::Estop(false)).await?;
                self.settle_on_off(Query::Estop, false).await?;
                self.set(&Request::Machine(true)).await?;
            }
            if !self.settle_on_off(Query::Machine, true).await? {
                let why = self.error_text().await?.unwrap_or_default();
                return Err(self.rejected(format!(
                    "LinuxCNC's machine stays off after `set machine on` {why}"
                )));
            }
        }
        Ok(())
    }

    /// Joints 0..joints homed; homes them (`set home -1`) if the config allows it.
    async fn ensure_homed(&mut self) -> Result<(), DeviceError> {
        let unhomed = self.unhomed_joints().await?;
        if unhomed.is_empty() {
            return Ok(());
        }
        if self.cfg.home == HomePolicy::Refuse {
            return Err(self.rejected(format!(
                "LinuxCNC's joints {unhomed:?} are not homed and home = \"refuse\": home the \
                 machine at its console, or set home = \"allow\" to let geocal home all joints"
            )));
        }
        self.ensure_mode(Mode::Manual).await?;
        self.set(&Request::Home(-1)).await?;
        let deadline = Instant::now() + Duration::from_secs_f64(self.cfg.home_timeout_s);
        loop {
            let unhomed = self.unhomed_joints().await?;
            if unhomed.is_empty() {
                return Ok(());
            }
            if let Some(e) = self.error_text().await? {
                return Err(self.rejected(format!("homing failed: {e}")));
            }
            if Instant::now() >= deadline {
                return Err(DeviceError::Timeout {
                    device: self.cfg.id.clone(),
                    what: format!("homing (joints {unhomed:?} still not homed)"),
                    after_s: self.cfg.home_timeout_s,
                });
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }

    async fn unhomed_joints(&mut self) -> Result<Vec<usize>, DeviceError> {
        let value = self.get(Query::JointHomed).await?;
        let flags =
            decode_homed(&value).map_err(|e| self.protocol(format!("`get joint_homed`: {e}")))?;
        if flags.len() < self.joints {
            return Err(self.protocol(format!(
                "`get joint_homed` reports {} joints, the machine has {}",
                flags.len(),
                self.joints
            )));
        }
        Ok((0..self.joints).filter(|&j| !flags[j]).collect())
    }

    async fn ensure_mdi(&mut self) -> Result<(), DeviceError> {
        self.ensure_mode(Mode::Mdi).await
    }

    /// Switch the task mode if needed and wait until LinuxCNC reports it (a command sent
    /// before would be refused in the old mode).
    async fn ensure_mode(&mut self, want: Mode) -> Result<(), DeviceError> {
        if self.mode().await? == want {
            return Ok(());
        }
        let request = Request::SetMode(want);
        let refused = match self.set(&request).await {
            Err(DeviceError::Rejected { .. }) => true,
            Err(e) => return Err(e),
            Ok(()) => false,
        };
        let deadline = Instant::now() + Duration::from_secs_f64(self.cfg.reply_timeout_s);
        loop {
            let mode = self.mode().await?;
            if mode == want {
                return Ok(());
            }
            if refused || Instant::now() >= deadline {
                // LinuxCNC's own reason, e.g. "all joints must be homed before going into
                // coordinated mode".
                let errors = self.drain_errors().await?;
                let why = if errors.is_empty() {
                    String::new()
                } else {
                    format!(": LinuxCNC says \"{}\"", errors.join("; "))
                };
                let nak = if refused { " (NAK)" } else { "" };
                return Err(self.rejected(format!(
                    "LinuxCNC stays in mode {mode:?} after `{request}`{nak}{why}"
                )));
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }

    async fn mode(&mut self) -> Result<Mode, DeviceError> {
        let value = self.get(Query::Mode).await?;
        decode_mode(&value).map_err(|e| self.protocol(format!("`get mode`: {e}")))
    }

    /// Read `get error` until LinuxCNC says OK (it queues its messages); at most a few.
    async fn drain_errors(&mut self) -> Result<Vec<String>, DeviceError> {
        let mut errors = Vec::new();
        for _ in 0..16 {
            match self.error_text().await? {
                Some(e) => errors.push(e),
                None => break,
            }
        }
        Ok(errors)
    }

    /// The next queued LinuxCNC error message, if any.
    async fn error_text(&mut self) -> Result<Option<String>, DeviceError> {
        Ok(decode_error(&self.get(Query::Error).await?))
    }

    /// Poll an on/off state until it is `want` (a `set` is acknowledged once LinuxCNC's task
    /// received it; its status follows a few cycles later), at most `reply_timeout_s`;
    /// returns the last value.
    async fn settle_on_off(&mut self, q: Query, want: bool) -> Result<bool, DeviceError> {
        let within = Duration::from_secs_f64(self.cfg.reply_timeout_s);
        self.settle_on_off_within(q, want, within).await
    }

    /// `q` once it reads `want`, or as it reads after `within`.
    async fn settle_on_off_within(
        &mut self,
        q: Query,
        want: bool,
        within: Duration,
    ) -> Result<bool, DeviceError> {
        let deadline = Instant::now() + within;
        loop {
            let v = self.get_on_off(q).await?;
            if v == want || Instant::now() >= deadline {
                return Ok(v);
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }

    async fn get_on_off(&mut self, q: Query) -> Result<bool, DeviceError> {
        let value = self.get(q).await?;
        decode_on_off(&value)
            .map_err(|e| self.protocol(format!("`get {}`: {e}", q.key().to_ascii_lowercase())))
    }

    /// Send `get <q>` and return its value.
    async fn get(&mut self, q: Query) -> Result<String, DeviceError> {
        let request = Request::Get(q);
        match self.exchange(&request).await? {
            Reply::Value { key, value } if key == q.key() => Ok(value),
            Reply::GetNak(k) => Err(self.protocol(format!(
                "linuxcncrsh does not answer `{request}` (GET {k} NAK)"
            ))),
            other => Err(self.unexpected(&request, &other)),
        }
    }

    /// Send a `set` request and expect its `SET <SUB> ACK`; a NAK is a rejection.
    async fn set(&mut self, request: &Request) -> Result<(), DeviceError> {
        let key = request.set_key().unwrap_or_default();
        match self.exchange(request).await? {
            Reply::SetAck(k) if k == key => Ok(()),
            Reply::SetNak(k) if k == key || k.is_empty() => {
                Err(self.rejected(format!("LinuxCNC refused `{request}` (SET {key} NAK)")))
            }
            other => Err(self.unexpected(request, &other)),
        }
    }

    fn unexpected(&self, request: &Request, reply: &Reply) -> DeviceError {
        self.protocol(format!(
            "unexpected reply to `{request}`: {}",
            describe_reply(reply)
        ))
    }

    /// Write one request and read its reply (skipping its echo).
    async fn exchange(&mut self, request: &Request) -> Result<Reply, DeviceError> {
        if std::mem::take(&mut self.reply_owed) {
            self.skip_owed_reply().await?;
        }
        let reply = self.exchange_once(request).await;
        self.reply_owed = false;
        reply
    }

    /// Read and drop the reply still owed to an exchange whose future was dropped (LinuxCNC
    /// answers every request), up to `reply_timeout_s`.
    async fn skip_owed_reply(&mut self) -> Result<(), DeviceError> {
        let t = self.cfg.reply_timeout_s;
        let deadline = Instant::now() + Duration::from_secs_f64(t);
        match self
            .next_line(deadline, "the reply to an abandoned request", t)
            .await
        {
            Ok(_) | Err(DeviceError::Timeout { .. }) => Ok(()),
            Err(e) => Err(e),
        }
    }

    async fn exchange_once(&mut self, request: &Request) -> Result<Reply, DeviceError> {
        let line = request
            .encode()
            .map_err(|e| self.rejected(format!("cannot send `{request}`: {e}")))?;
        self.drain().await?;
        // Set from the write to the reply: left set only when this future is dropped (a
        // cancelled run), so that the late reply is not taken for the next request's.
        self.reply_owed = true;
        self.requests += 1;
        let written = async {
            self.io.write_all(line.as_bytes()).await?;
            self.io.flush().await
        }
        .await;
        written.map_err(|e| self.disconnected(format!("write of `{request}` failed: {e}")))?;
        let t = self.cfg.reply_timeout_s;
        let deadline = Instant::now() + Duration::from_secs_f64(t);
        loop {
            let l = self
                .next_line(deadline, &format!("the reply to `{request}`"), t)
                .await?;
            if request.is_echo(&l) {
                continue;
            }
            return Ok(parse_reply(&l));
        }
    }

    fn take_bytes(&mut self, bytes: &[u8]) {
        for f in self.framer.push(bytes) {
            match f {
                Framed::Line(l) => self.lines.push_back(l),
                // A line too long for any reply: make it fail the exchange it lands in.
                Framed::Overlong => self.lines.push_back("(overlong line)".into()),
                Framed::Realtime(_) => {}
            }
        }
    }

    async fn next_line(
        &mut self,
        deadline: Instant,
        what: &str,
        timeout_s: f64,
    ) -> Result<String, DeviceError> {
        let mut buf = [0u8; 1024];
        loop {
            if let Some(l) = self.lines.pop_front() {
                return Ok(l);
            }
            match tokio::time::timeout_at(deadline, self.io.read(&mut buf)).await {
                Err(_) => {
                    return Err(DeviceError::Timeout {
                        device: self.cfg.id.clone(),
                        what: what.to_string(),
                        after_s: timeout_s,
                    })
                }
                Ok(Ok(0)) => {
                    return Err(self.disconnected(format!(
                        "linuxcncrsh closed the connection while waiting for {what}"
                    )))
                }
                Ok(Ok(n)) => self.take_bytes(&buf[..n]),
                Ok(Err(e)) => {
                    return Err(self.disconnected(format!("read failed waiting for {what}: {e}")))
                }
            }
        }
    }

    /// Drop what arrived unasked (late replies of timed-out requests), so that it is not taken
    /// for the answer to the next request.
    async fn drain(&mut self) -> Result<(), DeviceError> {
        let mut buf = [0u8; 1024];
        loop {
            match tokio::time::timeout(Duration::ZERO, self.io.read(&mut buf)).await {
                Err(_) => break,
                Ok(Ok(0)) => {
                    return Err(self.disconnected("linuxcncrsh closed the connection".into()))
                }
                Ok(Ok(n)) => self.take_bytes(&buf[..n]),
                Ok(Err(e)) => return Err(self.disconnected(format!("read failed: {e}"))),
            }
        }
        self.lines.clear();
        Ok(())
    }

    /// Why LinuxCNC does not move: E-stop or machine off (an alarm geocal did not cause and
    /// does not clear: `unlock` refuses until the operator cleared it), else its error message
    /// if it has one.
    async fn fault(&mut self, context: &str) -> Result<Option<DeviceError>, DeviceError> {
        let mut errors = self.drain_errors().await?;
        let mut estop = self.get_on_off(Query::Estop).await?;
        let mut stopped = estop || !self.get_on_off(Query::Machine).await?;
        if !stopped && !self.get_on_off(Query::Enable).await? {
            // Another client took control: an operator's GUI or pendant does so to press
            // E-stop, which shows a few cycles later.
            let deadline = Instant::now() + STOP_SETTLE;
            while !stopped && Instant::now() < deadline {
                tokio::time::sleep(Duration::from_millis(20)).await;
                estop = self.get_on_off(Query::Estop).await?;
                stopped = estop || !self.get_on_off(Query::Machine).await?;
            }
        }
        if stopped {
            // Let the state settle before naming it: another client's E-stop shows as machine
            // off first.
            if !estop {
                estop = self
                    .settle_on_off_within(Query::Estop, true, STOP_SETTLE)
                    .await?;
            }
            errors.extend(self.drain_errors().await?);
        }
        let said = if errors.is_empty() {
            String::new()
        } else {
            format!(" (LinuxCNC: {})", errors.join("; "))
        };
        if stopped {
            let (code, what) = if estop {
                (ALARM_ESTOP, "LinuxCNC went into E-stop")
            } else {
                (ALARM_MACHINE_OFF, "LinuxCNC's machine was turned off")
            };
            return Ok(Some(DeviceError::Alarm {
                device: self.cfg.id.clone(),
                code,
                message: format!(
                    "{what} {context}{said}, not by geocal, which does not release an E-stop \
                     or power a machine on during a run"
                ),
            }));
        }
        if !errors.is_empty() {
            return Ok(Some(self.rejected(format!("{context}:{said}"))));
        }
        if !self.get_on_off(Query::Enable).await? {
            return Ok(Some(self.rejected(format!(
                "{context}: another linuxcncrsh client took control of LinuxCNC (`get enable` \
                 says OFF); geocal does not take it back during a move"
            ))));
        }
        Ok(None)
    }

    /// "in E-stop" or "powered off" while LinuxCNC is stopped (once the state settled), else
    /// None.
    async fn stopped_state(&mut self) -> Result<Option<&'static str>, DeviceError> {
        let mut estop = self.get_on_off(Query::Estop).await?;
        if !estop {
            if self.get_on_off(Query::Machine).await? {
                return Ok(None);
            }
            estop = self
                .settle_on_off_within(Query::Estop, true, STOP_SETTLE)
                .await?;
        }
        Ok(Some(if estop { IN_ESTOP } else { POWERED_OFF }))
    }

    /// Positions of the configured axes (metres) from `get abs_act_pos`.
    async fn actual_position(&mut self) -> Result<[Option<f64>; N_AXES], DeviceError> {
        let value = self.get(Query::AbsActPos).await?;
        let units = decode_positions(&value)
            .map_err(|e| self.protocol(format!("`get abs_act_pos`: {e}")))?;
        let to_m = self.mm_per_unit / MM_PER_M;
        Ok(std::array::from_fn(|k| {
            (k < 3).then(|| units.get(k).map(|u| u * to_m)).flatten()
        }))
    }

    async fn start_move_once(&mut self, target: &AxisPositions) -> Result<(), DeviceError> {
        if self.observer {
            return Err(self.rejected(
                "connected for watching only (`observe_with`): it commands nothing".into(),
            ));
        }
        let mut next = self.commanded;
        let mut words = Vec::new();
        for (name, &pos_m) in target {
            let k = *self
                .axis_index
                .get(name)
                .ok_or_else(|| self.rejected(format!("no LinuxCNC axis mapped to {name:?}")))?;
            if !pos_m.is_finite() {
                return Err(self.rejected(format!("target of axis {name:?} is not finite")));
            }
            words.push((k, pos_m));
            next[k] = Some(pos_m);
        }
        if words.is_empty() {
            return Ok(());
        }
        words.sort_by_key(|&(k, _)| k);
        // G21: the words are mm, whatever LinuxCNC's own units.
        let mm: Vec<(char, f64)> = words
            .iter()
            .map(|&(k, m)| (LETTERS[k], m * MM_PER_M))
            .collect();
        let kind = match self.cfg.motion {
            MoveMode::Feed => MoveKind::feed_m_s(self.cfg.feed_m_s),
            MoveMode::Rapid => MoveKind::Rapid,
        };
        let codes = match self.found {
            Some(found) => found.codes,
            None => self.program_codes().await?,
        };
        let line = format_move(&mm, kind, codes.inch)
            .map_err(|e| self.rejected(format!("cannot command the move: {e}")))?;
        // Errors queued before this move are not about it.
        self.drain_errors().await?;
        let mdi = Request::Mdi(line.clone());
        let sent = match self.ensure_mdi().await {
            Ok(()) => self.set(&mdi).await,
            Err(e) => Err(e),
        };
        if let Err(e @ DeviceError::Rejected { .. }) = sent {
            // A NAK: E-stop, machine off or not enabled; say which.
            return Err(self.fault(&format!("refusing `{mdi}`")).await?.unwrap_or(e));
        }
        sent?;
        self.modes_changed |= codes.restore_words().is_some();
        self.commanded = next;
        self.last_move = Some(line);
        self.last_state = None;
        self.last_poll = None;
        self.idle_short_since = None;
        self.move_accepted_at = Some(Instant::now());
        self.running_at_target_since = None;
        Ok(())
    }

    /// Whether every commanded axis is within `position_tolerance_m` of its target.
    fn at_target(&self, actual: &[Option<f64>; N_AXES]) -> bool {
        let tol = self.cfg.position_tolerance_m;
        self.commanded
            .iter()
            .zip(actual)
            .all(|(c, a)| c.is_none_or(|c| a.is_some_and(|a| (c - a).abs() <= tol)))
    }

    /// Whether every axis is within `standstill_band_m` of where it stood.
    fn standing(&self, stood: &[Option<f64>; N_AXES], actual: &[Option<f64>; N_AXES]) -> bool {
        let band = self.cfg.standstill_band_m;
        stood.iter().zip(actual).all(|(s, a)| match (s, a) {
            (Some(s), Some(a)) => (s - a).abs() <= band,
            (None, None) => true,
            _ => false,
        })
    }

    /// LinuxCNC reports the move running or paused. Moving, unless the machine has stood
    /// still at the target for `stall_timeout_s` (checked once the move is that old) while
    /// LinuxCNC keeps the MDI command RUNNING: then the command is stuck (docs/linuxcnc.md).
    /// `set abort` ends it — LinuxCNC's way to end an MDI command; the machine stands,
    /// nothing moves — recorded as an `mdi_stuck` link fault; the next poll then finds
    /// LinuxCNC idle at the target. A pause is the operator's and is left alone.
    async fn running(&mut self, status: ProgramStatus) -> Result<MachineState, DeviceError> {
        let stall = Duration::from_secs_f64(self.cfg.stall_timeout_s);
        if status != ProgramStatus::Running
            || self.observer
            || self.move_accepted_at.is_none_or(|t| t.elapsed() <= stall)
        {
            self.running_at_target_since = None;
            return Ok(MachineState::Moving);
        }
        let actual = self.actual_position().await?;
        if !self.at_target(&actual) {
            self.running_at_target_since = None;
            return Ok(MachineState::Moving);
        }
        let since = match self.running_at_target_since {
            Some((since, at)) if self.standing(&at, &actual) => since,
            _ => {
                self.running_at_target_since = Some((Instant::now(), actual));
                return Ok(MachineState::Moving);
            }
        };
        if since.elapsed() <= stall {
            return Ok(MachineState::Moving);
        }
        self.running_at_target_since = None;
        let shown = self.last_move.clone().unwrap_or_default();
        self.link_faults.push(LinkFault {
            code: "mdi_stuck".into(),
            message: format!(
                "LinuxCNC kept `{shown}` running (`get program_status` RUNNING) for {:.1} s with \
                 the machine standing at its target; `set abort` ends the command",
                since.elapsed().as_secs_f64()
            ),
        });
        self.abort().await?;
        self.wait_program_idle(&format!(
            "`set abort` to end `{shown}`, which LinuxCNC kept running at its target"
        ))
        .await?;
        Ok(MachineState::Moving)
    }

    async fn poll(&mut self) -> Result<MachineState, DeviceError> {
        self.last_poll = Some(Instant::now());
        self.status_polls += 1;
        let value = self.get(Query::ProgramStatus).await?;
        let status = decode_program_status(&value)
            .map_err(|e| self.protocol(format!("`get program_status`: {e}")))?;
        if status != ProgramStatus::Idle {
            self.idle_short_since = None;
            return self.running(status).await;
        }
        self.running_at_target_since = None;
        let actual = self.actual_position().await?;
        if self.at_target(&actual) {
            self.idle_short_since = None;
            // The operator's G91/G93/G95 again while the machine stands.
            if self.modes_changed {
                if let Some(words) = self.found.and_then(|f| f.codes.restore_words()) {
                    self.restore_modal_codes(&words).await?;
                }
            }
            let position = self
                .axis_index
                .iter()
                .filter_map(|(name, &k)| actual[k].map(|v| (name.clone(), v)))
                .collect();
            return Ok(MachineState::Idle { position });
        }
        let shown = self.last_move.clone().unwrap_or_default();
        let at_mm: Vec<String> = actual[..3]
            .iter()
            .map(|a| format!("{:.6}", a.unwrap_or(f64::NAN) * MM_PER_M))
            .collect();
        let context = format!("while moving (`{shown}`; idle at {} mm)", at_mm.join(" "));
        if let Some(e) = self.fault(&context).await? {
            self.idle_short_since = None;
            return Err(e);
        }
        let since = *self.idle_short_since.get_or_insert_with(Instant::now);
        if since.elapsed().as_secs_f64() > self.cfg.stall_timeout_s {
            self.idle_short_since = None;
            return Err(DeviceError::Timeout {
                device: self.cfg.id.clone(),
                what: format!(
                    "arrival: LinuxCNC is idle short of the target without an error {context}: \
                     it ended or dropped the move (an abort from another client, or a command \
                     its motion controller did not take within [EMCMOT] COMM_TIMEOUT, which \
                     LinuxCNC's log shows as `USRMOT: ERROR: command timeout`)"
                ),
                after_s: self.cfg.stall_timeout_s,
            });
        }
        Ok(MachineState::Moving)
    }

    async fn state_once(&mut self) -> Result<MachineState, DeviceError> {
        let interval = Duration::from_secs_f64(self.cfg.status_interval_s);
        let fresh = self.last_poll.is_some_and(|t| t.elapsed() < interval);
        if fresh {
            if let Some(s) = &self.last_state {
                return Ok(s.clone());
            }
        }
        match self.poll().await {
            Ok(s) => {
                self.last_state = Some(s.clone());
                Ok(s)
            }
            Err(e) => {
                self.last_state = None;
                Err(e)
            }
        }
    }

    /// After the connection was lost: reconnect until `reconnect_timeout_s` (`hello`), then
    /// take control again unless the machine was stopped meanwhile (an alarm: the operator's
    /// stop ends the run). LinuxCNC keeps moving without its client. Records `disconnect` and
    /// `reconnect` link faults; fails with the original error if it cannot reconnect.
    async fn reconnect(&mut self, lost: DeviceError) -> Result<(), DeviceError> {
        if self.cfg.reconnect_timeout_s <= 0.0 {
            return Err(lost);
        }
        self.link_faults.push(LinkFault {
            code: "disconnect".into(),
            message: lost.to_string(),
        });
        let started = Instant::now();
        let deadline = started + Duration::from_secs_f64(self.cfg.reconnect_timeout_s);
        loop {
            tokio::time::sleep(Duration::from_millis(100)).await;
            let attempt = match open_stream(&self.cfg, &self.connector).await {
                Ok(io) => {
                    self.io = io;
                    self.framer.clear();
                    self.lines.clear();
                    self.reply_owed = false;
                    self.last_state = None;
                    self.last_poll = None;
                    self.handshake().await
                }
                Err(e) => Err(e),
            };
            match attempt {
                Ok(()) => break,
                // A refused password will not get better.
                Err(e @ DeviceError::Rejected { .. }) => return Err(e),
                Err(e) if Instant::now() >= deadline => {
                    return Err(self.disconnected(format!(
                        "{}; could not reconnect within {} s: {}",
                        lost.detail(),
                        self.cfg.reconnect_timeout_s,
                        e.detail()
                    )))
                }
                Err(_) => {}
            }
        }
        self.link_faults.push(LinkFault {
            code: "reconnect".into(),
            message: format!(
                "reconnected to linuxcncrsh after {:.2} s",
                started.elapsed().as_secs_f64()
            ),
        });
        self.take_control_unless_stopped().await
    }

    /// After a reconnect, before anything is commanded: a stop made while the connection was
    /// down (E-stop, machine off) is the operator's, an alarm that stops the run; control is
    /// not taken (`set enable`) then. Otherwise take control again. Nothing that changes
    /// LinuxCNC's state (E-stop, power, mode) is sent either way.
    async fn take_control_unless_stopped(&mut self) -> Result<(), DeviceError> {
        if self.observer {
            return Ok(());
        }
        if let Some(what) = self.stopped_state().await? {
            let code = if what == IN_ESTOP {
                ALARM_ESTOP
            } else {
                ALARM_MACHINE_OFF
            };
            return Err(DeviceError::Alarm {
                device: self.cfg.id.clone(),
                code,
                message: format!(
                    "LinuxCNC was found {what} on reconnecting after the connection was lost, \
                     not by geocal, which does not release an E-stop or power a machine on \
                     during a run"
                ),
            });
        }
        self.enable().await
    }

    /// E-stop, machine power, interpreter state and position, queried now (reconnects after
    /// a lost connection).
    pub async fn status(&mut self) -> Result<ControllerStatus, DeviceError> {
        match self.status_once().await {
            Err(e @ DeviceError::Disconnected { .. }) => {
                self.reconnect(e).await?;
                self.status_once().await
            }
            r => r,
        }
    }

    async fn status_once(&mut self) -> Result<ControllerStatus, DeviceError> {
        self.status_polls += 1;
        let estop = self.get_on_off(Query::Estop).await?;
        let machine_on = self.get_on_off(Query::Machine).await?;
        let value = self.get(Query::ProgramStatus).await?;
        let program = decode_program_status(&value)
            .map_err(|e| self.protocol(format!("`get program_status`: {e}")))?;
        let p = self.actual_position().await?;
        Ok(ControllerStatus {
            estop,
            machine_on,
            program,
            position_m: [0, 1, 2].map(|k| p[k].unwrap_or(f64::NAN)),
        })
    }

    /// A cheap request that shows whether the connection still works (reconnects if not).
    pub async fn ping(&mut self) -> Result<(), DeviceError> {
        match self.get(Query::Enable).await {
            Err(e @ DeviceError::Disconnected { .. }) => self.reconnect(e).await,
            Err(e) => Err(e),
            Ok(_) => Ok(()),
        }
    }

    /// `set abort`: stop an MDI move (the interpreter and motion).
    pub async fn abort(&mut self) -> Result<(), DeviceError> {
        self.set(&Request::Abort).await?;
        self.last_state = None;
        self.last_poll = None;
        Ok(())
    }

    /// Put LinuxCNC into E-stop (`set estop on`), e.g. for a test of the alarm path.
    pub async fn estop(&mut self) -> Result<(), DeviceError> {
        self.set(&Request::Estop(true)).await?;
        self.last_state = None;
        self.last_poll = None;
        Ok(())
    }

    /// Close the session politely (`quit`); dropping the driver closes it too.
    pub async fn quit(mut self) -> Result<(), DeviceError> {
        let line = Request::Quit.encode().unwrap_or_default();
        self.io
            .write_all(line.as_bytes())
            .await
            .map_err(|e| self.disconnected(format!("write of `quit` failed: {e}")))
    }
}

async fn open_stream(
    cfg: &LinuxCncConfig,
    connector: &StreamConnector,
) -> Result<TcpStream, DeviceError> {
    let t = cfg.reply_timeout_s;
    let where_ = if cfg.host.is_empty() {
        "linuxcncrsh".to_string()
    } else {
        format!("linuxcncrsh at {}:{}", cfg.host, cfg.port)
    };
    match tokio::time::timeout(Duration::from_secs_f64(t), connector()).await {
        Ok(Ok(io)) => {
            let _ = io.set_nodelay(true);
            Ok(io)
        }
        Ok(Err(e)) => Err(DeviceError::Disconnected {
            device: cfg.id.clone(),
            message: format!("cannot connect to {where_}: {e}"),
        }),
        Err(_) => Err(DeviceError::Timeout {
            device: cfg.id.clone(),
            what: format!("a connection to {where_}"),
            after_s: t,
        }),
    }
}

fn describe_reply(reply: &Reply) -> String {
    match reply {
        Reply::HelloAck { server, version } => format!("`HELLO ACK {server} {version}`"),
        Reply::HelloNak => "`HELLO NAK`".into(),
        Reply::SetAck(k) => format!("`SET {k} ACK`"),
        Reply::SetNak(k) => format!("`SET {k} NAK`"),
        Reply::GetNak(k) => format!("`GET {k} NAK`"),
        Reply::Value { key, value } => {
            let mut shown = format!("{key} {value}");
            if shown.len() > 120 {
                let cut = (0..=120)
                    .rev()
                    .find(|&i| shown.is_char_boundary(i))
                    .unwrap_or(0);
                shown.truncate(cut);
                shown.push('…');
            }
            format!("`{}`", shown.trim())
        }
    }
}

#[async_trait]
impl Machine for LinuxCncMachine {
    fn id(&self) -> &str {
        &self.cfg.id
    }

    /// Send the move; after a lost connection, reconnect and send it again (it is absolute).
    async fn start_move(&mut self, target: &AxisPositions) -> Result<(), DeviceError> {
        match self.start_move_once(target).await {
            Err(e @ DeviceError::Disconnected { .. }) => {
                self.reconnect(e).await?;
                self.start_move_once(target).await
            }
            r => r,
        }
    }

    /// The motion state; after a lost connection, reconnect and report Moving (LinuxCNC
    /// went on with the move; the next poll sees where it is).
    async fn state(&mut self) -> Result<MachineState, DeviceError> {
        match self.state_once().await {
            Err(e @ DeviceError::Disconnected { .. }) => {
                self.reconnect(e).await?;
                Ok(MachineState::Moving)
            }
            r => r,
        }
    }

    /// After an E-stop or machine-off: geocal releases neither (the operator owns the
    /// E-stop), so this refuses while LinuxCNC is still stopped and the run stops, resumable.
    /// Once the operator has cleared it at the machine: take control again (`set enable`),
    /// check the homes (as `home` allows), MDI mode. The interrupted move must be commanded
    /// again.
    async fn unlock(&mut self) -> Result<(), DeviceError> {
        let still = match self.stopped_state().await {
            Err(e @ DeviceError::Disconnected { .. }) => {
                self.reconnect(e).await?;
                self.stopped_state().await?
            }
            r => r?,
        };
        if let Some(what) = still {
            return Err(self.rejected(format!(
                "LinuxCNC is {what}, which geocal did not cause and does not undo: clear it at \
                 the machine (release the E-stop, turn the machine on) and continue the run \
                 with `geocal run --resume DIR`"
            )));
        }
        self.enable().await?;
        self.ensure_homed().await?;
        self.ensure_mdi().await?;
        self.drain_errors().await?;
        self.last_state = None;
        self.last_poll = None;
        self.idle_short_since = None;
        self.running_at_target_since = None;
        Ok(())
    }

    fn take_link_faults(&mut self) -> Vec<LinkFault> {
        std::mem::take(&mut self.link_faults)
    }

    /// Set back the task mode and the distance/feed mode the run found.
    async fn finish(&mut self) -> Result<(), DeviceError> {
        self.leave_as_found().await
    }
}

/// `[KINS] JOINTS` of a LinuxCNC INI file's text (comments start with `#` or `;`).
fn ini_joints(text: &str) -> Option<usize> {
    let mut in_kins = false;
    for line in text.lines() {
        let line = line.trim();
        if line.starts_with('#') || line.starts_with(';') {
            continue;
        }
        if line.starts_with('[') {
            in_kins = line == "[KINS]";
            continue;
        }
        if !in_kins {
            continue;
        }
        if let Some((key, value)) = line.split_once('=') {
            if key.trim() == "JOINTS" {
                return value
                    .trim()
                    .parse()
                    .ok()
                    .filter(|j| (1..=MAX_JOINTS).contains(j));
            }
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn config_defaults_and_refusals() {
        let c: LinuxCncConfig = toml::from_str("host = \"cnc\"").expect("config");
        assert_eq!(
            (c.port, c.joints, c.home, c.power_on),
            (5007, None, HomePolicy::Refuse, false)
        );
        assert!(c.validate().is_ok());
        let inline: LinuxCncConfig =
            toml::from_str("host = \"cnc\"\nenable_password = \"EMCTOO\"").expect("parses");
        let e = inline.validate().unwrap_err().to_string();
        assert!(
            e.contains("enable_password") && e.contains("password_file"),
            "{e}"
        );
        // Never serialised, so never stored with a session.
        assert!(!toml::to_string(&inline).unwrap().contains("EMCTOO"));
        assert!(toml::from_str::<LinuxCncConfig>("hots = \"cnc\"").is_err());
        let rotary = LinuxCncConfig {
            axis_letters: [("c".to_string(), 'C')].into(),
            ..LinuxCncConfig::default()
        };
        assert!(rotary.validate().is_err());
        let slow = LinuxCncConfig {
            reply_timeout_s: f64::NAN,
            ..LinuxCncConfig::default()
        };
        assert!(slow.validate().is_err());
    }

    #[test]
    fn joint_count_from_the_ini() {
        let gantry = "[KINS]\n# a comment\nKINEMATICS = trivkins coordinates=xyyz\nJOINTS = 4\n\
                      [TRAJ]\nJOINTS = 9\n";
        assert_eq!(ini_joints(gantry), Some(4));
        assert_eq!(ini_joints("[TRAJ]\nJOINTS = 3\n"), None);
        assert_eq!(ini_joints("[KINS]\nJOINTS = 40\n"), None);
        assert_eq!(ini_joints("[KINS]\n;JOINTS = 2\nJOINTS=3"), Some(3));
    }

    #[test]
    fn password_file_is_private_and_never_echoed() {
        use std::io::Write;
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("pw.toml");
        let mut f = std::fs::File::create(&path).unwrap();
        writeln!(f, "connect = \"c0nnect\"\nenable = \"en4ble\"").unwrap();
        drop(f);
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o644)).unwrap();
            let e = Passwords::load("m", &path).unwrap_err().to_string();
            assert!(e.contains("chmod 600"), "{e}");
            std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o600)).unwrap();
        }
        let p = Passwords::load("m", &path).unwrap();
        assert_eq!(p, Passwords::new("c0nnect", "en4ble"));
        assert!(!format!("{p:?}").contains("c0nnect"));
        std::fs::write(&path, "connect = c0nnect\n").unwrap();
        let e = Passwords::load("m", &path).unwrap_err().to_string();
        assert!(!e.contains("c0nnect"), "{e}");
        assert!(e.contains("connect") && e.contains("enable"), "{e}");
    }
}
