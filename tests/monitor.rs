//! `geocal monitor`: for each device kind, the emulator runs here (pty or 127.0.0.1), the
//! monitor runs as another process with the real driver for 1.5 s and records a session, and
//! the session read back holds what the emulator's source said, in SI units.

use crate::common;

use std::path::{Path, PathBuf};

use geocal::session::reader::read_session;
use geocal_drivers::grbl::{GrblEmulator, GrblEmulatorConfig, KinematicSink};
use geocal_drivers::hpi3d::{
    EmulatorConfig, FnSource, Hpi3dEmulator, MeteoSensorReading, SourceReading,
};
use geocal_drivers::modbus_table::{
    KinematicTable, ModbusTableEmulator, ModbusTableEmulatorConfig, ModbusTableFaults,
};
use geocal_drivers::probe::{ProbeEmulator, ProbeEmulatorConfig};

const SECONDS: &str = "1.5";

/// Run `geocal monitor --device SPEC --seconds 1.5 --out FILE [extra]` off the runtime that
/// serves the emulator; its stdout.
async fn monitor(spec: String, out: PathBuf, extra: Vec<String>) -> String {
    let output = tokio::task::spawn_blocking(move || {
        std::process::Command::new(env!("CARGO_BIN_EXE_geocal"))
            .args(["monitor", "--device", &spec, "--seconds", SECONDS, "--out"])
            .arg(&out)
            .args(&extra)
            .output()
            .expect("geocal monitor")
    })
    .await
    .expect("join");
    let stdout = String::from_utf8_lossy(&output.stdout).to_string();
    assert!(
        output.status.success(),
        "stdout:\n{stdout}\nstderr:\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    stdout
}

fn header_device(path: &Path) -> (String, String) {
    let session = read_session(path).expect("monitor session");
    assert_eq!(session.header.kind, "monitor");
    assert!(session.completeness.is_complete());
    let d = &session.header.devices[0];
    (d.kind.clone(), d.driver.clone())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hpi3d_lengths_and_meteo_are_recorded_in_si() {
    const LENGTH_M: f64 = 0.123_456_789_1;
    let source = FnSource {
        sample: |_t: f64| SourceReading {
            length_m: LENGTH_M,
            beam_ok: true,
            signal: 0.9,
        },
        meteo: vec![MeteoSensorReading {
            sensor: 0,
            temperature_k: 293.65,
            humidity_pct: 45.0,
            pressure_pa: 101_320.0,
        }],
    };
    let config = EmulatorConfig {
        rate_hz: 200.0,
        meteo_period_s: 0.25,
        ..EmulatorConfig::default()
    };
    // The slave end stays open here while the monitor opens it by path.
    let (emulator, _slave) = Hpi3dEmulator::spawn_pty(config, Box::new(source)).expect("pty");
    let path = emulator
        .slave_path()
        .expect("pty path")
        .display()
        .to_string();
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("hpi3d.mcap");
    let stdout = monitor(format!("hpi3d:{path}"), out.clone(), vec![]).await;
    println!("{stdout}");
    assert!(stdout.contains("length 0.123456789 m"), "{stdout}");
    assert_eq!(header_device(&out), ("tracer".into(), "hpi3d".into()));

    let session = read_session(&out).expect("session");
    let samples = &session.tracers["hpi3d"];
    // 200 Hz for about 1.5 s less the connection: at least half of it, none lost between.
    assert!(samples.len() >= 150, "{} samples", samples.len());
    for pair in samples.windows(2) {
        assert_eq!(pair[1].msg.seq, pair[0].msg.seq + 1, "a sample was lost");
        // The driver's times never go backwards (frames read together may share one).
        assert!(pair[1].msg.t_s >= pair[0].msg.t_s);
    }
    for s in samples {
        // The wire carries 0.1 nm.
        assert!(
            (s.msg.length_m - LENGTH_M).abs() <= 0.5e-10,
            "{}",
            s.msg.length_m
        );
        assert!(s.msg.tracking);
    }
    let meteo = &session.env["hpi3d-meteo"];
    assert!(meteo.len() >= 3, "{} meteo readings", meteo.len());
    for m in meteo {
        // The wire carries 0.01 K and 10 Pa.
        assert!(
            (m.msg.air_temp_k - 293.65).abs() <= 0.005,
            "{}",
            m.msg.air_temp_k
        );
        assert!(
            (m.msg.pressure_pa - 101_320.0).abs() <= 5.0,
            "{}",
            m.msg.pressure_pa
        );
        assert!((m.msg.humidity_pct - 45.0).abs() <= 0.5);
    }
    common::python_check_session(&out, samples.len() as u64);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn grbl_status_is_recorded_in_metres() {
    let start_m = [0.1, 0.2, -0.3];
    let emulator = GrblEmulator::spawn_pty(
        GrblEmulatorConfig::default(),
        Box::new(KinematicSink::new(start_m)),
    )
    .expect("pty");
    let path = emulator.slave_path().expect("pty path").to_string();
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("grbl.mcap");
    // Settings from a run config's machine table: poll every 20 ms.
    let settings = dir.path().join("grbl.toml");
    std::fs::write(
        &settings,
        "[devices.machine.grbl]\nport = \"ignored\"\nstatus_interval_s = 0.02\n",
    )
    .expect("write settings");
    let stdout = monitor(
        format!("grbl:{path}"),
        out.clone(),
        vec!["--config".into(), settings.display().to_string()],
    )
    .await;
    println!("{stdout}");
    assert_eq!(header_device(&out), ("machine".into(), "grbl".into()));
    let session = read_session(&out).expect("session");
    let states = &session.machines["grbl"];
    // One report per 20 ms over ~1.5 s.
    assert!(states.len() >= 20, "{} reports", states.len());
    for s in states {
        assert_eq!(s.msg.state, "Idle");
        assert_eq!(s.msg.frame, "machine");
        for (p, start) in s.msg.position_m.iter().zip(start_m) {
            // GRBL reports mm with 3 decimals.
            assert!((p - start).abs() <= 0.5e-6, "{:?}", s.msg);
        }
    }
    assert!(
        emulator
            .stats()
            .status_queries
            .load(std::sync::atomic::Ordering::Relaxed)
            >= states.len() as u64,
        "every recorded report answered a query"
    );
    common::python_check_session(&out, 0);
}

fn table_emulator_config() -> ModbusTableEmulatorConfig {
    ModbusTableEmulatorConfig {
        map: geocal::monitor::default_register_map(),
        faults: ModbusTableFaults::default(),
    }
}

/// The table at rest at 0.5 rad: in position at that encoder angle; nobody commanded it, so
/// its target register reads 0.
fn check_table_session(out: &Path, driver: &str) {
    assert_eq!(header_device(out), ("rotary_table".into(), driver.into()));
    let session = read_session(out).expect("session");
    let states = &session.rotary["rotary"];
    assert!(states.len() >= 10, "{} readings", states.len());
    let count_rad = 1.0 / 57_295.779_513;
    for s in states {
        let encoder = s.msg.encoder_rad.expect("encoder angle");
        assert!((encoder - 0.5).abs() <= count_rad, "{encoder}");
        assert!(s.msg.in_position);
        assert_eq!(s.msg.commanded_rad, 0.0);
    }
    common::python_check_session(out, 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn modbus_tcp_table_angles_are_recorded_in_radians() {
    let emulator = ModbusTableEmulator::start_tcp(
        table_emulator_config(),
        Box::new(KinematicTable::new(0.5, 1.0, 0.0)),
    )
    .await
    .expect("modbus tcp emulator");
    let addr = emulator.addr().expect("address");
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("table.mcap");
    let stdout = monitor(format!("modbus-tcp:{addr}"), out.clone(), vec![]).await;
    println!("{stdout}");
    assert!(stdout.contains("in position"), "{stdout}");
    check_table_session(&out, "modbus-tcp");
    assert!(emulator.stats().requests >= 30);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn modbus_rtu_table_angles_are_recorded_in_radians() {
    let (master, slave) = geocal_drivers::serial::pty_pair().expect("pty");
    let path = slave.path().expect("pty path").to_string();
    let _emulator = ModbusTableEmulator::start_rtu(
        table_emulator_config(),
        Box::new(KinematicTable::new(0.5, 1.0, 0.0)),
        master,
    )
    .expect("modbus rtu emulator");
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("table.mcap");
    monitor(format!("modbus-rtu:{path}"), out.clone(), vec![]).await;
    check_table_session(&out, "modbus-rtu");
    drop(slave);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn probe_readings_are_recorded_in_metres() {
    let emulator = ProbeEmulator::spawn_pty(
        ProbeEmulatorConfig::default(),
        Box::new(|_t: f64| Some(-1.23456e-4)),
    )
    .expect("pty");
    let path = emulator.slave_path().expect("pty path").to_string();
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("probe.mcap");
    let stdout = monitor(format!("probe:{path}"), out.clone(), vec![]).await;
    println!("{stdout}");
    assert_eq!(header_device(&out), ("probe".into(), "probe".into()));
    let session = read_session(&out).expect("session");
    let readings = &session.probes["probe"];
    assert!(readings.len() >= 20, "{} readings", readings.len());
    for r in readings {
        // The default reply carries 4 decimals of mm: 0.1 µm.
        let value_m = r.msg.value_m.expect("an in-range reading");
        assert!((value_m + 1.23456e-4).abs() <= 0.5e-7, "{value_m}");
    }
    assert!(readings.windows(2).all(|p| p[1].msg.t_s > p[0].msg.t_s));
    // Every recorded reading answered one of the emulator's replies.
    let replies = emulator
        .stats()
        .replies
        .load(std::sync::atomic::Ordering::Relaxed);
    assert!(replies >= readings.len() as u64, "{replies} replies");
    common::python_check_session(&out, 0);
}

#[test]
fn a_bad_device_spec_says_what_was_expected() {
    for spec in ["hpi3d", "laser:/dev/ttyUSB0", "modbus-tcp:localhost"] {
        let output = std::process::Command::new(env!("CARGO_BIN_EXE_geocal"))
            .args(["monitor", "--device", spec, "--seconds", "0.1"])
            .output()
            .expect("geocal monitor");
        assert!(!output.status.success());
        let err = String::from_utf8_lossy(&output.stderr);
        assert!(
            err.contains(spec) && err.contains("expected KIND:WHERE"),
            "{spec}: {err}"
        );
    }
}
