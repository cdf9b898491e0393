//! GRBL recovery against the emulator on a pty: an injected alarm comes back as the distinct
//! `DeviceError::Alarm`, `$X` unlocks and the move runs again; a pulled cable (the emulator
//! closes its pty and reappears behind the same link path) is detected, the driver reopens
//! the path, re-sends the interrupted move and reports `disconnect` and `reconnect`.

use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use geocal_drivers::grbl::{
    GrblConfig, GrblEmulator, GrblEmulatorConfig, GrblFaults, GrblMachine, KinematicSink,
};
use geocal_drivers::{AxisPositions, DeviceError, Machine, MachineState};

fn cfg() -> GrblConfig {
    GrblConfig {
        ack_timeout_s: 0.4,
        status_timeout_s: 0.3,
        status_interval_s: 0.005,
        feed_m_s: 0.05,
        ..GrblConfig::default()
    }
}

fn target(x: f64) -> AxisPositions {
    [("x", x), ("y", 0.0), ("z", 0.0)]
        .into_iter()
        .map(|(n, v)| (n.to_string(), v))
        .collect()
}

/// Poll until Idle or an error; gives up after 5 s.
async fn settle(m: &mut impl Machine) -> Result<AxisPositions, DeviceError> {
    let t0 = Instant::now();
    loop {
        if let MachineState::Idle { position } = m.state().await? {
            return Ok(position);
        }
        assert!(t0.elapsed() < Duration::from_secs(5), "never idle");
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

#[tokio::test]
async fn alarm_is_distinct_and_unlock_recovers() {
    let mut emu = GrblEmulator::spawn_pty(
        GrblEmulatorConfig {
            faults: GrblFaults {
                alarm_at_line: Some(2),
                alarm_after_s: 0.05,
                alarm_code: 1,
                ..GrblFaults::default()
            },
            ..GrblEmulatorConfig::default()
        },
        Box::new(KinematicSink::new([0.0; 3])),
    )
    .expect("pty");
    let mut m = GrblMachine::from_stream(emu.take_slave().expect("slave"), cfg()).expect("driver");
    m.start_move(&target(0.001)).await.expect("move 1");
    settle(&mut m).await.expect("arrives");
    // Line 2 starts, then the controller aborts it with ALARM:1.
    m.start_move(&target(0.02)).await.expect("move 2 accepted");
    let err = settle(&mut m).await.expect_err("alarm");
    let DeviceError::Alarm { code, message, .. } = &err else {
        panic!("expected an alarm, got {err}");
    };
    assert_eq!(*code, 1);
    assert!(message.contains("$X"), "{message}");
    // Locked: a move is refused until unlocked, as an alarm (the caller's recovery is `$X`).
    let refused = m.start_move(&target(0.02)).await.expect_err("locked");
    assert!(refused.to_string().contains("error:9"), "{refused}");
    assert!(
        matches!(refused, DeviceError::Alarm { code: 1, .. }),
        "{refused}"
    );
    m.unlock().await.expect("unlock");
    m.start_move(&target(0.02)).await.expect("move again");
    let at = settle(&mut m).await.expect("arrives after unlock");
    assert!((at["x"] - 0.02).abs() < 1e-6);
    assert_eq!(emu.stats().alarms.load(Ordering::Relaxed), 1);
    assert_eq!(emu.stats().unlocks.load(Ordering::Relaxed), 1);
}

#[tokio::test]
async fn pulled_cable_is_detected_and_the_port_reopened() {
    let dir = tempfile::tempdir().expect("tempdir");
    let link = dir.path().join("ttyGRBL");
    let emu = GrblEmulator::spawn_pty_linked(
        GrblEmulatorConfig {
            faults: GrblFaults {
                disconnect_at_line: Some(2),
                reconnect_after_s: Some(0.2),
                ..GrblFaults::default()
            },
            ..GrblEmulatorConfig::default()
        },
        Box::new(KinematicSink::new([0.0; 3])),
        link.clone(),
    )
    .expect("linked pty");
    assert_eq!(emu.slave_path(), link.to_str());
    let mut m = GrblMachine::open(GrblConfig {
        port: link.display().to_string(),
        ..cfg()
    })
    .expect("open by link");
    m.start_move(&target(0.001)).await.expect("move 1");
    settle(&mut m).await.expect("arrives");
    assert!(m.take_link_faults().is_empty());
    // Line 2 pulls the cable; the driver reopens the link and sends the move again.
    let started = Instant::now();
    m.start_move(&target(0.003))
        .await
        .expect("move 2 after reconnect");
    assert!(started.elapsed() >= Duration::from_millis(200));
    let at = settle(&mut m).await.expect("arrives");
    assert!((at["x"] - 0.003).abs() < 1e-6);
    let faults = m.take_link_faults();
    let codes: Vec<&str> = faults.iter().map(|f| f.code.as_str()).collect();
    assert_eq!(codes, ["disconnect", "reconnect"], "{faults:?}");
    assert!(faults[1].message.contains("ttyGRBL"), "{faults:?}");
    assert_eq!(emu.stats().connections.load(Ordering::Relaxed), 2);
    assert!(m.take_link_faults().is_empty());
}

#[tokio::test]
async fn no_reconnect_without_a_path_or_when_disabled() {
    let dir = tempfile::tempdir().expect("tempdir");
    let link = dir.path().join("ttyGRBL");
    let _emu = GrblEmulator::spawn_pty_linked(
        GrblEmulatorConfig {
            faults: GrblFaults {
                disconnect_at_line: Some(1),
                ..GrblFaults::default()
            },
            ..GrblEmulatorConfig::default()
        },
        Box::new(KinematicSink::new([0.0; 3])),
        link.clone(),
    )
    .expect("linked pty");
    let mut m = GrblMachine::open(GrblConfig {
        port: link.display().to_string(),
        reconnect_timeout_s: 0.3,
        ..cfg()
    })
    .expect("open");
    // The controller never comes back: after the reconnect timeout, Disconnected.
    let err = m.start_move(&target(0.001)).await.expect_err("gone");
    assert!(matches!(err, DeviceError::Disconnected { .. }), "{err}");
    assert!(err.to_string().contains("could not reopen"), "{err}");
}

/// An alarm that strikes after the move already ended (between commands) is not lost in the
/// driver's drain: the next move reports it as `DeviceError::Alarm` instead of being sent into
/// the locked controller (which would answer `error:9`); after `$X` the move runs.
#[tokio::test]
async fn alarm_between_commands_is_reported_by_the_next_move() {
    let mut emu = GrblEmulator::spawn_pty(
        GrblEmulatorConfig {
            faults: GrblFaults {
                alarm_at_line: Some(1),
                alarm_after_s: 0.1,
                alarm_code: 1,
                ..GrblFaults::default()
            },
            ..GrblEmulatorConfig::default()
        },
        Box::new(KinematicSink::new([0.0; 3])),
    )
    .expect("pty");
    let mut m = GrblMachine::from_stream(emu.take_slave().expect("slave"), cfg()).expect("driver");
    // 0.1 mm at 50 mm/s: arrived after 2 ms, long before the alarm.
    m.start_move(&target(0.0001)).await.expect("move 1");
    settle(&mut m).await.expect("arrives");
    tokio::time::sleep(Duration::from_millis(200)).await;
    let err = m
        .start_move(&target(0.0002))
        .await
        .expect_err("the alarm comes first");
    assert!(matches!(err, DeviceError::Alarm { code: 1, .. }), "{err}");
    assert_eq!(emu.stats().errors_sent.load(Ordering::Relaxed), 0);
    m.unlock().await.expect("unlock");
    m.start_move(&target(0.0002)).await.expect("move 2");
    let at = settle(&mut m).await.expect("arrives");
    assert!((at["x"] - 0.0002).abs() < 1e-7);
}
