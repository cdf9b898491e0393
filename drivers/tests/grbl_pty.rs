//! The GRBL driver against the GRBL emulator over a pseudo-terminal: moves and arrival,
//! error codes, status rate limiting and injected faults (lost `ok`, silence, disconnect).

use std::time::{Duration, Instant};

use geocal_drivers::grbl::{
    GrblConfig, GrblEmulator, GrblEmulatorConfig, GrblFaults, GrblMachine, KinematicSink,
};
use geocal_drivers::{AxisPositions, DeviceError, Machine, MachineState};
use tokio_serial::SerialStream;

fn cfg() -> GrblConfig {
    GrblConfig {
        ack_timeout_s: 0.4,
        status_timeout_s: 0.3,
        feed_m_s: 0.05,
        ..GrblConfig::default()
    }
}

fn rig(emu_cfg: GrblEmulatorConfig, cfg: GrblConfig) -> (GrblEmulator, GrblMachine<SerialStream>) {
    let mut emu =
        GrblEmulator::spawn_pty(emu_cfg, Box::new(KinematicSink::new([0.0; 3]))).expect("pty");
    let slave = emu.take_slave().expect("slave");
    let m = GrblMachine::from_stream(slave, cfg).expect("driver");
    (emu, m)
}

fn faults(f: GrblFaults) -> GrblEmulatorConfig {
    GrblEmulatorConfig {
        faults: f,
        ..GrblEmulatorConfig::default()
    }
}

fn target(x: f64, y: f64, z: f64) -> AxisPositions {
    [("x", x), ("y", y), ("z", z)]
        .into_iter()
        .map(|(n, v)| (n.to_string(), v))
        .collect()
}

