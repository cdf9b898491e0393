//! Whole simulated runs: the recovered stations and points must match the simulated truth
//! within what the noise model predicts, the replay must give identical results, and an
//! independent reader must accept the session.

mod common;

use common::{assert_recovers_truth, run_with_truth};
use geocal::run::solve_file;

const DEMO: &str = include_str!("../config/demo-multilateration.toml");

#[test]
fn demo_recovers_truth_and_replays_identically() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (output, truth) = run_with_truth(DEMO, dir.path());
    let results = output.results.multilateration();
    assert_eq!(results.points.len(), 100);
    assert_recovers_truth(results, &truth);
    // The fit is consistent with the noise model: chi2/dof near 1 (dof ~ 700: 3 sigma ~ 0.16).
    assert!(
        (results.chi2_per_dof - 1.0).abs() < 0.2,
        "chi2/dof = {}",
        results.chi2_per_dof
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
    let replayed = solve_file(&output.session_path).expect("replay");
    assert_eq!(replayed.to_json_pretty(), output.results.to_json_pretty());
    let written = std::fs::read_to_string(&output.results_path).expect("results.json");
    assert_eq!(written, output.results.to_json_pretty());

    // An independent reader (Python mcap + jsonschema) accepts every message.
    common::python_check_session(&output.session_path, output.summary.samples);
}

#[test]
fn two_targets_each_get_their_own_homing_distance() {
    let cut = DEMO
        .find("[[plan.stations]]\nid = \"s5\"")
        .expect("station s5");
    let sim = DEMO.find("\n[sim]").expect("[sim]");
    let text = format!("{}{}", &DEMO[..cut], &DEMO[sim..])
        .replace("count = 5 }", "count = 3 }")
        .replace("count = 4 }", "count = 2 }")
        .replace(
            "targets = [{ id = \"t0\", offset_m = [0.0, 0.0, -0.12] }]",
            "targets = [{ id = \"t0\", offset_m = [0.0, 0.0, -0.12] }, { id = \"t1\", offset_m = [0.15, 0.10, -0.12] }]",
        )
        .replace("targets = [\"t0\"]", "targets = [\"t0\", \"t1\"]");
    let dir = tempfile::tempdir().expect("tempdir");
    let (output, truth) = run_with_truth(&text, dir.path());
    let results = output.results.multilateration();
    assert_eq!(results.points.len(), 2 * 18);
    for s in &results.stations {
        let targets: Vec<&str> = s.segments.iter().map(|g| g.target.as_str()).collect();
        assert_eq!(targets, ["t0", "t1"], "station {}", s.id);
    }
    assert_recovers_truth(results, &truth);
}
