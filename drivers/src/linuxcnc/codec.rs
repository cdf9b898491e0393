//! linuxcncrsh wire codec, sans-I/O: request lines out, reply lines in. Millimetres and
//! mm/min exist only here and in the driver's unit conversion; everything outside is SI.
//!
//! The protocol (man linuxcncrsh): `hello <pw> <client> <version>` answered `HELLO ACK <server>
//! <version>` or `HELLO NAK`; `set <sub> ...` answered `SET <SUB> ACK` (verbose on) or
//! `SET <SUB> NAK`; `get <sub> ...` answered `<SUB> <value...>` or `GET <SUB> NAK`. Replies
//! end in `\r\n` or `\n\r` (both occur): lines are split at any run of CR/LF (the GRBL
//! framer does exactly that). With echo on, every request line comes back first.

use std::fmt;

/// Replies are short (a position line is under 200 bytes); `help` text lines are longer but
/// still well below this.
pub const MAX_LINE_BYTES: usize = 4096;

/// The protocol version geocal speaks in `hello`.
pub const PROTOCOL_VERSION: &str = "1.0";

/// Millimetres per metre: MDI words are written in mm (`G21`).
pub const MM_PER_M: f64 = 1000.0;
/// Seconds per minute: feeds are mm/min.
const S_PER_MIN: f64 = 60.0;

/// Task mode of LinuxCNC.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mode {
    Manual,
    Auto,
    Mdi,
}

impl Mode {
    fn word(self) -> &'static str {
        match self {
            Mode::Manual => "manual",
            Mode::Auto => "auto",
            Mode::Mdi => "mdi",
        }
    }
}

/// What `get` can ask for (the subset the driver uses).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Query {
    Estop,
    Machine,
    Mode,
    JointHomed,
    AbsActPos,
    AbsCmdPos,
    ProgramStatus,
    Error,
    UserLinearUnits,
    Enable,
    /// The interpreter's active G and M codes (units, distance and feed mode among them).
    ProgramCodes,
    /// The path of the INI file LinuxCNC runs with.
    IniFile,
}

impl Query {
    /// The sub-command word, as the reply names it (upper case).
    pub fn key(self) -> &'static str {
        match self {
            Query::Estop => "ESTOP",
            Query::Machine => "MACHINE",
            Query::Mode => "MODE",
            Query::JointHomed => "JOINT_HOMED",
            Query::AbsActPos => "ABS_ACT_POS",
            Query::AbsCmdPos => "ABS_CMD_POS",
            Query::ProgramStatus => "PROGRAM_STATUS",
            Query::Error => "ERROR",
            Query::UserLinearUnits => "USER_LINEAR_UNITS",
            Query::Enable => "ENABLE",
            Query::ProgramCodes => "PROGRAM_CODES",
            Query::IniFile => "INIFILE",
        }
    }
}

/// One request line.
#[derive(Clone, PartialEq)]
pub enum Request {
    Hello {
        password: String,
        client: String,
    },
    /// `set enable <password>`: this connection may command the machine.
    Enable {
        password: String,
    },
    Verbose(bool),
    Echo(bool),
    /// `set estop on|off` (`on` = in emergency stop).
    Estop(bool),
    Machine(bool),
    SetMode(Mode),
    /// `set home N` (joint N) or `set home -1` (all joints, in their HOME_SEQUENCE).
    Home(i32),
    /// `set mdi <line>`.
    Mdi(String),
    /// `set abort`: stop MDI execution and motion.
    Abort,
    /// `set set_wait received`: a `set` is answered once LinuxCNC's task received it, not
    /// when it is done (the setting is global to linuxcncrsh: another client may change it).
    WaitReceived,
    Get(Query),
    Quit,
}

/// Why a request cannot be written.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum EncodeError {
    #[error("{what} must be non-empty printable ASCII without spaces (linuxcncrsh splits words at whitespace)")]
    BadWord { what: &'static str },
    #[error("the MDI line must be printable ASCII without CR or LF, got {0:?}")]
    BadMdi(String),
}

