//! `geocal diagnose` on rotary_tracer sessions (the tracer on the rotary table): the outside
//! sessions of another recorder and geocal's own simulator with each effect of the kind's
//! library withheld name that effect, clean sessions name nothing, an effect outside the
//! library is `unexplained`; `geocal solve --effects tracer_eccentricity` gives step angles as
//! good as a clean session's, with honest σ.

use crate::common;

use std::path::{Path, PathBuf};

use geocal::diagnose::{text, Diagnosis};
use geocal::kinds::diagnosis::diagnose_file;
use geocal::kinds::rotary_tracer::solve::RotaryTracerResults;
use geocal::method::SolveSettings;
use serde_json::Value;

/// An outside session (`../shared/sessions/`, beside the checkout; one level further up from
/// a worktree under `wt/`).
fn outside_dir(name: &str) -> PathBuf {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let beside = root.join("../shared/sessions").join(name);
    if beside.exists() {
        return beside;
    }
    root.join("../../shared/sessions").join(name)
}

fn truth(dir: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(dir.join("truth.json")).expect("truth.json"))
        .expect("truth json")
}

fn diagnosed(dir: &Path) -> Diagnosis {
    diagnose_file(&dir.join("session.mcap"), &Default::default()).expect("diagnose")
}

fn param(d: &Diagnosis, effect: &str, name: &str) -> (f64, f64) {
    let c = d
        .candidates
        .iter()
        .find(|c| c.effect == effect)
        .expect("candidate");
    let v = c.params[name].as_f64().expect("value");
    let s = c.params[&format!("{name}.sigma")].as_f64().expect("sigma");
    (v, s)
}

fn solved(session: &Path, effects: &[&str]) -> RotaryTracerResults {
    let settings = SolveSettings {
        effects: geocal::kinds::tracer_plan::diagnosis::correct::fit_named(
            effects
                .iter()
                .map(|e| match *e {
                    "tracer_eccentricity" => "tracer_eccentricity",
                    "station_drift" => "station_drift",
                    other => panic!("no such effect here: {other}"),
                })
                .collect(),
        ),
        ..Default::default()
    };
    let results = geocal::kinds::solve_file(session, &settings).expect("solve");
    results
        .get::<RotaryTracerResults>()
        .expect("rotary results")
        .clone()
}

/// Per step (but the reference): (estimated − true error, σ); the truth's `error_rad` is the
/// pivot's turn on the true pivots' circle, relative to the reference station.
fn step_errors(results: &RotaryTracerResults, truth: &Value) -> Vec<(f64, f64)> {
    let steps = truth["rotary"]["steps"].as_array().expect("truth steps");
    results
        .rotary
        .steps
        .iter()
        .skip(1)
        .map(|s| {
            let t = steps
                .iter()
                .find(|t| t["station"] == s.station.as_str())
                .expect("true step");
            (
                s.error_rad - t["error_rad"].as_f64().expect("error_rad"),
                s.sigma_rad,
            )
        })
        .collect()
}

fn rms(v: &[f64]) -> f64 {
    (v.iter().map(|x| x * x).sum::<f64>() / v.len().max(1) as f64).sqrt()
}

#[test]
fn outside_clean_session_selects_nothing() {
    let d = diagnosed(&outside_dir("outside-rotary-clean-2"));
    println!("{}", text(&d));
    assert!(d.selected.is_empty(), "{}", text(&d));
    assert!(!d.unexplained, "{}", text(&d));
    assert!(
        d.candidates
            .iter()
            .any(|c| c.effect == "table_error_motion"),
        "{}",
        text(&d)
    );
}

