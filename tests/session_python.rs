//! Cross-check of the recorder against an independent reader: the PyPI `mcap` package plus
//! `jsonschema` validate every message of a recorded session (tests/python/check_session.py).

use std::path::Path;
use std::process::Command;

use geocal::session::messages::{
    EnvSample, MachineInfo, RunEvent, SessionHeader, TracerSample, SESSION_FORMAT,
};
use geocal::session::{Recorder, RecorderOptions};

const INSTALL_HINT: &str = "pip install mcap jsonschema";

fn header() -> SessionHeader {
    SessionHeader {
        format: SESSION_FORMAT.into(),
        session_id: "py-check".into(),
        started_at: "2026-11-01T10:00:00Z".into(),
        kind: "multilateration".into(),
        machine: MachineInfo {
            name: "mill".into(),
            structure: "FYXZ".into(),
            axes: vec!["x".into(), "y".into(), "z".into()],
            travel_m: [("x".to_owned(), [0.0, 0.8])].into_iter().collect(),
            targets: vec![],
        },
        devices: vec![],
        plan: serde_json::json!({"stations": 1}),
    }
}

#[test]
fn python_mcap_reader_validates_a_recorded_session() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("session.mcap");
    let rec = Recorder::create(
        &path,
        RecorderOptions {
            chunk_size: 16 * 1024,
            ..RecorderOptions::default()
        },
    )
    .unwrap();
    let h = rec.handle();
    let mut t = 1_700_000_000_000_000_000u64;
    h.session(&header(), t);
    h.event(
        &RunEvent::StationBegin {
            station: "s1".into(),
            station_index: 0,
            hint_m: None,
        },
        t,
    );
    let n = 3000u64;
    for i in 0..n {
        t += 1_000_000;
        let s = TracerSample {
            seq: i / 2,
            t_s: i as f64 * 1e-3,
            length_m: 0.25 + i as f64 * 1e-7,
            signal: 0.9,
            tracking: i % 50 != 3,
            beam_segment: 0,
        };
        h.tracer(if i % 2 == 0 { "tracer0" } else { "tracer1" }, &s, t);
        if i % 500 == 0 {
            let e = EnvSample {
                t_s: i as f64 * 1e-3,
                air_temp_k: 293.15,
                pressure_pa: 101_325.0,
                humidity_pct: 40.0,
                material_temp_k: vec![293.2],
            };
            h.env("air", &e, t);
        }
    }
    h.event(
        &RunEvent::StationEnd {
            station: "s1".into(),
        },
        t + 1,
    );
    rec.finish().unwrap();

    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/check_session.py");
    let out = Command::new("python3")
        .arg(&script)
        .arg(&path)
        .arg("--expect-tracer-samples")
        .arg(n.to_string())
        .output()
        .unwrap_or_else(|e| {
            panic!("cannot run python3 ({e}); install Python 3 and {INSTALL_HINT}")
        });
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_ne!(
        out.status.code(),
        Some(3),
        "Python modules missing: {INSTALL_HINT}\n{stderr}"
    );
    assert!(
        out.status.success(),
        "check_session.py failed ({}):\n{stdout}\n{stderr}",
        out.status
    );
    assert!(stdout.contains("/tracer/tracer0/range\t1500"), "{stdout}");
    assert!(stdout.contains("/env/air\t6"), "{stdout}");
}
