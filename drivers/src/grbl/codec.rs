//! GRBL wire codec, sans-I/O: line framing of a byte stream, parsing of controller and host
//! lines, and formatting of host lines. Millimetres and degrees exist only here; everything
//! outside is SI (linear axes X, Y, Z in metres, rotary axes A, B, C in radians).

use std::fmt::Write as _;

/// Millimetres per metre: the wire speaks mm and mm/min.
const MM_PER_M: f64 = 1000.0;
/// Seconds per minute: feeds are mm/min on the wire.
const S_PER_MIN: f64 = 60.0;
/// Degrees per radian: rotary axes (A, B, C) are in degrees on the wire.
const DEG_PER_RAD: f64 = 180.0 / std::f64::consts::PI;

/// Linear axis letters, in the order of a position report.
pub const LINEAR_LETTERS: [char; 3] = ['X', 'Y', 'Z'];
/// Rotary axis letters (GRBL derivatives with more axes, e.g. grblHAL), reported after X, Y, Z.
pub const ROTARY_LETTERS: [char; 3] = ['A', 'B', 'C'];

/// True for a rotary axis letter (A, B, C; either case).
pub fn is_rotary(letter: char) -> bool {
    ROTARY_LETTERS.contains(&letter.to_ascii_uppercase())
}

/// Wire units of a value in SI: mm for a linear axis, degrees for a rotary one.
fn to_wire(letter: char, si: f64) -> f64 {
    if is_rotary(letter) {
        si * DEG_PER_RAD
    } else {
        si * MM_PER_M
    }
}

/// Real-time status query: answered at once, never followed by a newline.
pub const STATUS_QUERY: u8 = b'?';
/// Real-time feed hold.
pub const FEED_HOLD: u8 = b'!';
/// Real-time cycle start / resume.
pub const CYCLE_START: u8 = b'~';
/// Real-time soft reset (Ctrl-X): aborts motion, the controller prints its banner again.
pub const SOFT_RESET: u8 = 0x18;

/// GRBL's own input line limit; longer lines are rejected (error:11 on the controller).
pub const MAX_LINE_BYTES: usize = 256;

/// One framed item of a byte stream.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Framed {
    /// A complete line without its terminator (never empty).
    Line(String),
    /// A real-time byte picked out of the stream (only when the framer is told to).
    Realtime(u8),
    /// A line longer than the limit was dropped (its bytes up to the next terminator).
    Overlong,
}

/// Splits a byte stream into lines at CR or LF; partial lines carry over between chunks.
///
/// Both sides use it: the host frames controller output, the controller (emulator) frames
/// host input and, with `realtime` set, picks `?`, `!`, `~` and 0x18 out of the stream
/// wherever they fall, as GRBL does.
#[derive(Debug, Clone)]
pub struct LineFramer {
    buf: Vec<u8>,
    max_line_bytes: usize,
    realtime: bool,
    discarding: bool,
    overlong_count: u64,
}

impl LineFramer {
    /// A framer for controller output (no real-time bytes).
    pub fn new(max_line_bytes: usize) -> Self {
        Self {
            buf: Vec::new(),
            max_line_bytes,
            realtime: false,
            discarding: false,
            overlong_count: 0,
        }
    }

    /// A framer for host input that also extracts real-time bytes.
    pub fn with_realtime(max_line_bytes: usize) -> Self {
        Self {
            realtime: true,
            ..Self::new(max_line_bytes)
        }
    }

    /// Number of overlong lines dropped so far.
    pub fn overlong_count(&self) -> u64 {
        self.overlong_count
    }

    /// Bytes of an unfinished line held back.
    pub fn pending_bytes(&self) -> usize {
        self.buf.len()
    }

    /// Forget any unfinished line (after a reset or reconnect).
    pub fn clear(&mut self) {
        self.buf.clear();
        self.discarding = false;
    }

