//! Helpers shared by the whole-run tests: comparing estimates with the simulated truth.
#![allow(dead_code)]

use std::path::Path;

use geocal::config::Config;
use geocal::method::multilateration::MultilaterationResults;
use geocal::run::{run, RunOptions, RunOutput};
use nalgebra::{Matrix3, Rotation3, Vector3};
use serde_json::Value;

pub const DEMO: &str = include_str!("../../config/demo-multilateration.toml");

/// The demo configuration shrunk to 4 stations x 3x3x2 points, so whole runs stay quick.
pub fn small_demo() -> String {
    let cut = DEMO
        .find("[[plan.stations]]\nid = \"s5\"")
        .expect("station s5");
    let sim = DEMO.find("\n[sim]").expect("[sim]");
    format!("{}{}", &DEMO[..cut], &DEMO[sim..])
        .replace("count = 5 }", "count = 3 }")
        .replace("count = 4 }", "count = 2 }")
}

/// The demo shrunk for the diagnosis: all 5 stations, 3x3x3 points, both passes. Fewer
/// lengths than this leave held-out lengths undetermined (cross-validation needs each point
/// seen from 4 stations and each station to keep most of its points when a fold is held out).
pub fn diagnose_demo() -> String {
    DEMO.replace("count = 5 }", "count = 3 }")
        .replace("count = 4 }", "count = 3 }")
}

/// Rigid motion (R, t) minimising sum |R a_i + t - b_i|^2 (Kabsch), written independently of
/// the solver's own datum code so that the tests do not grade the solver with itself.
pub fn rigid_fit(a: &[[f64; 3]], b: &[[f64; 3]]) -> (Rotation3<f64>, Vector3<f64>) {
    assert_eq!(a.len(), b.len());
    let n = a.len() as f64;
    let ca = a.iter().map(|p| Vector3::from(*p)).sum::<Vector3<f64>>() / n;
    let cb = b.iter().map(|p| Vector3::from(*p)).sum::<Vector3<f64>>() / n;
    let mut h = Matrix3::zeros();
    for (p, q) in a.iter().zip(b) {
        h += (Vector3::from(*p) - ca) * (Vector3::from(*q) - cb).transpose();
    }
    let svd = h.svd(true, true);
    let (u, v_t) = (svd.u.expect("u"), svd.v_t.expect("v_t"));
    let mut d = Matrix3::identity();
    if (v_t.transpose() * u.transpose()).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    let r = Rotation3::from_matrix_unchecked(v_t.transpose() * d * u.transpose());
    (r, cb - r * ca)
}

/// RMS over points of |R a_i + t - b_i| per coordinate (i.e. sqrt(mean |.|^2 / 3)).
pub fn rms_after(r: &Rotation3<f64>, t: &Vector3<f64>, a: &[[f64; 3]], b: &[[f64; 3]]) -> f64 {
    let ss: f64 = a
        .iter()
        .zip(b)
        .map(|(p, q)| (r * Vector3::from(*p) + t - Vector3::from(*q)).norm_squared())
        .sum();
    (ss / (3.0 * a.len() as f64)).sqrt()
}

/// The RMS per coordinate that the reported sigmas predict.
pub fn predicted_rms(sigmas: &[[f64; 3]]) -> f64 {
    let ss: f64 = sigmas
        .iter()
        .map(|s| s[0] * s[0] + s[1] * s[1] + s[2] * s[2])
        .sum();
    (ss / (3.0 * sigmas.len() as f64)).sqrt()
}

/// Run the Python checker on a session; fails the test if Python or its packages are missing.
pub fn python_check_session(session: &std::path::Path, expect_tracer_samples: u64) {
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/check_session.py");
    let output = std::process::Command::new("python3")
        .arg(script)
        .arg(session)
        .arg("--expect-tracer-samples")
        .arg(expect_tracer_samples.to_string())
        .output()
        .expect("python3 must be installed to run the independent session reader");
    let stdout = String::from_utf8_lossy(&output.stdout);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        output.status.success(),
        "independent reader failed (pip install mcap jsonschema?)\nstdout:\n{stdout}\nstderr:\n{stderr}"
    );
}

