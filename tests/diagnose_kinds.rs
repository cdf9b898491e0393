//! The diagnosis of the kinds with a residual model (hexapod, probe_install, rotary_sphere;
//! docs/diagnosis.md): each kind's own simulator with one library effect withheld from the
//! solve's model → exactly that effect selected, where it says, the held-out gap closed to
//! within 1.3× the clean session's; clean sessions → nothing selected (false alarms counted
//! over seeds); an effect outside the library → `unexplained` with nothing selected; the
//! outside sessions (../shared/sessions) of these kinds; `geocal solve --effects` against the
//! simulated truth (within 2× the clean case's error, σ honest).

use std::path::{Path, PathBuf};

use geocal::diagnose::Diagnosis;
use geocal::method::SolveSettings;
use serde_json::Value;

use crate::common;

/// An outside session's folder: `../shared/sessions` beside the checkout, or the folder
/// `GEOCAL_OUTSIDE_SESSIONS` names (a worktree elsewhere).
fn outside(name: &str) -> PathBuf {
    std::env::var_os("GEOCAL_OUTSIDE_SESSIONS")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/sessions"))
        .join(name)
}

fn outside_truth(name: &str) -> Value {
    let text = std::fs::read_to_string(outside(name).join("truth.json")).expect("truth.json");
    serde_json::from_str(&text).expect("truth json")
}

/// The diagnosis of a session file, its progress checked (`common::diagnose_checking_progress`).
fn diagnose(session: &Path) -> Diagnosis {
    let start = std::time::Instant::now();
    let d = common::diagnose_checking_progress(session);
    eprintln!("diagnosed in {:.1} s", start.elapsed().as_secs_f64());
    d
}

fn solve_with(session: &Path, effects: &[&str]) -> Value {
    let settings = SolveSettings {
        effect_names: effects.iter().map(|e| e.to_string()).collect(),
        ..Default::default()
    };
    let results = geocal::kinds::solve_file(session, &settings).expect("solve");
    serde_json::from_str(&results.to_json_pretty()).expect("results json")
}

/// A simulated session of `config` in `dir`: (session path, truth).
fn simulate(config: &str, dir: &Path, file: &str) -> (PathBuf, Value) {
    std::fs::create_dir_all(dir).expect("dir");
    let path = dir.join(file);
    std::fs::write(&path, config).expect("write config");
    let truth_path = dir.join("truth.json");
    let options = geocal::run::RunOptions {
        out_dir: dir.to_path_buf(),
        truth: Some(truth_path.clone()),
        progress: false,
        settings: Default::default(),
        control: Default::default(),
    };
    let output = geocal::kinds::kind_of_config(&path)
        .expect("kind")
        .run(&path, &options, &Default::default())
        .expect("run");
    let truth = serde_json::from_slice(&std::fs::read(&truth_path).expect("truth file"))
        .expect("truth json");
    (output.session_path, truth)
}

fn summary(d: &Diagnosis) -> String {
    geocal::diagnose::summary(d).join("\n")
}

/// The diagnosis selects exactly `effect`, names in its summary's `where` (the first two
/// groups) one of the coordinate `where_key` or whose key contains it, and closes the held-out
/// gap to within 1.3× the clean session's.
fn assert_selects(d: &Diagnosis, effect: &str, where_key: &str, clean_heldout: f64) {
    let text = summary(d);
    assert_eq!(d.selected, vec![effect.to_string()], "{text}");
    assert!(!d.unexplained, "{text}");
    assert!(
        d.where_
            .first()
            .into_iter()
            .chain(
                d.where_
                    .iter()
                    .find(|w| Some(&w.group) != d.where_.first().map(|f| &f.group))
            )
            .any(|w| w.group == where_key || w.key.contains(where_key)),
        "where should name {where_key}: {text}"
    );
    assert!(
        d.gap_after.heldout_ratio <= 1.3 * clean_heldout,
        "held-out after {:.3} vs clean {clean_heldout:.3}: {text}",
        d.gap_after.heldout_ratio
    );
}

fn assert_clean(d: &Diagnosis) {
    let text = summary(d);
    assert!(d.selected.is_empty(), "{text}");
    assert!(!d.unexplained, "{text}");
}

fn assert_unexplained(d: &Diagnosis) {
    let text = summary(d);
    assert!(d.selected.is_empty(), "{text}");
    assert!(d.unexplained, "{text}");
}

fn number(v: &Value) -> f64 {
    v.as_f64().expect("number")
}

