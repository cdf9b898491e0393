//! Whole simulated run of the four-axis method (tracer on the rotary table), reduced for speed:
//! the stations, points, table axis and true step angles must match the simulated truth
//! within what the reported uncertainties allow; the replay must give identical results.

use crate::common;

use common::{assert_recovers_truth, run_with_truth, xyz};
use geocal::kinds::solve_file;
use geocal::session::messages::RunEvent;
use geocal::session::reader::read_session;
use nalgebra::Vector3;

/// The published setup shrunk: 6 table stations 60° apart + 1 off the table.
fn reduced() -> String {
    common::reduced_rotary(60f64.to_radians(), 6, "")
}

#[test]
fn rotary_tracer_recovers_table_angles_axis_and_points() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (output, truth) = run_with_truth(&reduced(), dir.path());
    let Some(results) = output
        .results
        .get::<geocal::kinds::rotary_tracer::solve::RotaryTracerResults>()
    else {
        panic!("expected rotary_tracer results");
    };
    let ml = &results.multilateration;
    assert_eq!(ml.kind, "rotary_tracer");
    assert_eq!(ml.points.len(), 24);
    assert_eq!(ml.stations.len(), 7);
    assert_recovers_truth(ml, &truth);

    // Step angles: invariant under the datum, compared directly with the truth relative to
    // the first table station, each within 3 of its reported sigmas.
    let rotary = &results.rotary;
    let truth_steps = truth["rotary"]["steps"].as_array().expect("truth steps");
    assert_eq!(rotary.steps.len(), 6);
    assert_eq!(truth_steps.len(), 6);
    let true_error = |k: usize| truth_steps[k]["error_rad"].as_f64().expect("error_rad");
    let mut chi2 = 0.0;
    for (k, step) in rotary.steps.iter().enumerate() {
        assert_eq!(truth_steps[k]["station"], step.station.as_str());
        let commanded = 60f64.to_radians() * k as f64;
        assert!((step.commanded_rad - commanded).abs() < 1e-12);
        assert_eq!(
            step.encoder_rad,
            Some(step.commanded_rad),
            "{}",
            step.station
        );
        let want = true_error(k) - true_error(0);
        let diff = step.error_rad - want;
        println!(
            "{}: error {:.4e} rad, truth {:.4e} rad, sigma {:.2e} rad",
            step.station, step.error_rad, want, step.sigma_rad
        );
        assert!((step.measured_rad - step.commanded_rad - step.error_rad).abs() < 1e-15);
        if k == 0 {
            assert_eq!((step.error_rad, step.sigma_rad), (0.0, 0.0));
            continue;
        }
        assert!(step.sigma_rad > 0.0);
        assert!(
            diff.abs() <= 3.0 * step.sigma_rad,
            "{}: error {} rad, truth {} rad, sigma {} rad",
            step.station,
            step.error_rad,
            want,
            step.sigma_rad
        );
        chi2 += (diff / step.sigma_rad).powi(2);
    }
    // The table errors are real (arcseconds) and resolved far above their sigma (about 18
    // sigma with the ppm noise term on the absolute beam of ~1.5 m).
    let max_error = rotary
        .steps
        .iter()
        .map(|s| s.error_rad.abs())
        .fold(0.0, f64::max);
    let max_sigma = rotary.steps.iter().map(|s| s.sigma_rad).fold(0.0, f64::max);
    assert!(
        max_error > 5e-6 && max_error > 10.0 * max_sigma,
        "max error {max_error:e} rad, max sigma {max_sigma:e} rad"
    );
    println!("steps: chi2 {chi2:.2} over 5 (correlated) steps");

    // The axis, in the truth's frame: the datum (inner constraints relative to the nominal
    // points) differs from it by the rigid part of the machine's errors, so move the estimate
    // by the rigid motion that best fits the estimated points onto the true ones, as
    // assert_recovers_truth does. That alignment is itself uncertain: about the mean point
    // sigma / sqrt(n) in translation, added to the tolerance.
    let truth_points: Vec<[f64; 3]> = ml
        .points
        .iter()
        .map(|p| {
            let t = truth["points"]
                .as_array()
                .expect("truth points")
                .iter()
                .find(|t| t["point"] == p.point)
                .expect("truth point");
            xyz(&t["actual_m"])
        })
        .collect();
    let est_points: Vec<[f64; 3]> = ml.points.iter().map(|p| p.actual_m).collect();
    let (r, t) = common::rigid_fit(&est_points, &truth_points);
    let align_sigma_m =
        common::predicted_rms(&ml.points.iter().map(|p| p.sigma_m).collect::<Vec<_>>())
            / (ml.points.len() as f64).sqrt();
    let true_dir = Vector3::from(xyz(&truth["rotary"]["axis_direction"]));
    let est_dir = r * Vector3::from(rotary.axis_direction);
    for k in 0..2 {
        println!(
            "axis direction {k}: {:.3e} vs truth {:.3e}, sigma {:.1e}",
            est_dir[k], true_dir[k], rotary.axis_direction_sigma[k]
        );
        assert!(
            (est_dir[k] - true_dir[k]).abs() <= 3.0 * rotary.axis_direction_sigma[k],
            "axis direction {k}: {} vs truth {}, sigma {}",
            est_dir[k],
            true_dir[k],
            rotary.axis_direction_sigma[k]
        );
    }
    // The fitted centre lies on the true axis line (its height along the axis is the tracer's).
    let true_point = Vector3::from(xyz(&truth["rotary"]["axis_point_m"]));
    let d = r * Vector3::from(rotary.axis_point_m) + t - true_point;
    let off_axis = d - true_dir * d.dot(&true_dir);
    let sigma = Vector3::from(rotary.axis_point_sigma_m);
    let tolerance = 3.0 * (sigma.xy().norm_squared() + 2.0 * align_sigma_m.powi(2)).sqrt();
    println!(
        "axis point off the true axis by {:.3e} m (tolerance {:.1e} m)",
        off_axis.norm(),
        tolerance
    );
    assert!(off_axis.norm() <= tolerance);
    // Radius: the true tracer base is at this distance from the true axis.
    let base = Vector3::from(xyz(&truth["rotary"]["tracer_base_m"])) - true_point;
    let true_radius = (base - true_dir * base.dot(&true_dir)).norm();
    assert!(
        (rotary.radius_m - true_radius).abs() <= 3.0 * rotary.radius_sigma_m,
        "radius {} vs truth {}, sigma {}",
        rotary.radius_m,
        true_radius,
        rotary.radius_sigma_m
    );
    assert!(rotary.circle_residual_rms_m < 3.0 * sigma.norm());

    // The session holds the rotations and the table's state stream.
    let session = read_session(&output.session_path).expect("read session");
    let rotations: Vec<f64> = session
        .events
        .iter()
        .filter_map(|e| match &e.msg {
            RunEvent::Rotation {
                table,
                commanded_rad,
                ..
            } => {
                assert_eq!(table, "c");
                Some(*commanded_rad)
            }
            _ => None,
        })
        .collect();
    assert_eq!(rotations.len(), 6);
    let states = &session.rotary["c"];
    assert!(states.iter().filter(|s| s.msg.in_position).count() >= 6);
    assert!(states
        .iter()
        .any(|s| !s.msg.in_position && s.msg.encoder_rad.is_none()));

    // Replay: solving the recorded session gives the same results JSON.
    let replayed = solve_file(&output.session_path, &Default::default()).expect("replay");
    assert_eq!(replayed.to_json_pretty(), output.results.to_json_pretty());
    let json: serde_json::Value =
        serde_json::from_str(&output.results.to_json_pretty()).expect("results json");
    assert_eq!(json["kind"], "rotary_tracer");
    assert_eq!(json["rotary"]["steps"].as_array().map(Vec::len), Some(6));
    assert!(json["stations"].is_array() && json["points"].is_array());

    common::python_check_session(&output.session_path, output.summary.samples);
}
