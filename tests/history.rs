//! A machine's history on simulated histories: a generator of results documents shaped as a
//! multilateration's (the 21 error functions at their grid positions, the 3 squareness errors,
//! each with its σ), each run the truth plus independent Gaussian noise of that σ. No change →
//! no event (the false-alarm rate over many seeds is within the family-wise level); a 3σ
//! squareness step at run 7 → a step named at run 7; a slow thermal growth of one positioning
//! error → a drift with its rate. And `geocal compare` on real demo runs: different noise
//! seeds → no significant change; a changed `[sim]` squareness → the squareness errors only.

use crate::common;

use std::path::Path;
use std::process::Command;

use geocal::history::trend::EventKind;
use geocal::history::{trend, MachineIdentity, Run, TrendOptions};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use serde_json::{json, Value};

const AXES: [(&str, [&str; 6]); 3] = [
    ("x", ["EXX", "EYX", "EZX", "EAX", "EBX", "ECX"]),
    ("y", ["EXY", "EYY", "EZY", "EAY", "EBY", "ECY"]),
    ("z", ["EXZ", "EYZ", "EZZ", "EAZ", "EBZ", "ECZ"]),
];
const SQUARENESS: [&str; 3] = ["EC0Y", "EA0Z", "EB0Z"];
/// Grid positions of each axis (the first is the reference, σ 0).
const POSITIONS_M: [f64; 4] = [0.1, 0.5, 0.9, 1.3];
const LINEAR_SIGMA_M: f64 = 0.2e-6;
const ANGULAR_SIGMA_RAD: f64 = 0.5e-6;
const SQUARENESS_SIGMA_RAD: f64 = 0.3e-6;
const RUNS: usize = 12;
const DAYS_BETWEEN_RUNS: i64 = 7;

/// What changes over the history, as a function of the run index.
#[derive(Clone, Copy)]
enum Change {
    None,
    /// `size_rad` added to EB0Z from run `from` on (0-based).
    SquarenessStep {
        from: usize,
        size_rad: f64,
    },
    /// EXX grows by `per_m_day` × (position − first position) × days since the first run.
    ThermalGrowth {
        per_m_day: f64,
    },
}

fn truth_value(name: &str, i: usize) -> f64 {
    // A fixed machine: smooth values of the usual size, zero at the reference position.
    let scale = if name.starts_with("EA") || name.starts_with("EB") || name.starts_with("EC") {
        5e-6
    } else {
        3e-6
    };
    let phase = name.bytes().map(f64::from).sum::<f64>();
    scale * ((phase + i as f64).sin() - phase.sin())
}

fn history(seed: u64, change: Change) -> Vec<Run> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let normal = Normal::new(0.0, 1.0).expect("normal");
    let t0 = chrono::DateTime::parse_from_rfc3339("2026-01-05T06:00:00Z")
        .expect("time")
        .with_timezone(&chrono::Utc);
    (0..RUNS)
        .map(|run| {
            let days = (run as i64 * DAYS_BETWEEN_RUNS) as f64;
            let mut axes = serde_json::Map::new();
            for (axis, names) in AXES {
                let mut errors = serde_json::Map::new();
                for name in names {
                    let (unit, sigma) = if name.starts_with("EA")
                        || name.starts_with("EB")
                        || name.starts_with("EC")
                    {
                        ("rad", ANGULAR_SIGMA_RAD)
                    } else {
                        ("m", LINEAR_SIGMA_M)
                    };
                    let mut values = Vec::new();
                    let mut sigmas = Vec::new();
                    for (i, x) in POSITIONS_M.iter().enumerate() {
                        if i == 0 {
                            values.push(0.0);
                            sigmas.push(0.0);
                            continue;
                        }
                        let mut v = truth_value(name, i) + sigma * normal.sample(&mut rng);
                        if let (Change::ThermalGrowth { per_m_day }, "EXX") = (change, name) {
                            v += per_m_day * (x - POSITIONS_M[0]) * days;
                        }
                        values.push(v);
                        sigmas.push(sigma);
                    }
                    errors.insert(
                        name.into(),
                        json!({"unit": unit, "values": values, "sigma": sigmas, "identifiable": true}),
                    );
                }
                axes.insert(
                    axis.into(),
                    json!({"positions_m": POSITIONS_M, "errors": errors}),
                );
            }
            let mut squareness = serde_json::Map::new();
            for (k, name) in SQUARENESS.iter().enumerate() {
                let mut v = 4e-6 * (k as f64 - 1.0)
                    + SQUARENESS_SIGMA_RAD * normal.sample(&mut rng);
                if let Change::SquarenessStep { from, size_rad } = change {
                    if *name == "EB0Z" && run >= from {
                        v += size_rad;
                    }
                }
                squareness.insert(
                    (*name).into(),
                    json!({"value_rad": v, "sigma_rad": SQUARENESS_SIGMA_RAD, "identifiable": true}),
                );
            }
            let results = json!({
                "format": "geocal-results/1", "kind": "multilateration",
                "session_id": format!("sim-{seed}-{run}"),
                "stations": [{"id": "s1", "position_m": [0, 0, 0], "sigma_m": [1e-6, 1e-6, 1e-6]}],
                "geometric_errors": {"axes": axes, "squareness": squareness},
            });
            Run::from_results(
                &format!("run{:02}", run + 1),
                results,
                MachineIdentity {
                    name: Some("Bridge CMM (simulated history)".into()),
                    serial: Some("SN-1".into()),
                    id: None,
                },
                Some(t0 + chrono::Duration::days(run as i64 * DAYS_BETWEEN_RUNS)),
            )
            .expect("run")
        })
        .collect()
}