    /// Feed a chunk; returns what it completed, in stream order.
    pub fn push(&mut self, bytes: &[u8]) -> Vec<Framed> {
        let mut out = Vec::new();
        for &b in bytes {
            if self.realtime && matches!(b, STATUS_QUERY | FEED_HOLD | CYCLE_START | SOFT_RESET) {
                out.push(Framed::Realtime(b));
                continue;
            }
            if b == b'\r' || b == b'\n' {
                if self.discarding {
                    self.discarding = false;
                } else if !self.buf.is_empty() {
                    let line = String::from_utf8_lossy(&self.buf).into_owned();
                    out.push(Framed::Line(line));
                }
                self.buf.clear();
                continue;
            }
            if self.discarding {
                continue;
            }
            if self.buf.len() >= self.max_line_bytes {
                // Report once per line, then skip to its end: a partial line is never valid.
                self.buf.clear();
                self.discarding = true;
                self.overlong_count += 1;
                out.push(Framed::Overlong);
                continue;
            }
            self.buf.push(b);
        }
        out
    }
}

/// Controller state as named in a status report.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GrblState {
    Idle,
    Run,
    Hold,
    Jog,
    Alarm,
    Door,
    Check,
    Home,
    Sleep,
}

impl GrblState {
    pub fn as_str(self) -> &'static str {
        match self {
            GrblState::Idle => "Idle",
            GrblState::Run => "Run",
            GrblState::Hold => "Hold",
            GrblState::Jog => "Jog",
            GrblState::Alarm => "Alarm",
            GrblState::Door => "Door",
            GrblState::Check => "Check",
            GrblState::Home => "Home",
            GrblState::Sleep => "Sleep",
        }
    }

    fn parse(s: &str) -> Option<Self> {
        Some(match s {
            "Idle" => GrblState::Idle,
            "Run" => GrblState::Run,
            "Hold" => GrblState::Hold,
            "Jog" => GrblState::Jog,
            "Alarm" => GrblState::Alarm,
            "Door" => GrblState::Door,
            "Check" => GrblState::Check,
            "Home" => GrblState::Home,
            "Sleep" => GrblState::Sleep,
            _ => return None,
        })
    }
}

/// Which frame a reported position is in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PosFrame {
    /// `MPos`: machine coordinates.
    Machine,
    /// `WPos`: work coordinates (machine minus work coordinate offset).
    Work,
}

/// A decoded `<...>` status report.
#[derive(Debug, Clone, PartialEq)]
pub struct StatusReport {
    pub state: GrblState,
    /// Sub-state after the colon (`Hold:0`, `Door:1`).
    pub substate: Option<u8>,
    /// X, Y, Z position, metres.
    pub position_m: [f64; 3],
    /// Rotary axes reported after X, Y, Z (A, then B, then C), radians; empty on 3 axes.
    pub rotary_rad: Vec<f64>,
    pub frame: PosFrame,
    /// Work coordinate offset if this report carried one (`WCO:`), metres.
    pub wco_m: Option<[f64; 3]>,
    /// Rotary part of that offset (A, B, C), radians; empty when absent.
    pub wco_rotary_rad: Vec<f64>,
    /// Current feed if reported (`FS:` or `F:`), m/s.
    pub feed_m_s: Option<f64>,
}

/// One line from the controller.
#[derive(Debug, Clone, PartialEq)]
pub enum ControllerLine {
    Ok,
    Error(u16),
    Alarm(u16),
    Status(StatusReport),
    /// `Grbl 1.1h ['$' for help]`: printed at power-up and after every reset.
    Banner {
        version: String,
    },
    /// `[MSG:...]`, `[GC:...]` and other bracketed feedback.
    Feedback(String),
    /// Anything else, kept for logging.
    Other(String),
}

/// Why a controller line could not be decoded.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("malformed controller line {line:?}: {reason}")]
pub struct ParseError {
    pub line: String,
    pub reason: String,
}

fn perr(line: &str, reason: impl Into<String>) -> ParseError {
    ParseError {
        line: line.to_string(),
        reason: reason.into(),
    }
}