pub fn run_with_truth(config_text: &str, dir: &Path) -> (RunOutput, Value) {
    let config = Config::parse(config_text, Path::new("test.toml")).expect("config");
    let truth_path = dir.join("truth.json");
    let output = run(
        &config,
        &RunOptions {
            out_dir: dir.to_path_buf(),
            truth: Some(truth_path.clone()),
            progress: false,
            settings: Default::default(),
        },
    )
    .expect("run");
    let truth = serde_json::from_slice(&std::fs::read(&truth_path).expect("truth file"))
        .expect("truth json");
    (output, truth)
}

pub fn truth_station<'a>(truth: &'a Value, id: &str) -> &'a Value {
    truth["stations"]
        .as_array()
        .expect("stations")
        .iter()
        .find(|x| x["id"] == id)
        .expect("station in truth")
}

/// The simulated truth of one target's point.
pub fn truth_point<'a>(truth: &'a Value, target: &str, point: usize) -> &'a Value {
    truth["points"]
        .as_array()
        .expect("truth points")
        .iter()
        .find(|t| t["point"] == point && t["target"] == target)
        .expect("truth point")
}

pub fn xyz(v: &Value) -> [f64; 3] {
    [0, 1, 2].map(|k| v[k].as_f64().expect("coordinate"))
}

/// Points and stations within 3x the RMS the reported covariance predicts (after removing a
/// best-fit rigid motion: the datum is a convention), home distances within 4 sigma.
pub fn assert_recovers_truth(results: &MultilaterationResults, truth: &Value) {
    assert!(results.converged, "solver did not converge");
    assert_eq!(
        results.extraction.windows_dropped, 0,
        "{:?}",
        results.extraction.dropped_reasons
    );
    let truth_points: Vec<[f64; 3]> = results
        .points
        .iter()
        .map(|p| xyz(&truth_point(truth, &p.target, p.point)["actual_m"]))
        .collect();
    let estimated: Vec<[f64; 3]> = results.points.iter().map(|p| p.actual_m).collect();
    let (r, t) = rigid_fit(&estimated, &truth_points);
    let point_rms = rms_after(&r, &t, &estimated, &truth_points);
    let point_predicted =
        predicted_rms(&results.points.iter().map(|p| p.sigma_m).collect::<Vec<_>>());
    println!("points: RMS error {point_rms:.3e} m, predicted {point_predicted:.3e} m");
    assert!(
        point_rms <= 3.0 * point_predicted,
        "point RMS {point_rms:e} m exceeds 3x the predicted {point_predicted:e} m"
    );

    let truth_stations: Vec<[f64; 3]> = results
        .stations
        .iter()
        .map(|s| xyz(&truth_station(truth, &s.id)["position_m"]))
        .collect();
    let est_stations: Vec<[f64; 3]> = results.stations.iter().map(|s| s.position_m).collect();
    let station_rms = rms_after(&r, &t, &est_stations, &truth_stations);
    let station_predicted = predicted_rms(
        &results
            .stations
            .iter()
            .map(|s| s.sigma_m)
            .collect::<Vec<_>>(),
    );
    println!("stations: RMS error {station_rms:.3e} m, predicted {station_predicted:.3e} m");
    assert!(
        station_rms <= 3.0 * station_predicted,
        "station RMS {station_rms:e} m exceeds 3x the predicted {station_predicted:e} m"
    );

    // Distances to the homing point do not depend on the datum.
    for s in &results.stations {
        for seg in &s.segments {
            let true_d = truth_station(truth, &s.id)["home_distance_m"][&seg.target]
                .as_f64()
                .expect("true home distance");
            assert!(
                (seg.home_distance_m - true_d).abs() <= 4.0 * seg.sigma_m,
                "station {} target {}: d = {} m, truth {} m, sigma {} m",
                s.id,
                seg.target,
                seg.home_distance_m,
                true_d,
                seg.sigma_m
            );
        }
    }
}