// ---------------------------------------------------------------------------------------
// hexapod

const HEXAPOD: &str = include_str!("../config/hexapod.toml");

/// The example hexapod with a measuring pose sensor (2 µm, 5 µrad), 0.5 µm encoders read 4
/// times per pose and 40 poses: the outside sessions' noise model.
fn hexapod(seed: u64, sim: &str) -> String {
    HEXAPOD
        .replace(
            "noise_m = 0.0\nnoise_rad = 0.0",
            "noise_m = 2.0e-6\nnoise_rad = 5.0e-6",
        )
        .replace("encoder_noise_m = 1.0e-6", "encoder_noise_m = 5.0e-7")
        .replace("readings_per_pose = 1", "readings_per_pose = 4")
        .replace(
            "count = 29, seed = 5",
            &format!("count = 40, seed = {seed}"),
        )
        .replace("seed = 424242", &format!("seed = {}{sim}", 1000 + seed))
}

/// (hinge errors / σ RMS, hinge error RMS m) of a results JSON against a truth.
fn hinge_errors(results: &Value, truth: &Value) -> (f64, f64) {
    let (mut z2, mut e2, mut n) = (0.0, 0.0, 0.0);
    for h in results["hinges"].as_array().expect("hinges") {
        let leg = h["leg"].as_u64().expect("leg") as usize;
        for (est, sig, tru) in [
            ("base_m", "base_sigma_m", &truth["base_m"][leg]),
            ("platform_m", "platform_sigma_m", &truth["platform_m"][leg]),
        ] {
            for k in 0..3 {
                let e = number(&h[est][k]) - number(&tru[k]);
                z2 += (e / number(&h[sig][k])).powi(2);
                e2 += e * e;
                n += 1.0;
            }
        }
    }
    ((z2 / n).sqrt(), (e2 / n).sqrt())
}

#[test]
fn hexapod_effects_withheld_are_named_and_fitted() {
    let dir = tempfile::tempdir().expect("tempdir");
    let run =
        |name: &str, sim: &str| simulate(&hexapod(7, sim), &dir.path().join(name), "hexapod.toml");
    let (clean, clean_truth) = run("clean", "");
    let d = diagnose(&clean);
    assert_clean(&d);
    let clean_heldout = d.gap.heldout_ratio;
    let (clean_z, clean_error) = hinge_errors(&solve_with(&clean, &[]), &clean_truth);
    eprintln!(
        "clean: held-out {clean_heldout:.3}, hinge error {clean_error:.2e} m, z RMS {clean_z:.2}"
    );
    let cases = [
        (
            "leg_scale",
            "\nleg_scale = [0.0, 3.0e-4, 0.0, 0.0, -2.0e-4, 0.0]",
            "leg 1",
        ),
        (
            "leg_backlash",
            "\nleg_backlash_m = [0.0, 0.0, 3.0e-6, 0.0, 0.0, 0.0]",
            "leg 2",
        ),
        (
            "sensor_drift",
            "\nsensor_drift = [6.0e-8, 0.0, 0.0, 0.0, 1.5e-7, 0.0]",
            "pose sensor",
        ),
    ];
    for (effect, sim, where_key) in cases {
        let (session, truth) = run(effect, sim);
        let d = diagnose(&session);
        eprintln!("{effect}:\n{}", summary(&d));
        assert_selects(&d, effect, where_key, clean_heldout);
        let corrected = solve_with(&session, &[effect]);
        let (z, error) = hinge_errors(&corrected, &truth);
        eprintln!("{effect}: solve --effects hinge error {error:.2e} m, z RMS {z:.2}");
        assert!(
            error <= 2.0 * clean_error,
            "{effect}: {error:.2e} vs clean {clean_error:.2e}"
        );
        assert!(z < 1.6, "{effect}: σ not honest, z RMS {z:.2}");
        assert!(corrected["effects"][effect].is_object(), "{corrected}");
    }
    // Out of the library: an elastic sag of the platform with its tilt.
    let (sag, _) = run("sag", "\nplatform_sag_m = 8.0e-6");
    let d = diagnose(&sag);
    eprintln!("platform sag:\n{}", summary(&d));
    assert_unexplained(&d);
}

/// Clean sessions of seeds 11–15 (`config` of a seed, written as `file`): how many selected
/// an effect or were `unexplained`.
fn clean_alarms(config: impl Fn(u64) -> String, file: &str) -> usize {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut alarms = 0;
    for seed in 11..16 {
        let (session, _) = simulate(&config(seed), &dir.path().join(format!("s{seed}")), file);
        let d = diagnose(&session);
        if !d.selected.is_empty() || d.unexplained {
            eprintln!("seed {seed}:\n{}", summary(&d));
            alarms += 1;
        }
    }
    alarms
}

