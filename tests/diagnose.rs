//! `geocal diagnose` on simulated sessions with unmodelled effects switched on: the right
//! effect is named, the held-out gap falls to the noise floor, and effect-free data stay clean.

use crate::common;

use common::{diagnose_demo, run_and_diagnose, two_target_diagnose_demo, with_effects};

/// Held-out gap after the selected effects, each held-out residual in units of its predicted
/// standard deviation (noise floor plus prediction uncertainty), RMS over ~270 lengths: 1 when
/// the model holds, standard error sqrt(1/(2·270)) = 0.04, so 1.3 is a > 7-sigma departure.
const HELDOUT_RATIO_MAX: f64 = 1.3;

fn check_named(effect: &str, line: &str, seed: u64) {
    let d = run_and_diagnose(&with_effects(&diagnose_demo(), seed, line));
    assert_eq!(
        d.selected.first().map(String::as_str),
        Some(effect),
        "{}",
        geocal::diagnose::text(&d)
    );
    let ratio = d.gap_after.heldout_ratio;
    assert!(
        ratio < HELDOUT_RATIO_MAX,
        "held-out ratio {ratio}\n{}",
        geocal::diagnose::text(&d)
    );
    // The gap was there before, several times the floor.
    assert!(d.gap.heldout_ratio > 2.0, "{}", geocal::diagnose::text(&d));
    assert!(!d.unexplained, "{}", geocal::diagnose::text(&d));
    // The points level departs before (the effect moves the solved points) and fits the
    // noise model after the effect's contribution is taken off the lengths.
    let before = &d.points_level.as_ref().expect("points level").gap;
    let after = d.points_level_after.as_ref().expect("points level after");
    assert!(after.p_value >= 0.01, "{}", geocal::diagnose::text(&d));
    assert!(
        after.chi2_per_dof < before.chi2_per_dof,
        "{}",
        geocal::diagnose::text(&d)
    );
}

#[test]
fn station_drift_is_named() {
    check_named(
        "station_drift",
        "station_drift = { enabled = true, size = 5e-9 }",
        11,
    );
}

#[test]
fn reversal_is_named() {
    check_named("reversal", "reversal = { enabled = true, size = 1e-6 }", 12);
}

#[test]
fn length_step_is_named() {
    check_named(
        "length_step",
        "length_step = { enabled = true, size = 1e-6 }",
        13,
    );
}

#[test]
fn air_refraction_is_named() {
    check_named(
        "air_refraction",
        "air_refraction = { enabled = true, size = 1.0 }",
        14,
    );
}

#[test]
fn tracer_eccentricity_is_named() {
    check_named(
        "tracer_eccentricity",
        "tracer_eccentricity = { enabled = true, size_m = 4e-6, z_size_m = 2e-6 }",
        15,
    );
}

/// A drift common to all stations (the machine warming up): nested in station_drift (3
/// parameters instead of 15), so the test also shows that BIC tells the two apart.
#[test]
fn thermal_drift_is_named() {
    check_named(
        "thermal_drift",
        "thermal_drift = { enabled = true, size = 4e-9 }",
        16,
    );
}

/// A dead path 1-2 m longer than declared, so its refraction is left uncompensated:
/// dn(t)·(1..2 m) per station, about ±0.5-1 µm over the air's ±0.5 K cycle, with no dependence
/// on where the target is.
#[test]
fn dead_path_is_named() {
    check_named(
        "dead_path",
        "dead_path = { enabled = true, size = 2.0 }",
        17,
    );
}

/// Scales compensated with a coefficient 2 ppm/K off (steel is 11.5 ppm/K) while the
/// structure's temperature swings ±0.25 K, an eighth of the air's period late.
#[test]
fn thermal_expansion_is_named() {
    check_named(
        "thermal_expansion",
        "thermal_expansion = { enabled = true, size = 2e-6 }",
        18,
    );
}

