//! `geocal check` for the kinds rotary_sphere, probe_install and hexapod: the σ it predicts
//! from the plan alone must match the scatter of the solver against the simulated truth over
//! several seeds, and a deliberately poor plan must have its unidentifiable parameters named.
//!
//! Statistics: with a correct prediction every normalised error z = (estimate − truth) / σ is
//! N(0, 1), so the RMS of N of them has a standard deviation of about 1/√(2N) (less when the
//! errors are correlated, so the bounds below take the number of seeds as the least N).

use std::path::{Path, PathBuf};
use std::process::Command;

use geocal::kinds::registry::kind_layout_plan_check;
use geocal::method::plan_check_kinds::KindPlanCheck;
use geocal::run::{RunOptions, RunOutput};
use nalgebra::{Matrix3, Vector3};
use serde_json::Value;

const SPHERE: &str = include_str!("../config/rotary-sphere.toml");
const PROBE: &str = include_str!("../config/probe-install.toml");
const HEXAPOD: &str = include_str!("../config/hexapod.toml");

fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
    let path = dir.join(name);
    std::fs::write(&path, text).expect("write config");
    path
}

fn predicted(path: &Path) -> KindPlanCheck {
    kind_layout_plan_check(path)
        .expect("check")
        .expect("a kind checked here")
}

fn sigma_of(check: &KindPlanCheck, name: &str) -> f64 {
    check
        .parameters
        .iter()
        .find(|p| p.name == name)
        .and_then(|p| p.sigma)
        .unwrap_or_else(|| panic!("{name}: no predicted σ"))
}

fn options(dir: &Path) -> RunOptions {
    RunOptions {
        out_dir: dir.to_path_buf(),
        truth: Some(dir.join("truth.json")),
        progress: false,
        settings: Default::default(),
        control: Default::default(),
    }
}

fn truth(dir: &Path) -> Value {
    serde_json::from_slice(&std::fs::read(dir.join("truth.json")).expect("truth")).expect("json")
}

fn rms(z: &[f64]) -> f64 {
    (z.iter().map(|v| v * v).sum::<f64>() / z.len() as f64).sqrt()
}

/// The RMS of normalised errors must lie within 3.5 standard deviations of 1 for `n` (the
/// number of independent draws; the seeds at least).
fn assert_rms_near_one(what: &str, z: &[f64], n: usize) {
    let r = rms(z);
    let sd = 1.0 / (2.0 * n as f64).sqrt();
    println!(
        "{what}: RMS of {} normalised errors {r:.3} (bounds 1 ± {:.3})",
        z.len(),
        3.5 * sd
    );
    assert!((r - 1.0).abs() <= 3.5 * sd, "{what}: RMS {r:.3}");
}

fn geocal(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_geocal"))
        .args(args)
        .output()
        .expect("run geocal")
}

