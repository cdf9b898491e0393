//! Hardware-in-the-loop tests of the Modbus rotary-table driver against its TCP emulator,
//! an RTU emulator on a pty, and an independent peer (a pymodbus server).

use std::net::TcpListener as StdListener;
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use geocal_drivers::modbus_table::{
    KinematicTable, ModbusTable, ModbusTableConfig, ModbusTableEmulator, ModbusTableEmulatorConfig,
    ModbusTableFaults, ModbusTransport, RegisterMap, WordOrder,
};
use geocal_drivers::{DeviceError, RotaryState, RotaryTable};

const COUNTS_PER_RAD: f64 = 1000.0 * 180.0 / std::f64::consts::PI;

fn map() -> RegisterMap {
    serde_json::from_value(serde_json::json!({
        "unit_id": 1,
        "target": {"address": 100, "width_bits": 32, "word_order": "big",
                    "counts_per_rad": COUNTS_PER_RAD},
        "actual": {"address": 200, "kind": "input", "width_bits": 32, "word_order": "big",
                    "counts_per_rad": COUNTS_PER_RAD},
        "status": {"address": 300, "kind": "input", "in_position_bit": 0,
                    "moving_bit": 1, "fault_bit": 2},
        "command": {"address": 110, "go_value": 1, "clear_value": 0},
        "ack": {"bit": 3},
        "fault_code": {"address": 301, "kind": "input"}
    }))
    .expect("test map")
}

fn cfg(map: RegisterMap) -> ModbusTableConfig {
    let mut c = ModbusTableConfig::new(map);
    c.id = "c-table".into();
    c.timeout_s = 0.2;
    c.retries = 2;
    c.ack_timeout_s = 1.0;
    c.poll_interval_s = 0.01;
    c
}

async fn emulator(map: RegisterMap, faults: ModbusTableFaults) -> ModbusTableEmulator {
    ModbusTableEmulator::start_tcp(
        ModbusTableEmulatorConfig { map, faults },
        Box::new(KinematicTable::new(0.0, 2.0, 0.05)),
    )
    .await
    .expect("emulator starts")
}

async fn rig(map: RegisterMap, faults: ModbusTableFaults) -> (ModbusTableEmulator, ModbusTable) {
    let emu = emulator(map.clone(), faults).await;
    let addr = emu.addr().expect("tcp address");
    let table = ModbusTable::connect_tcp(addr, cfg(map))
        .await
        .expect("driver connects");
    (emu, table)
}