/// Each moved axis lags 1-2 µm behind its target and settles with a 0.5 s time constant:
/// the window means carry a reversal-like bias, the raw samples inside the windows a decay.
#[test]
fn settling_is_named() {
    check_named(
        "settling",
        "settling = { enabled = true, size_m = 3e-6, tau_s = 0.5 }",
        19,
    );
}

/// A reflector 1 mm off its configured offset: every point moves by R(axes)·δo, which the free
/// points of the multilateration model absorb. Nothing can be named from the lengths and
/// nothing may be: the diagnosis selects nothing, stays explained, and says target_offset is
/// not identifiable here (docs/diagnosis.md: it needs the points level with several targets).
#[test]
fn target_offset_is_not_identifiable_from_lengths() {
    let d = run_and_diagnose(&with_effects(
        &diagnose_demo(),
        20,
        "target_offset = { enabled = true, size_m = 1e-3 }",
    ));
    let text = geocal::diagnose::text(&d);
    assert!(d.selected.is_empty(), "{text}");
    assert!(!d.unexplained, "{text}");
    assert!(d.gap.heldout_ratio < HELDOUT_RATIO_MAX, "{text}");
    assert!(
        d.notes
            .iter()
            .any(|n| n.starts_with("target_offset: absorbed")),
        "{text}"
    );
}

/// Two reflectors, each 20 µm off its configured offset (in its own direction): at the points
/// level the second target's points shift against the first's by a constant the quasi-rigid
/// model cannot hold, so target_offset is named there, the fitted shift is the true offset
/// difference, and the points level is explained afterwards. Effect-free with two targets:
/// nothing named.
#[test]
fn target_offset_is_named_at_the_points_level_with_two_targets() {
    let two_targets = two_target_diagnose_demo();
    let d = run_and_diagnose(&with_effects(
        &two_targets,
        22,
        "target_offset = { enabled = true, size_m = 2e-5 }",
    ));
    let text = geocal::diagnose::text(&d);
    println!("{text}");
    assert_eq!(d.selected, vec!["target_offset".to_string()], "{text}");
    assert!(!d.unexplained, "{text}");
    let before = d.points_level.as_ref().expect("points level");
    assert!(before.gap.p_value < 1e-6, "{text}");
    let test = before.target_offset.as_ref().expect("target_offset test");
    let after_p = geocal::diagnose::stats::chi2_sf(test.chi2_after, test.dof_after as f64);
    assert!(
        after_p > 1e-3,
        "points level after the shift: p {after_p}\n{text}"
    );

    let clean = run_and_diagnose(&with_effects(&two_targets, 23, ""));
    let text = geocal::diagnose::text(&clean);
    assert!(clean.selected.is_empty(), "{text}");
}

/// The two-target seeds of the validation matrix (docs/diagnosis.md) in which a points-level
/// residual used to remain after the shift (the rank of the shifts was judged after
/// normalising their projected columns: the absorbed z direction's rounding remainder counted
/// as a second shift, df 2, and the fitted offsets were 1e5-1e6 m). The gauge rotation takes
/// ω × (o₁ − o₀), so one direction is identifiable, along o₁ − o₀; the fitted offset must be
/// the true difference's component there, within 4 of its standard deviations, and the points
/// level explained afterwards.
#[test]
fn target_offset_two_targets_fits_the_true_offset_difference() {
    let line = "target_offset = { enabled = true, size_m = 2e-5 }";
    for seed in [5002, 5007, 5010, 5012] {
        let config_text = with_effects(&two_target_diagnose_demo(), seed, line);
        let d = run_and_diagnose(&config_text);
        let text = geocal::diagnose::text(&d);
        assert_eq!(d.selected, vec!["target_offset".to_string()], "{text}");
        assert!(!d.unexplained, "seed {seed}\n{text}");
        let test = d
            .points_level
            .as_ref()
            .and_then(|p| p.target_offset.as_ref())
            .expect("target_offset test");
        assert_eq!(test.df, 1, "{text}");
        let config = geocal::config::Config::parse(&config_text, std::path::Path::new("x.toml"))
            .expect("config");
        let sim = config.sim.as_ref().expect("[sim]");
        let effects =
            geocal::sim::effects::SimEffects::new(&sim.effects, &sim.environment, seed, 5, 1);
        let (o0, o1) = ([0.0, 0.0, -0.12], [0.1, 0.05, -0.12]);
        let (a0, a1) = (effects.actual_offset_m(o0), effects.actual_offset_m(o1));
        let along = nalgebra::Vector3::new(0.1, 0.05, 0.0).normalize();
        let truth: f64 = (0..3)
            .map(|k| (a1[k] - o1[k] - a0[k] + o0[k]) * along[k])
            .sum();
        let fitted = nalgebra::Vector3::from(test.offsets_m["t1"]);
        let sigma = nalgebra::Vector3::from(test.offsets_sigma_m["t1"]).norm();
        assert!(
            (fitted.dot(&along) - truth).abs() < 4.0 * sigma,
            "seed {seed}: fitted {fitted:?} along o1 - o0 {:.4e} m, true {truth:.4e} m, sigma {sigma:.2e} m",
            fitted.dot(&along)
        );
        // Nothing across o₁ − o₀: that part of the shift is the gauge rotation's.
        assert!(
            (fitted - along * fitted.dot(&along)).norm() < 1e-3 * sigma,
            "{fitted:?}"
        );
    }
}