fn check_word(what: &'static str, w: &str) -> Result<(), EncodeError> {
    if !w.is_empty() && w.bytes().all(|b| b.is_ascii_graphic()) {
        Ok(())
    } else {
        Err(EncodeError::BadWord { what })
    }
}

fn on_off(v: bool) -> &'static str {
    if v {
        "on"
    } else {
        "off"
    }
}

impl Request {
    /// The line to send, terminated by CR LF.
    pub fn encode(&self) -> Result<String, EncodeError> {
        Ok(format!("{}\r\n", self.text()?))
    }

    /// The line without its terminator (what echo sends back).
    fn text(&self) -> Result<String, EncodeError> {
        Ok(match self {
            Request::Hello { password, client } => {
                check_word("the connect password", password)?;
                check_word("the client name", client)?;
                format!("hello {password} {client} {PROTOCOL_VERSION}")
            }
            Request::Enable { password } => {
                check_word("the enable password", password)?;
                // "off" as a password would disable instead of enable.
                if password.eq_ignore_ascii_case("off") {
                    return Err(EncodeError::BadWord {
                        what: "the enable password (\"off\" disables control)",
                    });
                }
                format!("set enable {password}")
            }
            Request::Verbose(v) => format!("set verbose {}", on_off(*v)),
            Request::Echo(v) => format!("set echo {}", on_off(*v)),
            Request::Estop(v) => format!("set estop {}", on_off(*v)),
            Request::Machine(v) => format!("set machine {}", on_off(*v)),
            Request::SetMode(m) => format!("set mode {}", m.word()),
            Request::Home(j) => format!("set home {j}"),
            Request::Mdi(line) => {
                if line.trim().is_empty() || !line.bytes().all(|b| (0x20..0x7f).contains(&b)) {
                    return Err(EncodeError::BadMdi(line.clone()));
                }
                format!("set mdi {line}")
            }
            Request::Abort => "set abort".into(),
            Request::WaitReceived => "set set_wait received".into(),
            Request::Get(q) => format!("get {}", q.key().to_ascii_lowercase()),
            Request::Quit => "quit".into(),
        })
    }

    /// The `set` sub-command this request's ACK/NAK names, upper case (None for get/hello).
    pub fn set_key(&self) -> Option<&'static str> {
        Some(match self {
            Request::Enable { .. } => "ENABLE",
            Request::Verbose(_) => "VERBOSE",
            Request::Echo(_) => "ECHO",
            Request::Estop(_) => "ESTOP",
            Request::Machine(_) => "MACHINE",
            Request::SetMode(_) => "MODE",
            Request::Home(_) => "HOME",
            Request::Mdi(_) => "MDI",
            Request::Abort => "ABORT",
            Request::WaitReceived => "SET_WAIT",
            Request::Hello { .. } | Request::Get(_) | Request::Quit => return None,
        })
    }

    /// True if `line` is this request coming back (echo on): the same words, any case.
    pub fn is_echo(&self, line: &str) -> bool {
        self.text().is_ok_and(|t| words_eq(&t, line))
    }
}

/// Shown in errors and logs: passwords are never printed.
impl fmt::Display for Request {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Request::Hello { client, .. } => {
                write!(f, "hello *** {client} {PROTOCOL_VERSION}")
            }
            Request::Enable { .. } => write!(f, "set enable ***"),
            other => match other.text() {
                Ok(t) => f.write_str(&t),
                Err(e) => write!(f, "(unencodable request: {e})"),
            },
        }
    }
}

impl fmt::Debug for Request {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Request({self})")
    }
}

fn words_eq(a: &str, b: &str) -> bool {
    let mut x = a.split_ascii_whitespace();
    let mut y = b.split_ascii_whitespace();
    loop {
        match (x.next(), y.next()) {
            (None, None) => return true,
            (Some(p), Some(q)) if p.eq_ignore_ascii_case(q) => {}
            _ => return false,
        }
    }
}

