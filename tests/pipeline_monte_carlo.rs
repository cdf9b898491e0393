//! The whole pipeline (simulated devices -> recording -> stillstand extraction -> adjustment)
//! is efficient and honest: over many seeds, the actual errors of points and stations match
//! the uncertainties the results report (ratio of RMS within [0.8, 1.25]).

use crate::common;

use std::path::Path;

use geocal::config::Config;
use geocal::kinds::tracer_plan::run::run;
use geocal::run::RunOptions;
use serde_json::Value;

use common::DEMO;
const SEEDS: u64 = 20;

#[test]
fn reported_uncertainty_matches_actual_error_over_seeds() {
    let base = DEMO
        .replace("count = 4 }", "count = 2 }")
        .replace("count = 5 }", "count = 4 }")
        .replace(
            "passes = [\"forward\", \"backward\"]",
            "passes = [\"forward\"]",
        );
    let (mut point_err, mut point_pred, mut station_err, mut station_pred) = (0.0, 0.0, 0.0, 0.0);
    for seed in 0..SEEDS {
        let text = base.replace("seed = 20261121", &format!("seed = {}", 1000 + seed));
        let config = Config::parse(&text, Path::new("mc.toml")).expect("config");
        let dir = tempfile::tempdir().expect("tempdir");
        let truth_path = dir.path().join("truth.json");
        let output = run(
            &config,
            &RunOptions {
                out_dir: dir.path().to_path_buf(),
                truth: Some(truth_path.clone()),
                progress: false,
                settings: Default::default(),
                control: Default::default(),
            },
        )
        .expect("run");
        let truth: Value =
            serde_json::from_slice(&std::fs::read(truth_path).expect("truth")).expect("json");
        let r = output.results.multilateration().expect("tracer results");
        let xyz = |v: &Value| [0, 1, 2].map(|k| v[k].as_f64().expect("number"));
        let true_points: Vec<[f64; 3]> = r
            .points
            .iter()
            .map(|p| xyz(&truth["points"][p.point]["actual_m"]))
            .collect();
        let points: Vec<[f64; 3]> = r.points.iter().map(|p| p.actual_m).collect();
        let (rot, t) = common::rigid_fit(&points, &true_points);
        point_err += common::rms_after(&rot, &t, &points, &true_points).powi(2);
        point_pred +=
            common::predicted_rms(&r.points.iter().map(|p| p.sigma_m).collect::<Vec<_>>()).powi(2);
        let true_stations: Vec<[f64; 3]> = r
            .stations
            .iter()
            .enumerate()
            .map(|(j, _)| xyz(&truth["stations"][j]["position_m"]))
            .collect();
        let stations: Vec<[f64; 3]> = r.stations.iter().map(|s| s.position_m).collect();
        station_err += common::rms_after(&rot, &t, &stations, &true_stations).powi(2);
        station_pred +=
            common::predicted_rms(&r.stations.iter().map(|s| s.sigma_m).collect::<Vec<_>>())
                .powi(2);
    }
    let point_ratio = (point_err / point_pred).sqrt();
    let station_ratio = (station_err / station_pred).sqrt();
    println!("pipeline Monte Carlo over {SEEDS} seeds: point ratio {point_ratio:.3}, station ratio {station_ratio:.3}");
    assert!(
        (0.8..1.25).contains(&point_ratio),
        "point ratio {point_ratio}"
    );
    assert!(
        (0.8..1.25).contains(&station_ratio),
        "station ratio {station_ratio}"
    );
}
