//! The LinuxCNC driver against a small fake linuxcncrsh on 127.0.0.1 (the fault cases the
//! real LinuxCNC does not produce on demand): a refused enable password, garbage and
//! mismatched replies, a connection dropped right after a move was accepted, and a server
//! that does not come back. The real LinuxCNC is exercised in tests/real_time/controller/driver.rs.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use geocal_drivers::linuxcnc::{
    tcp_connector, HomePolicy, LinuxCncConfig, LinuxCncMachine, StreamConnector,
};
use geocal_drivers::{AxisPositions, DeviceError, Machine, MachineState};
use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
use tokio::net::TcpListener;

#[derive(Clone, Default)]
struct Faults {
    nak_enable: bool,
    /// Answer `get <key>` with this line instead.
    replace: Option<(&'static str, &'static str)>,
    /// Close the first connection right after acknowledging its first `set mdi`.
    drop_after_first_mdi: bool,
    /// With that close, the operator presses E-stop (or turns the machine off) while the
    /// driver is away.
    stop_while_away: Option<Stop>,
    /// Every move reports RUNNING for this many polls with the machine short of its target
    /// (a long move) instead of 3.
    running_polls: Option<u32>,
    /// The move with this number (1, 2, ...) stays RUNNING at its target until `set abort`.
    stuck_mdi: Option<u32>,
    /// The move stays PAUSED (the operator's feed hold) at its target instead.
    paused_at_target: bool,
    /// The move stays RUNNING within 1 µm of its target, still creeping (1 µm/s).
    creeping_at_target: bool,
    /// The stuck move's position reads with the noise of a standing servo (±0.1 µm).
    noisy_standstill: bool,
}

#[derive(Clone, Copy, PartialEq)]
enum Stop {
    Estop,
    MachineOff,
}

#[derive(Default)]
struct Machine3 {
    pos: [f64; 3],
    target: [f64; 3],
    polls_left: u32,
    estop: bool,
    machine_on: bool,
    homed: bool,
    connections: u32,
    mdi_seen: u32,
    mode: String,
    /// The interpreter's units, distance and feed mode words, as MDI lines set them.
    units: String,
    distance: String,
    feed_mode: String,
    /// `get user_linear_units`.
    linear_units: String,
    /// Every MDI line received.
    mdi_lines: Vec<String>,
    /// Every line received, with the number of its connection (1, 2, ...).
    received: Vec<(u32, String)>,
    /// The interpreter keeps the current move's command RUNNING (or PAUSED) at its target.
    stuck: bool,
    /// When the current move started to creep.
    creep_started: Option<std::time::Instant>,
    /// Polls of a stuck move so far (the noise's sign).
    stuck_polls: u32,
}

/// Serve linuxcncrsh's protocol (as LinuxCNC 2.9 answers it) on an ephemeral port.
async fn fake(faults: Faults) -> (u16, Arc<Mutex<Machine3>>) {
    let listener = TcpListener::bind("127.0.0.1:0").await.expect("bind");
    let port = listener.local_addr().expect("addr").port();
    let state = Arc::new(Mutex::new(Machine3 {
        estop: true,
        mode: "MANUAL".into(),
        units: "G21".into(),
        linear_units: "MM".into(),
        distance: "G90".into(),
        feed_mode: "G94".into(),
        ..Machine3::default()
    }));
    let shared = state.clone();
    tokio::spawn(async move {
        while let Ok((sock, _)) = listener.accept().await {
            let state = shared.clone();
            let faults = faults.clone();
            tokio::spawn(async move {
                let connection = {
                    let mut s = state.lock().unwrap();
                    s.connections += 1;
                    s.connections
                };
                let first = connection == 1;
                let (rd, mut wr) = sock.into_split();
                let mut lines = BufReader::new(rd).lines();
                let mut echo = true;
                while let Ok(Some(line)) = lines.next_line().await {
                    let line = line.trim().to_string();
                    if line.is_empty() {
                        continue;
                    }
                    let words: Vec<String> = line
                        .split_whitespace()
                        .map(|w| w.to_ascii_lowercase())
                        .collect();
                    state
                        .lock()
                        .unwrap()
                        .received
                        .push((connection, line.clone()));
                    let (reply, close) = answer(&words, &line, &state, &faults, first);
                    let mut out = String::new();
                    if echo && words[0] != "hello" {
                        out.push_str(&format!("{line}\r\n"));
                    }
                    if words.len() >= 3 && words[0] == "set" && words[1] == "echo" {
                        echo = words[2] == "on";
                    }
                    out.push_str(&reply);
                    if wr.write_all(out.as_bytes()).await.is_err() || close {
                        return;
                    }
                }
            });
        }
    });
    (port, state)
}

