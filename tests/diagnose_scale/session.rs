//! A clean multilateration session of any size, recorded as the sequencer would: a grid of
//! points in serpentine order measured from 16 stations around a 1.4 × 2.4 × 1.0 m volume, a
//! 20 Hz tracer with noise 0.1 µm + 0.1 ppm, no unmodelled effect. Shared by the diagnosis's
//! scale test and its benchmark (`benches/diagnose_session.rs`).

use std::collections::BTreeMap;
use std::path::Path;

use geocal::session::messages::{
    AxisMap, DeviceInfo, MachineInfo, RunEvent, SessionHeader, TargetInfo, TracerSample,
    SESSION_FORMAT,
};
use geocal::session::recorder::{Recorder, RecorderOptions};
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

pub const STATIONS: usize = 16;
const TRACER: &str = "tracer0";
const DT_S: f64 = 0.05;
const DWELL_SAMPLES: usize = 9;
const FEED_M_S: f64 = 1.0;
const NOISE_M: f64 = 1.0e-7;
const NOISE_PPM: f64 = 0.1;
const WINDOW_S: f64 = 0.3;
const TOLERANCE_M: f64 = 2e-6;

fn plan_points(grid: [usize; 3]) -> Vec<[f64; 3]> {
    let size = [1.4, 2.4, 1.0];
    let coord = |k: usize, i: usize| size[k] * i as f64 / (grid[k] - 1) as f64;
    let mut points = Vec::with_capacity(grid.iter().product());
    for iz in 0..grid[2] {
        for row in 0..grid[1] {
            let iy = if iz % 2 == 0 { row } else { grid[1] - 1 - row };
            for col in 0..grid[0] {
                let ix = if (iz * grid[1] + row) % 2 == 0 {
                    col
                } else {
                    grid[0] - 1 - col
                };
                points.push([coord(0, ix), coord(1, iy), coord(2, iz)]);
            }
        }
    }
    points
}

fn header(grid: [usize; 3], seed: u64) -> SessionHeader {
    SessionHeader {
        format: SESSION_FORMAT.into(),
        session_id: format!(
            "diagnose-scale-{}x{STATIONS}-{seed}",
            grid.iter().product::<usize>()
        ),
        started_at: "2026-01-01T00:00:00Z".into(),
        kind: "multilateration".into(),
        machine: MachineInfo {
            name: "Bridge CMM 14-24-10 (scale)".into(),
            structure: "FYXZ".into(),
            axes: vec!["x".into(), "y".into(), "z".into()],
            travel_m: BTreeMap::from([
                ("x".into(), [0.0, 1.4]),
                ("y".into(), [0.0, 2.4]),
                ("z".into(), [0.0, 1.0]),
            ]),
            targets: vec![TargetInfo {
                id: "t0".into(),
                offset_m: [0.0, 0.0, 0.0],
            }],
        },
        devices: vec![DeviceInfo {
            id: TRACER.into(),
            kind: "tracer".into(),
            driver: "sim".into(),
            noise_m: Some(NOISE_M),
            noise_ppm: Some(NOISE_PPM),
            dead_path_m: Some(0.0),
            wavelength_m: Some(6.33e-7),
            compensated: Some(true),
            extra: BTreeMap::from([("sample_rate_hz".into(), (1.0 / DT_S).into())]),
        }],
        plan: serde_json::json!({
            "target": "t0",
            "passes": ["forward"],
            "dwell_s": DWELL_SAMPLES as f64 * DT_S,
            "stillstand": {"window_s": WINDOW_S, "tolerance_m": TOLERANCE_M},
            "grid": {"count": grid, "order": "serpentine"},
        }),
    }
}

