//! `geocal solve --effects`: on simulated sessions of each effect the solve can model, the
//! calibration with that effect fitted brings the points back to within 2x the error of the
//! same machine measured without the effect.

use crate::common;

use common::{diagnose_demo, rigid_fit, rms_after, run_with_truth, truth_point, with_effects, xyz};
use geocal::kinds::tracer_plan::diagnosis::correct::parse_effects;
use geocal::method::SolveSettings;

/// Point RMS error (m) after the best rigid fit onto the truth, χ²/dof, and the RMS of each
/// coordinate's error over its σ (1 when the σ are honest).
fn point_error_m(config: &str, effects: &str) -> (f64, f64, f64) {
    let dir = tempfile::tempdir().expect("tempdir");
    let (output, truth) = run_with_truth(config, dir.path());
    let settings = SolveSettings {
        effects: parse_effects(&[effects.to_string()]).expect("effect names"),
        ..Default::default()
    };
    let results = geocal::kinds::solve_file(&output.session_path, &settings).expect("solve");
    let results = results.multilateration().expect("multilateration");
    let truth_points: Vec<[f64; 3]> = results
        .points
        .iter()
        .map(|p| xyz(&truth_point(&truth, &p.target, p.point)["actual_m"]))
        .collect();
    let estimated: Vec<[f64; 3]> = results.points.iter().map(|p| p.actual_m).collect();
    let (r, t) = rigid_fit(&estimated, &truth_points);
    let z2: Vec<f64> = results
        .points
        .iter()
        .zip(&truth_points)
        .flat_map(|(p, truth)| {
            let moved = r * nalgebra::Vector3::from(p.actual_m) + t;
            (0..3).map(move |k| ((moved[k] - truth[k]) / p.sigma_m[k]).powi(2))
        })
        .collect();
    (
        rms_after(&r, &t, &estimated, &truth_points),
        results.chi2_per_dof,
        (z2.iter().sum::<f64>() / z2.len() as f64).sqrt(),
    )
}

#[test]
fn each_effect_modelled_restores_the_points() {
    let seed = 41;
    let (clean_m, _, clean_z) = point_error_m(&with_effects(&diagnose_demo(), seed, ""), "");
    println!(
        "effect-free point RMS error {:.3} um, error/sigma RMS {clean_z:.2}",
        clean_m * 1e6
    );
    let cases = [
        (
            "station_drift",
            "station_drift = { enabled = true, size = 5e-9 }",
        ),
        ("reversal", "reversal = { enabled = true, size = 1e-6 }"),
        (
            "length_step",
            "length_step = { enabled = true, size = 1e-6 }",
        ),
        (
            "air_refraction",
            "air_refraction = { enabled = true, size = 1.0 }",
        ),
        (
            "tracer_eccentricity",
            "tracer_eccentricity = { enabled = true, size_m = 4e-6, z_size_m = 2e-6 }",
        ),
        (
            "thermal_drift",
            "thermal_drift = { enabled = true, size = 4e-9 }",
        ),
        ("dead_path", "dead_path = { enabled = true, size = 2.0 }"),
        (
            "thermal_expansion",
            "thermal_expansion = { enabled = true, size = 2e-6 }",
        ),
    ];
    let mut failures = Vec::new();
    for (effect, line) in cases {
        let config = with_effects(&diagnose_demo(), seed, line);
        let (plain_m, _, _) = point_error_m(&config, "");
        let (modelled_m, chi2, z) = point_error_m(&config, effect);
        println!(
            "{effect:<20} point RMS error {:.3} um unmodelled, {:.3} um modelled (effect-free {:.3} um), chi2/dof {chi2:.2}, error/sigma RMS {z:.2}",
            plain_m * 1e6,
            modelled_m * 1e6,
            clean_m * 1e6
        );
        if modelled_m > 2.0 * clean_m {
            failures.push(effect);
        }
        // Honest sigma with the eccentricity fitted (its parameters' covariance in the
        // points'): error/sigma as on the same machine without the effect (0.78 there: the
        // points' sigma in the solve's datum against errors after a rigid fit), neither
        // overconfident nor inflated beyond a quarter.
        let ratio = z / clean_z;
        if effect == "tracer_eccentricity" && !(0.75..=1.3).contains(&ratio) {
            failures.push("tracer_eccentricity sigma");
        }
    }
    assert!(failures.is_empty(), "not restored: {failures:?}");
}

#[test]
fn unknown_and_unmodellable_effects_are_clear_errors() {
    let unknown = parse_effects(&["reversal,backlash".to_string()])
        .expect_err("unknown name refused")
        .to_string();
    assert!(unknown.contains("unknown effect `backlash`"), "{unknown}");
    assert!(
        unknown.contains("station_drift") && unknown.contains("reversal"),
        "{unknown}"
    );
    let settling = parse_effects(&["settling".to_string()])
        .expect_err("settling refused")
        .to_string();
    assert!(
        settling.contains("cannot be modelled in the calibration"),
        "{settling}"
    );
}
