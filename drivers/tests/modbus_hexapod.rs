//! Hardware-in-the-loop tests of the Modbus hexapod driver against its emulator on loopback
//! TCP and on a pty (RTU): pose command and handshake, leg encoders, timeouts and reconnects.

use std::time::Duration;

use geocal_drivers::modbus::ModbusFaults;
use geocal_drivers::modbus_hexapod::{
    HexapodRegisterMap, HexapodSource, ModbusHexapod, ModbusHexapodConfig, ModbusHexapodEmulator,
};
use geocal_drivers::{DeviceError, Hexapod, HexapodState, PlatformPose};

/// Legs that follow the pose linearly (leg i = 0.7 m + (i+1)·(x + y + z + rx + ry + rz)),
/// in position `settle_s` after each command.
struct LinearLegs {
    pose: PlatformPose,
    commanded_at_s: f64,
    settle_s: f64,
}

fn legs_of(p: &PlatformPose) -> [f64; 6] {
    let s: f64 = p.translation_m.iter().chain(&p.rotation_vector_rad).sum();
    std::array::from_fn(|i| 0.7 + (i as f64 + 1.0) * s)
}

impl HexapodSource for LinearLegs {
    fn command(&mut self, pose: PlatformPose, t_s: f64) {
        self.pose = pose;
        self.commanded_at_s = t_s;
    }
    fn in_position(&mut self, t_s: f64) -> bool {
        t_s >= self.commanded_at_s + self.settle_s
    }
    fn legs(&mut self, _t_s: f64) -> [f64; 6] {
        legs_of(&self.pose)
    }
}

fn map() -> HexapodRegisterMap {
    serde_json::from_value(serde_json::json!({
        "unit_id": 3,
        "pose_target": {"address": 100, "word_order": "little",
                        "counts_per_m": 1e7, "counts_per_rad": 1e7},
        "legs": {"address": 200, "kind": "input", "m_per_count": 1e-7},
        "status": {"address": 300, "kind": "input", "in_position_bit": 0,
                   "moving_bit": 1, "fault_bit": 2},
        "command": {"address": 120, "go_value": 1, "clear_value": 0},
        "ack": {"bit": 3},
        "fault_code": {"address": 301, "kind": "input"}
    }))
    .expect("test map")
}

fn cfg(retries: u32) -> ModbusHexapodConfig {
    let mut c = ModbusHexapodConfig::new(map());
    c.id = "hex0".into();
    c.timeout_s = 0.2;
    c.retries = retries;
    c.poll_interval_s = 0.005;
    c
}

fn source() -> Box<LinearLegs> {
    Box::new(LinearLegs {
        pose: PlatformPose {
            translation_m: [0.0, 0.0, -0.7],
            rotation_vector_rad: [0.0; 3],
        },
        commanded_at_s: 0.0,
        settle_s: 0.05,
    })
}

async fn rig(faults: ModbusFaults, retries: u32) -> (ModbusHexapodEmulator, ModbusHexapod) {
    let emu = ModbusHexapodEmulator::start_tcp(&map(), faults, source())
        .await
        .expect("emulator");
    let addr = emu.addr().expect("tcp address");
    let hex = ModbusHexapod::connect_tcp(addr, cfg(retries))
        .await
        .expect("driver connects");
    (emu, hex)
}

const POSE: PlatformPose = PlatformPose {
    translation_m: [0.0123456, -0.04, -0.68],
    rotation_vector_rad: [0.1, -0.05, 0.0174533],
};

async fn move_and_wait(hex: &mut ModbusHexapod, pose: &PlatformPose) -> u32 {
    hex.start_move(pose).await.expect("go accepted");
    let mut polls = 0;
    while hex.state().await.expect("state") != HexapodState::Idle {
        polls += 1;
        assert!(polls < 2000, "never in position");
        tokio::time::sleep(Duration::from_millis(2)).await;
    }
    polls
}

fn assert_legs_near(got: &[f64; 6], want: &[f64; 6], tol_m: f64) {
    for k in 0..6 {
        assert!(
            (got[k] - want[k]).abs() <= tol_m,
            "leg {k}: {got:?} vs {want:?}"
        );
    }
}

