//! Sessions recorded by another recorder (its own kinematics, tracer and noise models; copies
//! of `../shared/sessions/` in tests/data/outside with their `truth.json`): the solve fits
//! their declared noise model, its σ are honest against the truth, and the diagnosis neither
//! cries wolf on the clean one nor misses the reversal in the other.

use crate::common;

use std::path::{Path, PathBuf};

use geocal::kinds::tracer_plan::diagnosis::effects::EffectKind;
use geocal::method::multilateration::MultilaterationResults;
use geocal::method::SolveSettings;
use serde_json::Value;

fn session_dir(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/outside")
        .join(name)
}

fn truth(name: &str) -> Value {
    let path = session_dir(name).join("truth.json");
    let text = std::fs::read_to_string(&path).expect("truth.json");
    serde_json::from_str(&text).expect("truth json")
}

fn solve(name: &str, effects: Vec<EffectKind>) -> MultilaterationResults {
    let settings = SolveSettings {
        effects: geocal::kinds::tracer_plan::diagnosis::correct::fit(effects),
        ..Default::default()
    };
    let results = geocal::kinds::solve_file(&session_dir(name).join("session.mcap"), &settings)
        .expect("solve");
    results.multilateration().expect("multilateration").clone()
}

/// Per coordinate, RMS over points of (error / σ) after the best rigid fit of the solved
/// points onto the truth's, and the 3-D RMS error (m).
fn graded(results: &MultilaterationResults, truth: &Value) -> ([f64; 3], f64) {
    let truth_points: Vec<(u64, [f64; 3])> = truth["points"]
        .as_array()
        .expect("points")
        .iter()
        .map(|p| {
            let a = &p["actual_m"];
            (
                p["point"].as_u64().expect("point index"),
                std::array::from_fn(|k| a[k].as_f64().expect("coordinate")),
            )
        })
        .collect();
    let actual_of = |i: usize| {
        truth_points
            .iter()
            .find(|(p, _)| *p as usize == i)
            .map(|(_, a)| *a)
            .expect("truth of every solved point")
    };
    let solved: Vec<[f64; 3]> = results.points.iter().map(|p| p.actual_m).collect();
    let actual: Vec<[f64; 3]> = results.points.iter().map(|p| actual_of(p.point)).collect();
    let (r, t) = common::rigid_fit(&solved, &actual);
    let mut z2 = [0.0; 3];
    let mut e2 = 0.0;
    for ((p, s), a) in results.points.iter().zip(&solved).zip(&actual) {
        let moved = r * nalgebra::Vector3::from(*s) + t;
        for k in 0..3 {
            let e = moved[k] - a[k];
            z2[k] += (e / p.sigma_m[k]).powi(2);
            e2 += e * e;
        }
    }
    let n = results.points.len() as f64;
    (z2.map(|v| (v / n).sqrt()), (e2 / n).sqrt())
}

#[test]
fn clean_session_fits_its_declared_noise_and_its_sigmas_are_honest() {
    let results = solve("outside-clean-7", Vec::new());
    let (z, rms_m) = graded(&results, &truth("outside-clean-7"));
    println!(
        "outside-clean-7: chi2/dof {:.3}, RMS(error/sigma) x {:.2} y {:.2} z {:.2}, 3-D RMS error {:.3} um",
        results.chi2_per_dof,
        z[0],
        z[1],
        z[2],
        rms_m * 1e6
    );
    assert!(
        (0.85..=1.15).contains(&results.chi2_per_dof),
        "chi2/dof {}",
        results.chi2_per_dof
    );
    for (k, v) in z.iter().enumerate() {
        assert!(
            (0.7..=1.4).contains(v),
            "coordinate {k}: RMS(error/sigma) {v}"
        );
    }
}

#[test]
fn clean_session_diagnosis_finds_nothing() {
    let d = geocal::kinds::diagnosis::diagnose_file(
        &session_dir("outside-clean-7").join("session.mcap"),
        &Default::default(),
    )
    .expect("diagnose");
    let text = geocal::diagnose::text(&d);
    assert!(d.selected.is_empty(), "{text}");
    assert!(!d.unexplained, "{text}");
    assert!(d.noise_scale.is_none(), "{text}");
    assert!(d.corrected.is_none(), "{text}");
}