/// `unexplained` is one decision over three tests (the final χ², the final residuals' groups,
/// the points level after the effects), each at 1 %/3, so that its family-wise false-alarm
/// rate is 1 % (docs/diagnosis.md, How far). Settling, seed 5018 of the validation matrix:
/// named, the held-out gap closed, the final χ²/dof 1.28 (p 8.4e-3, a 1-in-120 draw), which
/// the uncorrected decision (each test at 1 %) flagged.
#[test]
fn unexplained_is_family_wise_at_alpha() {
    let d = run_and_diagnose(&with_effects(
        &diagnose_demo(),
        5018,
        "settling = { enabled = true, size_m = 1.5e-6, tau_s = 0.5 }",
    ));
    let text = geocal::diagnose::text(&d);
    assert_eq!(d.selected, vec!["settling".to_string()], "{text}");
    assert!(d.gap_after.heldout_ratio < HELDOUT_RATIO_MAX, "{text}");
    assert!(!d.unexplained, "{text}");
}

/// Held-out gap after the selected effect over the clean session's held-out level (the same
/// seed and plan without the effect: a floor independent of the effect's fit).
const HELDOUT_VS_CLEAN_MAX: f64 = 1.3;

/// The effect model leaves no residue: with the effect withheld, exactly that effect is
/// selected and the held-out RMS after it is the clean session's. Air refraction at 5 times
/// the Edlén index change (as a tracer without air compensation under a stronger cycle) shows
/// a residue the nominal size hides: the counter is zeroed at the homing, a second or more
/// before the home dwell's middle, and a model zeroed at the dwell left a constant per pass
/// (5 · L0 · dn/dt · ~1 s, up to ~40 nm) that dead_path or thermal_expansion took as a second
/// effect (seeds 6000-6002 before the fix).
#[test]
fn gap_after_the_effect_is_the_clean_sessions_level() {
    let effects = [
        (
            "air_refraction",
            "air_refraction = { enabled = true, size = 5.0 }",
        ),
        (
            "length_step",
            "length_step = { enabled = true, size = 1e-6 }",
        ),
    ];
    for seed in [6000, 6001, 6002] {
        let clean = run_and_diagnose(&with_effects(&diagnose_demo(), seed, ""));
        assert!(
            clean.selected.is_empty(),
            "{}",
            geocal::diagnose::text(&clean)
        );
        let clean_level = clean.gap.heldout_rms_m;
        for (effect, line) in effects {
            let d = run_and_diagnose(&with_effects(&diagnose_demo(), seed, line));
            let text = geocal::diagnose::text(&d);
            let ratio = d.gap_after.heldout_rms_m / clean_level;
            println!(
                "seed {seed} {effect}: selected {:?}, held-out {:.1} nm -> {:.1} nm, clean {:.1} nm: {ratio:.3} of clean",
                d.selected,
                d.gap.heldout_rms_m * 1e9,
                d.gap_after.heldout_rms_m * 1e9,
                clean_level * 1e9
            );
            assert_eq!(d.selected, vec![effect.to_string()], "seed {seed}\n{text}");
            assert!(!d.unexplained, "seed {seed}\n{text}");
            assert!(
                ratio <= HELDOUT_VS_CLEAN_MAX,
                "seed {seed}: held-out after {ratio:.3} of the clean level\n{text}"
            );
        }
    }
}

