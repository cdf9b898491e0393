//! The command line as a user drives it: run, solve (replay) and check.

use std::path::Path;
use std::process::Command;

use crate::common;

use common::DEMO;

fn geocal(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_geocal"))
        .args(args)
        .output()
        .expect("run geocal")
}

/// Run geocal and require success, showing its stderr otherwise.
fn geocal_ok(args: &[&str]) -> std::process::Output {
    let out = geocal(args);
    assert!(
        out.status.success(),
        "geocal {} failed: {}",
        args.join(" "),
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// `geocal run CONFIG --out DIR --json`; returns its output and the recorded session.
fn run_json(config: &Path, out: &Path) -> (std::process::Output, std::path::PathBuf) {
    let run = geocal_ok(&[
        "run",
        config.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--json",
    ]);
    (run, out.join("session.mcap"))
}

/// The demo shrunk to 4 stations x 3x3x2 points, one pass, so the CLI test stays quick.
fn small_config(dir: &Path) -> std::path::PathBuf {
    let text = common::small_demo().replace(
        "passes = [\"forward\", \"backward\"]",
        "passes = [\"forward\"]",
    );
    let path = dir.join("small.toml");
    std::fs::write(&path, text).expect("write config");
    path
}

#[test]
fn run_then_solve_prints_identical_json() {
    let dir = tempfile::tempdir().expect("tempdir");
    let config = small_config(dir.path());
    let out = dir.path().join("out");
    let (run, session) = run_json(&config, &out);
    let solve = geocal_ok(&["solve", session.to_str().unwrap(), "--json"]);
    assert_eq!(run.stdout, solve.stdout);
    let results: serde_json::Value = serde_json::from_slice(&solve.stdout).expect("json");
    assert_eq!(results["format"], "geocal-results/1");
    assert_eq!(results["points"].as_array().map(Vec::len), Some(18));
    // The text report names the stations and the volumetric error.
    let text = geocal_ok(&["solve", session.to_str().unwrap()]);
    let text = String::from_utf8_lossy(&text.stdout);
    assert!(
        text.contains("s4") && text.contains("volumetric error"),
        "{text}"
    );
}

#[test]
fn check_reports_a_bad_config_and_exits_nonzero() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("bad.toml");
    std::fs::write(&path, DEMO.replace("feed_m_s = 0.3", "feed_m_s = -1.0")).expect("write");
    let out = geocal(&["check", path.to_str().unwrap()]);
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("bad.toml")
            && stderr.contains("devices.machine.feed_m_s")
            && stderr.contains("positive"),
        "{stderr}"
    );
    geocal_ok(&[
        "check",
        concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/config/demo-multilateration.toml"
        ),
    ]);
}

#[test]
fn solve_of_a_missing_or_bad_file_is_a_clear_error() {
    let dir = tempfile::tempdir().expect("tempdir");
    let junk = dir.path().join("junk.mcap");
    std::fs::write(&junk, b"this is not an mcap file at all").expect("write");
    let out = geocal(&["solve", junk.to_str().unwrap()]);
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("junk.mcap"), "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
}

#[test]
fn diagnose_prints_the_diagnosis_format() {
    let dir = tempfile::tempdir().expect("tempdir");
    let config = dir.path().join("diag.toml");
    std::fs::write(&config, common::diagnose_demo()).expect("write config");
    let out = dir.path().join("out");
    let (_, session) = run_json(&config, &out);
    let diag = geocal_ok(&["diagnose", session.to_str().unwrap(), "--json"]);
    let d: serde_json::Value = serde_json::from_slice(&diag.stdout).expect("json");
    common::assert_diagnosis_format(&d);
    // Effect-free simulated data: nothing selected, nothing unexplained.
    assert_eq!(d["selected"], serde_json::json!([]), "{d}");
    assert_eq!(d["unexplained"], false, "{d}");
    let text = geocal_ok(&["diagnose", session.to_str().unwrap()]);
    assert!(!text.stdout.is_empty());
}

#[test]
fn yes_is_a_flag_not_configuration_and_a_resume_takes_it() {
    let dir = tempfile::tempdir().expect("tempdir");
    let config = small_config(dir.path());
    let config = config.to_str().unwrap();
    let out = dir.path().join("out");
    let out = out.to_str().unwrap();
    geocal_ok(&["run", config, "--out", out, "--yes", "--json"]);
    let stored = std::fs::read_to_string(Path::new(out).join("run-config.toml")).expect("stored");
    assert!(!stored.contains("piped_stdin"), "{stored}");
    // The stored configuration equals the given one, so both are accepted on resume (the run
    // had finished: the resume copies its session and solves it). Its log has no colour
    // codes on a pipe.
    let resumed = Command::new(env!("CARGO_BIN_EXE_geocal"))
        .args(["run", config, "--resume", out, "--yes", "--json"])
        .env("RUST_LOG", "info")
        .output()
        .expect("geocal run --resume");
    let stderr = String::from_utf8_lossy(&resumed.stderr);
    assert!(resumed.status.success(), "{stderr}");
    assert!(stderr.contains("resuming"), "a log line: {stderr}");
    assert!(
        !stderr.contains('\u{1b}'),
        "colour codes on a pipe: {stderr:?}"
    );
}

#[test]
fn output_to_a_closed_pipe_ends_quietly() {
    // `geocal check X | head -0`: the reader is gone before geocal writes.
    let mut child = Command::new(env!("CARGO_BIN_EXE_geocal"))
        .args([
            "check",
            concat!(
                env!("CARGO_MANIFEST_DIR"),
                "/config/demo-multilateration.toml"
            ),
        ])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("spawn geocal check");
    drop(child.stdout.take());
    let output = child.wait_with_output().expect("geocal check ends");
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert!(output.status.success(), "{:?}: {stderr}", output.status);
}