#[test]
fn reversal_is_found_alone_and_modelling_it_restores_the_calibration() {
    let truth_reversal = truth("outside-reversal-8");
    let backlash_m = truth_reversal["effect_params"]["reversal"]["backlash_m"]
        .as_f64()
        .expect("backlash");
    let d = geocal::kinds::diagnosis::diagnose_file(
        &session_dir("outside-reversal-8").join("session.mcap"),
        &Default::default(),
    )
    .expect("diagnose");
    let text = geocal::diagnose::text(&d);
    assert_eq!(d.selected, vec!["reversal".to_string()], "{text}");
    assert!(!d.unexplained, "{text}");
    let reversal = d
        .candidates
        .iter()
        .find(|c| c.effect == "reversal")
        .expect("reversal candidate");
    let bx = reversal.params["bx_m"].as_f64().expect("bx_m");
    assert!(
        (bx / backlash_m - 1.0).abs() < 0.05,
        "backlash {bx} for {backlash_m}"
    );
    let corrected = d.corrected.as_ref().expect("corrected calibration");
    assert!(
        corrected.command.ends_with("--effects reversal"),
        "{}",
        corrected.command
    );

    // The calibration with the reversal modelled: as good as the clean session's.
    let clean = solve("outside-clean-7", Vec::new());
    let (_, clean_rms_m) = graded(&clean, &truth("outside-clean-7"));
    let plain = solve("outside-reversal-8", Vec::new());
    let (_, plain_rms_m) = graded(&plain, &truth_reversal);
    let results = solve("outside-reversal-8", vec![EffectKind::Reversal]);
    let (z, rms_m) = graded(&results, &truth_reversal);
    println!(
        "outside-reversal-8: 3-D RMS error {:.3} um without the reversal, {:.3} um with it (clean session {:.3} um); chi2/dof {:.3}; RMS(error/sigma) {:.2} {:.2} {:.2}",
        plain_rms_m * 1e6,
        rms_m * 1e6,
        clean_rms_m * 1e6,
        results.chi2_per_dof,
        z[0],
        z[1],
        z[2]
    );
    assert!(rms_m <= 2.0 * clean_rms_m, "{rms_m} vs clean {clean_rms_m}");
    assert!(
        (0.85..=1.15).contains(&results.chi2_per_dof),
        "chi2/dof {}",
        results.chi2_per_dof
    );
    let fitted = results.effects["reversal"]["bx_m"];
    let sigma = results.effects["reversal"]["bx_m.sigma"];
    assert!(sigma > 0.0 && (fitted - backlash_m).abs() < 0.05 * backlash_m);
}

/// ISO 230-2 figures of the recording with a reversal on x: every target's reversal B_i is the
/// truth's backlash on x and none on y and z, and the run-to-run scatter is the noise's,
/// although the serpentine reaches a target ↑ and ↓ on other lines of the grid, whose own
/// geometry (the axis's angular errors over their levers) differs by micrometres.
#[test]
fn iso_230_2_figures_of_the_reversal_session_match_its_truth() {
    let path = session_dir("outside-reversal-8").join("session.mcap");
    let session = geocal::session::reader::read_session(&path).expect("session");
    let results =
        geocal::kinds::registry::solve_session(&session, &Default::default()).expect("solve");
    let iso = geocal::evaluate::of_results(&results, &session).expect("ISO 230-2");
    println!("{}", iso.text());
    let backlash_m = truth("outside-reversal-8")["effect_params"]["reversal"]["backlash_m"]
        .as_f64()
        .expect("backlash_m");
    let mut evaluated = Vec::new();
    for axis in &iso.axes {
        let figures = axis.evaluation.figures();
        let Some(b) = figures.bidirectional.as_ref() else {
            continue;
        };
        // One point's deviation in one pass is known to σ_t; a run's value at a target is a
        // mean over the lines the run reached it on, so no more uncertain than that.
        let sigma_t = axis
            .target_sigma_m
            .as_ref()
            .expect("σ per target")
            .iter()
            .cloned()
            .fold(0.0, f64::max);
        let expected = if axis.axis == "x" { backlash_m } else { 0.0 };
        for (i, bi) in b.reversal_i.iter().enumerate() {
            // B_i: the mean of n↑ runs less the mean of n↓ runs.
            let runs = (axis.evaluation.runs_up, axis.evaluation.runs_down);
            let sigma_b = sigma_t * (1.0 / runs.0 as f64 + 1.0 / runs.1 as f64).sqrt();
            assert!(
                (bi - expected).abs() <= 3.0 * sigma_b,
                "axis {} B_{i} = {bi:e} m, truth {expected:e} m, σ {sigma_b:e} m",
                axis.axis
            );
        }
        let s: Vec<f64> = [&figures.up, &figures.down]
            .iter()
            .filter_map(|d| d.as_ref())
            .flat_map(|d| d.s_i.iter().flatten().copied())
            .collect();
        if !s.is_empty() {
            // The truth's machine has no random scatter: the runs differ by noise alone. With
            // one degree of freedom per target and direction, the pooled s lies below 1.8 σ_t
            // with probability > 0.995 (χ² with 6 or more degrees of freedom).
            let pooled = (s.iter().map(|v| v * v).sum::<f64>() / s.len() as f64).sqrt();
            println!(
                "axis {}: pooled s {:.3} µm, σ_t {:.3} µm",
                axis.axis,
                pooled * 1e6,
                sigma_t * 1e6
            );
            assert!(s.len() >= 6, "axis {}: {} values of s", axis.axis, s.len());
            assert!(
                pooled < 1.8 * sigma_t,
                "axis {}: pooled s {pooled:e} m against σ {sigma_t:e} m",
                axis.axis
            );
        }
        evaluated.push(axis.axis.clone());
    }
    assert!(
        evaluated.contains(&"x".to_string()) && evaluated.contains(&"y".to_string()),
        "{evaluated:?}"
    );
}
