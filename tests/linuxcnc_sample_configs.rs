//! The LinuxCNC driver against LinuxCNC started from the sample configurations Debian ships
//! (`/usr/share/doc/linuxcnc/examples/sample-configs/sim/axis/`), copied with only `[DISPLAY]
//! DISPLAY = linuxcncrsh` changed, as a machine shop's LinuxCNC would be found rather than as
//! geocal writes it: the metric mill with home switches (`axis_mm.ini`), the inch mill
//! (`axis.ini`) and the gantry with 4 joints XYYZ (`gantry/gantry_mm.ini`). One LinuxCNC start
//! per configuration. The operator is another linuxcncrsh client, as a pendant or the AXIS GUI
//! would be. Skips without LinuxCNC or root (saying why), fails when `CI` is set.

mod common;

use std::io::{BufRead, BufReader, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::time::Duration;

use geocal::sim::linuxcnc::LinuxCnc;
use geocal_drivers::linuxcnc::{
    HomePolicy, LinuxCncConfig, LinuxCncMachine, MoveMode, StreamConnector, ALARM_ESTOP,
};
use geocal_drivers::{AxisPositions, DeviceError, Machine, MachineState};

const SAMPLES: &str = "/usr/share/doc/linuxcnc/examples/sample-configs/sim/axis";

/// A shipped sample configuration, or None (skip, saying why; CI fails in
/// `linuxcnc_available` already when LinuxCNC is missing).
fn sample(relative: &str) -> Option<PathBuf> {
    if !common::linuxcnc_available() {
        return None;
    }
    let path = Path::new(SAMPLES).join(relative);
    if path.is_file() {
        return Some(path);
    }
    assert!(
        std::env::var_os("CI").is_none(),
        "CI must run the sample-config tests, but {} is missing",
        path.display()
    );
    eprintln!("skipping: {} is missing", path.display());
    None
}

/// Start LinuxCNC from `ini`, run `exercise` on a current-thread runtime, shut LinuxCNC
/// down; LinuxCNC's log is printed when the exercise panics.
fn with_linuxcnc(ini: &Path, exercise: impl AsyncFnOnce(&LinuxCnc)) {
    let started = std::time::Instant::now();
    let lcnc = LinuxCnc::start_config(ini, Duration::from_secs(180)).expect("LinuxCNC starts");
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime");
    let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        rt.block_on(exercise(&lcnc))
    }));
    drop(rt);
    let log = lcnc.log_tail(40);
    lcnc.shutdown().expect("clean shutdown");
    println!(
        "{}: {:.1} s",
        ini.display(),
        started.elapsed().as_secs_f64()
    );
    if let Err(panic) = outcome {
        eprintln!("LinuxCNC's log:\n{log}");
        std::panic::resume_unwind(panic);
    }
}

fn connector(lcnc: &LinuxCnc) -> StreamConnector {
    let ns = lcnc.connector().expect("namespace connector");
    std::sync::Arc::new(move || {
        let ns = ns.clone();
        Box::pin(async move {
            let stream = tokio::task::spawn_blocking(move || ns.connect())
                .await
                .map_err(std::io::Error::other)??;
            stream.set_nonblocking(true)?;
            tokio::net::TcpStream::from_std(stream)
        })
    })
}

fn config(home: HomePolicy, power_on: bool) -> LinuxCncConfig {
    LinuxCncConfig {
        id: "mill".into(),
        home,
        power_on,
        motion: MoveMode::Rapid,
        reply_timeout_s: 30.0,
        reconnect_timeout_s: 10.0,
        ..LinuxCncConfig::default()
    }
}

fn target(x: f64, y: f64, z: f64) -> AxisPositions {
    [("x", x), ("y", y), ("z", z)]
        .into_iter()
        .map(|(a, v)| (a.to_string(), v))
        .collect()
}