/// Poll until Idle; returns the position and whether Moving was seen first.
async fn wait_idle(m: &mut impl Machine, within: Duration) -> (AxisPositions, bool) {
    let t0 = Instant::now();
    let mut saw_moving = false;
    loop {
        match m.state().await.expect("state") {
            MachineState::Idle { position } => return (position, saw_moving),
            MachineState::Moving => saw_moving = true,
        }
        assert!(
            t0.elapsed() < within,
            "machine did not arrive in {within:?}"
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

/// A 5-axis controller (X, Y, Z, A, B): rotary targets in radians go out in degrees, come
/// back in the status report and count for arrival; a 3-axis controller refuses A words.
#[tokio::test]
async fn rotary_axes_a_and_b() {
    let sink = KinematicSink::with_rotary([0.0; 3], vec![0.0, 0.0]);
    let mut emu =
        GrblEmulator::spawn_pty(GrblEmulatorConfig::default(), Box::new(sink)).expect("pty");
    let five = GrblConfig {
        axis_letters: [("x", 'X'), ("y", 'Y'), ("z", 'Z'), ("a", 'A'), ("b", 'B')]
            .into_iter()
            .map(|(n, l)| (n.to_string(), l))
            .collect(),
        feed_m_s: 1.0,
        ..cfg()
    };
    let mut m = GrblMachine::from_stream(emu.take_slave().expect("slave"), five).expect("driver");
    let goal: AxisPositions = [
        ("x", 0.01),
        ("y", 0.0),
        ("z", -0.02),
        ("a", std::f64::consts::FRAC_PI_2),
        ("b", -0.3),
    ]
    .into_iter()
    .map(|(n, v)| (n.to_string(), v))
    .collect();
    m.start_move(&goal).await.expect("move accepted");
    let (pos, saw_moving) = wait_idle(&mut m, Duration::from_secs(3)).await;
    // 90° and 17° at 60000 mm/min (a degree counts as a mm): about 0.1 s.
    assert!(saw_moving);
    assert!(
        (pos["a"] - std::f64::consts::FRAC_PI_2).abs() < 2e-7,
        "{pos:?}"
    );
    assert!((pos["b"] + 0.3).abs() < 2e-7, "{pos:?}");
    assert!((pos["z"] + 0.02).abs() < 1e-7, "{pos:?}");
    let status = m.last_status().expect("status");
    assert_eq!(status.rotary_rad.len(), 2);

    // The 3-axis emulator answers error:20 to an A word; the driver rejects the move.
    let (_emu3, mut m3) = rig(
        GrblEmulatorConfig::default(),
        GrblConfig {
            axis_letters: [("x", 'X'), ("a", 'A')]
                .into_iter()
                .map(|(n, l)| (n.to_string(), l))
                .collect(),
            ..cfg()
        },
    );
    let a_only: AxisPositions = [("a".to_string(), 0.1)].into_iter().collect();
    let err = m3.start_move(&a_only).await.expect_err("no A axis");
    assert!(err.to_string().contains("error:20"), "{err}");
}

#[tokio::test]
async fn move_and_arrival() {
    let (_emu, mut m) = rig(GrblEmulatorConfig::default(), cfg());
    let goal = target(0.01, -0.005, 0.0021234);
    m.start_move(&goal).await.expect("move accepted");
    let (pos, saw_moving) = wait_idle(&mut m, Duration::from_secs(3)).await;
    assert!(saw_moving, "an 11 mm move at 50 mm/s must be seen moving");
    for (axis, want) in &goal {
        assert!(
            (pos[axis] - want).abs() < 1e-7,
            "{axis}: {} vs {want}",
            pos[axis]
        );
    }
    assert_eq!(m.controller_version(), Some("1.1h"));
    // A partial move keeps the other axes where they were.
    let only_x: AxisPositions = [("x".to_string(), 0.0)].into_iter().collect();
    m.start_move(&only_x).await.expect("move accepted");
    let (pos, _) = wait_idle(&mut m, Duration::from_secs(3)).await;
    assert!(pos["x"].abs() < 1e-7 && (pos["y"] + 0.005).abs() < 1e-7);
}

#[tokio::test]
async fn opens_the_slave_by_path() {
    let emu = GrblEmulator::spawn_pty(
        GrblEmulatorConfig::default(),
        Box::new(KinematicSink::new([0.0; 3])),
    )
    .expect("pty");
    let path = emu.slave_path().expect("slave path").to_string();
    let mut m = GrblMachine::open(GrblConfig {
        port: path,
        ..cfg()
    })
    .expect("open by path");
    m.start_move(&target(0.001, 0.0, 0.0)).await.expect("move");
    let (pos, _) = wait_idle(&mut m, Duration::from_secs(3)).await;
    assert!((pos["x"] - 0.001).abs() < 1e-7);
}

#[tokio::test]
async fn error_codes_become_clear_errors() {
    let (emu, mut m) = rig(
        faults(GrblFaults {
            error_at_lines: vec![1],
            error_code: 20,
            ..GrblFaults::default()
        }),
        cfg(),
    );
    let err = m.start_move(&target(0.001, 0.0, 0.0)).await.unwrap_err();
    let msg = err.to_string();
    assert!(matches!(err, DeviceError::Rejected { .. }), "{msg}");
    assert!(
        msg.contains("error:20") && msg.contains("unsupported or invalid g-code"),
        "{msg}"
    );
    // Beyond travel (soft limits at +-1 m).
    let err = m.start_move(&target(1.5, 0.0, 0.0)).await.unwrap_err();
    assert!(err.to_string().contains("error:15"), "{err}");
    // Unknown axis: refused before anything is sent.
    let bad: AxisPositions = [("q".to_string(), 0.0)].into_iter().collect();
    assert!(m
        .start_move(&bad)
        .await
        .unwrap_err()
        .to_string()
        .contains("\"q\""));
    // The controller still works, and a rejected move did not change the target.
    m.start_move(&target(0.002, 0.0, 0.0)).await.expect("move");
    let (pos, _) = wait_idle(&mut m, Duration::from_secs(3)).await;
    assert!((pos["x"] - 0.002).abs() < 1e-7);
    assert_eq!(
        emu.stats().moves.load(std::sync::atomic::Ordering::Relaxed),
        1
    );
}

#[tokio::test]
async fn soft_limit_alarm_is_an_error() {
    let (_emu, mut m) = rig(
        GrblEmulatorConfig {
            soft_limit_alarm: true,
            ..GrblEmulatorConfig::default()
        },
        cfg(),
    );
    let err = m.start_move(&target(0.0, 0.0, -3.0)).await.unwrap_err();
    assert!(err.to_string().contains("ALARM:2"), "{err}");
    let err = m.state().await.unwrap_err();
    assert!(err.to_string().contains("Alarm"), "{err}");
}

#[tokio::test]
async fn status_queries_are_rate_limited() {
    let (emu, mut m) = rig(GrblEmulatorConfig::default(), cfg());
    let t0 = Instant::now();
    let mut calls = 0;
    while t0.elapsed() < Duration::from_millis(300) {
        m.state().await.expect("state");
        calls += 1;
        tokio::task::yield_now().await;
    }
    let sent = m.status_queries();
    // 300 ms at one query per 50 ms at most: 6, plus the first.
    assert!(calls > 50, "the loop should be tight ({calls} calls)");
    assert!((2..=7).contains(&sent), "{sent} queries in 300 ms");
    tokio::time::sleep(Duration::from_millis(20)).await;
    let seen = emu
        .stats()
        .status_queries
        .load(std::sync::atomic::Ordering::Relaxed);
    assert_eq!(seen, sent);
}

#[tokio::test]
async fn lost_ok_times_out_with_a_clear_message() {
    let (_emu, mut m) = rig(
        faults(GrblFaults {
            drop_ok_at_lines: vec![1],
            ..GrblFaults::default()
        }),
        cfg(),
    );
    let t0 = Instant::now();
    let err = m.start_move(&target(0.003, 0.0, 0.0)).await.unwrap_err();
    assert!(t0.elapsed() < Duration::from_millis(900));
    let msg = err.to_string();
    assert!(matches!(err, DeviceError::Timeout { .. }), "{msg}");
    assert!(
        msg.contains("`ok` to `G90 G1 X3.0000 Y0.0000 Z0.0000"),
        "{msg}"
    );
    assert!(msg.contains("0.4 s"), "{msg}");
    // The line ran anyway: the machine arrives at the new target.
    let (pos, _) = wait_idle(&mut m, Duration::from_secs(3)).await;
    assert!((pos["x"] - 0.003).abs() < 1e-7);
}

#[tokio::test]
async fn silence_times_out_then_recovers() {
    let (_emu, mut m) = rig(
        faults(GrblFaults {
            silence_at_line: Some(1),
            silence_s: 0.8,
            ..GrblFaults::default()
        }),
        cfg(),
    );
    let err = m.start_move(&target(0.001, 0.0, 0.0)).await.unwrap_err();
    assert!(matches!(err, DeviceError::Timeout { .. }), "{err}");
    tokio::time::sleep(Duration::from_millis(60)).await;
    let err = m.state().await.unwrap_err();
    assert!(err.to_string().contains("status report"), "{err}");
    tokio::time::sleep(Duration::from_millis(300)).await;
    // Silence over: the dropped line did not run; a resend does.
    m.start_move(&target(0.001, 0.0, 0.0))
        .await
        .expect("move after silence");
    let (pos, _) = wait_idle(&mut m, Duration::from_secs(3)).await;
    assert!((pos["x"] - 0.001).abs() < 1e-7);
}

#[tokio::test]
async fn disconnect_is_reported() {
    let (emu, mut m) = rig(
        faults(GrblFaults {
            disconnect_at_line: Some(1),
            ..GrblFaults::default()
        }),
        cfg(),
    );
    let err = m.start_move(&target(0.001, 0.0, 0.0)).await.unwrap_err();
    assert!(matches!(err, DeviceError::Disconnected { .. }), "{err}");
    assert!(emu.is_finished());
}

#[tokio::test]
async fn dwell_and_soft_reset() {
    let (emu, mut m) = rig(GrblEmulatorConfig::default(), cfg());
    let t0 = Instant::now();
    m.dwell(0.2).await.expect("dwell");
    assert!(
        t0.elapsed() >= Duration::from_millis(195),
        "ok came before the dwell ended"
    );
    // Reset in the middle of a long move: the machine stops short of the target.
    m.start_move(&target(0.05, 0.0, 0.0)).await.expect("move");
    tokio::time::sleep(Duration::from_millis(100)).await;
    m.soft_reset().await.expect("banner after reset");
    assert_eq!(
        emu.stats()
            .resets
            .load(std::sync::atomic::Ordering::Relaxed),
        1
    );
    let (pos, _) = wait_idle(&mut m, Duration::from_secs(1)).await;
    assert!(pos["x"] > 0.0 && pos["x"] < 0.05, "stopped at {}", pos["x"]);
    m.start_move(&target(0.0, 0.0, 0.0))
        .await
        .expect("move after reset");
    let (pos, _) = wait_idle(&mut m, Duration::from_secs(3)).await;
    assert!(pos["x"].abs() < 1e-7);
}
