//! The misfit flag: when a fit's χ²/dof is improbable for its degrees of freedom, the results
//! (`misfit`), the text output and the report say the σ are not trustworthy, give them scaled
//! by √(χ²/dof) and point to `geocal diagnose`; never on a clean session. Every kind.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use geocal::kinds::registry::solve_session;
use geocal::method::{Results, SolveSettings};
use geocal::session::read_session;
use geocal::solve::misfit::Misfit;

fn geocal() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_geocal"));
    c.stdin(Stdio::null());
    c
}

fn config(name: &str) -> String {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("config")
        .join(name);
    std::fs::read_to_string(&path).expect("config")
}

/// `geocal run` of this configuration text; the run directory.
fn run(text: &str, dir: &Path, name: &str) -> PathBuf {
    let config = dir.join(format!("{name}.toml"));
    std::fs::write(&config, text).expect("config");
    let out_dir = dir.join(name);
    let out = geocal()
        .arg("run")
        .arg(&config)
        .arg("--out")
        .arg(&out_dir)
        .output()
        .expect("geocal run");
    assert!(
        out.status.success(),
        "{name}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    out_dir
}

fn misfit_of(results: &serde_json::Value) -> Option<Misfit> {
    results
        .get("misfit")
        .map(|m| serde_json::from_value(m.clone()).expect("misfit parses"))
}

/// χ²/dof of any kind's results.
fn chi2_per_dof(results: &serde_json::Value) -> f64 {
    match results.get("chi2_per_dof") {
        Some(v) => v.as_f64().expect("chi2_per_dof"),
        None => results["chi2"].as_f64().expect("chi2") / results["dof"].as_f64().expect("dof"),
    }
}

/// The session solved as recorded, and with every device's declared noise 10 times smaller
/// than the noise the simulator drew: the same residuals then weigh 100 times more.
fn clean_and_overconfident(run_dir: &Path) -> (Results, Results) {
    let mut session = read_session(&run_dir.join("session.mcap")).expect("session");
    let clean = solve_session(&session, &SolveSettings::default()).expect("clean solve");
    for device in &mut session.header.devices {
        device.noise_m = device.noise_m.map(|n| n / 10.0);
        device.noise_ppm = device.noise_ppm.map(|n| n / 10.0);
        for key in ["noise_rad", "encoder_noise_m"] {
            if let Some(n) = device.extra.get_mut(key).and_then(|v| v.as_f64()) {
                device.extra.insert(key.into(), serde_json::json!(n / 10.0));
            }
        }
    }
    let tight = solve_session(&session, &SolveSettings::default()).expect("overconfident solve");
    (clean, tight)
}

/// Every kind: no flag on its clean simulated session; flagged, with σ scaled by about 10 ×
/// the clean √(χ²/dof), when the declared noise claims 10 times too much.
#[test]
fn every_kind_is_flagged_only_when_its_fit_is_improbable() {
    let dir = tempfile::tempdir().expect("tempdir");
    let demo = config("demo-multilateration.toml")
        .replace("count = 5 }", "count = 3 }")
        .replace("count = 4 }", "count = 3 }");
    for (name, text) in [
        ("multilateration", demo),
        ("rotary_tracer", config("rotary-tracer.toml")),
        ("rotary_sphere", config("rotary-sphere.toml")),
        ("probe_install", config("probe-install.toml")),
        ("hexapod", config("hexapod.toml")),
    ] {
        let run_dir = run(&text, dir.path(), name);
        let (clean, tight) = clean_and_overconfident(&run_dir);
        let clean_json = clean.to_json_value().expect("json");
        let tight_json = tight.to_json_value().expect("json");
        assert_eq!(clean_json["kind"], name);
        assert!(
            misfit_of(&clean_json).is_none(),
            "{name}: clean χ²/dof {} flagged",
            chi2_per_dof(&clean_json)
        );
        assert!(!clean.report().contains("MISFIT"), "{name}");
        let misfit = misfit_of(&tight_json)
            .unwrap_or_else(|| panic!("{name}: χ²/dof {} not flagged", chi2_per_dof(&tight_json)));
        let expected = 10.0 * chi2_per_dof(&clean_json).sqrt();
        println!(
            "{name}: clean χ²/dof {:.3}; noise declared 10× too small: χ²/dof {:.1}, p {:.1e}, \
             σ scale {:.2} (10 × clean √(χ²/dof) = {expected:.2})",
            chi2_per_dof(&clean_json),
            misfit.chi2_per_dof,
            misfit.p,
            misfit.sigma_scale
        );
        assert!(misfit.p < 1e-3, "{name}: {misfit:?}");
        assert!(
            (misfit.sigma_scale / expected - 1.0).abs() < 0.35,
            "{name}: σ scale {} for {expected}",
            misfit.sigma_scale
        );
        let text = tight.report();
        assert!(text.contains("MISFIT"), "{name}: {text}");
        assert!(text.contains("geocal diagnose"), "{name}");
        assert!(
            text.contains(&format!("× {:.2}", misfit.sigma_scale)),
            "{name}: {text}"
        );
    }
}

/// The case: a tracer pivot eccentricity on the rotary table, which turns with the
/// table and which no model here fits. The step-angle σ were the noise model's, far too small
/// by their own residuals: the results, `geocal solve` and `geocal report` now say so.
#[test]
fn rotary_tracer_with_an_eccentric_pivot_is_flagged_everywhere() {
    let dir = tempfile::tempdir().expect("tempdir");
    let text = format!(
        "{}\n[sim.effects]\ntracer_eccentricity = {{ enabled = true, size_m = 2e-5, z_size_m = 1e-5 }}\n",
        config("rotary-tracer.toml")
    );
    let run_dir = run(&text, dir.path(), "eccentric");
    let results: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(run_dir.join("results.json")).expect("results"),
    )
    .expect("results JSON");
    let misfit = misfit_of(&results).expect("flagged");
    println!(
        "eccentric pivot: χ²/dof {:.1} over {} dof, p {:.1e}, σ scale {:.2}",
        misfit.chi2_per_dof, misfit.dof, misfit.p, misfit.sigma_scale
    );
    assert!(misfit.chi2_per_dof > 5.0, "{misfit:?}");

    let out = geocal()
        .arg("solve")
        .arg(run_dir.join("session.mcap"))
        .output()
        .expect("geocal solve");
    assert!(out.status.success());
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("MISFIT"), "{text}");
    assert!(text.contains("geocal diagnose"), "{text}");
    // A step angle's σ, and beside it the same scaled.
    let step = &results["rotary"]["steps"][1];
    let sigma = step["sigma_rad"].as_f64().expect("sigma");
    let row = text
        .lines()
        .find(|l| l.contains("rotary.steps[1].sigma_rad"))
        .unwrap_or_else(|| panic!("no step σ row: {text}"));
    assert!(row.contains(&format!("{sigma:.4e}")), "{row}");
    assert!(
        row.contains(&format!("{:.4e}", sigma * misfit.sigma_scale)),
        "{row}"
    );

    let report = dir.path().join("report.md");
    let out = geocal()
        .arg("report")
        .arg(&run_dir)
        .arg("--out")
        .arg(&report)
        .arg("--format")
        .arg("md")
        .output()
        .expect("geocal report");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report = std::fs::read_to_string(&report).expect("report");
    assert!(
        report.contains("Misfit: the σ are not trustworthy"),
        "{report}"
    );
    assert!(report.contains("geocal diagnose"));
}

/// Outside sessions (tests/data/outside, recorded by another tool's simulator): the clean one
/// is not flagged, the one with an unmodelled reversal (backlash) on x is.
#[test]
fn outside_sessions_flag_the_unmodelled_reversal_only() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/outside");
    let solve = |name: &str| {
        let session = read_session(&dir.join(name).join("session.mcap")).expect("session");
        let results = solve_session(&session, &SolveSettings::default()).expect("solve");
        results.to_json_value().expect("json")
    };
    let clean = solve("outside-clean-7");
    assert!(
        misfit_of(&clean).is_none(),
        "clean: χ²/dof {}",
        chi2_per_dof(&clean)
    );
    let reversal = solve("outside-reversal-8");
    let misfit = misfit_of(&reversal).expect("the reversal's misfit is flagged");
    println!(
        "outside: clean χ²/dof {:.3}; reversal χ²/dof {:.1} over {} dof, σ scale {:.1}",
        chi2_per_dof(&clean),
        misfit.chi2_per_dof,
        misfit.dof,
        misfit.sigma_scale
    );
    assert!(misfit.chi2_per_dof > 10.0, "{misfit:?}");
}
