//! `geocal diagnose` beyond the lengths: the points level (solved points against the
//! quasi-rigid 21-error model), leave-one-station-out and the twin comparison.

use crate::common;

use common::{diagnose_demo, run_and_diagnose, with_effects};

/// A 1.2 µm bump of the tool along z around the x+ y+ z+ corner of the 3x3x3 grid (radius
/// 0.3 m): a local, non-rigid machine error. The lengths' model absorbs it (the points are
/// free there); the quasi-rigid model cannot.
const BUMP: &str = "local_bump = { enabled = true, size_m = 1.2e-6, centre_m = [1.3, 2.2, 0.95], radius_m = 0.3, direction = [0.0, 0.0, 1.0] }";

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
/// An effect the free points partly absorb moves the per-pass points by as much as its fitted
/// parameters' uncertainty leaves open: the points level after the selected effects fits that
/// response as free columns (docs/diagnosis.md, the points level, 5.). Seeds of the validation
/// matrix in which the points level used to fail after the right effect was named and the
/// lengths' gap closed (tracer_eccentricity 5009: chi2/dof 1.51, p 1.7e-4; 5012: 1.47,
/// p 4.2e-4), and a station drift (15 parameters, two directions nearly absorbed per pass).
#[test]
fn points_level_after_the_effect_holds_its_uncertainty() {
    let eccentricity = "tracer_eccentricity = { enabled = true, size_m = 4e-6, z_size_m = 2e-6 }";
    let drift = "station_drift = { enabled = true, size = 5e-9 }";
    for (effect, line, seed) in [
        ("tracer_eccentricity", eccentricity, 5009),
        ("tracer_eccentricity", eccentricity, 5012),
        ("station_drift", drift, 5002),
    ] {
        let d = run_and_diagnose(&with_effects(&diagnose_demo(), seed, line));
        let text = geocal::diagnose::text(&d);
        assert_eq!(d.selected, vec![effect.to_string()], "{text}");
        assert!(
            !d.notes
                .iter()
                .any(|n| n.starts_with("points level after the selected effects")),
            "seed {seed}\n{text}"
        );
        assert!(!d.unexplained, "seed {seed}\n{text}");
    }
}

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

/// Record a session with an effect, simulate its twin from the same config (effect off, the
/// recording's solved stations, noise of its own seed) and diagnose the recording against it.
fn against_twin(seed: u64, effects: &str) -> geocal::diagnose::Diagnosis {
    let dir = tempfile::tempdir().expect("tempdir");
    let recorded_config = with_effects(&diagnose_demo(), seed, effects);
    let config = geocal::config::Config::parse(&recorded_config, std::path::Path::new("rec.toml"))
        .expect("config");
    let output = geocal::kinds::tracer_plan::run::run(
        &config,
        &geocal::run::RunOptions {
            out_dir: dir.path().join("rec"),
            truth: None,
            progress: false,
            settings: Default::default(),
            control: Default::default(),
        },
    )
    .expect("run");
    // The twin's config: the same file the run used (its effects are switched off for the twin).
    let config_path = dir.path().join("rec.toml");
    std::fs::write(&config_path, &recorded_config).expect("write config");
    geocal::kinds::tracer_plan::diagnosis::twin::diagnose_file_with_twin(
        &output.session_path,
        &config_path,
        Some(&dir.path().join("twin")),
        &Default::default(),
    )
    .expect("diagnose against the twin")
}

#[test]
fn twin_comparison_names_the_effect() {
    let d = against_twin(12, "reversal = { enabled = true, size = 2e-6 }");
    let text = geocal::diagnose::text(&d);
    println!("{text}");
    let twin = d.twin.as_ref().expect("twin report");
    assert_eq!(twin.source, "config");
    assert_eq!(twin.unmatched_lengths, 0, "{text}");
    assert_eq!(
        d.selected.first().map(String::as_str),
        Some("reversal"),
        "{text}"
    );
    assert!(d.gap.heldout_ratio > 2.0, "{text}");
    assert!(d.gap_after.heldout_ratio < 1.3, "{text}");
    assert!(!d.unexplained, "{text}");
    // The points depart from the twin's by direction before, and agree after.
    let before = twin.points_before.as_ref().expect("points compared");
    let after = twin.points_after.as_ref().expect("points compared after");
    assert!(before.p_value < 1e-6, "{text}");
    assert!(after.p_value > 0.01, "{text}");
    assert!(
        d.where_.iter().any(|w| w.key.ends_with(" vs twin")),
        "{text}"
    );
    let json = serde_json::to_value(&d).expect("json");
    common::assert_diagnosis_format(&json);
    assert!(json["twin"]["points_before"]["chi2_per_dof"].is_number());
}

