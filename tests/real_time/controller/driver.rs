//! The LinuxCNC machine driver against the real LinuxCNC (`linuxcnc-uspace`, started headless
//! in a private network namespace by `geocal::sim::linuxcnc`): connect, passwords, the homing
//! policy, G53 moves and positions, a move LinuxCNC refuses, an E-stop pressed by another
//! client in the middle of a move and `unlock`, and a connection dropped mid-move. One
//! LinuxCNC instance for all of it (starting one takes seconds and holds a global lock).
//! Skips without LinuxCNC (with the reason); fails instead when `CI` is set.

use crate::common;

use common::{target, wait_idle};

use std::net::Shutdown;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use geocal::sim::linuxcnc::{self, LinuxCnc, MachineSetup};
use geocal_drivers::linuxcnc::{
    HomePolicy, LinuxCncConfig, LinuxCncMachine, MoveMode, Passwords, ProgramStatus,
    StreamConnector, ALARM_ESTOP,
};
use geocal_drivers::{AxisPositions, DeviceError, Machine, MachineState};

/// Connects inside LinuxCNC's namespace and keeps a handle on the latest connection, so that
/// the test can cut it as a pulled cable would.
fn cuttable_connector(
    lcnc: &LinuxCnc,
) -> (StreamConnector, Arc<Mutex<Option<std::net::TcpStream>>>) {
    let ns = lcnc.connector().expect("namespace connector");
    let latest: Arc<Mutex<Option<std::net::TcpStream>>> = Arc::default();
    let keep = latest.clone();
    let connector: StreamConnector = Arc::new(move || {
        let ns = ns.clone();
        let keep = keep.clone();
        Box::pin(async move {
            let std_stream = tokio::task::spawn_blocking(move || ns.connect())
                .await
                .map_err(std::io::Error::other)??;
            *keep.lock().expect("lock") = Some(std_stream.try_clone()?);
            std_stream.set_nonblocking(true)?;
            tokio::net::TcpStream::from_std(std_stream)
        })
    });
    (connector, latest)
}

fn config(home: HomePolicy) -> LinuxCncConfig {
    LinuxCncConfig {
        id: "lcnc".into(),
        home,
        // A fresh LinuxCNC starts in E-stop; the joint count comes from its INI.
        power_on: true,
        feed_m_s: 0.25,
        motion: MoveMode::Feed,
        reply_timeout_s: 30.0,
        reconnect_timeout_s: 30.0,
        ..LinuxCncConfig::default()
    }
}

fn assert_at(position: &AxisPositions, want: &AxisPositions) {
    for (axis, w) in want {
        let p = position[axis];
        // linuxcncrsh prints mm with 6 decimals: 1 nm, plus the float's rounding.
        assert!((p - w).abs() <= 0.6e-9, "{axis}: at {p}, commanded {w}");
    }
}

/// One raw linuxcncrsh session (another client: an operator's GUI) sending `lines` after
/// taking control.
fn operator_sends(lcnc: &LinuxCnc, lines: &[&str]) {
    use std::io::{BufRead, BufReader, Write};
    let mut s = lcnc.connect().expect("second client connects");
    s.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    let mut r = BufReader::new(s.try_clone().unwrap());
    let control = [
        "hello EMC operator 1.0",
        "set verbose on",
        "set enable EMCTOO",
    ];
    for line in control.iter().chain(lines) {
        s.write_all(format!("{line}\r\n").as_bytes()).unwrap();
        let mut reply = String::new();
        while reply.trim().is_empty() || reply.trim().eq_ignore_ascii_case(line) {
            reply.clear();
            r.read_line(&mut reply).expect("reply");
        }
        assert!(reply.contains("ACK"), "{line}: {reply}");
    }
}

pub fn drives_the_real_linuxcnc_through_faults() {
    if !common::linuxcnc_available() {
        return;
    }
    let setup = MachineSetup {
        travel_m: [[0.0, 1.0], [0.0, 1.0], [0.0, 0.5]],
        ..MachineSetup::default()
    };
    let lcnc = LinuxCnc::start(&setup, Duration::from_secs(180)).expect("LinuxCNC starts");
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime");
    let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        rt.block_on(exercise(&lcnc))
    }));
    drop(rt);
    let log = lcnc.log_tail(30);
    lcnc.shutdown().expect("clean shutdown");
    assert!(linuxcnc::linuxcnc_shared_memory().is_empty());
    if let Err(panic) = outcome {
        eprintln!("LinuxCNC's log:\n{log}");
        std::panic::resume_unwind(panic);
    }
}