/// The eccentricity with one size e for the instrument and a phase per placement of the
/// tracer (the simulator's and the outside recorder's physics): the held-out RMS after it is
/// the clean session's (same seed and plan, no effect) within 1.3, on the demo's full plan (5
/// stations x 100 points) and on the 27-point diagnosis plan, whose 35 redundant lengths leave
/// the per-station phases least determined (docs/diagnosis.md, Residue).
#[test]
fn eccentricity_gap_after_is_the_clean_sessions_level() {
    let line = "tracer_eccentricity = { enabled = true, size_m = 4e-6, z_size_m = 2e-6 }";
    let full_plan = [6000, 6001].map(|seed| (common::DEMO.to_string(), seed));
    let diagnosis_plan =
        [13, 14, 15, 5000, 5001, 5002, 5003, 5004, 5005].map(|seed| (diagnose_demo(), seed));
    for (plan, seed) in full_plan.into_iter().chain(diagnosis_plan) {
        let clean = run_and_diagnose(&with_effects(&plan, seed, ""));
        assert!(
            clean.selected.is_empty(),
            "{}",
            geocal::diagnose::text(&clean)
        );
        let d = run_and_diagnose(&with_effects(&plan, seed, line));
        let text = geocal::diagnose::text(&d);
        let ratio = d.gap_after.heldout_rms_m / clean.gap.heldout_rms_m;
        println!(
            "seed {seed} tracer_eccentricity: selected {:?}, held-out {:.1} nm -> {:.1} nm, clean {:.1} nm: {ratio:.3} of clean",
            d.selected,
            d.gap.heldout_rms_m * 1e9,
            d.gap_after.heldout_rms_m * 1e9,
            clean.gap.heldout_rms_m * 1e9
        );
        assert_eq!(d.selected, ["tracer_eccentricity"], "seed {seed}\n{text}");
        assert!(!d.unexplained, "seed {seed}\n{text}");
        assert!(
            ratio <= HELDOUT_VS_CLEAN_MAX,
            "seed {seed}: held-out after {ratio:.3} of the clean level\n{text}"
        );
    }
}

/// Each round's family-wise false-selection level is 1 %; over 20 seeds at most one seed may
/// select anything (the requirement is >= 95 % clean; P(2+ of 20 at 1 %) = 1.7 %).
#[test]
fn effect_free_selects_nothing() {
    let seeds: usize = 20;
    let (mut clean, mut explained, mut no_scale) = (0usize, 0usize, 0usize);
    for seed in 0..seeds {
        let d = run_and_diagnose(&with_effects(&diagnose_demo(), 100 + seed as u64, ""));
        if d.selected.is_empty() {
            clean += 1;
        } else {
            eprintln!("seed {seed}: {}", geocal::diagnose::text(&d));
        }
        explained += usize::from(!d.unexplained);
        if d.unexplained || d.noise_scale.is_some() {
            eprintln!("seed {seed}: {}", geocal::diagnose::text(&d));
        }
        no_scale += usize::from(d.noise_scale.is_none());
    }
    println!(
        "effect-free: nothing selected in {clean}, explained in {explained}, no noise_scale in {no_scale} of {seeds} seeds"
    );
    assert!(clean * 100 >= 95 * seeds, "{clean} of {seeds} clean");
    assert!(
        explained * 100 >= 95 * seeds,
        "{explained} of {seeds} explained"
    );
    assert!(
        no_scale * 100 >= 95 * seeds,
        "{no_scale} of {seeds} without noise_scale"
    );
}