/// Decode one controller line (without terminator).
pub fn parse_controller_line(line: &str) -> Result<ControllerLine, ParseError> {
    let t = line.trim();
    if t == "ok" {
        return Ok(ControllerLine::Ok);
    }
    if let Some(code) = t.strip_prefix("error:") {
        return code
            .parse::<u16>()
            .map(ControllerLine::Error)
            .map_err(|_| perr(line, "error code is not a number"));
    }
    if let Some(code) = t.strip_prefix("ALARM:") {
        return code
            .parse::<u16>()
            .map(ControllerLine::Alarm)
            .map_err(|_| perr(line, "alarm code is not a number"));
    }
    if t.starts_with('<') {
        return parse_status(t).map(ControllerLine::Status);
    }
    if let Some(rest) = t.strip_prefix("Grbl ") {
        let version = rest.split_whitespace().next().unwrap_or("").to_string();
        return Ok(ControllerLine::Banner { version });
    }
    if t.starts_with('[') && t.ends_with(']') {
        return Ok(ControllerLine::Feedback(t[1..t.len() - 1].to_string()));
    }
    Ok(ControllerLine::Other(t.to_string()))
}

/// A position list `x,y,z[,a[,b[,c]]]`: X, Y, Z in mm to metres, rotary axes in degrees to
/// radians.
fn parse_axes(line: &str, s: &str) -> Result<([f64; 3], Vec<f64>), ParseError> {
    let mut linear = [0.0; 3];
    let mut rotary = Vec::new();
    let mut n = 0;
    for part in s.split(',') {
        if n >= LINEAR_LETTERS.len() + ROTARY_LETTERS.len() {
            return Err(perr(line, "more than 6 axes in a position"));
        }
        let v: f64 = part
            .trim()
            .parse()
            .map_err(|_| perr(line, format!("bad number {part:?}")))?;
        if !v.is_finite() {
            return Err(perr(line, "non-finite position"));
        }
        if n < 3 {
            linear[n] = v / MM_PER_M;
        } else {
            rotary.push(v / DEG_PER_RAD);
        }
        n += 1;
    }
    if n < 3 {
        return Err(perr(
            line,
            "expected at least 3 axes (X, Y, Z) in a position",
        ));
    }
    Ok((linear, rotary))
}

fn parse_status(line: &str) -> Result<StatusReport, ParseError> {
    let inner = line
        .strip_prefix('<')
        .and_then(|s| s.strip_suffix('>'))
        .ok_or_else(|| perr(line, "status report not closed by '>'"))?;
    let mut fields = inner.split('|');
    let state_field = fields.next().unwrap_or("");
    let (state_name, substate) = match state_field.split_once(':') {
        Some((name, sub)) => (
            name,
            Some(sub.parse::<u8>().map_err(|_| perr(line, "bad sub-state"))?),
        ),
        None => (state_field, None),
    };
    let state = GrblState::parse(state_name)
        .ok_or_else(|| perr(line, format!("unknown state {state_name:?}")))?;
    let mut pos = None;
    let mut wco = None;
    let mut feed_m_s = None;
    for f in fields {
        if let Some(v) = f.strip_prefix("MPos:") {
            pos = Some((parse_axes(line, v)?, PosFrame::Machine));
        } else if let Some(v) = f.strip_prefix("WPos:") {
            pos = Some((parse_axes(line, v)?, PosFrame::Work));
        } else if let Some(v) = f.strip_prefix("WCO:") {
            wco = Some(parse_axes(line, v)?);
        } else if let Some(v) = f.strip_prefix("FS:").or_else(|| f.strip_prefix("F:")) {
            let feed_mm_min: f64 = v
                .split(',')
                .next()
                .unwrap_or("")
                .parse()
                .map_err(|_| perr(line, "bad feed"))?;
            feed_m_s = Some(feed_mm_min / MM_PER_M / S_PER_MIN);
        }
        // Other fields (Bf, Ln, Pn, Ov, A) carry nothing geocal uses.
    }
    let ((position_m, rotary_rad), frame) = pos.ok_or_else(|| perr(line, "no MPos or WPos"))?;
    let (wco_m, wco_rotary_rad) = match wco {
        Some((w, r)) => (Some(w), r),
        None => (None, Vec::new()),
    };
    Ok(StatusReport {
        state,
        substate,
        position_m,
        rotary_rad,
        frame,
        wco_m,
        wco_rotary_rad,
        feed_m_s,
    })
}