const PARAMETERS: usize = 3 * 6 * 3 + 3;

#[test]
fn no_change_raises_no_event_and_false_alarms_stay_within_alpha() {
    let options = TrendOptions::default();
    let seeds = 200u64;
    let mut alarmed = 0usize;
    for seed in 0..seeds {
        let t = trend(&history(seed, Change::None), &options).expect("trend");
        assert_eq!(t.parameters.len(), PARAMETERS);
        if !t.events.is_empty() {
            alarmed += 1;
        }
        if seed == 0 {
            assert!(t.events.is_empty(), "seed 0: {:#?}", t.events);
        }
    }
    let rate = alarmed as f64 / seeds as f64;
    eprintln!(
        "no change: {alarmed} of {seeds} histories of {RUNS} runs × {PARAMETERS} parameters \
         raised an event (rate {rate:.3}; family-wise level {})",
        options.alpha
    );
    // Binomial upper 3σ bound around the level over this many seeds.
    let bound = options.alpha + 3.0 * (options.alpha * (1.0 - options.alpha) / seeds as f64).sqrt();
    assert!(rate <= bound, "false-alarm rate {rate} > {bound}");
}

fn steps_and_drifts(t: &geocal::history::Trend) -> Vec<&geocal::history::trend::Event> {
    t.events
        .iter()
        .filter(|e| e.kind != EventKind::OutsideTolerance)
        .collect()
}

#[test]
fn a_three_sigma_squareness_step_at_run_7_is_found_there_and_named() {
    let step = Change::SquarenessStep {
        from: 6,
        size_rad: 3.0 * SQUARENESS_SIGMA_RAD,
    };
    let options = TrendOptions::default();
    let t = trend(&history(1, step), &options).expect("trend");
    let found = steps_and_drifts(&t);
    assert_eq!(found.len(), 1, "{found:#?}");
    let event = found[0];
    assert_eq!(event.kind, EventKind::Step);
    assert_eq!(event.parameter, "EB0Z");
    assert_eq!((event.run, event.run_label.as_str()), (6, "run07"));
    let size = event.size.expect("size");
    let sigma = event.sigma.expect("sigma");
    assert!(
        (size - 3.0 * SQUARENESS_SIGMA_RAD).abs() < 3.0 * sigma,
        "step {size} ± {sigma}"
    );
    assert!(geocal::history::trend::text(&t).contains("EB0Z"));
    // How often over seeds: found at run 7, and nothing else called a step or drift.
    let seeds = 100u64;
    let (mut exact, mut other) = (0usize, 0usize);
    for seed in 100..100 + seeds {
        let t = trend(&history(seed, step), &options).expect("trend");
        let found = steps_and_drifts(&t);
        if found
            .iter()
            .any(|e| e.kind == EventKind::Step && e.parameter.contains("EB0Z") && e.run == 6)
        {
            exact += 1;
        }
        if found.iter().any(|e| !e.parameter.contains("EB0Z")) {
            other += 1;
        }
    }
    eprintln!(
        "3σ squareness step at run 7: found there in {exact} of {seeds} histories; another \
         parameter called changed in {other}"
    );
    assert!(exact >= 60, "{exact} of {seeds}");
    assert!(other <= 10, "{other} of {seeds}");
}

