//! `geocal diagnose` beyond the lengths: the points level (solved points against the
//! quasi-rigid 21-error model), leave-one-station-out and the twin comparison.

mod common;

use common::{diagnose_demo, run_and_diagnose, with_effects};

/// A 0.6 µm bump of the tool along z around the x+ y+ z+ corner of the 3x3x3 grid (radius
/// 0.3 m): a local, non-rigid machine error. The lengths' model absorbs it (the points are
/// free there); the quasi-rigid model cannot.
const BUMP: &str = "local_bump = { enabled = true, size_m = 6e-7, centre_m = [1.3, 2.2, 0.95], radius_m = 0.3, direction = [0.0, 0.0, 1.0] }";

#[test]
fn local_bump_shows_at_the_points_level_only() {
    let d = run_and_diagnose(&with_effects(&diagnose_demo(), 51, BUMP));
    let text = geocal::diagnose::text(&d);
    println!("{text}");
    let points = d.points_level.as_ref().expect("points level");
    // Lengths level at the noise floor: nothing there, nothing selected.
    assert!(d.where_.iter().all(|w| w.level == "points"), "{text}");
    assert!(d.selected.is_empty(), "{text}");
    assert!(points.gap.p_value < 1e-6, "{text}");
    let first = |group: &str| {
        d.where_
            .iter()
            .find(|w| w.level == "points" && w.group == group)
            .map(|w| w.key.as_str())
    };
    assert_eq!(first("region"), Some("x+y+z+"), "{text}");
    assert_eq!(first("axis"), Some("z component"), "{text}");
    assert!(d.unexplained, "{text}");
}

/// Effect-free data: χ²/dof of the points level within 4 standard deviations sqrt(2/dof) of
/// 1 on every seed, no points-level group, and the points-level test's false alarms at most
/// one seed of 6 (1 % level each).
#[test]
fn effect_free_points_level_is_at_the_noise_floor() {
    let mut alarms = 0;
    for seed in 0..6 {
        let d = run_and_diagnose(&with_effects(&diagnose_demo(), 200 + seed, ""));
        let text = geocal::diagnose::text(&d);
        let g = &d.points_level.as_ref().expect("points level").gap;
        println!(
            "seed {seed}: points chi2/dof {:.3} (dof {}, p {:.3})",
            g.chi2_per_dof, g.dof, g.p_value
        );
        let spread = (2.0 / g.dof as f64).sqrt();
        assert!((g.chi2_per_dof - 1.0).abs() < 4.0 * spread, "{text}");
        if g.p_value < 0.01 || d.where_.iter().any(|w| w.level == "points") {
            alarms += 1;
        }
    }
    assert!(alarms <= 1, "{alarms} seeds with a points-level alarm");
}

/// Leave-one-station-out on a session with an unflagged fringe loss in one station: that
/// station (the one the change-point search puts the step in) stands out; on effect-free
/// data every station agrees with the others (standardised held-out RMS near 1).
#[test]
fn leave_one_station_out_singles_out_the_stepped_station() {
    let d = run_and_diagnose(&with_effects(
        &diagnose_demo(),
        13,
        "length_step = { enabled = true, size = 1e-6 }",
    ));
    let text = geocal::diagnose::text(&d);
    println!("{text}");
    let step = d
        .candidates
        .iter()
        .find(|c| c.effect == "length_step" && c.status == "selected")
        .expect("length_step selected");
    let pass = step.params["pass"].as_str().expect("pass name");
    let loso = &d.leave_one_station_out;
    assert_eq!(loso.len(), 5, "{text}");
    let worst = loso
        .iter()
        .max_by(|a, b| a.ratio.total_cmp(&b.ratio))
        .expect("stations");
    assert!(pass.starts_with(&format!("{} ", worst.station)), "{text}");
    assert!(worst.ratio > 3.0 && worst.p_value < 0.01, "{text}");
    let first_held_out = d.where_.iter().find(|w| w.key.ends_with(" held out"));
    assert_eq!(
        first_held_out.map(|w| w.key.clone()),
        Some(format!("{} held out", worst.station)),
        "{text}"
    );

    let clean = run_and_diagnose(&with_effects(&diagnose_demo(), 200, ""));
    let text = geocal::diagnose::text(&clean);
    println!("{text}");
    for h in &clean.leave_one_station_out {
        // sampling spread of the ratio: sqrt(1/(2 dof)) ≈ 0.1 for ~50 dof; 4 of them.
        let spread = (0.5 / h.dof as f64).sqrt();
        assert!((h.ratio - 1.0).abs() < 4.0 * spread, "{text}");
        assert!(h.p_value > 0.01, "{text}");
    }
}
