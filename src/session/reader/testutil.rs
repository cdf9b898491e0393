//! Shared by the session tests: a realistic header and sample streams.
use std::collections::BTreeMap;

use crate::session::messages::*;

pub fn header() -> SessionHeader {
    let mut extra = BTreeMap::new();
    extra.insert("rate_hz".to_owned(), serde_json::json!(1000));
    SessionHeader {
        format: SESSION_FORMAT.to_owned(),
        session_id: "s-test-1".to_owned(),
        started_at: "2026-11-01T10:00:00Z".to_owned(),
        kind: "multilateration".to_owned(),
        machine: MachineInfo {
            name: "mill".to_owned(),
            structure: "FYXZ".to_owned(),
            axes: vec!["x".into(), "y".into(), "z".into()],
            travel_m: [("x".to_owned(), [0.0, 0.8]), ("y".to_owned(), [0.0, 0.6])]
                .into_iter()
                .collect(),
            targets: vec![TargetInfo {
                id: "t0".into(),
                offset_m: [0.0, 0.0, 0.1],
            }],
        },
        devices: vec![DeviceInfo {
            id: "tracer0".into(),
            kind: "tracer".into(),
            driver: "sim".into(),
            noise_m: Some(5e-8),
            noise_ppm: Some(0.1),
            dead_path_m: Some(0.1),
            wavelength_m: Some(6.33e-7),
            compensated: Some(true),
            extra,
        }],
        plan: serde_json::json!({"stations": 2, "passes": 3}),
    }
}

pub fn tracer_sample(seq: u64) -> TracerSample {
    TracerSample {
        seq,
        t_s: seq as f64 * 1e-3,
        length_m: 0.1 + (seq as f64 * 0.37).sin() * 0.05 + seq as f64 * 1.234_567_89e-6,
        signal: 0.9 + (seq % 7) as f64 * 0.01,
        tracking: seq % 97 != 5,
        beam_segment: (seq / 1000) as u32,
    }
}

pub fn env_sample(i: u64) -> EnvSample {
    EnvSample {
        t_s: i as f64,
        air_temp_k: 293.15 + i as f64 * 1e-3,
        pressure_pa: 101_325.0 - i as f64,
        humidity_pct: 45.0,
        material_temp_k: if i % 2 == 0 {
            vec![293.2, 293.1]
        } else {
            vec![]
        },
    }
}

pub fn events() -> Vec<RunEvent> {
    vec![
        RunEvent::StationBegin {
            station: "s1".into(),
            station_index: 0,
            hint_m: Some([0.1, 0.2, 0.3]),
        },
        RunEvent::PointBegin {
            station: "s1".into(),
            point: 0,
            pass: 0,
            target: "t0".into(),
            nominal_m: [0.4, 0.3, -0.1],
            axes: [("x".to_owned(), 0.4), ("y".to_owned(), 0.3)]
                .into_iter()
                .collect(),
            approach: [("x".to_owned(), 1), ("y".to_owned(), -1)]
                .into_iter()
                .collect(),
        },
        RunEvent::PointEnd {
            station: "s1".into(),
            point: 0,
            pass: 0,
        },
        RunEvent::Rehome {
            station: "s1".into(),
            beam_segment: 1,
        },
        RunEvent::Fault {
            device: "tracer0".into(),
            code: "beam".into(),
            message: "beam broken".into(),
        },
        RunEvent::StationEnd {
            station: "s1".into(),
        },
    ]
}