#[test]
fn outside_eccentricity_is_named_and_fitted() {
    let dir = outside_dir("outside-rotary-eccentricity-21");
    let t = truth(&dir);
    let d = diagnosed(&dir);
    println!("{}", text(&d));
    assert_eq!(d.selected, ["tracer_eccentricity"], "{}", text(&d));
    assert!(!d.unexplained, "{}", text(&d));
    let ecc = &t["effect_params"]["tracer_eccentricity"];
    let e = ecc["e_m"].as_f64().expect("e");
    let phi0 = ecc["phi0_rad"][0].as_f64().expect("phi0");
    for (name, want) in [
        ("table.e_cos_phi0_m", e * phi0.cos()),
        ("table.e_sin_phi0_m", e * phi0.sin()),
    ] {
        let (v, s) = param(&d, "tracer_eccentricity", name);
        println!(
            "{name}: {v:.4e} ± {s:.2e}, truth {want:.4e}, z {:.2}",
            (v - want) / s
        );
        assert!(
            (v - want).abs() < 4.0 * s,
            "{name}: {v} ± {s}, truth {want}"
        );
    }
}

#[test]
fn outside_table_motion_is_named_at_the_stations() {
    let clean = diagnosed(&outside_dir("outside-rotary-clean-2"));
    let (clean_ratio, _) = stations_heldout(&clean);
    println!("outside-rotary-clean-2: stations held-out ratio {clean_ratio:.2}");
    for name in ["outside-rotary-table-motion-22", "outside-rotary-wobble-4"] {
        let dir = outside_dir(name);
        let d = diagnosed(&dir);
        println!("{name}\n{}", text(&d));
        assert_eq!(d.selected, ["table_error_motion"], "{name}: {}", text(&d));
        assert!(!d.unexplained, "{name}: {}", text(&d));
        let c = d
            .candidates
            .iter()
            .find(|c| c.effect == "table_error_motion")
            .expect("candidate");
        let before = c.params["stations_heldout_ratio"].as_f64().expect("ratio");
        let after = c.params["stations_heldout_ratio_after"]
            .as_f64()
            .expect("ratio");
        println!("{name}: stations held-out ratio {before:.2} -> {after:.2}");
        assert!(
            after <= HELDOUT_STATIONS_MAX,
            "{name}: held-out ratio after {after}, clean {clean_ratio}"
        );
        if name == "outside-rotary-table-motion-22" {
            check_motion_parameters(&d, &truth(&dir));
        }
    }
}

/// The fitted harmonics against the same harmonics fitted to the truth's own pivot
/// displacements (radial, axial per table station, by least squares with the circle's
/// harmonics 0-1 beside them).
fn check_motion_parameters(d: &Diagnosis, truth: &Value) {
    use nalgebra::{DMatrix, DVector};
    let c = d
        .candidates
        .iter()
        .find(|c| c.effect == "table_error_motion")
        .expect("candidate");
    let displacements = truth["effect_params"]["table_error_motion"]["pivot_displacement_m"]
        .as_array()
        .expect("pivot displacements");
    let angle = |station: &str| {
        truth["stations"]
            .as_array()
            .expect("stations")
            .iter()
            .find(|s| s["id"] == station)
            .and_then(|s| s["commanded_rad"].as_f64())
            .expect("commanded angle")
    };
    // Columns: (row 0 radial / 1 axial, order, sine).
    let mut columns: Vec<(usize, u32, bool)> = Vec::new();
    for (row, top) in [(0, 5), (1, 4)] {
        for order in 0..=top {
            columns.push((row, order, false));
            if order > 0 {
                columns.push((row, order, true));
            }
        }
    }
    let m = displacements.len();
    let mut x = DMatrix::zeros(2 * m, columns.len());
    let mut y = DVector::zeros(2 * m);
    for (k, p) in displacements.iter().enumerate() {
        let theta = angle(p["station"].as_str().expect("station"));
        y[2 * k] = p["radial"].as_f64().expect("radial");
        y[2 * k + 1] = p["axial"].as_f64().expect("axial");
        for (col, &(row, order, sine)) in columns.iter().enumerate() {
            let (s, co) = (f64::from(order) * theta).sin_cos();
            x[(2 * k + row, col)] = if sine { s } else { co };
        }
    }
    let fit = x.clone().svd(true, true).solve(&y, 1e-12).expect("lsq");
    let residual = (&x * &fit - &y).norm() / (2.0 * m as f64).sqrt();
    println!(
        "truth's displacements beyond the model: RMS {:.2} nm",
        1e9 * residual
    );
    let mut z2 = Vec::new();
    for (col, &(row, order, sine)) in columns.iter().enumerate() {
        if order < 2 {
            continue;
        }
        let name = format!(
            "{}_{}{order}_m",
            if row == 0 { "radial" } else { "axial" },
            if sine { "sin" } else { "cos" }
        );
        let v = c.params[&name].as_f64().expect("value");
        let s = c.params[&format!("{name}.sigma")].as_f64().expect("sigma");
        let z = (v - fit[col]) / s;
        println!(
            "{name}: {:.1} ± {:.1} nm, truth {:.1} nm, z {z:.2}",
            1e9 * v,
            1e9 * s,
            1e9 * fit[col]
        );
        assert!(z.abs() < 4.0, "{name}: {v} ± {s}, truth {}", fit[col]);
        z2.push(z * z);
    }
    let mean = z2.iter().sum::<f64>() / z2.len() as f64;
    println!(
        "table_error_motion parameters: mean z² {mean:.2} over {}",
        z2.len()
    );
}