/// Format a status report as the controller sends it (with CRLF).
pub fn format_status(report: &StatusReport) -> String {
    let mut s = String::from("<");
    s.push_str(report.state.as_str());
    if let Some(sub) = report.substate {
        let _ = write!(s, ":{sub}");
    }
    let tag = match report.frame {
        PosFrame::Machine => "MPos",
        PosFrame::Work => "WPos",
    };
    let _ = write!(s, "|{tag}:");
    write_axes(&mut s, &report.position_m, &report.rotary_rad);
    if let Some(feed) = report.feed_m_s {
        let _ = write!(s, "|FS:{:.0},0", feed * MM_PER_M * S_PER_MIN);
    }
    if let Some(w) = report.wco_m {
        s.push_str("|WCO:");
        write_axes(&mut s, &w, &report.wco_rotary_rad);
    }
    s.push_str(">\r\n");
    s
}

/// `x,y,z[,a,...]`: mm with 4 decimals (0.1 µm), degrees with 5 (0.17 µrad).
fn write_axes(s: &mut String, linear_m: &[f64; 3], rotary_rad: &[f64]) {
    let linear = linear_m.iter().map(|v| format!("{:.4}", v * MM_PER_M));
    let rotary = rotary_rad.iter().map(|v| format!("{:.5}", v * DEG_PER_RAD));
    let all: Vec<String> = linear.chain(rotary).collect();
    s.push_str(&all.join(","));
}

/// The power-up / reset banner, with CRLF.
pub fn format_banner(version: &str) -> String {
    format!("\r\nGrbl {version} ['$' for help]\r\n")
}

/// GRBL 1.1's description of an error code (the common ones; others get a generic text).
pub fn error_text(code: u16) -> &'static str {
    match code {
        1 => "G-code words consist of a letter and a value; letter was not found",
        2 => "numeric value format is not valid or missing an expected value",
        3 => "Grbl '$' system command was not recognized or supported",
        4 => "negative value received for an expected positive value",
        5 => "homing cycle is not enabled via settings",
        8 => "Grbl '$' command cannot be used unless Grbl is IDLE",
        9 => "G-code locked out during alarm or jog state",
        10 => "soft limits cannot be enabled without homing also enabled",
        11 => "max characters per line exceeded; line was not processed",
        13 => "safety door detected as opened and door state initiated",
        15 => "jog target exceeds machine travel; command ignored",
        16 => "jog command with no '=' or contains prohibited g-code",
        20 => "unsupported or invalid g-code command found in block",
        21 => "more than one g-code command from same modal group found in block",
        22 => "feed rate has not yet been set or is undefined",
        23 => "g-code command in block requires an integer value",
        24 => "two g-code commands that both require the use of the XYZ axis words were detected",
        25 => "a g-code word was repeated in the block",
        26 => "a g-code command implicitly or explicitly requires XYZ axis words, none found",
        27 => "N line number value is not within the valid range of 1 - 9,999,999",
        28 => "a g-code command was sent, but is missing some required P or L value words",
        33 => "the motion command has an invalid target",
        36 => "there are unused, leftover g-code words that aren't used by any command",
        _ => "unknown error code",
    }
}

/// GRBL 1.1's description of an alarm code.
pub fn alarm_text(code: u16) -> &'static str {
    match code {
        1 => "hard limit triggered; position lost, re-homing recommended",
        2 => "soft limit: motion target exceeds machine travel; position retained",
        3 => "reset while in motion; position lost, re-homing recommended",
        4 => "probe fail: probe not in the expected initial state",
        5 => "probe fail: probe did not contact the workpiece",
        6 => "homing fail: reset during active homing cycle",
        7 => "homing fail: safety door was opened during homing",
        8 => "homing fail: cycle failed to clear limit switch",
        9 => "homing fail: could not find limit switch",
        _ => "unknown alarm code",
    }
}