/// One reply line, classified.
#[derive(Debug, Clone, PartialEq)]
pub enum Reply {
    HelloAck {
        server: String,
        version: String,
    },
    HelloNak,
    /// `SET <SUB> ACK`.
    SetAck(String),
    /// `SET <SUB> NAK` (or a bare `SET NAK` for a set without sub-command).
    SetNak(String),
    /// `GET <SUB> NAK` (or a bare `GET NAK`).
    GetNak(String),
    /// `<KEY> <value...>`: the answer to `get <key>`; `value` is the rest of the line, trimmed.
    Value {
        key: String,
        value: String,
    },
}

/// Classify a reply line (already split off the stream). Any text gives some `Reply`; whether
/// it is the one expected is for the caller to judge.
pub fn parse_reply(line: &str) -> Reply {
    let words: Vec<&str> = line.split_ascii_whitespace().collect();
    let upper = |i: usize| words.get(i).map(|w| w.to_ascii_uppercase());
    let first = upper(0).unwrap_or_default();
    let last = words.last().map(|w| w.to_ascii_uppercase());
    match first.as_str() {
        "HELLO" if upper(1).as_deref() == Some("ACK") => Reply::HelloAck {
            server: words.get(2).copied().unwrap_or_default().to_string(),
            version: words.get(3).copied().unwrap_or_default().to_string(),
        },
        "HELLO" if upper(1).as_deref() == Some("NAK") => Reply::HelloNak,
        "SET" | "GET" if matches!(last.as_deref(), Some("ACK" | "NAK")) => {
            let sub = if words.len() > 2 {
                words[1..words.len() - 1].join(" ").to_ascii_uppercase()
            } else {
                String::new()
            };
            match (first.as_str(), last.as_deref()) {
                ("SET", Some("ACK")) => Reply::SetAck(sub),
                ("SET", _) => Reply::SetNak(sub),
                _ => Reply::GetNak(sub),
            }
        }
        _ => {
            let trimmed = line.trim();
            let rest = trimmed
                .split_once(|c: char| c.is_ascii_whitespace())
                .map(|(_, r)| r.trim())
                .unwrap_or("");
            Reply::Value {
                key: first,
                value: rest.to_string(),
            }
        }
    }
}

/// A reply value the driver cannot use.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct ValueError(pub String);

/// `ON` / `OFF` (any case).
pub fn decode_on_off(value: &str) -> Result<bool, ValueError> {
    match value.trim().to_ascii_uppercase().as_str() {
        "ON" => Ok(true),
        "OFF" => Ok(false),
        _ => Err(ValueError(format!("expected ON or OFF, got {value:?}"))),
    }
}

/// `MANUAL` / `AUTO` / `MDI`.
pub fn decode_mode(value: &str) -> Result<Mode, ValueError> {
    match value.trim().to_ascii_uppercase().as_str() {
        "MANUAL" => Ok(Mode::Manual),
        "AUTO" => Ok(Mode::Auto),
        "MDI" => Ok(Mode::Mdi),
        _ => Err(ValueError(format!(
            "expected MANUAL, AUTO or MDI, got {value:?}"
        ))),
    }
}

/// Interpreter state as `get program_status` reports it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ProgramStatus {
    Idle,
    Running,
    Paused,
}

pub fn decode_program_status(value: &str) -> Result<ProgramStatus, ValueError> {
    match value.trim().to_ascii_uppercase().as_str() {
        "IDLE" => Ok(ProgramStatus::Idle),
        "RUNNING" => Ok(ProgramStatus::Running),
        "PAUSED" => Ok(ProgramStatus::Paused),
        _ => Err(ValueError(format!(
            "expected IDLE, RUNNING or PAUSED, got {value:?}"
        ))),
    }
}

/// Homed flag per joint: `YES`/`NO` (or `HOMED`/`NOT`, as the man page says), in joint order.
pub fn decode_homed(value: &str) -> Result<Vec<bool>, ValueError> {
    let flags: Vec<bool> = value
        .split_ascii_whitespace()
        .map(|w| match w.to_ascii_uppercase().as_str() {
            "YES" | "HOMED" => Ok(true),
            "NO" | "NOT" => Ok(false),
            _ => Err(ValueError(format!(
                "expected YES or NO per joint, got {w:?} in {value:?}"
            ))),
        })
        .collect::<Result<_, _>>()?;
    if flags.is_empty() {
        return Err(ValueError("no joint in the homed reply".into()));
    }
    Ok(flags)
}