/// A tracer 2x noisier (and 2x quieter) than it declares: the residuals are uniformly off by
/// that factor with no structure, which is a statement about the noise declaration: the
/// diagnosis reports `noise_scale` with k near the factor, names no effect and stays explained.
#[test]
fn a_misdeclared_noise_is_a_noise_scale_not_an_effect() {
    for (factor, seed) in [(2.0, 31), (0.5, 32)] {
        // The whole demo plan (1000 lengths): k's sampling spread is then ~2.7 %.
        let text = with_effects(common::DEMO, seed, "").replace(
            "relocation_s = 180.0",
            &format!("relocation_s = 180.0\ntracer_noise_factor = {factor}"),
        );
        assert!(text.contains("tracer_noise_factor"));
        let d = run_and_diagnose(&text);
        let report = geocal::diagnose::text(&d);
        let scale = d.noise_scale.as_ref().expect(&report);
        println!(
            "noise x{factor}: k = {:.3} ({:.3}-{:.3}), {}",
            scale.k, scale.k_low, scale.k_high, scale.statement
        );
        assert!(
            (scale.k / factor - 1.0).abs() < 0.1,
            "k {} for {factor}\n{report}",
            scale.k
        );
        assert!(scale.k_low < scale.k && scale.k < scale.k_high, "{report}");
        assert!(d.selected.is_empty(), "{report}");
        assert!(!d.unexplained, "{report}");
    }
}

#[test]
fn drift_and_reversal_both_selected() {
    let d = run_and_diagnose(&with_effects(
        &diagnose_demo(),
        21,
        "station_drift = { enabled = true, size = 5e-9 }\nreversal = { enabled = true, size = 1e-6 }",
    ));
    let text = geocal::diagnose::text(&d);
    assert!(d.selected.iter().any(|s| s == "station_drift"), "{text}");
    assert!(d.selected.iter().any(|s| s == "reversal"), "{text}");
    assert_eq!(d.selected.len(), 2, "{text}");
    assert!(!d.unexplained, "{text}");
}

/// An interferometer nonlinearity (sin of the distance with a 5 cm period) is outside the
/// library: the diagnosis must say so rather than name something.
#[test]
fn effect_outside_the_library_is_unexplained() {
    let d = run_and_diagnose(&with_effects(
        &diagnose_demo(),
        31,
        "periodic_nonlinearity = { enabled = true, size_m = 3e-7, period_m = 0.05 }",
    ));
    let text = geocal::diagnose::text(&d);
    assert!(d.unexplained, "{text}");
    assert!(d.selected.is_empty(), "{text}");
}

/// The diagnosis reads the session file alone: a copy in an empty directory (no config, no
/// truth) gives the same result, and the JSON is geocal-diagnosis/1.
#[test]
fn reads_only_the_session() {
    let text = with_effects(
        &diagnose_demo(),
        41,
        "reversal = { enabled = true, size = 1e-6 }",
    );
    let config =
        geocal::config::Config::parse(&text, std::path::Path::new("x.toml")).expect("config");
    let dir = tempfile::tempdir().expect("tempdir");
    let output = geocal::kinds::tracer_plan::run::run(
        &config,
        &geocal::run::RunOptions {
            out_dir: dir.path().to_path_buf(),
            truth: Some(dir.path().join("truth.json")),
            progress: false,
            settings: Default::default(),
            control: Default::default(),
        },
    )
    .expect("run");
    let alone = tempfile::tempdir().expect("tempdir");
    let copy = alone.path().join("copy.mcap");
    std::fs::copy(&output.session_path, &copy).expect("copy");
    drop(dir);
    let options = Default::default();
    let d = geocal::kinds::diagnosis::diagnose_file(&copy, &options).expect("diagnose");
    let json: serde_json::Value = serde_json::to_value(&d).expect("json");
    common::assert_diagnosis_format(&json);
    assert_eq!(d.selected.first().map(String::as_str), Some("reversal"));
    let again = geocal::kinds::diagnosis::diagnose_file(&copy, &options).expect("diagnose");
    assert_eq!(d, again);
}