#[test]
fn hexapod_clean_sessions_raise_few_false_alarms() {
    let alarms = clean_alarms(|seed| hexapod(seed, ""), "hexapod.toml");
    // At α = 1 % per session, 5 sessions: one alarm has probability ~5 %, two ~0.1 %.
    assert!(alarms <= 1, "{alarms} false alarms in 5 clean sessions");
}

#[test]
fn hexapod_outside_sessions() {
    for clean in ["outside-hexapod-clean-2", "outside-hexapod-sensor-topic-3"] {
        assert_clean(&diagnose(&outside(clean).join("session.mcap")));
    }
    let name = "outside-hexapod-leg-scale-21";
    let truth = outside_truth(name);
    assert_eq!(truth["vocabulary_effects"][0], "leg_scale");
    let session = outside(name).join("session.mcap");
    let d = diagnose(&session);
    eprintln!("{name}:\n{}", summary(&d));
    assert_eq!(d.selected, vec!["leg_scale".to_string()], "{}", summary(&d));
    assert!(!d.unexplained, "{}", summary(&d));
    // The fitted scale of every leg against the truth's (0 on the legs it leaves alone).
    let corrected = solve_with(&session, &["leg_scale"]);
    let fitted = &corrected["effects"]["leg_scale"];
    let params = &truth["effect_params"]["leg_scale"];
    let mut z2 = 0.0;
    for leg in 0..6 {
        let k_true = params["legs"]
            .as_array()
            .expect("legs")
            .iter()
            .position(|l| l.as_u64() == Some(leg as u64))
            .map_or(0.0, |at| number(&params["k"][at]));
        let k = number(&fitted[format!("leg{leg}.k")]);
        let sigma = number(&fitted[format!("leg{leg}.k.sigma")]);
        eprintln!("leg {leg}: k {k:.4e} ± {sigma:.1e}, truth {k_true:.4e}");
        z2 += ((k - k_true) / sigma).powi(2);
        assert!(((k - k_true) / sigma).abs() < 4.0, "leg {leg}");
    }
    assert!(
        (z2 / 6.0).sqrt() < 2.0,
        "leg_scale z RMS {:.2}",
        (z2 / 6.0).sqrt()
    );
    // The hinges with leg_scale fitted: within their σ of the outside truth.
    let mut z = Vec::new();
    for h in corrected["hinges"].as_array().expect("hinges") {
        let leg = h["leg"].as_u64().expect("leg") as usize;
        let t = &truth["hinges"][leg];
        for (est, sig, tru) in [
            ("base_m", "base_sigma_m", "base_m"),
            ("platform_m", "platform_sigma_m", "platform_m"),
        ] {
            for k in 0..3 {
                z.push((number(&h[est][k]) - number(&t[tru][k])) / number(&h[sig][k]));
            }
        }
    }
    let rms = (z.iter().map(|v| v * v).sum::<f64>() / z.len() as f64).sqrt();
    eprintln!("{name}: hinges with leg_scale fitted, z RMS {rms:.2}");
    assert!(rms < 1.6, "hinge z RMS {rms:.2}");
}

// ---------------------------------------------------------------------------------------
// probe_install

const PROBE: &str = include_str!("../config/probe-install.toml");

/// The example installation with 40 points per posture and a short GA (the diagnosis uses
/// LM's parameters; the GA is reported beside them).
fn probe(seed: u64, effects: &str) -> String {
    PROBE
        .replace("points_per_posture = 25", "points_per_posture = 40")
        .replace("ga_generations = 2000", "ga_generations = 5")
        .replace("ga_population = 100", "ga_population = 10")
        .replace("seed = 1\n", &format!("seed = {seed}\n"))
        .replace("seed = 20110501", &format!("seed = {}", 20110501 + seed))
        + &format!("\n[sim.effects]\n{effects}\n")
}

/// (parameter errors / σ RMS, relative error RMS against the clean σ) of a probe results JSON.
fn probe_errors(results: &Value, truth: &Value) -> (f64, Vec<f64>) {
    let mut z2 = 0.0;
    let mut n = 0.0;
    let mut errors = Vec::new();
    for (p, t) in results["parameters"]
        .as_array()
        .expect("parameters")
        .iter()
        .zip(truth["parameters"].as_array().expect("truth parameters"))
    {
        let e = number(&p["value"]) - number(&t["value"]);
        errors.push(e);
        if let Some(s) = p["sigma"].as_f64() {
            z2 += (e / s).powi(2);
            n += 1.0;
        }
    }
    ((z2 / n).sqrt(), errors)
}