/// Positions in machine units, in axis order (X Y Z A B C [U V W]); at least 3.
pub fn decode_positions(value: &str) -> Result<Vec<f64>, ValueError> {
    let values: Vec<f64> = value
        .split_ascii_whitespace()
        .map(|w| {
            w.parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| ValueError(format!("{w:?} is not a finite number in {value:?}")))
        })
        .collect::<Result<_, _>>()?;
    if values.len() < 3 {
        return Err(ValueError(format!(
            "expected at least 3 positions (X Y Z), got {}",
            values.len()
        )));
    }
    Ok(values)
}

/// The machine's linear user units (`get user_linear_units`), as millimetres per unit.
pub fn decode_linear_units_mm(value: &str) -> Result<f64, ValueError> {
    match value.trim().to_ascii_uppercase().as_str() {
        "MM" => Ok(1.0),
        "CM" => Ok(10.0),
        "INCH" => Ok(25.4),
        _ => Err(ValueError(format!(
            "linear units {value:?}: geocal converts MM, CM and INCH only (set [TRAJ] LINEAR_UNITS)"
        ))),
    }
}

/// `get error`: None when LinuxCNC reports no error (`OK`), else its message.
pub fn decode_error(value: &str) -> Option<String> {
    let v = value.trim();
    if v.is_empty() || v.eq_ignore_ascii_case("ok") {
        None
    } else {
        Some(v.to_string())
    }
}

/// How a move is commanded.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum MoveKind {
    /// `G1` at a feed, mm/min.
    Feed { mm_per_min: f64 },
    /// `G0` at the machine's rapid rate.
    Rapid,
}

impl MoveKind {
    /// A feed move at `feed_m_s` metres per second.
    pub fn feed_m_s(feed_m_s: f64) -> Self {
        MoveKind::Feed {
            mm_per_min: feed_m_s * MM_PER_M * S_PER_MIN,
        }
    }
}

/// A number for an MDI word: fixed `decimals`, never `-0.000…`.
fn mdi_number(v: f64, decimals: usize) -> String {
    let s = format!("{v:.decimals$}");
    if s.trim_start_matches('-')
        .bytes()
        .all(|b| b == b'0' || b == b'.')
    {
        format!("{:.decimals$}", 0.0)
    } else {
        s
    }
}

/// The interpreter's distance mode (`G90` absolute, `G91` incremental).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Distance {
    Absolute,
    Incremental,
}

/// The interpreter's feed-rate mode: `G93` inverse time, `G94` units per minute, `G95` per
/// revolution.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FeedMode {
    InverseTime,
    PerMinute,
    PerRevolution,
}

/// The interpreter's motion mode (modal group 1), the first code of `get program_codes`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MotionMode {
    /// `G80`: no motion mode (LinuxCNC starts so).
    Off,
    /// `G0`.
    Rapid,
    /// `G1`.
    Feed,
    /// An arc, probe, canned cycle or spline mode: it cannot be set without axis words.
    Other,
}

impl MotionMode {
    fn word(self) -> Option<&'static str> {
        match self {
            MotionMode::Off => Some("G80"),
            MotionMode::Rapid => Some("G0"),
            MotionMode::Feed => Some("G1"),
            MotionMode::Other => None,
        }
    }
}

/// The interpreter's modal state that a move line changes, as `get program_codes` shows it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ModalCodes {
    /// `G20` (inch) rather than `G21` (mm).
    pub inch: bool,
    pub distance: Distance,
    pub feed_mode: FeedMode,
    /// None when the reply names no motion mode.
    pub motion: Option<MotionMode>,
    /// The `F` word (the feed rate in the interpreter's units), if reported.
    pub feed_rate: Option<f64>,
}

impl ModalCodes {
    /// The words that set this state again after a move line (`G90 G94` stated): none when
    /// the move left it as it is. Units are never changed (moves are written in them).
    pub fn restore_words(&self) -> Option<String> {
        let mut words = Vec::new();
        if self.distance == Distance::Incremental {
            words.push("G91");
        }
        match self.feed_mode {
            FeedMode::PerMinute => {}
            FeedMode::InverseTime => words.push("G93"),
            FeedMode::PerRevolution => words.push("G95"),
        }
        (!words.is_empty()).then(|| words.join(" "))
    }