fn answer(
    words: &[String],
    line: &str,
    state: &Arc<Mutex<Machine3>>,
    faults: &Faults,
    first: bool,
) -> (String, bool) {
    let mut s = state.lock().unwrap();
    let on_off = |b: bool| if b { "ON" } else { "OFF" };
    let ack = |k: &str| format!("SET {} ACK\n\r", k.to_ascii_uppercase());
    let nak = |k: &str| format!("SET {} NAK\n\r", k.to_ascii_uppercase());
    let w = |i: usize| words.get(i).map(String::as_str).unwrap_or("");
    match (w(0), w(1)) {
        ("hello", _) if w(1) == "emc" => ("HELLO ACK FAKE 1.1\r\n".into(), false),
        ("hello", _) => ("HELLO NAK\r\n".into(), false),
        ("set", "enable") if faults.nak_enable => (nak("enable"), false),
        ("set", "estop") => {
            s.estop = w(2) == "on";
            if s.estop {
                s.machine_on = false;
            }
            (ack("estop"), false)
        }
        ("set", "machine") if s.estop => (nak("machine"), false),
        ("set", "machine") => {
            s.machine_on = w(2) == "on";
            (ack("machine"), false)
        }
        ("set", "mode") => {
            s.mode = w(2).to_ascii_uppercase();
            (ack("mode"), false)
        }
        ("set", "home") if s.mode != "MANUAL" => (ack("home"), false),
        ("set", "home") => {
            s.homed = true;
            (ack("home"), false)
        }
        ("set", "mdi") if s.mode != "MDI" => (nak("mdi"), false),
        ("set", "mdi") => {
            s.mdi_lines.push(words[2..].join(" "));
            let mut moves = false;
            for word in &words[2..] {
                match word.as_str() {
                    "g20" | "g21" => s.units = word.to_ascii_uppercase(),
                    "g90" | "g91" => s.distance = word.to_ascii_uppercase(),
                    "g93" | "g94" | "g95" => s.feed_mode = word.to_ascii_uppercase(),
                    "g0" | "g1" => moves = true,
                    _ => {}
                }
                let (letter, num) = word.split_at(1);
                let k = match letter {
                    "x" => 0,
                    "y" => 1,
                    "z" => 2,
                    _ => continue,
                };
                s.target[k] = num.parse().unwrap_or(f64::NAN);
            }
            if !moves {
                return (ack("mdi"), false);
            }
            s.polls_left = faults.running_polls.unwrap_or(3);
            s.mdi_seen += 1;
            s.stuck = faults.stuck_mdi == Some(s.mdi_seen)
                || faults.paused_at_target
                || faults.creeping_at_target;
            s.creep_started = None;
            s.stuck_polls = 0;
            let close = faults.drop_after_first_mdi && first && s.mdi_seen == 1;
            if close {
                match faults.stop_while_away {
                    Some(Stop::Estop) => {
                        s.estop = true;
                        s.machine_on = false;
                    }
                    Some(Stop::MachineOff) => s.machine_on = false,
                    None => {}
                }
            }
            (ack("mdi"), close)
        }
        ("set", "abort") => {
            s.stuck = false;
            s.polls_left = 0;
            (ack("abort"), false)
        }
        ("set", sub) => (ack(sub), false),
        ("get", key) => {
            if let Some((k, r)) = faults.replace {
                if k == key {
                    return (format!("{r}\r\n"), false);
                }
            }
            let value = match key {
                "estop" => format!("ESTOP {}", on_off(s.estop)),
                "machine" => format!("MACHINE {}", on_off(s.machine_on)),
                "mode" => format!("MODE {}", s.mode),
                "enable" => "ENABLE ON".into(),
                "joint_homed" => {
                    let h = if s.homed { "YES" } else { "NO" };
                    format!("JOINT_HOMED {h} {h} {h} NO NO NO")
                }
                "user_linear_units" => format!("USER_LINEAR_UNITS {}", s.linear_units),
                "program_codes" => format!(
                    "PROGRAM_CODES G80 G17 G40 {} {} {} G54 G49 G99 G64 G97 G91.1 G8 G92.2 F0 S0",
                    s.units, s.distance, s.feed_mode
                ),
                "error" => "ERROR OK".into(),
                "program_status" => {
                    if s.stuck {
                        s.pos = s.target;
                        if faults.creeping_at_target {
                            // mm: from 0.9 µm short, 1 µm/s closer.
                            let started = *s.creep_started.get_or_insert_with(Instant::now);
                            s.pos[0] -= 0.0009 - 1e-3 * started.elapsed().as_secs_f64().min(0.9);
                        }
                        if faults.noisy_standstill {
                            // mm: ±0.1 µm about the target, alternating.
                            s.stuck_polls += 1;
                            s.pos[0] += if s.stuck_polls % 2 == 0 { 1e-4 } else { -1e-4 };
                        }
                        if faults.paused_at_target {
                            "PROGRAM_STATUS PAUSED".into()
                        } else {
                            "PROGRAM_STATUS RUNNING".into()
                        }
                    } else if s.polls_left > 0 {
                        s.polls_left -= 1;
                        "PROGRAM_STATUS RUNNING".into()
                    } else {
                        s.pos = s.target;
                        "PROGRAM_STATUS IDLE".into()
                    }
                }
                "abs_act_pos" => format!(
                    "ABS_ACT_POS {:.6} {:.6} {:.6} 0.000000 0.000000 0.000000",
                    s.pos[0], s.pos[1], s.pos[2]
                ),
                other => return (format!("GET {} NAK\r\n\r\n", other.to_uppercase()), false),
            };
            (format!("{value}\r\n"), false)
        }
        _ => (format!("unknown {line}\r\n"), false),
    }
}