/// Format an absolute linear move `G90 G1 X.. Y.. A.. F..`, LF-terminated as GRBL senders do.
/// Positions in metres become mm with 4 decimals (0.1 µm); rotary targets (A, B, C) in radians
/// become degrees with 5 decimals (0.17 µrad); feed m/s becomes mm/min.
///
/// `axes` pairs a G-code axis letter with its target in SI (metres, or radians for A, B, C).
pub fn format_move(axes: &[(char, f64)], feed_m_s: f64) -> String {
    let mut s = String::from("G90 G1");
    for &(letter, pos) in axes {
        let decimals = if is_rotary(letter) { 5 } else { 4 };
        let _ = write!(
            s,
            " {}{:.decimals$}",
            letter.to_ascii_uppercase(),
            to_wire(letter, pos)
        );
    }
    let _ = writeln!(s, " F{:.3}", feed_m_s * MM_PER_M * S_PER_MIN);
    s
}

/// Format a dwell; GRBL 1.1 reads `P` as seconds.
pub fn format_dwell(dwell_s: f64) -> String {
    format!("G4 P{:.3}\n", dwell_s)
}

/// A parsed host block, in SI units: what the emulator executes and what the round-trip
/// tests read back.
#[derive(Debug, Clone, PartialEq)]
pub enum Block {
    /// Nothing to do (empty line, comment, modal words only such as `G90`/`G21`).
    Empty,
    /// Linear move: targets (metres, absolute) of the axes named; `rapid` for G0.
    Move {
        rapid: bool,
        target_m: [Option<f64>; 3],
        /// Targets of the rotary axes A, B, C named (radians, absolute).
        target_rad: [Option<f64>; 3],
        feed_m_s: Option<f64>,
    },
    Dwell {
        dwell_s: f64,
    },
    /// `$X`: unlock after an alarm.
    Unlock,
    /// Other `$` system commands (not executed by the emulator).
    System(String),
}