    /// The MDI words that set everything of this state that differs in `now` back (units,
    /// distance and feed mode, motion mode, feed rate): none when nothing differs. A motion
    /// mode that cannot be set without axis words (an arc, a canned cycle) is left out.
    pub fn words_to_restore(&self, now: &ModalCodes) -> Option<String> {
        let mut words: Vec<String> = Vec::new();
        if now.inch != self.inch {
            words.push(if self.inch { "G20" } else { "G21" }.into());
        }
        if now.distance != self.distance {
            words.push(match self.distance {
                Distance::Absolute => "G90".into(),
                Distance::Incremental => "G91".into(),
            });
        }
        if now.feed_mode != self.feed_mode {
            words.push(match self.feed_mode {
                FeedMode::InverseTime => "G93".into(),
                FeedMode::PerMinute => "G94".into(),
                FeedMode::PerRevolution => "G95".into(),
            });
        }
        if let (Some(found), Some(current)) = (self.motion, now.motion) {
            if found != current {
                if let Some(word) = found.word() {
                    words.push(word.into());
                }
            }
        }
        if let (Some(found), Some(current)) = (self.feed_rate, now.feed_rate) {
            if found != current {
                words.push(format!("F{found}"));
            }
        }
        (!words.is_empty()).then(|| words.join(" "))
    }
}

/// `get program_codes` (`G80 G17 G40 G21 G90 G94 G54 … F0 S0`): units, distance and feed
/// mode, the motion mode (the first code) and the feed rate. `G91.1` is the arc distance
/// mode, not `G91`.
pub fn decode_program_codes(value: &str) -> Result<ModalCodes, ValueError> {
    let mut inch = None;
    let mut distance = None;
    let mut feed_mode = None;
    let mut feed_rate = None;
    let words: Vec<String> = value
        .split_ascii_whitespace()
        .map(|w| w.to_ascii_uppercase())
        .collect();
    let motion = words.first().and_then(|w| motion_mode(w));
    for w in &words {
        match w.as_str() {
            "G20" => inch = Some(true),
            "G21" => inch = Some(false),
            "G90" => distance = Some(Distance::Absolute),
            "G91" => distance = Some(Distance::Incremental),
            "G93" => feed_mode = Some(FeedMode::InverseTime),
            "G94" => feed_mode = Some(FeedMode::PerMinute),
            "G95" => feed_mode = Some(FeedMode::PerRevolution),
            _ => {
                if let Some(f) = w.strip_prefix('F') {
                    feed_rate = f.parse::<f64>().ok().filter(|f| f.is_finite());
                }
            }
        }
    }
    match (inch, distance, feed_mode) {
        (Some(inch), Some(distance), Some(feed_mode)) => Ok(ModalCodes {
            inch,
            distance,
            feed_mode,
            motion,
            feed_rate,
        }),
        _ => Err(ValueError(format!(
            "expected G20 or G21, G90 or G91, and G93, G94 or G95 among {value:?}"
        ))),
    }
}

/// The motion mode a code of modal group 1 sets, None for a code of another group.
fn motion_mode(word: &str) -> Option<MotionMode> {
    let number: f64 = word.strip_prefix('G')?.parse().ok()?;
    let tenths = (number * 10.0).round() as i64;
    match tenths {
        800 => Some(MotionMode::Off),
        0 => Some(MotionMode::Rapid),
        10 => Some(MotionMode::Feed),
        20 | 30 | 50 | 51 | 52 | 330 | 331 | 382..=385 | 730 | 740 | 760 | 810..=890 => {
            Some(MotionMode::Other)
        }
        _ => None,
    }
}

/// Millimetres per inch.
pub const MM_PER_INCH: f64 = 25.4;