fn config(port: u16) -> LinuxCncConfig {
    LinuxCncConfig {
        host: "127.0.0.1".into(),
        port,
        home: HomePolicy::Allow,
        power_on: true,
        joints: Some(3),
        status_interval_s: 0.0,
        reply_timeout_s: 2.0,
        reconnect_timeout_s: 2.0,
        ..LinuxCncConfig::default()
    }
}

fn target(x: f64, y: f64, z: f64) -> AxisPositions {
    [("x", x), ("y", y), ("z", z)]
        .into_iter()
        .map(|(a, v)| (a.to_string(), v))
        .collect()
}

async fn wait_idle(m: &mut LinuxCncMachine) -> Result<AxisPositions, DeviceError> {
    for _ in 0..200 {
        if let MachineState::Idle { position } = m.state().await? {
            return Ok(position);
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    panic!("no arrival");
}

#[tokio::test]
async fn connects_homes_moves_and_converts_units() {
    let (port, state) = fake(Faults::default()).await;
    let mut m = LinuxCncMachine::connect(config(port))
        .await
        .expect("connects");
    {
        let s = state.lock().unwrap();
        assert!(!s.estop && s.machine_on && s.homed, "powered up and homed");
    }
    let t = target(0.25, 0.5, 0.125);
    m.start_move(&t).await.expect("accepted");
    assert_eq!(m.state().await.unwrap(), MachineState::Moving);
    let at = wait_idle(&mut m).await.expect("arrives");
    assert_eq!(state.lock().unwrap().target, [250.0, 500.0, 125.0], "mm");
    for (a, v) in &t {
        assert!((at[a] - v).abs() < 1e-12, "{a}");
    }
}

#[tokio::test]
async fn refusals_are_clear_errors() {
    let (port, _) = fake(Faults {
        nak_enable: true,
        ..Faults::default()
    })
    .await;
    let e = LinuxCncMachine::connect(config(port))
        .await
        .err()
        .expect("refused");
    assert!(
        matches!(e, DeviceError::Rejected { .. }) && e.to_string().contains("enable password"),
        "{e}"
    );
    let (port, _) = fake(Faults::default()).await;
    let e = LinuxCncMachine::connect(LinuxCncConfig {
        home: HomePolicy::Refuse,
        ..config(port)
    })
    .await
    .err()
    .expect("not homed");
    assert!(e.to_string().contains("[0, 1, 2] are not homed"), "{e}");
}

/// Every check that could refuse a run comes before anything is changed: an unhomed machine
/// (`home = "refuse"`) or one in E-stop without `power_on` is refused with the E-stop, the
/// power and the mode exactly as found.
#[tokio::test]
async fn refusals_leave_the_machine_as_found() {
    for (home, power_on, says) in [
        (HomePolicy::Refuse, true, "not homed"),
        (HomePolicy::Allow, false, "power_on = true"),
    ] {
        let (port, state) = fake(Faults::default()).await;
        let e = LinuxCncMachine::connect(LinuxCncConfig {
            home,
            power_on,
            ..config(port)
        })
        .await
        .err()
        .expect("refused");
        assert!(
            matches!(e, DeviceError::Rejected { .. }) && e.to_string().contains(says),
            "{e}"
        );
        let s = state.lock().unwrap();
        assert!(
            s.estop && !s.machine_on && !s.homed && s.mode == "MANUAL",
            "changed: estop {} machine {} homed {} mode {}",
            s.estop,
            s.machine_on,
            s.homed,
            s.mode
        );
    }
}

/// An operator's modal state is kept: an interpreter in G20 gets its moves in inches (never
/// G21), G91/G93 are set again as soon as the machine stands, and `finish` sets the task
/// mode back.
#[tokio::test]
async fn the_operators_modes_are_left_as_found() {
    let (port, state) = fake(Faults::default()).await;
    {
        let mut s = state.lock().unwrap();
        s.linear_units = "INCH".into();
        s.units = "G20".into();
        s.distance = "G91".into();
        s.feed_mode = "G93".into();
    }
    let mut m = LinuxCncMachine::connect(config(port))
        .await
        .expect("connects");
    m.start_move(&target(0.0254, 0.0508, 0.00254))
        .await
        .expect("accepted");
    wait_idle(&mut m).await.expect("arrives");
    {
        let s = state.lock().unwrap();
        assert_eq!(
            s.mdi_lines,
            [
                "g20 g90 g94 g53 g1 x1.00000000 y2.00000000 z0.10000000 f23.6220",
                "g91 g93"
            ]
        );
        assert_eq!(s.target, [1.0, 2.0, 0.1], "inches");
        assert_eq!(
            (&*s.units, &*s.distance, &*s.feed_mode),
            ("G20", "G91", "G93")
        );
        assert_eq!(s.mode, "MDI");
    }
    m.finish().await.expect("finish");
    assert_eq!(state.lock().unwrap().mode, "MANUAL");
}

#[tokio::test]
async fn garbage_and_mismatched_replies_are_protocol_errors() {
    for (key, reply, says) in [
        (
            "program_status",
            "PROGRAM_STATUS W#@!",
            "get program_status",
        ),
        (
            "program_status",
            "ESTOP OFF",
            "unexpected reply to `get program_status`",
        ),
        ("abs_act_pos", "ABS_ACT_POS 1.0 banana 2", "banana"),
        ("abs_act_pos", "ABS_ACT_POS 1.0", "at least 3"),
        ("program_status", "\u{1}\u{2}\u{3}", "unexpected reply"),
    ] {
        let (port, _) = fake(Faults {
            replace: Some((key, reply)),
            ..Faults::default()
        })
        .await;
        let mut m = LinuxCncMachine::connect(config(port))
            .await
            .expect("connects");
        m.start_move(&target(0.1, 0.1, 0.1))
            .await
            .expect("accepted");
        let e = wait_idle(&mut m).await.expect_err("garbage is an error");
        assert!(
            matches!(e, DeviceError::Protocol { .. }) && e.to_string().contains(says),
            "{reply:?}: {e}"
        );
    }
    // A garbled unit reply fails the connection, naming it.
    let (port, _) = fake(Faults {
        replace: Some(("user_linear_units", "USER_LINEAR_UNITS FURLONG")),
        ..Faults::default()
    })
    .await;
    let e = LinuxCncMachine::connect(config(port))
        .await
        .err()
        .expect("refused");
    assert!(e.to_string().contains("user_linear_units"), "{e}");
}

#[tokio::test]
async fn a_connection_dropped_after_a_move_reconnects_and_arrives() {
    let (port, state) = fake(Faults {
        drop_after_first_mdi: true,
        ..Faults::default()
    })
    .await;
    let mut m = LinuxCncMachine::connect(config(port))
        .await
        .expect("connects");
    let t = target(0.3, 0.2, 0.1);
    m.start_move(&t).await.expect("accepted before the drop");
    let at = wait_idle(&mut m)
        .await
        .expect("arrives after the reconnect");
    assert!((at["x"] - 0.3).abs() < 1e-12);
    let codes: Vec<String> = m.take_link_faults().into_iter().map(|f| f.code).collect();
    assert_eq!(codes, ["disconnect", "reconnect"]);
    assert_eq!(state.lock().unwrap().connections, 2);
}

#[tokio::test]
async fn a_server_that_does_not_come_back_is_a_disconnection() {
    // A connector that works once, then finds nobody listening.
    let (port, _) = fake(Faults {
        drop_after_first_mdi: true,
        ..Faults::default()
    })
    .await;
    let calls = Arc::new(Mutex::new(0u32));
    let inner = tcp_connector("127.0.0.1", port);
    let counted = calls.clone();
    let connector: StreamConnector = Arc::new(move || {
        let n = {
            let mut c = counted.lock().unwrap();
            *c += 1;
            *c
        };
        if n == 1 {
            inner()
        } else {
            Box::pin(async {
                Err(std::io::Error::new(
                    std::io::ErrorKind::ConnectionRefused,
                    "refused",
                ))
            })
        }
    });
    let mut m = LinuxCncMachine::connect_with(
        LinuxCncConfig {
            reconnect_timeout_s: 0.5,
            ..config(port)
        },
        connector,
    )
    .await
    .expect("connects");
    m.start_move(&target(0.1, 0.1, 0.1))
        .await
        .expect("accepted");
    let e = wait_idle(&mut m).await.expect_err("gone");
    assert!(
        matches!(e, DeviceError::Disconnected { .. })
            && e.to_string().contains("could not reconnect"),
        "{e}"
    );
    assert!(*calls.lock().unwrap() >= 2);
}

/// The connection drops while the operator stops the machine (E-stop, or machine off): the
/// driver reconnects and, before commanding anything, finds the stop and reports it as an
/// alarm naming it; `unlock` refuses while it lasts. The new connection sends no command that
/// changes LinuxCNC's state (E-stop, power, mode, homing, MDI, abort), nor takes control
/// (`set enable`) of a machine someone else stopped.
#[tokio::test]
async fn a_reconnect_finds_the_operators_stop_and_changes_nothing() {
    for (stop, code, says) in [
        (
            Stop::Estop,
            geocal_drivers::linuxcnc::ALARM_ESTOP,
            "in E-stop",
        ),
        (
            Stop::MachineOff,
            geocal_drivers::linuxcnc::ALARM_MACHINE_OFF,
            "powered off",
        ),
    ] {
        let (port, state) = fake(Faults {
            drop_after_first_mdi: true,
            stop_while_away: Some(stop),
            ..Faults::default()
        })
        .await;
        let mut m = LinuxCncMachine::connect(config(port))
            .await
            .expect("connects");
        m.start_move(&target(0.3, 0.2, 0.1))
            .await
            .expect("accepted before the drop");
        let e = wait_idle(&mut m).await.expect_err("the stop is found");
        assert!(
            matches!(e, DeviceError::Alarm { code: c, .. } if c == code)
                && e.to_string().contains(says)
                && e.to_string().contains("not by geocal"),
            "{e}"
        );
        let e = m.unlock().await.expect_err("geocal does not undo it");
        assert!(e.to_string().contains("--resume"), "{e}");
        let codes: Vec<String> = m.take_link_faults().into_iter().map(|f| f.code).collect();
        assert_eq!(codes, ["disconnect", "reconnect"]);
        let s = state.lock().unwrap();
        let after: Vec<&str> = s
            .received
            .iter()
            .filter(|(c, _)| *c > 1)
            .map(|(_, l)| l.as_str())
            .collect();
        let commands: Vec<&str> = after
            .iter()
            .copied()
            .filter(|l| {
                let l = l.to_ascii_lowercase();
                l.starts_with("set ")
                    && !["set verbose", "set echo"]
                        .iter()
                        .any(|ok| l.starts_with(ok))
            })
            .collect();
        assert!(
            commands.is_empty(),
            "the reconnect sent {commands:?} (all: {after:?})"
        );
        assert!(s.estop || !s.machine_on, "still stopped");
    }
}

/// Poll until the machine reports Idle, at most `limit`; None if it did not.
async fn idle_within(
    m: &mut LinuxCncMachine,
    limit: Duration,
) -> Result<Option<AxisPositions>, DeviceError> {
    let start = std::time::Instant::now();
    while start.elapsed() < limit {
        if let MachineState::Idle { position } = m.state().await? {
            return Ok(Some(position));
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    Ok(None)
}

/// The lines of connection 1 from the `n`-th `set mdi` on.
fn lines_from_mdi(state: &Arc<Mutex<Machine3>>, n: usize) -> Vec<String> {
    let s = state.lock().unwrap();
    let first = s
        .received
        .iter()
        .enumerate()
        .filter(|(_, (_, l))| l.to_ascii_lowercase().starts_with("set mdi"))
        .nth(n - 1)
        .map(|(i, _)| i)
        .expect("that MDI line");
    s.received[first..].iter().map(|(_, l)| l.clone()).collect()
}

/// LinuxCNC keeps a move's MDI command RUNNING with the machine standing at its target (as
/// LinuxCNC 2.9.0~pre1 does now and then on a loaded computer): once the machine has stood
/// there for `stall_timeout_s`, the driver ends the command with `set abort` (and nothing
/// else: no E-stop, power, mode or homing command), records an `mdi_stuck` link fault, and
/// the move arrives. A long move short of its target and an operator's pause at the target
/// are never aborted.
#[tokio::test]
async fn a_move_kept_running_at_its_target_is_aborted_and_arrives() {
    let limit = Duration::from_secs(20);
    let stall = |port| LinuxCncConfig {
        stall_timeout_s: 0.2,
        ..config(port)
    };
    let (port, state) = fake(Faults {
        stuck_mdi: Some(2),
        ..Faults::default()
    })
    .await;
    let mut m = LinuxCncMachine::connect(stall(port))
        .await
        .expect("connects");
    m.start_move(&target(0.1, 0.2, 0.3)).await.expect("move 1");
    idle_within(&mut m, limit)
        .await
        .expect("polls")
        .expect("move 1 arrives");
    m.start_move(&target(0.3, 0.2, 0.1)).await.expect("move 2");
    let at = idle_within(&mut m, limit)
        .await
        .expect("polls")
        .expect("the stuck move arrives once aborted");
    assert!((at["x"] - 0.3).abs() < 1e-12 && (at["z"] - 0.1).abs() < 1e-12);
    let faults = m.take_link_faults();
    assert_eq!(faults.len(), 1, "{faults:?}");
    assert_eq!(faults[0].code, "mdi_stuck");
    assert!(
        faults[0].message.contains("RUNNING") && faults[0].message.contains("set abort"),
        "{}",
        faults[0].message
    );
    let commands: Vec<String> = lines_from_mdi(&state, 2)
        .into_iter()
        .filter(|l| l.to_ascii_lowercase().starts_with("set "))
        .collect();
    assert_eq!(commands.len(), 2, "the move and one abort: {commands:?}");
    assert!(
        commands[1].eq_ignore_ascii_case("set abort"),
        "{commands:?}"
    );

    // The same with the position reading the noise of a standing servo (±0.1 µm, inside the
    // standstill band): still standing, aborted once.
    let (port, state) = fake(Faults {
        stuck_mdi: Some(1),
        noisy_standstill: true,
        ..Faults::default()
    })
    .await;
    let mut m = LinuxCncMachine::connect(stall(port))
        .await
        .expect("connects");
    m.start_move(&target(0.1, 0.2, 0.3)).await.expect("move");
    let at = idle_within(&mut m, limit)
        .await
        .expect("polls")
        .expect("the noisy stuck move arrives once aborted");
    assert!((at["x"] - 0.1).abs() <= 1e-6, "{at:?}");
    let faults = m.take_link_faults();
    assert_eq!(faults.len(), 1, "{faults:?}");
    assert_eq!(faults[0].code, "mdi_stuck");
    assert_eq!(
        lines_from_mdi(&state, 1)
            .iter()
            .filter(|l| l.eq_ignore_ascii_case("set abort"))
            .count(),
        1
    );

    // A long move, short of its target for longer than `stall_timeout_s`: no abort.
    let (port, state) = fake(Faults {
        running_polls: Some(100),
        ..Faults::default()
    })
    .await;
    let mut m = LinuxCncMachine::connect(stall(port))
        .await
        .expect("connects");
    let started = std::time::Instant::now();
    m.start_move(&target(0.1, 0.2, 0.3)).await.expect("move");
    idle_within(&mut m, limit)
        .await
        .expect("polls")
        .expect("the long move arrives");
    assert!(
        started.elapsed() > Duration::from_secs_f64(0.4),
        "longer than the stall"
    );
    assert!(m.take_link_faults().is_empty());
    assert!(!lines_from_mdi(&state, 1)
        .iter()
        .any(|l| l.eq_ignore_ascii_case("set abort")));

    // The operator's pause (PAUSED) at the target is theirs, and a move still creeping
    // within the tolerance (1 µm/s) is moving on a machine whose feedback resolves 0.05 µm:
    // no abort, not arrived.
    for (faults, what) in [
        (
            Faults {
                paused_at_target: true,
                ..Faults::default()
            },
            "paused",
        ),
        (
            Faults {
                creeping_at_target: true,
                ..Faults::default()
            },
            "creeping",
        ),
    ] {
        let (port, state) = fake(faults).await;
        let fine = LinuxCncConfig {
            standstill_band_m: 0.05e-6,
            ..stall(port)
        };
        let mut m = LinuxCncMachine::connect(fine).await.expect("connects");
        m.start_move(&target(0.1, 0.2, 0.3)).await.expect("move");
        let at = idle_within(&mut m, Duration::from_millis(700))
            .await
            .expect("polls");
        assert!(at.is_none(), "a {what} move has not arrived");
        assert!(m.take_link_faults().is_empty(), "{what}");
        assert!(
            !lines_from_mdi(&state, 1)
                .iter()
                .any(|l| l.eq_ignore_ascii_case("set abort")),
            "{what}"
        );
    }
}