#[test]
fn outside_eccentricity_fitted_gives_step_angles_as_good_as_clean() {
    let clean_dir = outside_dir("outside-rotary-clean-2");
    let clean = step_errors(
        &solved(&clean_dir.join("session.mcap"), &[]),
        &truth(&clean_dir),
    );
    let dir = outside_dir("outside-rotary-eccentricity-21");
    let session = dir.join("session.mcap");
    let t = truth(&dir);
    let plain = step_errors(&solved(&session, &[]), &t);
    let fitted = step_errors(&solved(&session, &["tracer_eccentricity"]), &t);
    let err = |v: &[(f64, f64)]| rms(&v.iter().map(|e| e.0).collect::<Vec<_>>());
    let z2 =
        |v: &[(f64, f64)]| v.iter().map(|(e, s)| (e / s).powi(2)).sum::<f64>() / v.len() as f64;
    println!(
        "step error RMS: clean {:.3}\", plain {:.3}\" (z² {:.1}), fitted {:.3}\" (z² {:.2}); clean z² {:.2}",
        err(&clean).to_degrees() * 3600.0,
        err(&plain).to_degrees() * 3600.0,
        z2(&plain),
        err(&fitted).to_degrees() * 3600.0,
        z2(&fitted),
        z2(&clean)
    );
    assert!(err(&fitted) <= 2.0 * err(&clean), "fitted {fitted:?}");
    // Honest σ: mean z² of 11 steps near 1 (its 99 % range for 11 dof is 0.23-2.2).
    assert!(z2(&fitted) < 2.3, "z² {}", z2(&fitted));
}

/// The published set-up (12 table stations 30° apart + 1 off the table, 6 x 6 x 2 points) at
/// 10 Hz with 1 s dwells, at `seed`, the air swinging 0.5 K in 15 min, with `effects`.
fn simulated(seed: u64, effects: &str) -> String {
    let base = common::ROTARY
        .replace("sample_rate_hz = 25.0", "sample_rate_hz = 10.0")
        .replace("dwell_s = 2.0", "dwell_s = 1.0")
        .replace("window_s = 0.6", "window_s = 0.4")
        .replace("seed = 20240611", &format!("seed = {seed}"));
    assert!(base.contains(&format!("seed = {seed}")) && base.contains("dwell_s = 1.0"));
    format!(
        "{base}\n[sim.environment]\ntemp_swing_k = 0.5\ntemp_period_s = 900.0\n\n[sim.effects]\n{effects}\n"
    )
}

fn stations_heldout(d: &Diagnosis) -> (f64, f64) {
    let c = d
        .candidates
        .iter()
        .find(|c| c.effect == "table_error_motion")
        .expect("table_error_motion candidate");
    let f = |k: &str| c.params[k].as_f64().expect(k);
    (
        f("stations_heldout_ratio"),
        f("stations_heldout_ratio_after"),
    )
}

/// Held-out gap after the selected effect within this factor of the clean session's (the
/// lengths: ~300 held-out lengths, sampling spread of the ratio ≈ 0.04).
const HELDOUT_VS_CLEAN_MAX: f64 = 1.3;