#[test]
fn a_slow_thermal_growth_of_a_positioning_error_is_a_drift_with_its_rate() {
    // 1 µm/m over the 77 days of the history at the far end: 0.013 µm/m/day.
    let per_m_day = 1e-6 / 77.0;
    let t = trend(
        &history(2, Change::ThermalGrowth { per_m_day }),
        &TrendOptions::default(),
    )
    .expect("trend");
    let found = steps_and_drifts(&t);
    assert!(!found.is_empty(), "no drift found");
    for event in &found {
        assert_eq!(event.kind, EventKind::Drift, "{event:#?}");
        assert!(event.parameter.contains("EXX"), "{event:#?}");
        let parameter = t
            .parameters
            .iter()
            .find(|p| p.id == event.parameter)
            .expect("parameter");
        let x = parameter.x.expect("position");
        let truth = per_m_day * (x - POSITIONS_M[0]);
        let rate = event.rate_per_day.expect("rate");
        let sigma = event.sigma.expect("sigma");
        assert!(
            (rate - truth).abs() < 3.0 * sigma,
            "{}: {rate} ± {sigma} per day, truth {truth}",
            event.parameter
        );
        eprintln!(
            "drift of {} found: {:.4} ± {:.4} µm/day (truth {:.4})",
            event.parameter,
            rate * 1e6,
            sigma * 1e6,
            truth * 1e6
        );
    }
    // The far end grows 1 µm, 5σ: it must be among those found.
    assert!(found.iter().any(|e| e.parameter == "EXX@x=1.300"));
}

#[test]
fn trend_cli_writes_json_and_html_from_a_folder_of_runs() {
    let dir = tempfile::tempdir().expect("tempdir");
    let runs = history(
        3,
        Change::SquarenessStep {
            from: 6,
            size_rad: 3.0 * SQUARENESS_SIGMA_RAD,
        },
    );
    for run in &runs {
        let folder = dir.path().join(&run.label);
        std::fs::create_dir_all(&folder).expect("mkdir");
        std::fs::write(
            folder.join("results.json"),
            serde_json::to_string(&run.results).expect("json"),
        )
        .expect("results");
        std::fs::write(
            folder.join("run-config.toml"),
            "kind = \"multilateration\"\n[machine]\nname = \"Bridge CMM (simulated history)\"\n",
        )
        .expect("config");
    }
    let html = dir.path().join("trend.html");
    let output = Command::new(env!("CARGO_BIN_EXE_geocal"))
        .arg("trend")
        .arg(dir.path())
        .arg("--json")
        .arg("--html")
        .arg(&html)
        .output()
        .expect("geocal trend");
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let trend: Value = serde_json::from_slice(&output.stdout).expect("trend JSON");
    assert_eq!(trend["format"], "geocal-trend/1");
    assert_eq!(trend["runs"].as_array().map(Vec::len), Some(RUNS));
    assert_eq!(trend["machine"]["name"], "Bridge CMM (simulated history)");
    let page = std::fs::read_to_string(&html).expect("html");
    assert!(page.contains("<svg") && page.contains("Events"), "html");
}

/// Run `config_text` (the demo, 5 stations × 100 points: the smallest example plan whose grid
/// the 21-error model can use) into `dir/name`.
fn small_demo_run(dir: &Path, name: &str, config_text: &str) -> std::path::PathBuf {
    let config = dir.join(format!("{name}.toml"));
    std::fs::write(&config, config_text).expect("config");
    let out = dir.join(name);
    let status = Command::new(env!("CARGO_BIN_EXE_geocal"))
        .arg("run")
        .arg(&config)
        .arg("--out")
        .arg(&out)
        .stdout(std::process::Stdio::null())
        .status()
        .expect("geocal run");
    assert!(status.success(), "{name}: geocal run failed");
    out
}

fn compare_json(a: &Path, b: &Path, extra: &[&str]) -> Value {
    let output = Command::new(env!("CARGO_BIN_EXE_geocal"))
        .arg("compare")
        .arg(a)
        .arg(b)
        .arg("--json")
        .args(extra)
        .output()
        .expect("geocal compare");
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    serde_json::from_slice(&output.stdout).expect("compare JSON")
}

