//! Whole simulated runs: the recovered stations and points must match the simulated truth
//! within what the noise model predicts, the replay must give identical results, and an
//! independent reader must accept the session.

mod common;

use std::path::Path;

use geocal::config::Config;
use geocal::method::multilateration::MultilaterationResults;
use geocal::run::{run, solve_file, RunOptions, RunOutput};
use serde_json::Value;

const DEMO: &str = include_str!("../config/demo-multilateration.toml");

fn run_with_truth(config_text: &str, dir: &Path) -> (RunOutput, Value) {
    let config = Config::parse(config_text, Path::new("test.toml")).expect("config");
    let truth_path = dir.join("truth.json");
    let output = run(
        &config,
        &RunOptions {
            out_dir: dir.to_path_buf(),
            truth: Some(truth_path.clone()),
            progress: false,
        },
    )
    .expect("run");
    let truth = serde_json::from_slice(&std::fs::read(&truth_path).expect("truth file"))
        .expect("truth json");
    (output, truth)
}

fn truth_station<'a>(truth: &'a Value, id: &str) -> &'a Value {
    truth["stations"]
        .as_array()
        .expect("stations")
        .iter()
        .find(|x| x["id"] == id)
        .expect("station in truth")
}

fn xyz(v: &Value) -> [f64; 3] {
    [0, 1, 2].map(|k| v[k].as_f64().expect("coordinate"))
}

/// Points and stations within 3x the RMS the reported covariance predicts (after removing a
/// best-fit rigid motion: the datum is a convention), home distances within 4 sigma.
fn assert_recovers_truth(results: &MultilaterationResults, truth: &Value) {
    assert!(results.converged, "solver did not converge");
    assert_eq!(
        results.extraction.windows_dropped, 0,
        "{:?}",
        results.extraction.dropped_reasons
    );
    let truth_points: Vec<[f64; 3]> = results
        .points
        .iter()
        .map(|p| {
            let t = truth["points"]
                .as_array()
                .expect("truth points")
                .iter()
                .find(|t| t["point"] == p.point && t["target"] == p.target.as_str())
                .expect("truth point");
            xyz(&t["actual_m"])
        })
        .collect();
    let estimated: Vec<[f64; 3]> = results.points.iter().map(|p| p.actual_m).collect();
    let (r, t) = common::rigid_fit(&estimated, &truth_points);
    let point_rms = common::rms_after(&r, &t, &estimated, &truth_points);
    let point_predicted =
        common::predicted_rms(&results.points.iter().map(|p| p.sigma_m).collect::<Vec<_>>());
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
    let station_rms = common::rms_after(&r, &t, &est_stations, &truth_stations);
    let station_predicted = common::predicted_rms(
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