#[tokio::test]
async fn moves_to_a_pose_and_reads_the_legs() {
    let (emu, mut hex) = rig(ModbusFaults::default(), 2).await;
    let polls = move_and_wait(&mut hex, &POSE).await;
    assert!(polls > 0, "the platform was moving for a while");
    let seen = emu.last_target().expect("target decoded");
    for k in 0..3 {
        assert!((seen.translation_m[k] - POSE.translation_m[k]).abs() <= 0.5e-7);
        assert!((seen.rotation_vector_rad[k] - POSE.rotation_vector_rad[k]).abs() <= 0.5e-7);
    }
    let back = hex.read_target().await.expect("target read back");
    assert_eq!(back, seen);
    let r = hex.read_legs().await.expect("legs");
    // The legs of the decoded pose, to half a count of the leg registers.
    assert_legs_near(&r.lengths_m, &legs_of(&seen), 0.5e-7 + 1e-12);
    assert!(r.t_s > 0.0);
    assert_eq!(emu.stats().go_commands, 1);
    assert!(hex.take_link_faults().is_empty());
    assert_eq!(hex.stats().timeouts, 0);
}

#[tokio::test]
async fn an_unanswered_request_is_a_timeout_then_a_reconnect() {
    // Request 1 = pose write, 2 = go, 3 = status (ack), 4 = clear, 5 = first state poll.
    let faults = ModbusFaults {
        drop_at_requests: vec![5],
        ..ModbusFaults::default()
    };
    let (emu, mut hex) = rig(faults, 0).await;
    hex.start_move(&POSE).await.expect("go accepted");
    match hex.state().await {
        Err(DeviceError::Timeout { device, .. }) => assert_eq!(device, "hex0"),
        other => panic!("expected a timeout, got {other:?}"),
    }
    // The next call reopens the connection and works.
    tokio::time::sleep(Duration::from_millis(60)).await;
    assert_eq!(hex.state().await.expect("state"), HexapodState::Idle);
    let faults = hex.take_link_faults();
    assert_eq!(faults.len(), 1, "{faults:?}");
    assert_eq!(faults[0].code, "reconnect");
    assert!(
        faults[0].message.contains("no reply"),
        "{}",
        faults[0].message
    );
    assert!(hex.take_link_faults().is_empty());
    assert_eq!(emu.stats().connections, 2);
    assert_eq!(emu.stats().dropped, 1);
}

#[tokio::test]
async fn retries_inside_the_driver_survive_drops() {
    let faults = ModbusFaults {
        seed: 7,
        drop_probability: 0.1,
        ..ModbusFaults::default()
    };
    let (emu, mut hex) = rig(faults, 4).await;
    move_and_wait(&mut hex, &POSE).await;
    for _ in 0..20 {
        hex.read_legs().await.expect("legs despite drops");
    }
    assert!(emu.stats().dropped > 0, "{:?}", emu.stats());
    assert_eq!(hex.stats().timeouts, emu.stats().dropped);
    assert_eq!(hex.take_link_faults()[0].code, "reconnect");
}

#[tokio::test]
async fn fault_bit_and_unreachable_poses_are_clear_errors() {
    let faults = ModbusFaults {
        fault_at_go: Some(1),
        fault_code: 17,
        ..ModbusFaults::default()
    };
    let (_emu, mut hex) = rig(faults, 0).await;
    match hex.start_move(&POSE).await {
        Err(DeviceError::Rejected { message, .. }) => {
            assert!(message.contains("fault code 17"), "{message}")
        }
        other => panic!("expected the fault, got {other:?}"),
    }
    let far = PlatformPose {
        translation_m: [300.0, 0.0, 0.0],
        rotation_vector_rad: [0.0; 3],
    };
    match hex.start_move(&far).await {
        Err(DeviceError::Rejected { message, .. }) => {
            assert!(message.contains("x: 300 m"), "{message}")
        }
        other => panic!("expected a rejection, got {other:?}"),
    }
}

#[tokio::test]
async fn rtu_over_a_pty() {
    let (master, slave) = geocal_drivers::serial::pty_pair().expect("pty");
    let path = slave.path().expect("pty path").to_string();
    let _emu = ModbusHexapodEmulator::start_rtu(&map(), ModbusFaults::default(), source(), master)
        .expect("rtu emulator");
    let mut c = cfg(1);
    c.transport = Some(geocal_drivers::modbus::ModbusTransport::Rtu {
        port: path,
        baud: 115_200,
    });
    let mut hex = ModbusHexapod::connect(c).await.expect("driver on the pty");
    move_and_wait(&mut hex, &POSE).await;
    let r = hex.read_legs().await.expect("legs");
    assert_legs_near(&r.lengths_m, &legs_of(&POSE), 1e-6);
    drop(slave);
}