#[test]
fn probe_install_effects_withheld_are_named_and_fitted() {
    let dir = tempfile::tempdir().expect("tempdir");
    let run = |name: &str, effects: &str| {
        simulate(&probe(3, effects), &dir.path().join(name), "probe.toml")
    };
    let (clean, clean_truth) = run("clean", "");
    let d = diagnose(&clean);
    assert_clean(&d);
    let clean_heldout = d.gap.heldout_ratio;
    let clean_results = solve_with(&clean, &[]);
    let (clean_z, clean_errors) = probe_errors(&clean_results, &clean_truth);
    let sigmas: Vec<f64> = clean_results["parameters"]
        .as_array()
        .expect("parameters")
        .iter()
        .map(|p| p["sigma"].as_f64().unwrap_or(f64::NAN))
        .collect();
    // Errors in units of the clean solve's σ: the scale every parameter shares.
    let scaled_rms = |errors: &[f64]| {
        (errors
            .iter()
            .zip(&sigmas)
            .filter(|(_, s)| s.is_finite())
            .map(|(e, s)| (e / s).powi(2))
            .sum::<f64>()
            / sigmas.iter().filter(|s| s.is_finite()).count() as f64)
            .sqrt()
    };
    let clean_scaled = scaled_rms(&clean_errors);
    eprintln!(
        "clean: held-out {clean_heldout:.3}, z RMS {clean_z:.2}, error {clean_scaled:.2} clean σ"
    );
    let cases = [
        ("a_axis_tilt", "a_axis_tilt_rad = 3.0e-4", "posture"),
        ("reading_scale", "reading_scale = 2.0e-3", "reading"),
        (
            "thermal_drift",
            "thermal_drift_m_per_s = [6.0e-8, -3.0e-8, 3.0e-8]",
            "time",
        ),
    ];
    for (effect, switch, where_key) in cases {
        let (session, truth) = run(effect, switch);
        let d = diagnose(&session);
        eprintln!("{effect}:\n{}", summary(&d));
        assert_selects(&d, effect, where_key, clean_heldout);
        let corrected = solve_with(&session, &[effect]);
        let (z, errors) = probe_errors(&corrected, &truth);
        let scaled = scaled_rms(&errors);
        eprintln!("{effect}: solve --effects z RMS {z:.2}, error {scaled:.2} clean σ");
        assert!(
            scaled <= 2.0 * clean_scaled.max(1.0),
            "{effect}: error {scaled:.2} vs clean {clean_scaled:.2} (clean σ)"
        );
        assert!(z < 1.6, "{effect}: σ not honest, z RMS {z:.2}");
    }
    let (periodic, _) = run("periodic", "x_periodic_error_m = 3.0e-6");
    let d = diagnose(&periodic);
    eprintln!("x periodic error:\n{}", summary(&d));
    assert_unexplained(&d);
}

#[test]
fn probe_install_clean_sessions_raise_few_false_alarms() {
    let alarms = clean_alarms(|seed| probe(seed, ""), "probe.toml");
    assert!(alarms <= 1, "{alarms} false alarms in 5 clean sessions");
}

#[test]
fn probe_install_outside_sessions() {
    assert_clean(&diagnose(
        &outside("outside-probe-clean-2").join("session.mcap"),
    ));
    for (name, effect, key) in [
        ("outside-probe-scale-21", "reading_scale", "k"),
        ("outside-probe-tilt-22", "a_axis_tilt", "tilt_rad"),
    ] {
        let truth = outside_truth(name);
        assert_eq!(truth["vocabulary_effects"][0], effect);
        let session = outside(name).join("session.mcap");
        let d = diagnose(&session);
        eprintln!("{name}:\n{}", summary(&d));
        assert_eq!(d.selected, vec![effect.to_string()], "{}", summary(&d));
        assert!(!d.unexplained, "{}", summary(&d));
        let corrected = solve_with(&session, &[effect]);
        let fitted = number(&corrected["effects"][effect][key]);
        let sigma = number(&corrected["effects"][effect][format!("{key}.sigma")]);
        let true_value = number(&truth["effect_params"][effect][key]);
        eprintln!("{name}: {key} {fitted:.4e} ± {sigma:.1e}, truth {true_value:.4e}");
        assert!(((fitted - true_value) / sigma).abs() < 4.0, "{name}");
    }
}