/// Poll until Idle (or an error), at most `limit`.
async fn wait_idle(m: &mut LinuxCncMachine, limit: Duration) -> Result<AxisPositions, DeviceError> {
    let t0 = tokio::time::Instant::now();
    loop {
        if let MachineState::Idle { position } = m.state().await? {
            return Ok(position);
        }
        assert!(t0.elapsed() < limit, "no arrival within {limit:?}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// Move to each target in turn; each must arrive within `tolerance_m`.
async fn visit(m: &mut LinuxCncMachine, targets: &[AxisPositions], tolerance_m: f64) {
    for t in targets {
        m.start_move(t).await.expect("move accepted");
        let at = wait_idle(m, Duration::from_secs(60))
            .await
            .expect("arrives");
        for (axis, want) in t {
            assert!(
                (at[axis] - want).abs() <= tolerance_m,
                "{axis}: at {}, commanded {want}",
                at[axis]
            );
        }
    }
}

/// Another linuxcncrsh client: the operator at a pendant or the AXIS GUI.
struct Operator {
    stream: TcpStream,
    reader: BufReader<TcpStream>,
}

impl Operator {
    /// Connected with control taken (`set enable`), as a GUI holds it.
    fn connect(lcnc: &LinuxCnc) -> Operator {
        let stream = lcnc.connect().expect("operator connects");
        stream
            .set_read_timeout(Some(Duration::from_secs(30)))
            .expect("timeout");
        let reader = BufReader::new(stream.try_clone().expect("clone"));
        let mut op = Operator { stream, reader };
        for line in [
            "hello EMC operator 1.0",
            "set verbose on",
            "set enable EMCTOO",
        ] {
            op.send(line);
        }
        op
    }

    /// The reply to `line` (its echo skipped).
    fn ask(&mut self, line: &str) -> String {
        self.stream
            .write_all(format!("{line}\r\n").as_bytes())
            .expect("write");
        loop {
            let mut reply = String::new();
            let n = self.reader.read_line(&mut reply).expect("reply");
            assert!(n > 0, "{line}: linuxcncrsh closed the connection");
            let reply = reply.trim();
            if !reply.is_empty() && !reply.eq_ignore_ascii_case(line) {
                return reply.to_string();
            }
        }
    }

    /// A `set` that must be acknowledged.
    fn send(&mut self, line: &str) {
        let reply = self.ask(line);
        assert!(
            reply.contains("ACK") && !reply.contains("NAK"),
            "{line}: {reply}"
        );
    }

    /// The value of `get <key>` (without the key).
    fn get(&mut self, key: &str) -> String {
        let reply = self.ask(&format!("get {key}"));
        let (k, value) = reply.split_once(' ').unwrap_or((&reply, ""));
        assert!(k.eq_ignore_ascii_case(key), "get {key}: {reply}");
        value.trim().to_string()
    }

    /// E-stop, machine power, mode and the interpreter's modal codes, as one comparable
    /// line. The motion mode (the first code: G80 found, G0 or G1 after a move) is left out:
    /// every move sets it.
    fn controller_state(&mut self) -> String {
        let codes = self.get("program_codes");
        let modal: Vec<&str> = codes.split_whitespace().skip(1).collect();
        format!(
            "estop {} machine {} mode {} codes {}",
            self.get("estop"),
            self.get("machine"),
            self.get("mode"),
            modal.join(" ")
        )
    }

    /// Wait until `get key` answers `want` (LinuxCNC's status follows a `set` within cycles).
    fn wait_for(&mut self, key: &str, want: &str) {
        for _ in 0..500 {
            if self.get(key).eq_ignore_ascii_case(want) {
                return;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        panic!("get {key} never answered {want}");
    }

    /// Home all joints and wait until the first `joints` report homed.
    fn home_all(&mut self, joints: usize) {
        self.send("set mode manual");
        self.send("set home -1");
        for _ in 0..1500 {
            let flags = self.get("joint_homed");
            if flags.split_whitespace().take(joints).all(|f| f == "YES") {
                return;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        panic!("homing did not finish");
    }
}

/// The metric mill with home switches: refusals leave it exactly as found; an E-stop pressed
/// by the operator in the middle of a run stops it (LinuxCNC stays in E-stop, geocal sends
/// nothing that would release it); once the operator cleared it, a new connection (as
/// `geocal run --resume` opens) finishes the moves.
#[test]
fn axis_mm_estop_stops_the_run_and_refusals_change_nothing() {
    let Some(ini) = sample("axis_mm.ini") else {
        return;
    };
    with_linuxcnc(&ini, async |lcnc| {
        let mut op = Operator::connect(lcnc);
        let fresh = op.controller_state();
        assert!(fresh.starts_with("estop ON machine OFF"), "{fresh}");
        // home = "refuse" with unhomed joints: refused although power_on allows powering on.
        let e = LinuxCncMachine::connect_with(config(HomePolicy::Refuse, true), connector(lcnc))
            .await
            .err()
            .expect("unhomed machine refused");
        assert!(e.to_string().contains("not homed"), "{e}");
        assert_eq!(
            op.controller_state(),
            fresh,
            "refusal changed the controller"
        );
        // In E-stop without power_on: refused, nothing changed.
        let e = LinuxCncMachine::connect_with(config(HomePolicy::Allow, false), connector(lcnc))
            .await
            .err()
            .expect("E-stop refused without power_on");
        let text = e.to_string();
        assert!(
            text.contains("in E-stop") && text.contains("power_on = true"),
            "{text}"
        );
        assert_eq!(
            op.controller_state(),
            fresh,
            "refusal changed the controller"
        );

        // power_on and home allowed: geocal powers on and homes (home switches), then runs.
        let mut m = LinuxCncMachine::connect_with(config(HomePolicy::Allow, true), connector(lcnc))
            .await
            .expect("connects, powers on, homes");
        let plan = [
            target(0.010, 0.005, 0.002),
            target(0.030, -0.010, 0.010),
            target(-0.030, 0.020, -0.005),
            target(0.0, 0.0, 0.0),
        ];
        visit(&mut m, &plan[..1], 1e-6).await;
        // The operator presses E-stop in the middle of the next move.
        m.start_move(&plan[1]).await.expect("move accepted");
        tokio::time::sleep(Duration::from_millis(300)).await;
        assert_eq!(m.state().await.expect("moving"), MachineState::Moving);
        // One linuxcncrsh client has control at a time: the operator takes it, as a GUI does.
        op.send("set enable EMCTOO");
        op.send("set estop on");
        let e = wait_idle(&mut m, Duration::from_secs(30))
            .await
            .expect_err("the E-stop stops the move");
        assert!(
            matches!(
                e,
                DeviceError::Alarm {
                    code: ALARM_ESTOP,
                    ..
                }
            ) && e.to_string().contains("not by geocal"),
            "named as an E-stop once settled: {e}"
        );
        let requests = m.requests();
        let e = m.unlock().await.expect_err("geocal does not release it");
        assert!(e.to_string().contains("--resume"), "{e}");
        let stopped_at = op.get("abs_act_pos");
        std::thread::sleep(Duration::from_millis(1500));
        let state = op.controller_state();
        assert!(state.starts_with("estop ON machine OFF"), "{state}");
        assert_eq!(op.get("abs_act_pos"), stopped_at, "nothing moved");
        // What `unlock` asked: queries only (estop, machine and their settling).
        println!(
            "unlock sent {} queries and no command",
            m.requests() - requests
        );
        // The run ends (its `finish`): in E-stop LinuxCNC refuses mode changes; it says so.
        let e = m
            .finish()
            .await
            .expect_err("nothing can be set back in E-stop");
        assert!(e.to_string().contains("E-stop"), "{e}");
        assert!(op.controller_state().starts_with("estop ON machine OFF"));
        drop(m);

        // The operator clears it at the machine; the resumed run connects without power_on.
        op.send("set estop off");
        op.send("set machine on");
        op.wait_for("machine", "ON");
        let mut m =
            LinuxCncMachine::connect_with(config(HomePolicy::Allow, false), connector(lcnc))
                .await
                .expect("the resumed run connects");
        visit(&mut m, &plan[1..], 1e-6).await;
        m.finish().await.expect("finish");
    });
}

/// The inch mill, found in G20 with the operator's G91 and in manual mode: geocal's moves
/// arrive (positions in inches converted), and afterwards LinuxCNC is in G20, G91 and manual
/// mode again.
#[test]
fn axis_inch_machine_ends_in_g20_with_its_modes() {
    let Some(ini) = sample("axis.ini") else {
        return;
    };
    with_linuxcnc(&ini, async |lcnc| {
        let mut op = Operator::connect(lcnc);
        op.send("set estop off");
        op.send("set machine on");
        op.wait_for("machine", "ON");
        op.home_all(3);
        op.send("set mode mdi");
        op.wait_for("mode", "MDI");
        op.send("set mdi G91");
        op.send("set mode manual");
        op.wait_for("mode", "MANUAL");
        let found = op.controller_state();
        assert!(
            found.contains(" G20 ") && found.contains(" G91 ") && found.contains("mode MANUAL"),
            "{found}"
        );
        let mut m =
            LinuxCncMachine::connect_with(config(HomePolicy::Refuse, false), connector(lcnc))
                .await
                .expect("connects");
        assert_eq!(m.mm_per_unit(), 25.4);
        // linuxcncrsh reports inches with 6 decimals: 25.4 nm.
        visit(
            &mut m,
            &[
                target(0.0254, -0.0127, -0.01),
                target(-0.05, 0.03, -0.02),
                target(0.0, 0.0, 0.0),
            ],
            13e-9,
        )
        .await;
        m.finish().await.expect("finish");
        assert_eq!(op.controller_state(), found, "left as found");
    });
}

/// The gantry (4 joints XYYZ): the driver reads the joint count from LinuxCNC's INI (4;
/// linuxcncrsh itself reports six), refuses with `home = "refuse"` naming all four joints,
/// homes all four with `allow`, and moves; both Y joints follow the Y axis.
#[test]
fn gantry_runs_with_its_four_joints() {
    let Some(ini) = sample("gantry/gantry_mm.ini") else {
        return;
    };
    with_linuxcnc(&ini, async |lcnc| {
        let mut op = Operator::connect(lcnc);
        assert_eq!(op.get("joint_homed"), "NO NO NO NO NO NO");
        let e = LinuxCncMachine::connect_with(config(HomePolicy::Refuse, true), connector(lcnc))
            .await
            .err()
            .expect("unhomed gantry refused");
        assert!(e.to_string().contains("[0, 1, 2, 3] are not homed"), "{e}");
        let mut m = LinuxCncMachine::connect_with(config(HomePolicy::Allow, true), connector(lcnc))
            .await
            .expect("connects, homes 4 joints");
        let homed = op.get("joint_homed");
        assert!(homed.starts_with("YES YES YES YES"), "{homed}");
        let t = target(0.040, 0.030, 0.090);
        visit(&mut m, std::slice::from_ref(&t), 1e-6).await;
        let joints: Vec<f64> = op
            .get("joint_pos")
            .split_whitespace()
            .map(|v| v.parse().expect("number"))
            .collect();
        // Joint 0 is X, joints 1 and 2 the two sides of Y (mm).
        assert!((joints[0] - 40.0).abs() < 1e-5, "{joints:?}");
        assert!((joints[1] - 30.0).abs() < 1e-5, "{joints:?}");
        assert!((joints[2] - 30.0).abs() < 1e-5, "{joints:?}");
        m.finish().await.expect("finish");
    });
}
