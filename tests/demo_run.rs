//! The demo configuration run end to end in simulation: the recovered stations and points
//! must match the simulated truth within what the noise model predicts, the replay must give
//! identical results, and an independent reader must accept the session.

mod common;

use std::path::Path;

use geocal::config::Config;
use geocal::method::Results;
use geocal::run::{run, solve_file, RunOptions};
use serde_json::Value;

#[test]
fn demo_recovers_truth_and_replays_identically() {
    let dir = tempfile::tempdir().expect("tempdir");
    let config = Config::load(Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/config/demo-multilateration.toml"
    )))
    .expect("demo config");
    let truth_path = dir.path().join("truth.json");
    let output = run(
        &config,
        &RunOptions {
            out_dir: dir.path().to_path_buf(),
            truth: Some(truth_path.clone()),
            progress: false,
        },
    )
    .expect("demo run");
    let Results::Multilateration(results) = &output.results;
    let truth: Value = serde_json::from_slice(&std::fs::read(&truth_path).expect("truth file"))
        .expect("truth json");

    assert!(results.converged, "solver did not converge");
    assert_eq!(
        results.extraction.windows_dropped, 0,
        "{:?}",
        results.extraction.dropped_reasons
    );
    assert_eq!(results.points.len(), 100);
    // The fit is consistent with the noise model: chi2/dof near 1 (dof ~ 800: 3 sigma ~ 0.15).
    assert!(
        (results.chi2_per_dof - 1.0).abs() < 0.2,
        "chi2/dof = {}",
        results.chi2_per_dof
    );

    // Points: estimated vs true actual positions after removing a best-fit rigid motion.
    let truth_points: Vec<[f64; 3]> = results
        .points
        .iter()
        .map(|p| {
            let v = &truth["points"][p.point]["actual_m"];
            [0, 1, 2].map(|k| v[k].as_f64().expect("truth point"))
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

    // Stations, in the same frame as the points.
    let truth_stations: Vec<[f64; 3]> = results
        .stations
        .iter()
        .map(|s| {
            let st = truth["stations"]
                .as_array()
                .expect("stations")
                .iter()
                .find(|x| x["id"] == s.id.as_str())
                .expect("station in truth");
            [0, 1, 2].map(|k| st["position_m"][k].as_f64().expect("station"))
        })
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

    // Distances to the homing point do not depend on the datum: each within 4 sigma.
    for s in &results.stations {
        let true_d = truth["stations"]
            .as_array()
            .expect("stations")
            .iter()
            .find(|x| x["id"] == s.id.as_str())
            .and_then(|x| x["home_distance_m"].as_f64())
            .expect("true home distance");
        let seg = &s.segments[0];
        assert!(
            (seg.home_distance_m - true_d).abs() <= 4.0 * seg.sigma_m,
            "station {}: d = {} m, truth {} m, sigma {} m",
            s.id,
            seg.home_distance_m,
            true_d,
            seg.sigma_m
        );
    }

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