/// Parse one host line of the G-code subset geocal emits (G0, G1, G4, G90, G21, F, XYZ, ABC,
/// P).
/// Errors carry the GRBL error code a controller would answer with.
pub fn parse_block(line: &str) -> Result<Block, u16> {
    let t = line.trim();
    if let Some(sys) = t.strip_prefix('$') {
        return Ok(if sys.eq_ignore_ascii_case("X") {
            Block::Unlock
        } else {
            Block::System(sys.to_string())
        });
    }
    // Drop comments: `;` to end of line, `( ... )` inline.
    let mut code = String::new();
    let mut in_paren = false;
    for c in t.chars() {
        match c {
            '(' => in_paren = true,
            ')' => in_paren = false,
            ';' if !in_paren => break,
            c if !in_paren && !c.is_whitespace() => code.push(c.to_ascii_uppercase()),
            _ => {}
        }
    }
    let bytes = code.as_bytes();
    let mut i = 0;
    let mut motion: Option<u8> = None; // 0, 1 or 4
    let mut target_m = [None; 3];
    let mut target_rad = [None; 3];
    let mut feed_m_s = None;
    let mut p_value = None;
    while i < bytes.len() {
        let letter = bytes[i];
        if !letter.is_ascii_uppercase() {
            return Err(1);
        }
        i += 1;
        let start = i;
        while i < bytes.len()
            && (bytes[i].is_ascii_digit() || matches!(bytes[i], b'.' | b'-' | b'+'))
        {
            i += 1;
        }
        let num_str = &code[start..i];
        let value: f64 = num_str.parse().map_err(|_| 2u16)?;
        if !value.is_finite() {
            return Err(2);
        }
        match letter {
            b'G' => {
                let g = value;
                if g == 90.0 || g == 21.0 || g == 94.0 || g == 17.0 {
                    // Modes geocal always uses; accepted and otherwise ignored.
                } else if g == 0.0 || g == 1.0 || g == 4.0 {
                    if motion.is_some() {
                        return Err(21);
                    }
                    motion = Some(g as u8);
                } else if g.fract() != 0.0 {
                    return Err(23);
                } else {
                    return Err(20);
                }
            }
            b'X' | b'Y' | b'Z' => {
                let k = (letter - b'X') as usize;
                if target_m[k].is_some() {
                    return Err(25);
                }
                target_m[k] = Some(value / MM_PER_M);
            }
            b'A' | b'B' | b'C' => {
                let k = (letter - b'A') as usize;
                if target_rad[k].is_some() {
                    return Err(25);
                }
                target_rad[k] = Some(value / DEG_PER_RAD);
            }
            b'F' => {
                if feed_m_s.is_some() {
                    return Err(25);
                }
                if value < 0.0 {
                    return Err(4);
                }
                feed_m_s = Some(value / MM_PER_M / S_PER_MIN);
            }
            b'P' => {
                if p_value.is_some() {
                    return Err(25);
                }
                p_value = Some(value);
            }
            b'N' => {}
            _ => return Err(20),
        }
    }
    let has_axes = target_m.iter().chain(&target_rad).any(Option::is_some);
    match motion {
        None if has_axes => Err(33), // geocal always names the motion mode
        None => Ok(Block::Empty),
        Some(4) => {
            if has_axes {
                return Err(31);
            }
            match p_value {
                Some(p) if p >= 0.0 => Ok(Block::Dwell { dwell_s: p }),
                Some(_) => Err(4),
                None => Err(28),
            }
        }
        Some(m) => {
            if p_value.is_some() {
                return Err(36);
            }
            if !has_axes {
                return Err(26);
            }
            Ok(Block::Move {
                rapid: m == 0,
                target_m,
                target_rad,
                feed_m_s,
            })
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn frames_lines_across_chunks() {
        let mut f = LineFramer::new(64);
        assert!(f.push(b"o").is_empty());
        assert_eq!(f.push(b"k\r\nerr"), vec![Framed::Line("ok".into())]);
        assert_eq!(f.push(b"or:9\n"), vec![Framed::Line("error:9".into())]);
        assert_eq!(f.pending_bytes(), 0);
    }

    #[test]
    fn overlong_lines_are_dropped_and_counted() {
        let mut f = LineFramer::new(4);
        let out = f.push(b"abcdefgh\nok\n");
        assert_eq!(out, vec![Framed::Overlong, Framed::Line("ok".into())]);
        assert_eq!(f.overlong_count(), 1);
    }

    #[test]
    fn realtime_bytes_are_picked_out() {
        let mut f = LineFramer::with_realtime(64);
        let out = f.push(b"G4?P1\x18\n");
        assert_eq!(
            out,
            vec![
                Framed::Realtime(b'?'),
                Framed::Realtime(SOFT_RESET),
                Framed::Line("G4P1".into())
            ]
        );
    }

    #[test]
    fn parses_controller_lines() {
        assert_eq!(parse_controller_line("ok"), Ok(ControllerLine::Ok));
        assert_eq!(
            parse_controller_line("error:22"),
            Ok(ControllerLine::Error(22))
        );
        assert_eq!(
            parse_controller_line("ALARM:2"),
            Ok(ControllerLine::Alarm(2))
        );
        assert_eq!(
            parse_controller_line("Grbl 1.1h ['$' for help]"),
            Ok(ControllerLine::Banner {
                version: "1.1h".into()
            })
        );
        let Ok(ControllerLine::Status(s)) =
            parse_controller_line("<Idle|MPos:1.000,2.000,-3.500|FS:0,0>")
        else {
            panic!("not a status");
        };
        assert_eq!(s.state, GrblState::Idle);
        assert_eq!(s.frame, PosFrame::Machine);
        assert!((s.position_m[2] + 0.0035).abs() < 1e-12);
        let Ok(ControllerLine::Status(s)) =
            parse_controller_line("<Hold:0|WPos:0.000,0.000,0.000|Bf:15,128|FS:600,0|WCO:1.0,0,0>")
        else {
            panic!("not a status");
        };
        assert_eq!(
            (s.state, s.substate, s.frame),
            (GrblState::Hold, Some(0), PosFrame::Work)
        );
        assert!((s.feed_m_s.unwrap_or(0.0) - 0.01).abs() < 1e-12);
        assert_eq!(s.wco_m, Some([0.001, 0.0, 0.0]));
        assert!(parse_controller_line("<Idle|FS:0,0>").is_err());
        assert!(parse_controller_line("<Bogus|MPos:0,0,0>").is_err());
        assert!(parse_controller_line("error:x").is_err());
    }

    #[test]
    fn formats_host_lines() {
        assert_eq!(
            format_move(&[('X', 0.0123456), ('z', -0.5)], 0.05),
            "G90 G1 X12.3456 Z-500.0000 F3000.000\n"
        );
        assert_eq!(format_dwell(0.5), "G4 P0.500\n");
    }

    #[test]
    fn rotary_axes_are_degrees_on_the_wire_and_radians_inside() {
        let half_pi = std::f64::consts::FRAC_PI_2;
        let line = format_move(&[('X', 0.1), ('A', half_pi), ('b', -0.25 * half_pi)], 0.01);
        assert_eq!(line, "G90 G1 X100.0000 A90.00000 B-22.50000 F600.000\n");
        let Ok(Block::Move {
            target_m,
            target_rad,
            ..
        }) = parse_block(line.trim_end())
        else {
            panic!("did not parse back: {line}");
        };
        assert_eq!(target_m, [Some(0.1), None, None]);
        assert!((target_rad[0].unwrap_or(0.0) - half_pi).abs() < 1e-12);
        assert!((target_rad[1].unwrap_or(0.0) + 0.25 * half_pi).abs() < 1e-12);
        assert_eq!(target_rad[2], None);
        assert_eq!(parse_block("G1 A1 A2"), Err(25));
        assert!(matches!(parse_block("G1 C-3.5"), Ok(Block::Move { .. })));

        let Ok(ControllerLine::Status(s)) = parse_controller_line(
            "<Idle|MPos:1.0000,2.0000,-3.0000,90.00000,-45.00000|FS:0,0|WCO:0,0,0,1.0,0>",
        ) else {
            panic!("not a status");
        };
        assert_eq!(s.position_m, [0.001, 0.002, -0.003]);
        assert_eq!(s.rotary_rad.len(), 2);
        assert!((s.rotary_rad[0] - half_pi).abs() < 1e-12);
        assert!((s.rotary_rad[1] + 0.5 * half_pi).abs() < 1e-12);
        assert_eq!(s.wco_m, Some([0.0; 3]));
        assert!((s.wco_rotary_rad[0] - 1f64.to_radians()).abs() < 1e-15);
        // Format and parse back: the 5 decimals of a degree keep 0.2 µrad.
        let again = format_status(&s);
        let Ok(ControllerLine::Status(t)) = parse_controller_line(again.trim_end()) else {
            panic!("{again}");
        };
        for (a, b) in s.rotary_rad.iter().zip(&t.rotary_rad) {
            assert!((a - b).abs() < 2e-7);
        }
        assert!(parse_controller_line("<Idle|MPos:1,2>").is_err());
        assert!(parse_controller_line("<Idle|MPos:1,2,3,4,5,6,7>").is_err());
    }

    #[test]
    fn parses_blocks_with_grbl_codes() {
        assert_eq!(parse_block("G4 P0.25"), Ok(Block::Dwell { dwell_s: 0.25 }));
        assert_eq!(parse_block("G1 X1 F"), Err(2));
        assert_eq!(parse_block("G4"), Err(28));
        assert_eq!(parse_block("G2 X1"), Err(20));
        assert_eq!(parse_block("hello"), Err(2));
        assert_eq!(parse_block("M3 S100"), Err(20));
        assert_eq!(parse_block("G0 G1 X1"), Err(21));
        assert_eq!(parse_block("G1 X1 X2"), Err(25));
        assert_eq!(parse_block("1"), Err(1));
        assert_eq!(parse_block("G90 G21 ; setup"), Ok(Block::Empty));
        assert_eq!(parse_block("$X"), Ok(Block::Unlock));
    }

    fn arb_status() -> impl Strategy<Value = StatusReport> {
        (
            prop::sample::select(vec![
                GrblState::Idle,
                GrblState::Run,
                GrblState::Hold,
                GrblState::Alarm,
                GrblState::Jog,
            ]),
            proptest::option::of(0u8..2),
            prop::array::uniform3(-2000i64..2000).prop_map(|a| a.map(|v| v as f64 * 1e-4)),
            any::<bool>(),
        )
            .prop_map(|(state, substate, position_m, work)| StatusReport {
                state,
                substate,
                position_m,
                rotary_rad: Vec::new(),
                wco_rotary_rad: Vec::new(),
                frame: if work {
                    PosFrame::Work
                } else {
                    PosFrame::Machine
                },
                wco_m: None,
                feed_m_s: None,
            })
    }

    proptest! {
        #[test]
        fn random_bytes_never_panic(chunks in prop::collection::vec(prop::collection::vec(any::<u8>(), 0..64), 0..8)) {
            let mut host = LineFramer::new(32);
            let mut dev = LineFramer::with_realtime(32);
            for c in &chunks {
                for f in host.push(c).into_iter().chain(dev.push(c)) {
                    if let Framed::Line(l) = f {
                        let _ = parse_controller_line(&l);
                        let _ = parse_block(&l);
                    }
                }
            }
        }

        #[test]
        fn split_output_parses_identically(reports in prop::collection::vec(arb_status(), 1..5),
                                           errs in prop::collection::vec(1u16..40, 0..3),
                                           cut in any::<prop::sample::Index>()) {
            let mut stream = format_banner("1.1h");
            for r in &reports { stream.push_str(&format_status(r)); stream.push_str("ok\r\n"); }
            for e in &errs { stream.push_str(&format!("error:{e}\r\n")); }
            let bytes = stream.as_bytes();
            let parse_all = |chunks: &[&[u8]]| {
                let mut f = LineFramer::new(MAX_LINE_BYTES);
                let mut out = Vec::new();
                for c in chunks {
                    for fr in f.push(c) {
                        if let Framed::Line(l) = fr { out.push(parse_controller_line(&l)); }
                    }
                }
                out
            };
            let whole = parse_all(&[bytes]);
            let k = cut.index(bytes.len() + 1);
            let split = parse_all(&[&bytes[..k], &bytes[k..]]);
            prop_assert_eq!(&whole, &split);
            let bytewise: Vec<&[u8]> = bytes.chunks(1).collect();
            prop_assert_eq!(&whole, &parse_all(&bytewise));
            // Status reports survive the format/parse round trip to the 0.1 µm of the wire.
            let parsed: Vec<StatusReport> = whole.iter().filter_map(|r| match r {
                Ok(ControllerLine::Status(s)) => Some(s.clone()), _ => None }).collect();
            prop_assert_eq!(parsed.len(), reports.len());
            for (p, r) in parsed.iter().zip(&reports) {
                prop_assert_eq!(p.state, r.state);
                for k in 0..3 { prop_assert!((p.position_m[k] - r.position_m[k]).abs() < 1e-10); }
            }
        }

        #[test]
        fn formatted_moves_parse_back(x in -2.0f64..2.0, y in -2.0f64..2.0, z in -2.0f64..2.0,
                                      feed in 1e-4f64..1.0, mask in 1u8..8, dwell in 0.0f64..100.0) {
            let letters = ['X', 'Y', 'Z'];
            let vals = [x, y, z];
            let axes: Vec<(char, f64)> = (0..3).filter(|k| mask & (1 << k) != 0)
                .map(|k| (letters[k], vals[k])).collect();
            let line = format_move(&axes, feed);
            let mut f = LineFramer::with_realtime(MAX_LINE_BYTES);
            let framed = f.push(line.as_bytes());
            prop_assert_eq!(framed.len(), 1);
            let Framed::Line(l) = &framed[0] else { panic!("not a line") };
            let Ok(Block::Move { rapid, target_m, feed_m_s, .. }) = parse_block(l) else {
                panic!("did not parse back: {l}")
            };
            prop_assert!(!rapid);
            for k in 0..3 {
                match target_m[k] {
                    Some(v) => {
                        prop_assert!(mask & (1 << k) != 0);
                        prop_assert!((v - vals[k]).abs() <= 0.5e-7 + 1e-12, "{} vs {}", v, vals[k]);
                    }
                    None => prop_assert!(mask & (1 << k) == 0),
                }
            }
            let fb = feed_m_s.unwrap_or(f64::NAN);
            prop_assert!((fb - feed).abs() <= 0.5e-3 / 60_000.0 + 1e-15);
            let d = format_dwell(dwell);
            let Ok(Block::Dwell { dwell_s }) = parse_block(d.trim_end()) else { panic!("dwell: {d}") };
            prop_assert!((dwell_s - dwell).abs() <= 0.5e-3 + 1e-12);
        }
    }
}