/// The eccentricity's ten parameters are mostly absorbed by the free points, so their
/// estimates' uncertainty moves the recording's points; compared with the twin's points
/// after the effect, that move is fitted as free columns (as the points level does). Removing
/// the fitted contribution with its parameters taken as exact left the points departing from
/// the twin's (matrix: `unexplained` in 17 of 20 seeds; here seeds 5002 and 5004: p 1.1e-3 and 4.2e-6).
#[test]
fn twin_points_after_the_effect_hold_its_uncertainty() {
    for seed in [5002, 5004] {
        let d = against_twin(
            seed,
            "tracer_eccentricity = { enabled = true, size_m = 4e-6, z_size_m = 2e-6 }",
        );
        let text = geocal::diagnose::text(&d);
        assert_eq!(
            d.selected,
            vec!["tracer_eccentricity".to_string()],
            "{text}"
        );
        let twin = d.twin.as_ref().expect("twin report");
        let before = twin.points_before.as_ref().expect("points compared");
        let after = twin.points_after.as_ref().expect("points compared after");
        println!(
            "seed {seed}: points vs twin chi2/dof {:.2} -> {:.2} (dof {} -> {}, p {:.2e})",
            before.chi2_per_dof, after.chi2_per_dof, before.dof, after.dof, after.p_value
        );
        assert!(before.p_value < 1e-6, "{text}");
        assert!(after.p_value > 0.01, "{text}");
        assert!(after.dof < before.dof, "{text}");
        assert!(!d.unexplained, "{text}");
    }
}

#[test]
fn session_against_its_effect_free_twin_shows_no_gap() {
    let d = against_twin(202, "");
    let text = geocal::diagnose::text(&d);
    println!("{text}");
    let twin = d.twin.as_ref().expect("twin report");
    assert!(d.selected.is_empty(), "{text}");
    assert!(!d.unexplained, "{text}");
    // χ²/dof of the lengths within 4 sampling standard deviations of 1: 270 lengths −
    // (27 points·3 + 5 stations·3 + 5 distances − 6 gauge) = 175 dof.
    assert_eq!(d.observations, 270, "{text}");
    let spread = (2.0f64 / 175.0).sqrt();
    assert!((d.gap.chi2_per_dof - 1.0).abs() < 4.0 * spread, "{text}");
    // Nothing selected: the gap before and after are one model's on the same (twin-corrected)
    // lengths. A gap before taken from the recording's own calibration differs.
    let relative = |a: f64, b: f64| (a - b).abs() / b;
    assert!(relative(d.gap.rms_m, d.gap_after.rms_m) < 1e-6, "{text}");
    assert!(
        relative(d.gap.chi2_per_dof, d.gap_after.chi2_per_dof) < 1e-6,
        "{text}"
    );
    let before = twin.points_before.as_ref().expect("points compared");
    assert!(before.p_value > 0.01, "{text}");
    assert!(
        !d.where_.iter().any(|w| w.key.ends_with(" vs twin")),
        "{text}"
    );
}

#[test]
#[ignore]
fn twin_clean_seeds_figures() {
    for seed in 203..209 {
        let d = against_twin(seed, "");
        let t = d.twin.as_ref().unwrap();
        println!(
            "seed {seed}: heldout ratio {:.3} chi2/dof {:.3} selected {:?} points vs twin chi2/dof {:.3} p {:.3} unexplained {}",
            d.gap.heldout_ratio,
            d.gap.chi2_per_dof,
            d.selected,
            t.points_before.as_ref().unwrap().chi2_per_dof,
            t.points_before.as_ref().unwrap().p_value,
            d.unexplained
        );
    }
}

/// The command line: `geocal diagnose REC --twin TWIN.mcap --json`, the twin a second session
/// (the same config, effect off, noise of its own seed).
#[test]
fn cli_twin_session() {
    let dir = tempfile::tempdir().expect("tempdir");
    let geocal = |args: &[&str]| {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_geocal"))
            .args(args)
            .output()
            .expect("run geocal");
        assert!(
            out.status.success(),
            "geocal {}: {}",
            args.join(" "),
            String::from_utf8_lossy(&out.stderr)
        );
        out
    };
    let mut sessions = Vec::new();
    for (name, text) in [
        (
            "rec",
            with_effects(
                &diagnose_demo(),
                12,
                "reversal = { enabled = true, size = 1e-6 }",
            ),
        ),
        (
            "twin",
            with_effects(&diagnose_demo(), 12, "")
                .replace("[sim]\nseed = 12", "[sim]\nseed = 12\nnoise_seed = 99"),
        ),
    ] {
        assert!(name == "rec" || text.contains("noise_seed = 99"));
        let config = dir.path().join(format!("{name}.toml"));
        std::fs::write(&config, text).expect("write config");
        let out = dir.path().join(name);
        geocal(&[
            "run",
            config.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ]);
        sessions.push(out.join("session.mcap"));
    }
    let out = geocal(&[
        "diagnose",
        sessions[0].to_str().unwrap(),
        "--twin",
        sessions[1].to_str().unwrap(),
        "--json",
    ]);
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).expect("json");
    common::assert_diagnosis_format(&json);
    assert_eq!(json["twin"]["source"], "session", "{json}");
    assert_eq!(json["selected"][0], "reversal", "{json}");
    assert!(
        json["gap_after"]["heldout_ratio"].as_f64().unwrap() < 1.3,
        "{json}"
    );
    let text = geocal(&[
        "diagnose",
        sessions[0].to_str().unwrap(),
        "--twin",
        sessions[1].to_str().unwrap(),
    ]);
    let text = String::from_utf8_lossy(&text.stdout);
    assert!(text.contains("points minus the twin's"), "{text}");
}