// ---------------------------------------------------------------------------------------
// rotary_sphere

const SPHERE: &str = include_str!("../config/rotary-sphere.toml");

/// The example table probed every 15° with 8 points of a 0.4 µm probe read twice (the
/// outside sessions' plan), with `[sim]` extras.
fn sphere(seed: u64, sim: &str) -> String {
    SPHERE
        .replace("noise_m = 2.7e-5", "noise_m = 4.0e-7")
        .replace("points = 5 ", "points = 8 ")
        .replace("readings_per_point = 1 ", "readings_per_point = 2 ")
        .replace(
            "step_rad = 0.17453292519943295 # 10°",
            "step_rad = 0.2617993877991494",
        )
        .replace("count = 36", "count = 24")
        .replace(
            "seed = 20240612",
            &format!("seed = {}{sim}", 20240612 + seed),
        )
}

/// (centre errors / σ RMS, centre error RMS m) of a sphere results JSON against the truth's
/// centres moved by `shift` (what no reading can tell from the centres, e.g. a probe-tip offset).
fn centre_errors(results: &Value, truth: &Value, shift: [f64; 3]) -> (f64, f64) {
    let (mut z2, mut e2, mut n) = (0.0, 0.0, 0.0);
    for s in results["spheres"].as_array().expect("spheres") {
        let h = s["height_index"].as_u64().expect("h") as usize;
        let a = s["angle_index"].as_u64().expect("a") as usize;
        // geocal's truth: centres_m[h][a]; the outside generator's: centres_m[h].centres_m[a].
        let height = &truth["centres_m"][h];
        let t = match height.get("centres_m") {
            Some(list) => &list[a],
            None => &height[a],
        };
        for k in 0..3 {
            let e = number(&s["centre_m"][k]) - number(&t[k]) - shift[k];
            z2 += (e / number(&s["centre_sigma_m"][k])).powi(2);
            e2 += e * e;
            n += 1.0;
        }
    }
    ((z2 / n).sqrt(), (e2 / n).sqrt())
}

/// How far the simulator's lobing of amplitude `a` (docs/diagnosis.md, the `[sim]` switch)
/// moves every fitted centre: its degree-1 part over the plan's 8 equally weighted probing
/// directions, d_k ≈ n_k·v (least squares), reads as the centres at −v.
fn lobing_centre_shift(a: f64) -> [f64; 3] {
    let directions = geocal::solve::rotary_sphere::simulation::probe_directions(8);
    let mut normal = nalgebra::Matrix3::zeros();
    let mut rhs = nalgebra::Vector3::zeros();
    for n in &directions {
        let (az, el) = (n.y.atan2(n.x), n.z.clamp(-1.0, 1.0).asin());
        let d = a * ((3.0 * az).cos() * el.cos() + 0.6 * (el.cos().powi(2) - 0.5));
        normal += n * n.transpose();
        rhs += n * d;
    }
    let v = normal.try_inverse().expect("directions span space") * rhs;
    [-v.x, -v.y, -v.z]
}

#[test]
fn rotary_sphere_effects_withheld_are_named_and_fitted() {
    let dir = tempfile::tempdir().expect("tempdir");
    let run =
        |name: &str, sim: &str| simulate(&sphere(6, sim), &dir.path().join(name), "sphere.toml");
    let (clean, clean_truth) = run("clean", "");
    let d = diagnose(&clean);
    assert_clean(&d);
    let clean_heldout = d.gap.heldout_ratio;
    let (clean_z, clean_error) = centre_errors(&solve_with(&clean, &[]), &clean_truth, [0.0; 3]);
    eprintln!(
        "clean: held-out {clean_heldout:.3}, centre error {clean_error:.2e} m, z RMS {clean_z:.2}"
    );
    let cases = [
        ("probe_lobing", "\nprobe_lobing_m = 2.0e-6", "direction"),
        (
            "sphere_form",
            "\nsphere_form_m = [1.5e-6, 0.0, 0.0, 1.0e-6]",
            "",
        ),
        (
            "thermal_drift",
            "\nthermal_drift_m_per_s = [-3.0e-9, -1.7e-8, 1.3e-9]",
            // The heights are probed one after another (a remount between): the drift's
            // contribution is largest at the last one.
            "height",
        ),
    ];
    for (effect, sim, where_key) in cases {
        let (session, truth) = run(effect, sim);
        let d = diagnose(&session);
        eprintln!("{effect}:\n{}", summary(&d));
        assert_selects(&d, effect, where_key, clean_heldout);
        if effect != "thermal_drift" {
            // The truth's centres are the drift-free ones: only the static effects compare.
            let corrected = solve_with(&session, &[effect]);
            let shift = if effect == "probe_lobing" {
                lobing_centre_shift(2.0e-6)
            } else {
                [0.0; 3]
            };
            let (z, error) = centre_errors(&corrected, &truth, shift);
            eprintln!("{effect}: solve --effects centre error {error:.2e} m, z RMS {z:.2}");
            assert!(
                error <= 2.0 * clean_error,
                "{effect}: {error:.2e} vs {clean_error:.2e}"
            );
            assert!(z < 1.6, "{effect}: σ not honest, z RMS {z:.2}");
        }
    }
    let (vibration, _) = run("vibration", "\nprobe_vibration_m = 2.0e-6");
    let d = diagnose(&vibration);
    eprintln!("probe vibration:\n{}", summary(&d));
    assert_unexplained(&d);
}