#[test]
fn compare_of_demo_runs_sees_noise_as_noise_and_a_squareness_change_as_that() {
    let dir = tempfile::tempdir().expect("tempdir");
    let demo = |extra: &str| format!("{}\n{extra}\n", common::DEMO);
    let a = small_demo_run(dir.path(), "a", &demo("noise_seed = 101"));
    let b = small_demo_run(dir.path(), "b", &demo("noise_seed = 202"));
    let same = compare_json(&a, &b, &[]);
    assert_eq!(same["format"], "geocal-compare/1");
    assert_eq!(same["machine"]["name"], "Bridge CMM 14-24-10 (simulated)");
    let compared = same["compared"].as_u64().expect("compared");
    assert!(compared > 20, "{compared} parameters compared");
    let z: Vec<f64> = same["parameters"]
        .as_array()
        .expect("parameters")
        .iter()
        .filter_map(|p| p["z"].as_f64())
        .collect();
    let rms_z = (z.iter().map(|z| z * z).sum::<f64>() / z.len() as f64).sqrt();
    eprintln!("noise seeds 101 vs 202: {compared} parameters, RMS z {rms_z:.2}");
    assert_eq!(
        same["significant"].as_array().map(Vec::len),
        Some(0),
        "{}",
        same["significant"]
    );
    // The machine's squareness doubled (the same seed draws the same errors, squareness twice
    // as large): the squareness errors change, nothing else.
    let changed_text =
        demo("noise_seed = 303").replace("squareness_rad = 5e-6 }", "squareness_rad = 10e-6 }");
    assert!(changed_text.contains("10e-6"), "the demo's squareness size");
    let c = small_demo_run(dir.path(), "c", &changed_text);
    let html = dir.path().join("compare.html");
    let changed = compare_json(&a, &c, &["--html", html.to_str().expect("utf-8")]);
    let significant: Vec<&str> = changed["significant"]
        .as_array()
        .expect("significant")
        .iter()
        .filter_map(|s| s.as_str())
        .collect();
    eprintln!("squareness ×2: significant {significant:?}");
    assert!(!significant.is_empty());
    assert!(
        significant.iter().all(|id| SQUARENESS.contains(id)),
        "{significant:?}"
    );
    let page = std::fs::read_to_string(&html).expect("html");
    assert!(page.contains("<svg") && page.contains("±2σ"), "html");
    // Another machine is refused, saying why.
    let other = dir.path().join("other.toml");
    std::fs::write(
        &other,
        common::DEMO.replace("Bridge CMM 14-24-10 (simulated)", "Gantry 2"),
    )
    .expect("config");
    let other_out = dir.path().join("other");
    std::fs::create_dir_all(&other_out).expect("mkdir");
    std::fs::copy(b.join("results.json"), other_out.join("results.json")).expect("copy");
    std::fs::copy(&other, other_out.join("run-config.toml")).expect("copy");
    let output = Command::new(env!("CARGO_BIN_EXE_geocal"))
        .arg("compare")
        .arg(&a)
        .arg(&other_out)
        .output()
        .expect("geocal compare");
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(stderr.contains("different machines"), "{stderr}");
}

#[test]
fn every_kinds_parameters_are_compared() {
    let dir = tempfile::tempdir().expect("tempdir");
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("config");
    for (example, expected) in [
        (
            "rotary-sphere.toml",
            &["location[EXOC].value", "motion[*].errors[5]"][..],
        ),
        (
            "probe-install.toml",
            &["parameters[b_offset_rad].value", "parameters[beam_l].value"][..],
        ),
        (
            "hexapod.toml",
            &["hinges[*].base_m[2]", "hinges[*].platform_m[0]"][..],
        ),
        (
            "rotary-tracer.toml",
            &[
                "rotary.steps[*].error_rad",
                "rotary.axis_point_m[0]",
                "geometric_errors.squareness.EB0Z.value_rad",
            ][..],
        ),
    ] {
        let text = std::fs::read_to_string(root.join(example)).expect("example");
        let out = small_demo_run(dir.path(), example.trim_end_matches(".toml"), &text);
        // A run compared with itself: every parameter found, none changed.
        let c = compare_json(&out, &out, &[]);
        let curves: Vec<&str> = c["parameters"]
            .as_array()
            .expect("parameters")
            .iter()
            .filter_map(|p| p["curve"].as_str())
            .collect();
        for curve in expected {
            assert!(
                curves.contains(curve),
                "{example}: no {curve} in {curves:?}"
            );
        }
        assert_eq!(
            c["significant"].as_array().map(Vec::len),
            Some(0),
            "{example}"
        );
        eprintln!("{example}: {} parameters", c["compared"]);
    }
}