async fn exercise(lcnc: &LinuxCnc) {
    // Connections of other clients go through `connector`; the driver under test has its
    // own, so that `latest` is its connection.
    let (connector, _) = cuttable_connector(lcnc);
    let (own_connector, latest) = cuttable_connector(lcnc);

    // Wrong passwords: clear refusals naming which one.
    let e = LinuxCncMachine::connect_with_passwords(
        config(HomePolicy::Allow),
        connector.clone(),
        Passwords::new("nope", "EMCTOO"),
    )
    .await
    .err()
    .expect("wrong connect password refused");
    assert!(e.to_string().contains("connect password"), "{e}");
    let e = LinuxCncMachine::connect_with_passwords(
        config(HomePolicy::Allow),
        connector.clone(),
        Passwords::new("EMC", "nope"),
    )
    .await
    .err()
    .expect("wrong enable password refused");
    assert!(e.to_string().contains("enable password"), "{e}");

    // A fresh LinuxCNC is not homed: refused unless the config allows homing, before
    // anything is changed (E-stop and power as found, although power_on allows them).
    let e = LinuxCncMachine::connect_with(config(HomePolicy::Refuse), connector.clone())
        .await
        .err()
        .expect("unhomed machine refused");
    let text = e.to_string();
    assert!(
        matches!(e, DeviceError::Rejected { .. })
            && text.contains("not homed")
            && text.contains("home = \"allow\""),
        "{text}"
    );
    let mut watcher = LinuxCncMachine::observe_with(config(HomePolicy::Refuse), connector.clone())
        .await
        .expect("watcher connects");
    let s = watcher.status().await.expect("status");
    assert!(s.estop && !s.machine_on, "as found: {s:?}");

    let mut m = LinuxCncMachine::connect_with(config(HomePolicy::Allow), own_connector)
        .await
        .expect("connects, homes, MDI");
    assert!(m.server().starts_with("EMCNETSVR"), "{}", m.server());
    assert_eq!(m.mm_per_unit(), 1.0);
    // Homed now: a second connection with homing refused is fine.
    let other = LinuxCncMachine::connect_with(config(HomePolicy::Refuse), connector.clone())
        .await
        .expect("homed machine accepted without homing");
    drop(other);
    // That connection took control; unlock enables this one again.
    m.unlock().await.expect("enable again");

    // G53 moves in metres, positions back in metres to linuxcncrsh's nanometre.
    let a = target(0.1234567, 0.2, 0.05);
    m.start_move(&a).await.expect("move accepted");
    let at = wait_idle(&mut m, Duration::from_secs(60))
        .await
        .expect("arrives");
    assert_at(&at, &a);
    // Polled often, queried at most once per status interval.
    let polls = m.status_polls();
    for _ in 0..200 {
        assert!(matches!(m.state().await, Ok(MachineState::Idle { .. })));
    }
    assert!(
        m.status_polls() - polls <= 3,
        "{}",
        m.status_polls() - polls
    );

    // A move beyond the soft limits: accepted by linuxcncrsh, refused by LinuxCNC; the error
    // says so and the machine stays where it was.
    m.start_move(&target(1.5, 0.2, 0.05)).await.expect("sent");
    let e = wait_idle(&mut m, Duration::from_secs(60))
        .await
        .expect_err("refused");
    assert!(
        matches!(e, DeviceError::Rejected { .. }) && e.to_string().contains("limit"),
        "{e}"
    );

    // E-stop pressed at another client in the middle of a move: an alarm (E-stop, once the
    // state settled); unlock refuses while it is pressed and nothing is sent; once the
    // operator cleared it, unlock takes control back and the move commanded again arrives.
    let b = target(0.9, 0.6, 0.3);
    m.start_move(&b).await.expect("move accepted");
    tokio::time::sleep(Duration::from_millis(800)).await;
    assert_eq!(m.state().await.expect("moving"), MachineState::Moving);
    // (A blocking client on the test's single thread: nothing else needs to run meanwhile.)
    operator_sends(
        lcnc,
        &[
            // Global to linuxcncrsh: a move would then be answered only when done.
            "set set_wait done",
            "set estop on",
        ],
    );
    let e = wait_idle(&mut m, Duration::from_secs(60))
        .await
        .expect_err("E-stop is an alarm");
    assert!(
        matches!(
            e,
            DeviceError::Alarm {
                code: ALARM_ESTOP,
                ..
            }
        ),
        "{e}"
    );
    let e = m
        .start_move(&b)
        .await
        .expect_err("a move is refused in E-stop");
    assert!(matches!(e, DeviceError::Alarm { .. }), "{e}");
    let stopped_at = watcher.status().await.expect("status").position_m;
    let e = m
        .unlock()
        .await
        .expect_err("geocal does not release the E-stop");
    assert!(
        matches!(e, DeviceError::Rejected { .. })
            && e.to_string().contains("in E-stop")
            && e.to_string().contains("--resume"),
        "{e}"
    );
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let s = watcher.status().await.expect("status");
    assert!(
        s.estop && !s.machine_on && s.position_m == stopped_at,
        "still stopped where it stopped: {s:?}"
    );
    operator_sends(lcnc, &["set estop off", "set machine on"]);
    m.unlock()
        .await
        .expect("unlock once the operator cleared it");
    m.start_move(&b).await.expect("move accepted again");
    let at = wait_idle(&mut m, Duration::from_secs(60))
        .await
        .expect("arrives");
    assert_at(&at, &b);

    // The connection cut in the middle of a move: the driver reconnects, LinuxCNC went on,
    // the move arrives; the link faults are reported.
    let c = target(0.2, 0.1, 0.4);
    m.start_move(&c).await.expect("move accepted");
    tokio::time::sleep(Duration::from_millis(500)).await;
    latest
        .lock()
        .expect("lock")
        .as_ref()
        .expect("a connection")
        .shutdown(Shutdown::Both)
        .expect("cut");
    let at = wait_idle(&mut m, Duration::from_secs(60))
        .await
        .expect("arrives after a reconnect");
    assert_at(&at, &c);
    let faults: Vec<String> = m.take_link_faults().into_iter().map(|f| f.code).collect();
    assert_eq!(faults, ["disconnect", "reconnect"]);

    // A watcher (geocal monitor): sees the state and position, commands nothing.
    let s = watcher.status().await.expect("status");
    assert!(
        !s.estop && s.machine_on && s.program == ProgramStatus::Idle,
        "{s:?}"
    );
    for (k, axis) in ["x", "y", "z"].iter().enumerate() {
        assert!((s.position_m[k] - c[*axis]).abs() <= 0.6e-9, "{s:?}");
    }
    let e = watcher
        .start_move(&a)
        .await
        .expect_err("a watcher does not move");
    assert!(e.to_string().contains("watching only"), "{e}");
    m.quit().await.expect("quit");
}