#[test]
fn rotary_sphere_clean_sessions_raise_few_false_alarms() {
    let alarms = clean_alarms(|seed| sphere(seed, ""), "sphere.toml");
    assert!(alarms <= 1, "{alarms} false alarms in 5 clean sessions");
}

#[test]
fn rotary_sphere_outside_sessions() {
    for name in ["outside-sphere-clean-2", "outside-sphere-offaxis-1"] {
        let d = diagnose(&outside(name).join("session.mcap"));
        eprintln!("{name}:\n{}", summary(&d));
        assert_clean(&d);
    }
    // The drift moves the centres between spheres; the axis model (the diagnosis's nominal
    // model) predicts them, so the drift stays in the residuals and is named, its velocity
    // within its σ of the truth's.
    let (name, effect) = ("outside-sphere-thermal-22", "thermal_drift");
    let truth = outside_truth(name);
    assert_eq!(truth["vocabulary_effects"][0], effect);
    let d = diagnose(&outside(name).join("session.mcap"));
    eprintln!("{name}:\n{}", summary(&d));
    assert_eq!(d.selected, vec![effect.to_string()], "{}", summary(&d));
    assert!(!d.unexplained, "{}", summary(&d));
    let fitted = &d
        .candidates
        .iter()
        .find(|c| c.effect == effect)
        .expect("candidate")
        .params;
    let velocity = &truth["effect_params"][effect]["velocity_m_per_s"];
    for (k, axis) in ["vx", "vy", "vz"].iter().enumerate() {
        let v = number(&fitted[&format!("{axis}_m_per_s")]);
        let sigma = number(&fitted[&format!("{axis}_m_per_s.sigma")]);
        let t = number(&velocity[k]);
        eprintln!("{name}: {axis} {v:.4e} ± {sigma:.1e}, truth {t:.4e}");
        assert!(
            ((v - t) / sigma).abs() < 4.0,
            "{axis}: {v:.4e} ± {sigma:.1e} vs {t:.4e}"
        );
    }
    let (name, effect) = ("outside-sphere-lobing-21", "probe_lobing");
    let truth = outside_truth(name);
    assert_eq!(truth["vocabulary_effects"][0], effect);
    let session = outside(name).join("session.mcap");
    let d = diagnose(&session);
    eprintln!("{name}:\n{}", summary(&d));
    assert_eq!(d.selected, vec![effect.to_string()], "{}", summary(&d));
    assert!(!d.unexplained, "{}", summary(&d));
    // The centres with the lobing fitted: the truth's, moved by the lobing's degree-1 part
    // (the outside generator's `absorbed_centre_shift_m`, the same at every sphere), within
    // honest σ.
    let shift = &truth["effect_params"][effect]["absorbed_centre_shift_m"][0][0];
    let shift = [number(&shift[0]), number(&shift[1]), number(&shift[2])];
    let (z, error) = centre_errors(&solve_with(&session, &[effect]), &truth, shift);
    let (z_raw, _) = centre_errors(&solve_with(&session, &[]), &truth, [0.0; 3]);
    eprintln!(
        "{name}: solve --effects centre error {error:.2e} m, z RMS {z:.2} (without: {z_raw:.2})"
    );
    assert!(z < 1.6, "{name}: σ not honest, z RMS {z:.2}");
}