/// `geocal check --json` of a poor plan: succeeds, and names `expected` as unidentifiable.
fn assert_names_unidentifiable(path: &Path, expected: &[&str]) -> Value {
    let out = geocal(&["check", path.to_str().expect("path"), "--json"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: Value = serde_json::from_slice(&out.stdout).expect("json");
    let id = &v["identifiability"];
    assert!(id["deficiency"].as_u64().expect("deficiency") > 0, "{id}");
    let names: Vec<&str> = id["unidentifiable"]
        .as_array()
        .expect("list")
        .iter()
        .filter_map(Value::as_str)
        .collect();
    for e in expected {
        assert!(names.contains(e), "{e} not in {names:?}");
    }
    assert!(!id["null_directions"].as_array().expect("list").is_empty());
    // The text names them too.
    let text = geocal(&["check", path.to_str().expect("path")]);
    let text = String::from_utf8_lossy(&text.stdout);
    assert!(text.contains("cannot identify"), "{text}");
    assert!(text.contains(expected[0]), "{text}");
    v
}

// ---- rotary_sphere ----

/// 12 angles (every 30°), two fit heights and the validation height.
fn small_sphere(seed: u64) -> String {
    SPHERE
        .replace(
            "step_rad = 0.17453292519943295 # 10°",
            "step_rad = 0.5235987755982988",
        )
        .replace("count = 36", "count = 12")
        .replace("max_harmonic_order = 8", "max_harmonic_order = 4")
        .replace("seed = 20240612", &format!("seed = {seed}"))
}

/// The identifiable truth: the same identification on the true, noise-free centres (the
/// location errors are the least-squares axis; docs/rotary-sphere.md).
fn sphere_errors(
    r: &geocal::kinds::rotary_sphere::solve::RotarySphereResults,
    truth: &Value,
    check: &KindPlanCheck,
) -> (Vec<f64>, Vec<f64>) {
    use geocal::solve::rotary_sphere::{
        identify_rotary_axis, CentreSeries, HarmonicOrder, IdentifyOptions, TangentialConvention,
    };
    let v3 = |v: &Value| Vector3::from_fn(|k, _| v[k].as_f64().expect("number"));
    let series: Vec<CentreSeries> = [0usize, 1]
        .iter()
        .map(|&h| {
            let s: Vec<_> = r.spheres.iter().filter(|s| s.height_index == h).collect();
            CentreSeries {
                angles_rad: s.iter().map(|s| s.commanded_rad).collect(),
                centres_m: s
                    .iter()
                    .map(|s| v3(&truth["centres_m"][h][s.angle_index]))
                    .collect(),
                covariances_m2: s
                    .iter()
                    .map(|s| Matrix3::from_fn(|i, j| s.centre_covariance_m2[i][j]))
                    .collect(),
            }
        })
        .collect();
    let ideal = identify_rotary_axis(
        &series,
        &IdentifyOptions {
            convention: TangentialConvention::AngularPositioning,
            harmonics: HarmonicOrder::Fixed(0),
            radial_azimuth_rad: Some(r.radial_azimuth_rad),
        },
    )
    .expect("noise-free identification");
    let location = r
        .location
        .iter()
        .enumerate()
        .map(|(k, v)| (v.value - ideal.location[k]) / sigma_of(check, v.name))
        .collect();
    let mut motion = Vec::new();
    for (i, m) in r.motion.iter().enumerate() {
        let angle = format!("{:.0}°", m.commanded_rad.to_degrees());
        for (k, name) in r.motion_names.iter().enumerate() {
            let sigma = sigma_of(check, &format!("{name}@{angle}"));
            // EXC, EYC are the radial error's components: σ 0 where it is perpendicular.
            if sigma > 1e-3 * r.probe_noise_m {
                motion.push((m.errors[k] - ideal.motion[i][k]) / sigma);
                // The check predicts what the solver reports on the run's data.
                assert!(
                    (m.sigma[k] / sigma - 1.0).abs() < 0.05,
                    "{name}@{angle}: reported {} predicted {sigma}",
                    m.sigma[k]
                );
            }
        }
    }
    (location, motion)
}

#[test]
fn rotary_sphere_prediction_matches_the_scatter_over_seeds() {
    let dir = tempfile::tempdir().expect("tempdir");
    let check = predicted(&write(dir.path(), "c.toml", &small_sphere(1)));
    assert_eq!(check.identifiability.deficiency, 0);
    let seeds = 8;
    let (mut location, mut motion) = (Vec::new(), Vec::new());
    for seed in 0..seeds {
        let sub = dir.path().join(format!("s{seed}"));
        let cfg = geocal::kinds::rotary_sphere::config::RotarySphereConfig::parse(
            &small_sphere(300 + seed),
            Path::new("sphere.toml"),
        )
        .expect("config");
        let out = geocal::kinds::rotary_sphere::run::run(&cfg, &options(&sub)).expect("run");
        let Some(r) = out
            .results
            .get::<geocal::kinds::rotary_sphere::solve::RotarySphereResults>()
        else {
            panic!("rotary_sphere results expected");
        };
        let (l, m) = sphere_errors(r, &truth(&sub), &check);
        location.extend(l);
        motion.extend(m);
    }
    assert_rms_near_one("rotary_sphere location errors", &location, location.len());
    assert_rms_near_one("rotary_sphere motion errors", &motion, seeds as usize * 12);
}

#[test]
fn rotary_sphere_with_one_height_names_the_tilts() {
    let dir = tempfile::tempdir().expect("tempdir");
    // Both fit heights at the same place: one effective height.
    let text = small_sphere(1).replace(
        "sphere_m = [0.071, 0.0, 0.279]",
        "sphere_m = [0.071, 0.0, 0.179]",
    );
    let v = assert_names_unidentifiable(
        &write(dir.path(), "poor.toml", &text),
        &["EAC@30°", "EBC@30°"],
    );
    // Two unseen directions per angle; the location errors stay identifiable.
    assert_eq!(v["identifiability"]["deficiency"], 2 * 12);
    let loc = v["parameters"]
        .as_array()
        .expect("list")
        .iter()
        .find(|p| p["name"] == "EAOC")
        .expect("EAOC");
    assert!(loc["sigma"].as_f64().is_some_and(|s| s > 0.0), "{loc}");
}

// ---- probe_install ----

/// 15 points per posture, 2 readings each, a short GA (the check is about LM's σ).
fn small_probe(seed: u64) -> String {
    PROBE
        .replace("points_per_posture = 25", "points_per_posture = 15")
        .replace("readings_per_point = 5", "readings_per_point = 2")
        .replace("ga_population = 100", "ga_population = 10")
        .replace("ga_generations = 2000", "ga_generations = 5")
        .replace("seed = 20110501", &format!("seed = {seed}"))
}

#[test]
fn probe_install_prediction_matches_the_scatter_over_seeds() {
    let dir = tempfile::tempdir().expect("tempdir");
    let check = predicted(&write(dir.path(), "c.toml", &small_probe(1)));
    assert_eq!(check.identifiability.deficiency, 0);
    let seeds = 8;
    let (mut z, mut ratios) = (Vec::new(), Vec::new());
    for seed in 0..seeds {
        let sub = dir.path().join(format!("s{seed}"));
        std::fs::create_dir_all(&sub).expect("dir");
        let cfg = write(&sub, "pi.toml", &small_probe(500 + seed));
        let out: RunOutput = geocal::kinds::run_file(&cfg, &options(&sub))
            .expect("run")
            .expect("probe_install");
        let Some(r) = out
            .results
            .get::<geocal::kinds::probe_install::solve::ProbeInstallResults>()
        else {
            panic!("probe_install results expected");
        };
        let t = truth(&sub);
        for (p, tp) in r
            .parameters
            .iter()
            .zip(t["parameters"].as_array().expect("list"))
        {
            assert_eq!(tp["name"], p.name.as_str());
            // n is second order in the beam tilt: its first-order σ is 0.
            if p.name == "beam_n" {
                continue;
            }
            let sigma = sigma_of(&check, &p.name);
            z.push((p.value - tp["value"].as_f64().expect("value")) / sigma);
            ratios.push(p.sigma.expect("identifiable") / sigma);
        }
    }
    // The check linearises at the design installation; each run reports σ at its own (true)
    // geometry, where the set-up errors (sphere ±1 mm) shift the readings by up to a millimetre
    // against their ±2 mm design spread: the beam tilts, seen through Σ t², come out up to ~30 % better
    // determined (0.68–1.20 over these seeds). A gross error in either would leave this band.
    let (lo, hi) = ratios
        .iter()
        .fold((f64::INFINITY, 0.0f64), |(a, b), r| (a.min(*r), b.max(*r)));
    println!("probe_install: reported σ / predicted σ within [{lo:.3}, {hi:.3}]");
    assert!(lo > 0.5 && hi < 1.5, "[{lo}, {hi}]");
    assert_rms_near_one("probe_install parameters", &z, z.len());
}

#[test]
fn probe_install_with_two_postures_names_what_it_cannot_separate() {
    let dir = tempfile::tempdir().expect("tempdir");
    let text = small_probe(1).replace(
        "postures_rad = [
    [0.0, 0.0],
    [1.5707963267948966, 0.0],
    [-1.5707963267948966, 0.0],
    [1.5707963267948966, 1.5707963267948966],
]",
        "postures_rad = [[0.0, 0.0], [1.5707963267948966, 0.0]]",
    );
    assert!(text.contains("postures_rad = [[0.0, 0.0], [1.57"));
    let v = assert_names_unidentifiable(
        &write(dir.path(), "poor.toml", &text),
        &[
            "y_offset_m",
            "zero_point_x_m",
            "sphere_centre_x_m",
            "sphere_centre_y_m",
        ],
    );
    // The two unseen combinations: the zero point's and the sphere's x move together, and the
    // y offset with the sphere's y.
    let combos: Vec<Vec<&str>> = v["identifiability"]["null_directions"]
        .as_array()
        .expect("list")
        .iter()
        .map(|d| {
            let mut p: Vec<&str> = d["parameters"]
                .as_array()
                .expect("list")
                .iter()
                .filter_map(Value::as_str)
                .collect();
            p.sort();
            p
        })
        .collect();
    assert!(
        combos.contains(&vec!["sphere_centre_x_m", "zero_point_x_m"]),
        "{combos:?}"
    );
    assert!(
        combos.contains(&vec!["sphere_centre_y_m", "y_offset_m"]),
        "{combos:?}"
    );
}

// ---- hexapod ----

/// 12 poses besides home; the pose sensor's noise (5 µm, 10 µrad) dominates the encoders,
/// so a prediction without it in the weights falls well short of the scatter.
fn small_hexapod(seed: u64) -> String {
    let text = HEXAPOD
        .replace("count = 29", "count = 12")
        .replace("\nnoise_m = 0.0", "\nnoise_m = 5.0e-6")
        .replace("\nnoise_rad = 0.0", "\nnoise_rad = 1.0e-5");
    assert!(text.contains("noise_m = 5.0e-6") && text.contains("noise_rad = 1.0e-5"));
    text.replace("seed = 424242", &format!("seed = {seed}"))
}

#[test]
fn hexapod_prediction_matches_the_scatter_over_seeds() {
    let dir = tempfile::tempdir().expect("tempdir");
    let check = predicted(&write(dir.path(), "c.toml", &small_hexapod(1)));
    assert_eq!(check.identifiability.deficiency, 0);
    let seeds = 8;
    let mut z = Vec::new();
    for seed in 0..seeds {
        let sub = dir.path().join(format!("s{seed}"));
        std::fs::create_dir_all(&sub).expect("dir");
        let cfg = write(&sub, "hx.toml", &small_hexapod(700 + seed));
        let out: RunOutput = geocal::kinds::run_file(&cfg, &options(&sub))
            .expect("run")
            .expect("hexapod");
        let Some(r) = out
            .results
            .get::<geocal::kinds::hexapod::solve::HexapodResults>()
        else {
            panic!("hexapod results expected");
        };
        let t = truth(&sub);
        for h in &r.hinges {
            for k in 0..3 {
                let c = ["x", "y", "z"][k];
                for (part, est, key) in [
                    ("base", h.base_m[k], "base_m"),
                    ("platform", h.platform_m[k], "platform_m"),
                ] {
                    let sigma = sigma_of(&check, &format!("{part}_{}_{c}_m", h.leg));
                    let truth = t[key][h.leg][k].as_f64().expect("truth");
                    z.push((est - truth) / sigma);
                }
            }
        }
    }
    assert_rms_near_one("hexapod hinge coordinates", &z, z.len());
}

#[test]
fn hexapod_without_rotations_names_the_confounded_hinges() {
    let dir = tempfile::tempdir().expect("tempdir");
    let text = small_hexapod(1).replace(
        "tilt_half_range_rad = 0.17453292519943295",
        "tilt_half_range_rad = 0.0",
    );
    let v = assert_names_unidentifiable(
        &write(dir.path(), "poor.toml", &text),
        &["base_0_x_m", "platform_0_x_m"],
    );
    assert_eq!(v["identifiability"]["deficiency"], 18);
}