/// The demo with the air (and the structure behind it) warming slowly: a 2 K swing over an
/// 11 h period, so over the session both temperatures are ramps; `grid` replaces the plan's
/// grid. Used by the confounded-pair test and its control.
fn slow_warming(seed: u64, grid: Option<&str>) -> String {
    let text = with_effects(
        &diagnose_demo(),
        seed,
        "thermal_drift = { enabled = true, size = 5e-9 }",
    )
    .replace("temp_swing_k = 0.5", "temp_swing_k = 2.0")
    .replace("temp_period_s = 900.0", "temp_period_s = 40000.0");
    assert!(text.contains("temp_period_s = 40000.0") && text.contains("temp_swing_k = 2.0"));
    match grid {
        None => text,
        Some(grid) => {
            let start = text.find("x = { from").expect("plan grid");
            let end = text.find("order = \"serpentine\"").expect("grid order");
            format!("{}{grid}\n{}", &text[..start], &text[end..])
        }
    }
}

/// The confounded-pair rule (DESIGN.md: nearly collinear candidates are reported as such, not
/// a winner). A small measuring volume (15 x 20 x 15 cm) in the far corner of the travel,
/// 1.2-2.2 m from the axes' zero, while the structure warms at a steady rate: the thermal
/// expansion about the axes' zero moves the whole volume almost uniformly, which is what a
/// drift of the target does, and a dead path following the warming air is a ramp along
/// beams that barely change direction. The data hold a 5 nm/s thermal drift; the diagnosis
/// must not pick one of these, nor hand the signal to station_drift (which nests
/// thermal_drift) once the group is set aside. Control: the same warming and drift on the
/// demo's grid over the whole travel, where the signatures differ and thermal_drift wins.
#[test]
fn confounded_pair_is_reported_not_named() {
    let compact = "x = { from = 1.15, to = 1.3, count = 3 }\ny = { from = 2.05, to = 2.25, count = 3 }\nz = { from = 0.8, to = 0.95, count = 3 }";
    let d = run_and_diagnose(&slow_warming(16, Some(compact)));
    let text = geocal::diagnose::text(&d);
    println!("{text}");
    let status = |d: &geocal::diagnose::Diagnosis, effect: &str| {
        d.candidates
            .iter()
            .find(|c| c.effect == effect)
            .map(|c| (c.status.clone(), c.confounded_with.clone()))
            .unwrap_or_else(|| panic!("no candidate {effect}\n{text}"))
    };
    // The drift is there, strongly.
    let drift = d
        .candidates
        .iter()
        .find(|c| c.effect == "thermal_drift")
        .expect("thermal_drift candidate");
    assert!(drift.p_value < 1e-6 && drift.round == 0, "{text}");
    // Reported as a confounded group, none of it named, nothing named in its place.
    let (drift_status, group) = status(&d, "thermal_drift");
    assert_eq!(drift_status, "confounded", "{text}");
    assert!(!group.is_empty(), "{text}");
    for other in &group {
        assert!(
            ["thermal_expansion", "dead_path"].contains(&other.as_str()),
            "{other}\n{text}"
        );
        let (s, with) = status(&d, other);
        assert_eq!(s, "confounded", "{text}");
        assert!(with.iter().any(|w| w == "thermal_drift"), "{text}");
    }
    assert!(d.selected.is_empty(), "{text}");
    // The group's common signal is fitted: the gap closes. (In this small volume a length's
    // held-out prediction is uncertain, so the held-out ratio starts near 1; χ²/dof shows
    // the gap: 4 sampling standard deviations sqrt(2/dof) of 1 as the bound, ~175 dof.)
    let bound = 1.0 + 4.0 * (2.0f64 / 175.0).sqrt();
    assert!(d.gap.chi2_per_dof > bound, "{text}");
    assert!(d.gap_after.chi2_per_dof < bound, "{text}");
    assert!(d.gap_after.heldout_ratio < HELDOUT_RATIO_MAX, "{text}");
    let json = serde_json::to_value(&d).expect("json");
    common::assert_diagnosis_format(&json);
    let entry = json["candidates"]
        .as_array()
        .expect("candidates")
        .iter()
        .find(|c| c["effect"] == "thermal_drift")
        .expect("thermal_drift in JSON");
    assert_eq!(entry["status"], "confounded");
    assert!(entry["confounded_with"]
        .as_array()
        .is_some_and(|a| !a.is_empty()));

    // Control: the whole travel, same warming, same drift: separable, the right one wins.
    let d = run_and_diagnose(&slow_warming(16, None));
    let text = geocal::diagnose::text(&d);
    assert_eq!(d.selected, vec!["thermal_drift".to_string()], "{text}");
    assert!(
        d.candidates.iter().all(|c| c.status != "confounded"),
        "{text}"
    );
    assert!(d.gap_after.heldout_ratio < HELDOUT_RATIO_MAX, "{text}");
}