/// A degree-2 form withheld, over 8 seeds: `sphere_form` is named every time and alone in all
/// but at most one. A further effect after it passes a round's tests with probability ≤ 1 %
/// (Bonferroni over the round's candidates) where the model holds: 2 of 8 has probability
/// ≤ 0.3 %. Measured over seeds 3–50: alone in 46 of 48 (seed 3 adds `thermal_drift`, p 1.3e-3
/// in round 1; seed 44 `reading_scale`, which its effect-free twin of the same noise draw
/// selects too).
#[test]
fn probe_install_sphere_form_alone_is_named() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut extra = 0;
    for seed in 3..11 {
        let run = |name: &str, effects: &str| {
            simulate(
                &probe(seed, effects),
                &dir.path().join(format!("{name}{seed}")),
                "probe.toml",
            )
            .0
        };
        let clean_heldout = diagnose(&run("clean", "")).gap.heldout_ratio;
        let d = diagnose(&run(
            "form",
            "sphere_form_m = [2.0e-6, 0.0, 1.5e-6, 0.0, -1.0e-6]",
        ));
        let text = summary(&d);
        assert_eq!(
            d.selected.first().map(String::as_str),
            Some("sphere_form"),
            "{text}"
        );
        if d.selected.len() > 1 {
            eprintln!("seed {seed}: {text}");
            extra += 1;
            continue;
        }
        assert_selects(&d, "sphere_form", "", clean_heldout);
    }
    assert!(extra <= 1, "{extra} of 8 seeds select a further effect");
}

// ---------------------------------------------------------------------------------------
// The local parameters eliminated group by group (a hexapod's measured poses) against the
// dense design: the same fits on random designs, full rank and rank-deficient.

mod blocked {
    use std::sync::Arc;

    use geocal::diagnose::blocked::{BlockedDesign, LocalBlock, ModelDesign};
    use geocal::diagnose::engine::{LinearDesign, LinearFit};
    use geocal::diagnose::whitened::WhitenedDesign;
    use geocal::method::blocked_lsq::solve_blocked;
    use nalgebra::{DMatrix, DVector};

    /// Uniform in [−1, 1) (xorshift).
    struct Noise(u64);