/// The MDI line of an absolute move in machine coordinates: `G21 G90 G94 G53 G1 X.. F..`.
/// `words` are (axis letter, position in mm). The line is written in the interpreter's
/// units as found (`inch`: `G20`, 8 decimals, 0.25 nm; else `G21`, 6 decimals, 1 nm), so
/// that a move never changes them; G90 (absolute) and G94 (units per minute) are stated on
/// every line so that an operator's modal state cannot change what the numbers mean; G53
/// ignores work offsets (G54.., G92) and tool length offsets.
pub fn format_move(
    words: &[(char, f64)],
    kind: MoveKind,
    inch: bool,
) -> Result<String, EncodeError> {
    let (per_mm, decimals, feed_decimals) = if inch {
        (1.0 / MM_PER_INCH, 8, 4)
    } else {
        (1.0, 6, 3)
    };
    let mut line = String::from(if inch { "G20" } else { "G21" });
    line.push_str(" G90 G94 G53 ");
    line.push_str(match kind {
        MoveKind::Feed { .. } => "G1",
        MoveKind::Rapid => "G0",
    });
    for &(letter, mm) in words {
        if !letter.is_ascii_alphabetic() || !mm.is_finite() {
            return Err(EncodeError::BadMdi(format!("{letter}{mm}")));
        }
        line.push(' ');
        line.push(letter.to_ascii_uppercase());
        line.push_str(&mdi_number(mm * per_mm, decimals));
    }
    if let MoveKind::Feed { mm_per_min } = kind {
        if !(mm_per_min.is_finite() && mm_per_min > 0.0) {
            return Err(EncodeError::BadMdi(format!("F{mm_per_min}")));
        }
        line.push_str(&format!(" F{:.feed_decimals$}", mm_per_min * per_mm));
    }
    Ok(line)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grbl::codec::{Framed, LineFramer};
    use proptest::prelude::*;

    fn lines(bytes: &[u8]) -> Vec<String> {
        LineFramer::new(MAX_LINE_BYTES)
            .push(bytes)
            .into_iter()
            .filter_map(|f| match f {
                Framed::Line(l) => Some(l),
                _ => None,
            })
            .collect()
    }

    #[test]
    fn replies_split_on_any_run_of_cr_lf() {
        // linuxcncrsh ends SET replies with \n\r and GET replies with \r\n.
        let got = lines(b"SET MODE ACK\n\rESTOP OFF\r\nJOINT_HOMED YES YES NO\r\n\r\n\n");
        assert_eq!(got, ["SET MODE ACK", "ESTOP OFF", "JOINT_HOMED YES YES NO"]);
    }

    #[test]
    fn requests_encode_and_redact_passwords() {
        let hello = Request::Hello {
            password: "s3cret".into(),
            client: "geocal".into(),
        };
        assert_eq!(hello.encode().unwrap(), "hello s3cret geocal 1.0\r\n");
        assert!(!hello.to_string().contains("s3cret"));
        let enable = Request::Enable {
            password: "EMCTOO".into(),
        };
        assert_eq!(enable.encode().unwrap(), "set enable EMCTOO\r\n");
        assert_eq!(enable.to_string(), "set enable ***");
        assert!(!format!("{enable:?}").contains("EMCTOO"));
        assert_eq!(Request::Home(-1).encode().unwrap(), "set home -1\r\n");
        assert_eq!(
            Request::Get(Query::AbsActPos).encode().unwrap(),
            "get abs_act_pos\r\n"
        );
        assert_eq!(Request::SetMode(Mode::Mdi).set_key(), Some("MODE"));
    }

    #[test]
    fn bad_words_are_refused() {
        let spaced = Request::Hello {
            password: "two words".into(),
            client: "geocal".into(),
        };
        assert!(spaced.encode().is_err());
        let off = Request::Enable {
            password: "OFF".into(),
        };
        assert!(off.encode().is_err());
        assert!(Request::Mdi("G0 X1\nG0 X2".into()).encode().is_err());
        assert!(Request::Mdi("  ".into()).encode().is_err());
    }

    #[test]
    fn echo_is_recognised_whatever_the_case() {
        let r = Request::Mdi("G21 G90 G94 G53 G1 X1.000000 F600.000".into());
        assert!(r.is_echo("set mdi g21 g90 g94 g53 g1 x1.000000 f600.000"));
        assert!(r.is_echo("SET MDI G21  G90 G94 G53 G1 X1.000000 F600.000"));
        assert!(!r.is_echo("SET MDI ACK"));
        assert!(Request::Get(Query::Estop).is_echo("GET ESTOP"));
    }

    #[test]
    fn replies_are_classified() {
        assert_eq!(
            parse_reply("HELLO ACK EMCNETSVR 1.1"),
            Reply::HelloAck {
                server: "EMCNETSVR".into(),
                version: "1.1".into()
            }
        );
        assert_eq!(parse_reply("HELLO NAK"), Reply::HelloNak);
        assert_eq!(parse_reply("SET MDI ACK"), Reply::SetAck("MDI".into()));
        assert_eq!(parse_reply("SET MODE NAK"), Reply::SetNak("MODE".into()));
        assert_eq!(parse_reply("SET NAK"), Reply::SetNak(String::new()));
        assert_eq!(parse_reply("GET FOO NAK"), Reply::GetNak("FOO".into()));
        assert_eq!(
            parse_reply("ABS_ACT_POS 1.000000 -2.500000 0.000000 0.000000 0.000000 0.000000"),
            Reply::Value {
                key: "ABS_ACT_POS".into(),
                value: "1.000000 -2.500000 0.000000 0.000000 0.000000 0.000000".into()
            }
        );
        assert_eq!(
            parse_reply("ERROR joint 0 following error"),
            Reply::Value {
                key: "ERROR".into(),
                value: "joint 0 following error".into()
            }
        );
    }

    #[test]
    fn values_decode() {
        assert!(decode_on_off("on").unwrap());
        assert!(!decode_on_off("OFF").unwrap());
        assert!(decode_on_off("maybe").is_err());
        assert_eq!(decode_mode("MDI").unwrap(), Mode::Mdi);
        assert_eq!(
            decode_homed("YES YES NO NO NO NO").unwrap(),
            [true, true, false, false, false, false]
        );
        assert_eq!(decode_homed("HOMED NOT").unwrap(), [true, false]);
        assert!(decode_homed("").is_err());
        assert!(decode_homed("YES MAYBE").is_err());
        let p = decode_positions("10.000000 -0.000001 250.5 0 0 0").unwrap();
        assert_eq!(&p[..3], &[10.0, -0.000001, 250.5]);
        assert!(decode_positions("1 2").is_err());
        assert!(decode_positions("1 nan 3").is_err());
        assert!(decode_positions("1 inf 3").is_err());
        assert_eq!(decode_linear_units_mm("INCH").unwrap(), 25.4);
        assert!(decode_linear_units_mm("CUSTOM").is_err());
        assert_eq!(decode_error("OK"), None);
        assert_eq!(
            decode_error(" joint 1 on limit ").as_deref(),
            Some("joint 1 on limit")
        );
        assert_eq!(
            decode_program_status("running").unwrap(),
            ProgramStatus::Running
        );
    }

    #[test]
    fn moves_format_in_mm_with_units_stated() {
        let line = format_move(
            &[('X', 100.0), ('Y', -0.0000001), ('Z', 12.3456789)],
            MoveKind::feed_m_s(0.01),
            false,
        )
        .unwrap();
        assert_eq!(
            line,
            "G21 G90 G94 G53 G1 X100.000000 Y0.000000 Z12.345679 F600.000"
        );
        assert_eq!(
            format_move(&[('X', 1.5)], MoveKind::Rapid, false).unwrap(),
            "G21 G90 G94 G53 G0 X1.500000"
        );
        // An interpreter found in G20 stays in G20: inches, 0.25 nm.
        assert_eq!(
            format_move(
                &[('X', 25.4), ('Z', -0.0000001)],
                MoveKind::feed_m_s(0.01),
                true
            )
            .unwrap(),
            "G20 G90 G94 G53 G1 X1.00000000 Z0.00000000 F23.6220"
        );
        assert!(format_move(&[('X', f64::NAN)], MoveKind::Rapid, false).is_err());
        assert!(format_move(&[('X', 1.0)], MoveKind::feed_m_s(0.0), false).is_err());
    }

    #[test]
    fn program_codes_decode_and_restore() {
        let metric = decode_program_codes(
            "G80 G17 G40 G21 G90 G94 G54 G49 G99 G64 G97 G91.1 G8 G92.2 F0 S0",
        )
        .unwrap();
        assert_eq!(
            metric,
            ModalCodes {
                inch: false,
                distance: Distance::Absolute,
                feed_mode: FeedMode::PerMinute,
                motion: Some(MotionMode::Off),
                feed_rate: Some(0.0),
            }
        );
        assert_eq!(metric.restore_words(), None);
        assert_eq!(metric.words_to_restore(&metric), None);
        // After a feed move: G1 and its F; set back to G80 and F0.
        let moved = decode_program_codes(
            "G1 G17 G40 G21 G90 G94 G54 G49 G99 G64 G97 G91.1 G8 G92.2 F1800 S0",
        )
        .unwrap();
        assert_eq!(moved.motion, Some(MotionMode::Feed));
        assert_eq!(metric.words_to_restore(&moved).as_deref(), Some("G80 F0"));
        // An arc mode found cannot be set back without axis words; the rest is.
        let arc = decode_program_codes("G2 G17 G40 G20 G91 G94 G54 F12.5 S0").unwrap();
        assert_eq!(arc.motion, Some(MotionMode::Other));
        assert_eq!(
            arc.words_to_restore(&moved).as_deref(),
            Some("G20 G91 F12.5")
        );
        let odd = decode_program_codes("G80 G17 G40 G20 G91 G93 G54 G91.1 F0 S0").unwrap();
        assert!(odd.inch);
        assert_eq!(odd.restore_words().as_deref(), Some("G91 G93"));
        assert!(decode_program_codes("G80 G17 G91.1 F0").is_err());
    }

    proptest! {
        #[test]
        fn arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..512)) {
            for line in lines(&bytes) {
                let reply = parse_reply(&line);
                if let Reply::Value { value, .. } = reply {
                    let _ = decode_positions(&value);
                    let _ = decode_homed(&value);
                    let _ = decode_on_off(&value);
                    let _ = decode_mode(&value);
                    let _ = decode_program_status(&value);
                    let _ = decode_linear_units_mm(&value);
                    let _ = decode_error(&value);
                    let _ = decode_program_codes(&value);
                }
            }
        }

        #[test]
        fn arbitrary_text_never_panics(text in ".{0,200}") {
            let _ = parse_reply(&text);
            let _ = Request::Mdi(text.clone()).encode();
            let _ = Request::Enable { password: text.clone() }.encode();
            let _ = Request::Hello { password: text.clone(), client: text }.encode();
        }

        #[test]
        fn positions_round_trip(xs in proptest::collection::vec(-1e4f64..1e4, 3..9)) {
            let value = xs.iter().map(|v| format!("{v:.6}")).collect::<Vec<_>>().join(" ");
            let line = format!("ABS_ACT_POS {value}");
            let Reply::Value { key, value } = parse_reply(&line) else {
                return Err(TestCaseError::fail("not a value"));
            };
            prop_assert_eq!(key, "ABS_ACT_POS");
            let got = decode_positions(&value).unwrap();
            prop_assert_eq!(got.len(), xs.len());
            for (g, x) in got.iter().zip(&xs) {
                prop_assert!((g - x).abs() <= 5e-7);
            }
        }

        #[test]
        fn moves_round_trip(x in -2000.0f64..2000.0, y in -2000.0f64..2000.0, feed in 1e-4f64..1.0) {
            let line = format_move(&[('X', x), ('Y', y)], MoveKind::feed_m_s(feed), false).unwrap();
            let words: Vec<&str> = line.split(' ').collect();
            let num = |prefix: char| words.iter().find_map(|w| w.strip_prefix(prefix)).unwrap().parse::<f64>().unwrap();
            prop_assert!((num('X') - x).abs() <= 5e-7);
            prop_assert!((num('Y') - y).abs() <= 5e-7);
            prop_assert!((num('F') - feed * 60_000.0).abs() <= 5e-4);
            prop_assert!(Request::Mdi(line).encode().is_ok());
        }
    }
}
