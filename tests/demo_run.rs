//! Whole simulated runs: the recovered stations and points must match the simulated truth
//! within what the noise model predicts, the replay must give identical results, and an
//! independent reader must accept the session.

use crate::common;

use std::path::Path;

use common::{assert_recovers_truth, run_with_truth, truth_point, xyz, DEMO};
use geocal::config::Config;
use geocal::kinds::solve_file;
use geocal::method::multilateration::MultilaterationResults;
use serde_json::Value;

/// Every identifiable geometric error value of the results beside the simulated truth,
/// expressed in the decomposition's datum.
fn grade_geometric_errors(
    results: &MultilaterationResults,
    truth: &Value,
) -> Vec<geocal::solve::geometric_errors::validation::Comparison> {
    use geocal::solve::geometric_errors::{grid_from_points, PointObservation};
    let errors: geocal::sim::truth::TruthErrors =
        serde_json::from_value(truth["error_model"].clone()).expect("truth error model");
    let structure = geocal::model::kinematics::Structure::parse(
        truth["structure"].as_str().expect("structure"),
    )
    .expect("structure");
    let config = Config::parse(DEMO, Path::new("demo.toml")).expect("config");
    let points: Vec<PointObservation> = results
        .points
        .iter()
        .map(|p| {
            let t = truth_point(truth, &p.target, p.point);
            PointObservation {
                axes_m: xyz(&t["axes_m"]),
                target_offset_m: config.target_offset(&p.target).expect("target"),
                error_m: p.error_m,
                covariance: nalgebra::Matrix3::from_diagonal(&nalgebra::Vector3::from(
                    p.sigma_m.map(|s| s * s),
                )),
            }
        })
        .collect();
    let grid = grid_from_points(&points, 1e-9);
    let json = results
        .geometric_errors
        .as_ref()
        .expect("geometric errors in results");
    geocal::solve::geometric_errors::validation::compare_with_truth(
        &structure, &grid, &points, json, &errors,
    )
    .expect("comparison")
}

#[test]
fn demo_recovers_truth_and_replays_identically() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (output, truth) = run_with_truth(DEMO, dir.path());
    let results = output.results.multilateration().expect("tracer results");
    assert_eq!(results.points.len(), 100);
    assert_recovers_truth(results, &truth);
    // The fit is consistent with the noise model: chi2/dof near 1 (dof ~ 700: 3 sigma ~ 0.16).
    assert!(
        (results.chi2_per_dof - 1.0).abs() < 0.2,
        "chi2/dof = {}",
        results.chi2_per_dof
    );

    // The 21 geometric errors, where identifiable, match the truth within their sigmas.
    let graded = grade_geometric_errors(results, &truth);
    let z: Vec<f64> = graded.iter().map(|c| c.normalised()).collect();
    let within = z.iter().filter(|v| v.abs() <= 3.0).count() as f64 / z.len() as f64;
    let rms = (z.iter().map(|v| v * v).sum::<f64>() / z.len() as f64).sqrt();
    println!(
        "geometric errors: {} values, {:.1}% within 3 sigma, normalised RMS {rms:.2}",
        z.len(),
        100.0 * within
    );
    assert!(z.len() > 40, "only {} identifiable values", z.len());
    assert!(within >= 0.97, "{:.1}% within 3 sigma", 100.0 * within);
    assert!((0.6..1.4).contains(&rms), "normalised RMS {rms}");

    // The plan check predicted these uncertainties before measuring, from the plan alone.
    let config = Config::parse(DEMO, Path::new("demo.toml")).expect("config");
    let check =
        geocal::method::plan_check::check(&config, &geocal::plan::Plan::from_config(&config))
            .expect("check");
    let predicted = check.point_sigma.expect("point sigmas").rms_sigma_m;
    let reported =
        common::predicted_rms(&results.points.iter().map(|p| p.sigma_m).collect::<Vec<_>>());
    let predicted_rms = (predicted.iter().map(|s| s * s).sum::<f64>() / 3.0).sqrt();
    println!(
        "plan check predicted point sigma {predicted_rms:.3e} m, run reported {reported:.3e} m"
    );
    assert!(
        (0.8..1.25).contains(&(reported / predicted_rms)),
        "plan check predicted {predicted_rms:e} m, the run reported {reported:e} m"
    );

    // The volumetric errors are real (micrometres) and resolved far above their sigma.
    let max_error = results
        .points
        .iter()
        .flat_map(|p| p.error_m)
        .fold(0.0f64, |m, e| m.max(e.abs()));
    assert!(
        max_error > 1e-6,
        "simulated errors should reach micrometres, max {max_error:e}"
    );

    // Replay: solving the recorded session gives the same results JSON.
    let replayed = solve_file(&output.session_path, &Default::default()).expect("replay");
    assert_eq!(replayed.to_json_pretty(), output.results.to_json_pretty());
    let written = std::fs::read_to_string(&output.results_path).expect("results.json");
    assert_eq!(written, output.results.to_json_pretty());

    // An independent reader (Python mcap + jsonschema) accepts every message.
    common::python_check_session(&output.session_path, output.summary.samples);
}

#[test]
fn two_targets_each_get_their_own_homing_distance() {
    let text = common::small_demo()
        .replace(
            "targets = [{ id = \"t0\", offset_m = [0.0, 0.0, -0.12] }]",
            "targets = [{ id = \"t0\", offset_m = [0.0, 0.0, -0.12] }, { id = \"t1\", offset_m = [0.15, 0.10, -0.12] }]",
        )
        .replace("targets = [\"t0\"]", "targets = [\"t0\", \"t1\"]");
    let dir = tempfile::tempdir().expect("tempdir");
    let (output, truth) = run_with_truth(&text, dir.path());
    let results = output.results.multilateration().expect("tracer results");
    assert_eq!(results.points.len(), 2 * 18);
    for s in &results.stations {
        let targets: Vec<&str> = s.segments.iter().map(|g| g.target.as_str()).collect();
        assert_eq!(targets, ["t0", "t1"], "station {}", s.id);
    }
    assert_recovers_truth(results, &truth);
}