/// `geocal diagnose` on sessions of the kinds with a residual model (rotary_sphere,
/// probe_install, hexapod): diagnosed by their own model (`tests/diagnose_kinds.rs` checks the
/// findings); `--twin`, which compares tracer lengths, is refused clearly, never a panic.
#[test]
fn sessions_of_other_kinds_are_diagnosed_and_twins_refused_clearly() {
    let dir = tempfile::tempdir().expect("tempdir");
    let sphere = include_str!("../config/rotary-sphere.toml")
        .replace(
            "step_rad = 0.17453292519943295 # 10°",
            "step_rad = 0.5235987755982988",
        )
        .replace("count = 36", "count = 12")
        .replace("max_harmonic_order = 8", "max_harmonic_order = 4");
    let probe = include_str!("../config/probe-install.toml")
        .replace("points_per_posture = 25", "points_per_posture = 10")
        .replace("ga_generations = 2000", "ga_generations = 5")
        .replace("ga_population = 100", "ga_population = 10");
    let hexapod = include_str!("../config/hexapod.toml").replace("count = 29", "count = 8");
    for (kind, text) in [
        ("rotary_sphere", sphere),
        ("probe_install", probe),
        ("hexapod", hexapod),
    ] {
        let sub = dir.path().join(kind);
        std::fs::create_dir_all(&sub).expect("dir");
        let config = sub.join("c.toml");
        std::fs::write(&config, text).expect("write config");
        let out = sub.join("out");
        let geocal = |args: &[&std::ffi::OsStr]| {
            std::process::Command::new(env!("CARGO_BIN_EXE_geocal"))
                .args(args)
                .output()
                .expect("run geocal")
        };
        let run = geocal(&[
            "run".as_ref(),
            config.as_os_str(),
            "--out".as_ref(),
            out.as_os_str(),
        ]);
        assert!(
            run.status.success(),
            "{}",
            String::from_utf8_lossy(&run.stderr)
        );
        let session = out.join("session.mcap");
        let d = geocal(&["diagnose".as_ref(), session.as_os_str()]);
        let text = String::from_utf8_lossy(&d.stdout);
        assert!(d.status.success(), "{}", String::from_utf8_lossy(&d.stderr));
        assert!(
            text.contains(&format!("Diagnosis of {kind} session")),
            "{text}"
        );
        let d = geocal(&[
            "diagnose".as_ref(),
            session.as_os_str(),
            "--twin".as_ref(),
            config.as_os_str(),
        ]);
        let err = String::from_utf8_lossy(&d.stderr);
        assert_eq!(d.status.code(), Some(1), "{err}");
        assert!(!err.contains("panicked"), "{err}");
        assert!(err.contains("--twin compares tracer lengths"), "{err}");
        assert!(err.contains(&format!("a {kind} session")), "{err}");
        assert!(err.contains("session.mcap"), "{err}");
    }
}