async fn wait_in_position(t: &mut impl RotaryTable, within: Duration) -> f64 {
    let deadline = tokio::time::Instant::now() + within;
    loop {
        match t.state().await.expect("state") {
            RotaryState::InPosition { encoder_rad } => return encoder_rad,
            RotaryState::Moving => {}
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "not in position in {within:?}"
        );
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

#[tokio::test]
async fn rotates_and_reaches_position() {
    let (emu, mut t) = rig(map(), ModbusTableFaults::default()).await;
    for deg in [30.0f64, -45.5, 0.25] {
        let target = deg.to_radians();
        t.start_rotation(target).await.expect("accepted");
        let got = wait_in_position(&mut t, Duration::from_secs(3)).await;
        assert!(
            (got - target).abs() < 1e-3 / COUNTS_PER_RAD * 1000.0,
            "{got} vs {target}"
        );
        let last = emu.stats().last_target_rad.expect("target seen");
        assert!((last - target).abs() <= 0.5 / COUNTS_PER_RAD + 1e-12);
    }
    assert_eq!(emu.stats().go_commands, 3);
    assert_eq!(t.stats().timeouts, 0);
}

#[tokio::test]
async fn word_order_and_scale_from_config() {
    // 16-bit signed actual (0.01 degree per count), little-word 32-bit target,
    // acknowledge as a value in a separate holding register.
    let mut m = map();
    m.target.word_order = WordOrder::Little;
    m.target.counts_per_rad = None;
    m.target.rad_per_count = Some(1e-3f64.to_radians());
    m.actual.width_bits = 16;
    m.actual.kind = geocal_drivers::modbus_table::RegisterKind::Holding;
    m.actual.counts_per_rad = Some(100.0 * 180.0 / std::f64::consts::PI);
    m.ack.bit = None;
    m.ack.value = Some(0x55);
    m.ack.register = Some(geocal_drivers::modbus_table::RegisterRef {
        address: 120,
        kind: geocal_drivers::modbus_table::RegisterKind::Holding,
    });
    let (emu, mut t) = rig(m.clone(), ModbusTableFaults::default()).await;
    let target = (-123.456f64).to_radians();
    t.start_rotation(target).await.expect("accepted");
    let got = wait_in_position(&mut t, Duration::from_secs(5)).await;
    // 16-bit actual at 0.01 degree per count.
    assert!(
        (got.to_degrees() - -123.46).abs() < 1e-9,
        "{}",
        got.to_degrees()
    );
    let last = emu.stats().last_target_rad.expect("target");
    assert!((last.to_degrees() - -123.456).abs() < 1e-9);

    // A driver with the other word order reads a wrong target: the map matters.
    let mut wrong = m.clone();
    wrong.target.word_order = WordOrder::Big;
    let mut t2 = ModbusTable::connect_tcp(emu.addr().expect("addr"), cfg(wrong))
        .await
        .expect("connects");
    t2.start_rotation(0.1).await.expect("accepted");
    let seen = emu.stats().last_target_rad.expect("target");
    assert!((seen - 0.1).abs() > 0.01, "{seen}");
}

#[tokio::test]
async fn out_of_range_target_rejected_before_sending() {
    let mut m = map();
    m.target.width_bits = 16;
    let (emu, mut t) = rig(m, ModbusTableFaults::default()).await;
    let err = t
        .start_rotation(1.0)
        .await
        .expect_err("57 degrees overflows 16 bits");
    assert!(matches!(err, DeviceError::Rejected { .. }), "{err}");
    assert!(err.to_string().contains("16-bit"), "{err}");
    assert_eq!(emu.stats().requests, 0);
}

#[tokio::test]
async fn exception_becomes_clear_error() {
    // Injected once: the first request (the target write) gets ServerDeviceFailure.
    let faults = ModbusTableFaults {
        exception_at_requests: vec![1],
        exception_code: 4,
        ..Default::default()
    };
    let (_emu, mut t) = rig(map(), faults).await;
    let err = t.start_rotation(0.5).await.expect_err("exception");
    let msg = err.to_string();
    assert!(matches!(err, DeviceError::Rejected { .. }), "{msg}");
    assert!(msg.contains("ServerDeviceFailure"), "{msg}");
    assert!(msg.contains("holding register 100"), "{msg}");
    assert!(msg.contains("target angle"), "{msg}");
    // Once only: the next attempt goes through.
    t.start_rotation(0.5).await.expect("second attempt");
    wait_in_position(&mut t, Duration::from_secs(3)).await;

    // A register the device does not have: IllegalDataAddress naming the register.
    let mut m = map();
    m.status.address = 999;
    let emu = emulator(map(), ModbusTableFaults::default()).await;
    let mut bad = ModbusTable::connect_tcp(emu.addr().expect("addr"), cfg(m))
        .await
        .expect("connects");
    let err = bad.state().await.expect_err("no such register");
    let msg = err.to_string();
    assert!(msg.contains("IllegalDataAddress"), "{msg}");
    assert!(msg.contains("input register 999 (status"), "{msg}");
}

#[tokio::test]
async fn dropped_response_times_out_then_reconnects() {
    let faults = ModbusTableFaults {
        drop_at_requests: vec![2],
        ..Default::default()
    };
    let (emu, mut t) = rig(map(), faults).await;
    let start = tokio::time::Instant::now();
    t.start_rotation(0.3)
        .await
        .expect("retried after the timeout");
    assert!(start.elapsed() >= Duration::from_millis(200));
    wait_in_position(&mut t, Duration::from_secs(3)).await;
    assert_eq!(t.stats().timeouts, 1);
    assert_eq!(t.stats().reconnects, 1);
    assert_eq!(emu.stats().connections, 2);
    assert_eq!(emu.stats().dropped, 1);
}

#[tokio::test]
async fn silence_longer_than_retries_is_a_timeout() {
    let faults = ModbusTableFaults {
        silence_at_request: Some(1),
        silence_s: 1.0,
        ..Default::default()
    };
    let (_emu, mut t) = rig(map(), faults).await;
    let err = t.state().await.expect_err("silent");
    assert!(matches!(err, DeviceError::Timeout { .. }), "{err}");
    assert!(err.to_string().contains("3 attempts"), "{err}");
    tokio::time::sleep(Duration::from_millis(600)).await;
    // The device talks again: the driver reconnects and carries on.
    t.state().await.expect("recovered");
}

#[tokio::test]
async fn fault_bit_is_an_error_with_code() {
    let faults = ModbusTableFaults {
        fault_at_go: Some(2),
        fault_code: 42,
        ..Default::default()
    };
    let (emu, mut t) = rig(map(), faults).await;
    t.start_rotation(0.1).await.expect("first move");
    wait_in_position(&mut t, Duration::from_secs(3)).await;
    let err = t.start_rotation(0.2).await.expect_err("fault");
    let msg = err.to_string();
    assert!(msg.contains("fault"), "{msg}");
    assert!(msg.contains("fault code 42"), "{msg}");
    let err = t.state().await.expect_err("still faulted");
    assert!(err.to_string().contains("fault code 42"), "{err}");
    emu.set_fault(false);
    tokio::time::sleep(Duration::from_millis(20)).await;
    t.state().await.expect("fault cleared");
}

#[tokio::test]
async fn state_polls_are_rate_limited() {
    let mut c = cfg(map());
    c.poll_interval_s = 0.1;
    let emu = emulator(map(), ModbusTableFaults::default()).await;
    let mut slow = ModbusTable::connect_tcp(emu.addr().expect("addr"), c)
        .await
        .expect("connects");
    for _ in 0..50 {
        slow.state().await.expect("state");
    }
    assert!(slow.stats().status_polls <= 2, "{:?}", slow.stats());
}

#[tokio::test]
async fn rtu_over_pty() {
    use tokio_serial::{SerialPort, SerialStream};
    let (master, slave) = SerialStream::pair().expect("pty pair");
    let path = slave.name().expect("pty name");
    // Kept open: with every slave descriptor closed the pty reports errors to the master.
    let _slave = slave;
    // The reply to the go write is lost: the driver times out, reopens the port, retries.
    let emu = ModbusTableEmulator::start_rtu(
        ModbusTableEmulatorConfig {
            map: map(),
            faults: ModbusTableFaults {
                drop_at_requests: vec![2],
                ..Default::default()
            },
        },
        Box::new(KinematicTable::new(0.0, 2.0, 0.05)),
        master,
    )
    .expect("rtu emulator");
    let mut t = ModbusTable::open_rtu(&path, 115_200, cfg(map()))
        .await
        .expect("opens");
    let target = (-10f64).to_radians();
    t.start_rotation(target).await.expect("accepted");
    let got = wait_in_position(&mut t, Duration::from_secs(3)).await;
    assert!((got - target).abs() < 1e-6);
    assert_eq!(t.stats().timeouts, 1);
    assert_eq!(t.stats().reconnects, 1);
    assert_eq!(emu.stats().go_commands, 1);
}

#[tokio::test]
async fn connects_by_config_transport() {
    let emu = emulator(map(), ModbusTableFaults::default()).await;
    let mut c = cfg(map());
    c.transport = Some(ModbusTransport::Tcp {
        address: emu.addr().expect("addr"),
    });
    let mut t = ModbusTable::connect(c).await.expect("connects");
    assert_eq!(t.id(), "c-table");
    t.start_rotation(-0.2).await.expect("accepted");
    let got = wait_in_position(&mut t, Duration::from_secs(3)).await;
    assert!((got + 0.2).abs() < 1e-4);

    // No transport configured, or nobody listening: clear errors, no panic.
    let err = ModbusTable::connect(cfg(map()))
        .await
        .err()
        .expect("no transport");
    assert!(err.to_string().contains("no transport"), "{err}");
    let closed = free_port();
    let err = ModbusTable::connect_tcp(
        format!("127.0.0.1:{closed}").parse().expect("addr"),
        cfg(map()),
    )
    .await
    .err()
    .expect("refused");
    assert!(matches!(err, DeviceError::Disconnected { .. }), "{err}");
}

/// A free loopback port (a short race with other processes is acceptable in tests).
fn free_port() -> u16 {
    StdListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .expect("free port")
}

struct Peer(Child);
impl Drop for Peer {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

#[tokio::test]
async fn rotates_against_pymodbus_peer() {
    let python = std::env::var("PYTHON").unwrap_or_else(|_| "python3".into());
    let probe = Command::new(&python)
        .args(["-c", "import pymodbus.simulator"])
        .output();
    let missing = match &probe {
        Ok(out) if out.status.success() => None,
        Ok(out) => Some(String::from_utf8_lossy(&out.stderr).trim().to_string()),
        Err(e) => Some(format!("cannot run {python}: {e}")),
    };
    assert!(
        missing.is_none(),
        "the independent Modbus peer needs Python 3 with pymodbus 3.x: \
         `pip install pymodbus` ({})",
        missing.unwrap_or_default()
    );
    let port = free_port();
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/modbus_peer.py");
    let child = Command::new(&python)
        .args([script, "--port", &port.to_string()])
        .stdout(Stdio::null())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("peer starts");
    let _peer = Peer(child);
    let addr = format!("127.0.0.1:{port}").parse().expect("addr");
    let mut c = cfg(map());
    c.timeout_s = 1.0;
    // The peer needs a moment to bind.
    let mut t = None;
    for _ in 0..100 {
        if let Ok(table) = ModbusTable::connect_tcp(addr, c.clone()).await {
            t = Some(table);
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let mut t = t.expect("pymodbus peer reachable");
    for deg in [12.5f64, -200.0] {
        let target = deg.to_radians();
        t.start_rotation(target)
            .await
            .expect("accepted by the peer");
        let got = wait_in_position(&mut t, Duration::from_secs(3)).await;
        assert!(
            (got - target).abs() <= 0.5 / COUNTS_PER_RAD + 1e-12,
            "{got} vs {target}"
        );
    }
}

#[tokio::test]
async fn seeded_random_drops_are_survived() {
    let faults = ModbusTableFaults {
        seed: 7,
        drop_probability: 0.15,
        ..Default::default()
    };
    let emu = emulator(map(), faults).await;
    let mut c = cfg(map());
    c.timeout_s = 0.05;
    c.retries = 6;
    let mut t = ModbusTable::connect_tcp(emu.addr().expect("addr"), c)
        .await
        .expect("connects");
    for deg in [5.0f64, -5.0, 2.5] {
        t.start_rotation(deg.to_radians()).await.expect("accepted");
        let got = wait_in_position(&mut t, Duration::from_secs(3)).await;
        assert!((got - deg.to_radians()).abs() < 1e-4);
    }
    assert!(emu.stats().dropped > 0, "{:?}", emu.stats());
    assert_eq!(t.stats().timeouts, emu.stats().dropped);
}
