//! `geocal diagnose` on rotary_tracer sessions (the tracer on the rotary table): the outside
//! sessions of another recorder and geocal's own simulator with each effect of the kind's
//! library withheld name that effect, clean sessions name nothing, an effect outside the
//! library is `unexplained`; `geocal solve --effects tracer_eccentricity` gives step angles as
//! good as a clean session's, with honest σ.

mod common;

use std::path::{Path, PathBuf};

use geocal::diagnose::{diagnose_file, text, Diagnosis};
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
        effects: geocal::diagnose::correct::fit_named(
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
        d.candidates.iter().any(|c| c.effect == "table_error_motion"),
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
        println!("{name}: {v:.4e} ± {s:.2e}, truth {want:.4e}, z {:.2}", (v - want) / s);
        assert!((v - want).abs() < 4.0 * s, "{name}: {v} ± {s}, truth {want}");
    }
}

#[test]
fn outside_table_motion_is_named_at_the_stations() {
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
        let before = c.params["stations.heldout_ratio"].as_f64().expect("ratio");
        let after = c.params["stations.heldout_ratio_after"]
            .as_f64()
            .expect("ratio");
        println!("{name}: stations held-out ratio {before:.2} -> {after:.2}");
        assert!(after < 1.3 * 1.0_f64.max(before.min(1.0)) + 0.3, "{after}");
    }
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
    let z2 = |v: &[(f64, f64)]| {
        v.iter().map(|(e, s)| (e / s).powi(2)).sum::<f64>() / v.len() as f64
    };
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

/// The published set-up shrunk for speed (12 table stations 30° apart + 1 off the table,
/// 4 x 3 x 2 points, 10 Hz) at `seed`, the air swinging 0.5 K in 15 min, with `effects`.
fn simulated(seed: u64, effects: &str) -> String {
    let base = common::reduced_rotary(30f64.to_radians(), 12, "");
    assert!(base.contains("seed = 20240611"));
    format!(
        "{}\n[sim.environment]\ntemp_swing_k = 0.5\ntemp_period_s = 900.0\n\n[sim.effects]\n{effects}\n",
        base.replace("seed = 20240611", &format!("seed = {seed}"))
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
        f("stations.heldout_ratio"),
        f("stations.heldout_ratio_after"),
    )
}

/// Held-out gap after the selected effect within this factor of the clean session's.
const HELDOUT_VS_CLEAN_MAX: f64 = 1.3;

#[test]
fn simulated_effects_are_named_against_the_clean_case() {
    let seed = 31;
    let clean = common::run_and_diagnose(&simulated(seed, ""));
    println!("clean\n{}", text(&clean));
    assert!(clean.selected.is_empty(), "{}", text(&clean));
    assert!(!clean.unexplained, "{}", text(&clean));
    let clean_lengths = clean.gap_after.heldout_ratio;
    let clean_stations = stations_heldout(&clean).0;

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
        "stations held-out ratio: clean {clean_stations:.3}, table motion {before:.3} -> {after:.3}"
    );
    assert!(after <= HELDOUT_VS_CLEAN_MAX * clean_stations.max(1.0));

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