/// A config with unmodelled effects switched on: `effects` is the body of `[sim.effects]`
/// (TOML lines), `seed` replaces the demo's seed. The air temperature swings 0.5 K with a
/// 15 min period (an air-conditioning cycle), so refraction has something to follow.
pub fn with_effects(base: &str, seed: u64, effects: &str) -> String {
    format!(
        "{}\n[sim.environment]\ntemp_swing_k = 0.5\ntemp_period_s = 900.0\n\n[sim.effects]\n{effects}\n",
        base.replace("seed = 20261121", &format!("seed = {seed}"))
    )
}

/// Run a simulated session for `config_text` and diagnose the recorded file.
pub fn run_and_diagnose(config_text: &str) -> geocal::diagnose::Diagnosis {
    let config = geocal::config::Config::parse(config_text, std::path::Path::new("effects.toml"))
        .expect("config");
    let dir = tempfile::tempdir().expect("tempdir");
    let output = geocal::run::run(
        &config,
        &geocal::run::RunOptions {
            out_dir: dir.path().to_path_buf(),
            truth: None,
            progress: false,
            settings: Default::default(),
        },
    )
    .expect("run");
    geocal::diagnose::diagnose_file(&output.session_path, &Default::default()).expect("diagnose")
}

/// A geocal-diagnosis/1 object with every field SESSION_FORMAT.md requires.
pub fn assert_diagnosis_format(d: &Value) {
    assert_eq!(d["format"], "geocal-diagnosis/1");
    for key in [
        "noise_floor_m",
        "gap",
        "where",
        "candidates",
        "selected",
        "gap_after",
        "unexplained",
    ] {
        assert!(d.get(key).is_some(), "missing `{key}` in {d}");
    }
}

/// The small demo (4 stations x 3x3x2 points, one pass) over the emulators: a 1000 Hz
/// stream, a fast machine and short dwells so the run takes seconds of real time. The
/// stillstand window holds 30 samples; its tolerance stays the demo's.
pub fn hil_config(extra: &str) -> String {
    let base = small_demo();
    let text = base
        .replace(
            "id = \"tracer0\"\ndriver = \"sim\"",
            "id = \"tracer0\"\ndriver = \"hpi3d\"",
        )
        .replace("sample_rate_hz = 25.0", "sample_rate_hz = 1000.0")
        .replace(
            "id = \"env0\"\ndriver = \"sim\"\nsample_rate_hz = 1.0",
            "id = \"env0\"\ndriver = \"hpi3d\"\nsample_rate_hz = 4.0",
        )
        .replace(
            "driver = \"sim\"\nfeed_m_s = 0.3",
            "driver = \"grbl\"\nfeed_m_s = 20.0",
        )
        .replace(
            "passes = [\"forward\", \"backward\"]",
            "passes = [\"forward\"]",
        )
        .replace("dwell_s = 2.0", "dwell_s = 0.03")
        .replace("max_dwell_s = 20.0", "max_dwell_s = 2.0")
        .replace("window_s = 0.6", "window_s = 0.03");
    assert!(
        !text.contains("\ndriver = \"sim\""),
        "every device replaced:\n{text}"
    );
    format!(
        "{text}
[devices.tracer.hpi3d]
ack_timeout_s = 0.05
retries = 3
stream_timeout_s = 0.2
flag_clear_interval_s = 0.05

[devices.machine.grbl]
port = \"\"
ack_timeout_s = 0.3
status_interval_s = 0.005

[hil]
emulate = true
{extra}
"
    )
}

/// Every fault the HIL emulators inject (`[hil.tracer_faults]`, `[hil.machine_faults]`), for
/// `hil_config`: dropped, corrupted and garbage frames, a silent tracer, a beam break, a lost `ok`.
pub const HIL_FAULTS: &str = "
[hil.tracer_faults]
seed = 7
drop_fraction = 0.002
corrupt_fraction = 0.002
garbage_fraction = 0.002
silence = { from_s = 3.0, to_s = 3.5 }
beam_break = { from_s = 6.0, to_s = 6.3 }

[hil.machine_faults]
drop_ok_at_lines = [20]
";