/// Writes the session to `path`: per station a `station_begin`, then per point the motion
/// samples, `point_begin`, the dwell samples, `point_end`. Returns the number of points.
pub fn generate(path: &Path, grid: [usize; 3], seed: u64) -> usize {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let nominal = plan_points(grid);
    let truth: Vec<Vector3<f64>> = nominal
        .iter()
        .map(|p| Vector3::from(*p) + Vector3::from_fn(|_, _| rng.random_range(-4e-6..4e-6)))
        .collect();
    let stations: Vec<Vector3<f64>> = (0..STATIONS)
        .map(|k| {
            let a = k as f64 * std::f64::consts::TAU / STATIONS as f64;
            Vector3::new(
                0.7 + 1.8 * a.cos(),
                1.2 + 2.2 * a.sin(),
                -0.3 + 0.4 * (k % 4) as f64,
            )
        })
        .collect();
    let recorder = Recorder::create(path, RecorderOptions::default()).expect("recorder");
    let h = recorder.handle();
    let epoch_ns: u64 = 1_767_225_600_000_000_000;
    let log_ns = |t_s: f64| epoch_ns + (t_s * 1e9).round() as u64 + 2_000_000;
    h.session(&header(grid, seed), epoch_ns);
    let mut seq = 0u64;
    let mut t_s = 0.0;
    let mut sample = |t_s: f64, length_m: f64, beam_m: f64, rng: &mut ChaCha8Rng| {
        let sigma = NOISE_M + NOISE_PPM * 1e-6 * beam_m;
        let s = TracerSample {
            seq,
            t_s,
            length_m: length_m + sigma * rng.sample::<f64, _>(StandardNormal),
            signal: 0.95,
            tracking: true,
            beam_segment: 0,
        };
        h.tracer(TRACER, &s, log_ns(t_s));
        seq += 1;
    };
    let axes = |p: &[f64; 3]| -> AxisMap<f64> { ["x", "y", "z"].into_iter().zip(*p).collect() };
    for (j, station) in stations.iter().enumerate() {
        let id = format!("s{}", j + 1);
        let hint = station + Vector3::from_fn(|_, _| rng.random_range(-0.03..0.03));
        t_s += 180.0;
        h.event(
            &RunEvent::StationBegin {
                station: id.as_str().into(),
                station_index: j,
                hint_m: Some([hint.x, hint.y, hint.z]),
            },
            log_ns(t_s),
        );
        let home = (station - truth[0]).norm();
        let length = |x: &Vector3<f64>| (station - x).norm() - home;
        let mut approach: AxisMap<i8> = ["x", "y", "z"].into_iter().map(|a| (a, 0)).collect();
        for (i, nom) in nominal.iter().enumerate() {
            if i > 0 {
                let from = truth[i - 1];
                let steps = ((truth[i] - from).norm() / FEED_M_S / DT_S).ceil().max(1.0) as usize;
                for k in 0..steps {
                    t_s += DT_S;
                    let x = from + (truth[i] - from) * (k as f64 / steps as f64);
                    sample(t_s, length(&x), (station - x).norm(), &mut rng);
                }
                for (a, axis) in ["x", "y", "z"].iter().enumerate() {
                    let d = nom[a] - nominal[i - 1][a];
                    if d != 0.0 {
                        approach.insert(*axis, d.signum() as i8);
                    }
                }
            }
            t_s += DT_S;
            h.event(
                &RunEvent::PointBegin {
                    station: id.as_str().into(),
                    point: i,
                    pass: 0,
                    target: "t0".into(),
                    nominal_m: *nom,
                    axes: axes(nom),
                    approach: approach.clone(),
                },
                log_ns(t_s) - 1_000_000,
            );
            let at = length(&truth[i]);
            let beam = (station - truth[i]).norm();
            for k in 0..DWELL_SAMPLES {
                if k > 0 {
                    t_s += DT_S;
                }
                sample(t_s, at, beam, &mut rng);
            }
            h.event(
                &RunEvent::PointEnd {
                    station: id.as_str().into(),
                    point: i,
                    pass: 0,
                },
                log_ns(t_s) + 1_000_000,
            );
        }
        h.event(
            &RunEvent::StationEnd { station: id.into() },
            log_ns(t_s) + 2_000_000,
        );
    }
    drop(h);
    recorder.finish().expect("finish session");
    nominal.len()
}