/// The stations level's held-out ratio where the model holds: 12 table stations, each
/// predicted from the others, z²/2 per station ~ χ²(2)/2 (variance 1), so the mean over 12 has
/// a standard deviation of 0.29 and the ratio √(mean) of 0.14: one clean draw lies anywhere in
/// 0.7-1.3 (outside-rotary-clean-2: 0.70). The bound is 3 of those above 1. Against one clean
/// draw the level is the clean session's held-out ratio under the same model (its
/// `table_error_motion` candidate, fitted though not selected): the nominal model's predicts
/// from other columns, another random variable of the same noise (seeds 31-36: 0.58-1.44 of
/// it after the effect, 0.999-1.001 of the same model's).
const HELDOUT_STATIONS_MAX: f64 = 1.43;

#[test]
fn simulated_effects_are_named_against_the_clean_case() {
    let seed = 31;
    let clean = common::run_and_diagnose(&simulated(seed, ""));
    println!("clean\n{}", text(&clean));
    assert!(clean.selected.is_empty(), "{}", text(&clean));
    assert!(!clean.unexplained, "{}", text(&clean));
    let clean_lengths = clean.gap_after.heldout_ratio;
    let (clean_stations, clean_stations_same_model) = stations_heldout(&clean);

    let ecc = common::run_and_diagnose(&simulated(
        seed,
        "tracer_eccentricity = { enabled = true, size_m = 4e-6, z_size_m = 2e-6 }",
    ));
    println!("tracer_eccentricity\n{}", text(&ecc));
    assert_eq!(ecc.selected, ["tracer_eccentricity"], "{}", text(&ecc));
    assert!(!ecc.unexplained, "{}", text(&ecc));
    println!(
        "lengths held-out ratio: clean {clean_lengths:.3}, eccentricity {:.3} -> {:.3}",
        ecc.gap.heldout_ratio, ecc.gap_after.heldout_ratio
    );
    assert!(ecc.gap_after.heldout_ratio <= HELDOUT_VS_CLEAN_MAX * clean_lengths);

    let motion = common::run_and_diagnose(&simulated(
        seed,
        "table_error_motion = { enabled = true, size = 1e-6 }",
    ));
    println!("table_error_motion\n{}", text(&motion));
    assert_eq!(motion.selected, ["table_error_motion"], "{}", text(&motion));
    assert!(!motion.unexplained, "{}", text(&motion));
    let (before, after) = stations_heldout(&motion);
    println!(
        "stations held-out ratio: clean {clean_stations:.3} ({clean_stations_same_model:.3} with the motion's harmonics), table motion {before:.3} -> {after:.3}"
    );
    assert!(
        after <= HELDOUT_STATIONS_MAX,
        "held-out ratio after {after}"
    );
    assert!(
        after <= HELDOUT_VS_CLEAN_MAX * clean_stations_same_model,
        "held-out ratio after {after}, clean {clean_stations_same_model} under the same model"
    );

    let outside_library = common::run_and_diagnose(&simulated(
        seed,
        "periodic_nonlinearity = { enabled = true, size_m = 3e-7, period_m = 0.05 }",
    ));
    println!("periodic_nonlinearity\n{}", text(&outside_library));
    assert!(outside_library.unexplained, "{}", text(&outside_library));
    assert!(
        outside_library.selected.is_empty(),
        "{}",
        text(&outside_library)
    );
}

/// The table stations' angles come from the `rotation` events alike from the streamed file and
/// from the whole read.
#[test]
fn rotations_stream_as_read_whole() {
    let path = outside_dir("outside-rotary-clean-2").join("session.mcap");
    let streamed =
        geocal::extract::stream_settled(&path, |k| k == "rotary_tracer").expect("streams");
    let session = geocal::session::reader::read_session(&path).expect("session");
    let whole = geocal::extract::SettledSession::of_session(&session).expect("settled");
    assert_eq!(streamed.rotations.len(), 12);
    assert_eq!(streamed.rotations, whole.rotations);
}