    impl Noise {
        fn next(&mut self) -> f64 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            (self.0 >> 11) as f64 / (1u64 << 52) as f64 - 1.0
        }
    }

    /// `groups` groups of `per` rows with `width` local columns each, `global` columns and
    /// `free` rows in no group; `deficient` makes it rank-deficient three ways: a global column
    /// repeated, a local column repeated in one block, a global column in the blocks' span (a
    /// null direction with local parts).
    fn design(
        seed: u64,
        (groups, per, width, global, free): (usize, usize, usize, usize, usize),
        deficient: bool,
    ) -> (DMatrix<f64>, Vec<LocalBlock>) {
        let mut noise = Noise(seed);
        let n = groups * per + free;
        let mut x = DMatrix::zeros(n, global + groups * width);
        let mut blocks = Vec::new();
        for r in 0..n {
            for c in 0..global {
                x[(r, c)] = noise.next() * 10f64.powi((c % 3) as i32);
            }
        }
        for g in 0..groups {
            let columns = global + g * width..global + (g + 1) * width;
            let rows: Vec<usize> = (g * per..(g + 1) * per).collect();
            for &r in &rows {
                for c in columns.clone() {
                    x[(r, c)] = noise.next() * 1e3;
                }
            }
            blocks.push(LocalBlock { columns, rows });
        }
        if deficient {
            for r in 0..n {
                x[(r, 1)] = 2.0 * x[(r, 0)];
                x[(r, global - 1)] = 0.0;
            }
            for g in 0..groups {
                for r in g * per..(g + 1) * per {
                    x[(r, global - 1)] = 1e-3 * x[(r, global + g * width)];
                }
            }
            for r in 0..per {
                x[(r, global + 1)] = -x[(r, global)];
            }
        }
        (x, blocks)
    }

    fn relative(a: &DVector<f64>, b: &DVector<f64>) -> f64 {
        (a - b).amax() / b.amax().max(f64::MIN_POSITIVE)
    }

    const TOL: f64 = 1e-10;

    fn compare(x: &DMatrix<f64>, blocks: &[LocalBlock], rows: Vec<usize>, seed: u64) {
        let x = Arc::new(x.clone());
        let dense = WhitenedDesign(x.clone()).fit(rows.clone());
        let blocked = BlockedDesign::new(x.clone(), blocks.to_vec())
            .expect("valid blocks")
            .fit(rows.clone());
        assert_eq!(blocked.rank(), dense.rank());
        let mut noise = Noise(seed);
        let y = DVector::from_fn(rows.len(), |_, _| noise.next());
        // The minimum-norm solution itself.
        let (xb, xd) = (blocked.solve(&y), dense.solve(&y));
        assert!(relative(&xb, &xd) < TOL, "solve {:e}", relative(&xb, &xd));
        let (pb, pd) = (blocked.project_off_vec(&y), dense.project_off_vec(&y));
        assert!(
            relative(&pb, &pd) < TOL,
            "project_off {:e}",
            relative(&pb, &pd)
        );
        let m = DMatrix::from_fn(rows.len(), 3, |_, _| noise.next());
        let (mb, md) = (
            blocked.project_off_owned(m.clone()),
            dense.project_off_owned(m),
        );
        assert!((&mb - &md).amax() < TOL * md.amax());
        let mut held = Vec::new();
        let mut outside = 0;
        for i in 0..x.nrows() {
            assert_eq!(blocked.in_row_space(i), dense.in_row_space(i), "row {i}");
            match dense.in_row_space(i) {
                true => held.push(i),
                false => outside += 1,
            }
        }
        let vb = DVector::from_vec(blocked.prediction_variances(&held));
        let vd = DVector::from_vec(dense.prediction_variances(&held));
        assert!(
            relative(&vb, &vd) < TOL,
            "variances {:e}",
            relative(&vb, &vd)
        );
        let lb = DVector::from_vec(blocked.leverages());
        let ld = DVector::from_vec(dense.basis.leverages());
        assert!(
            relative(&lb, &ld) < TOL,
            "leverages {:e}",
            relative(&lb, &ld)
        );
        assert_eq!(blocked.factorises_by_svd(), dense.factorises_by_svd());
        eprintln!(
            "rows {} rank {} outside the row space {outside}: solve {:.1e}, variances {:.1e}",
            rows.len(),
            dense.rank(),
            relative(&xb, &xd),
            relative(&vb, &vd)
        );
    }

    #[test]
    fn blocked_fits_equal_the_dense_fits() {
        let shape = (9, 8, 4, 7, 5);
        let per = shape.1;
        for (seed, deficient) in [(3, false), (5, false), (7, true), (11, true)] {
            let (x, blocks) = design(seed, shape, deficient);
            let n = x.nrows();
            compare(&x, &blocks, (0..n).collect(), seed + 1);
            // A fold: rows of several blocks held out, one block held out whole (its local
            // columns then have no training row), one left with fewer rows than columns.
            let training: Vec<usize> = (0..n)
                .filter(|&r| r % 5 != 2 && !(per..2 * per).contains(&r))
                .filter(|&r| !(2 * per + 2..3 * per).contains(&r))
                .collect();
            compare(&x, &blocks, training, seed + 2);
        }
    }

    #[test]
    fn blocks_that_do_not_hold_fall_back_to_dense() {
        let (mut x, blocks) = design(13, (3, 4, 2, 3, 0), false);
        // A local column non-zero on another group's row.
        x[(blocks[1].rows[0], blocks[0].columns.start)] = 1.0;
        assert!(matches!(
            ModelDesign::new(x.clone(), blocks.clone()),
            ModelDesign::Dense(_)
        ));
        let b = DVector::from_element(x.nrows(), 1.0);
        assert!(solve_blocked(&x, &b, &blocks).is_none());
    }

    /// The joint fit's least squares block by block: solution and covariance equal the dense
    /// inverse's; a design not of full rank is left to the dense pseudo-inverse.
    #[test]
    fn blocked_least_squares_equals_the_dense_inverse() {
        let (x, blocks) = design(17, (7, 9, 3, 5, 4), false);
        let mut noise = Noise(19);
        let b = DVector::from_fn(x.nrows(), |_, _| noise.next());
        let (theta, cov, rank) = solve_blocked(&x, &b, &blocks).expect("full rank");
        assert_eq!(rank, x.ncols());
        let pinv = x.clone().pseudo_inverse(1e-12).expect("svd");
        let dense_theta = &pinv * &b;
        let dense_cov = &pinv * pinv.transpose();
        assert!(relative(&theta, &dense_theta) < 1e-9);
        assert!((&cov - &dense_cov).amax() < 1e-9 * dense_cov.amax());
        let (deficient, blocks) = design(17, (7, 9, 3, 5, 4), true);
        assert!(solve_blocked(&deficient, &b, &blocks).is_none());
    }
}