/// The example configuration is valid; passwords inline, a missing host and an emulated
/// LinuxCNC are refused with errors naming the key.
#[test]
fn linuxcnc_configuration_is_checked() {
    use geocal::config::{Config, DriverKind};
    let path =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config/linuxcnc/machine.toml");
    let c = Config::load(&path).expect("the example is valid");
    assert_eq!(c.devices.machine.driver, DriverKind::Linuxcnc);
    let lc = c.devices.machine.linuxcnc.as_ref().expect("settings");
    let pw = lc.password_file.as_ref().expect("password file");
    assert!(
        pw.is_absolute() && pw.ends_with("config/linuxcnc/linuxcnc-passwords.toml"),
        "{pw:?}"
    );
    let stored = toml::to_string(&c).expect("serialises");
    assert!(stored.contains("driver = \"linuxcnc\""));

    let text = std::fs::read_to_string(&path).expect("read");
    let fails = |edited: String, says: &[&str]| {
        let e = Config::parse(&edited, &path)
            .expect_err("refused")
            .to_string();
        for s in says {
            assert!(e.contains(s), "{e}");
        }
    };
    fails(
        text.replace("client_name = \"geocal\"", "enable_password = \"EMCTOO\""),
        &[
            "devices.machine.linuxcnc",
            "enable_password",
            "password_file",
        ],
    );
    fails(
        text.replace("host = \"127.0.0.1\"", ""),
        &["devices.machine.linuxcnc.host", "missing"],
    );
    fails(
        text.replace("driver = \"linuxcnc\"", "driver = \"grbl\""),
        &["devices.machine.linuxcnc", "not \"linuxcnc\""],
    );
    fails(
        text.replace("home = \"refuse\"", "home = \"maybe\""),
        &["home"],
    );
}
