//! The operator's console in a real browser: Debian's chromium, headless, driven by Python
//! `playwright` (from PyPI, pointed at the system chromium) against two daemons — one on
//! loopback without a token with a plan library and a schedule, one with a token. The script
//! (`tests/python/console_browser.py`) submits the demo from the library and watches its
//! progress move to `succeeded`, opens its report, runs it twice more and reads the machine's
//! trend, answers a HIL run's operator prompts by clicking Continue, logs in to the token
//! daemon, has a page of another origin POST to both daemons (refused), checks that a phone's
//! viewport never scrolls sideways, and takes a screenshot of each page.

use crate::common;

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Instant;

const TOKEN: &str = "console-test-token-0123456789abcdef";

fn chromium() -> PathBuf {
    for name in ["chromium", "chromium-browser"] {
        if let Ok(out) = Command::new("which").arg(name).output() {
            let path = String::from_utf8_lossy(&out.stdout).trim().to_owned();
            if out.status.success() && !path.is_empty() {
                return PathBuf::from(path);
            }
        }
    }
    panic!("the console test needs `chromium` on PATH (Debian: apt-get install -y chromium)");
}

struct Daemon(Child, String);

impl Drop for Daemon {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn start(config: &Path, extra: &[&str]) -> Daemon {
    let mut child = Command::new(env!("CARGO_BIN_EXE_geocal"))
        .arg("serve")
        .arg("--config")
        .arg(config)
        .args(["--listen", "127.0.0.1:0", "--live", "off"])
        .args(extra)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("spawn geocal serve");
    let (url, _) = common::daemon_banner(&mut child);
    Daemon(child, url)
}

/// The demo at 300 times real speed, shrunk to 4 stations, 4 x 4 x 4 points and one pass:
/// about the smallest run whose results hold the 21 geometric errors (the trend's
/// parameters; fewer grid positions leave more unknowns than half the equations).
fn trend_demo() -> String {
    let cut = common::DEMO
        .find("[[plan.stations]]\nid = \"s5\"")
        .expect("station s5");
    let sim = common::DEMO.find("\n[sim]").expect("[sim]");
    let text = format!("{}{}", &common::DEMO[..cut], &common::DEMO[sim..])
        .replace("count = 5 }", "count = 4 }")
        .replace(
            "passes = [\"forward\", \"backward\"]",
            "passes = [\"forward\"]",
        );
    assert!(text.contains("passes = [\"forward\"]") && !text.contains("count = 5"));
    format!("{text}\npace = 300.0\n")
}

#[test]
fn the_console_runs_watches_and_answers_a_calibration_in_a_browser() {
    if !common::python_module_available("playwright.sync_api", "playwright") {
        return;
    }
    let started = Instant::now();
    let dir = tempfile::tempdir().expect("tempdir");
    let library = dir.path().join("plans");
    std::fs::create_dir(&library).expect("library");
    // Three runs of one machine, each with its own measurement noise (the machine's errors
    // are drawn from `seed`, the same in all three), so the trend has scatter to show; the
    // daemon's tolerances give its parameters a tolerance band.
    std::fs::write(library.join("demo.toml"), trend_demo()).expect("demo plan");
    for (name, seed) in [("demo-2.toml", 202), ("demo-3.toml", 303)] {
        std::fs::write(
            library.join(name),
            format!("{}noise_seed = {seed}\n", trend_demo()),
        )
        .expect("demo plan");
    }
    let hil = dir.path().join("hil-prompts.toml");
    std::fs::write(
        &hil,
        format!(
            "{}\n[operator]\nrehearse = true\n",
            common::generous_timeouts(&common::hil_config(""))
        ),
    )
    .expect("hil plan");
    let config = dir.path().join("serve.toml");
    std::fs::write(
        &config,
        format!(
            "data_dir = \"{}\"\nplan_library = \"plans\"\n\n\
             [history]\ntolerance_m = 5e-7\ntolerance_rad = 5e-7\n\n[[schedule]]\nname = \"nightly\"\n\
             cron = \"30 2 * * *\"\nplan = \"plans/demo.toml\"\ntime_zone = \"Europe/Berlin\"\n",
            dir.path().join("data").display()
        ),
    )
    .expect("config");
    let token_file = dir.path().join("token");
    std::fs::write(&token_file, TOKEN).expect("token");
    {
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&token_file, std::fs::Permissions::from_mode(0o600))
            .expect("chmod");
    }
    let token_config = dir.path().join("serve-token.toml");
    std::fs::write(
        &token_config,
        format!(
            "data_dir = \"{}\"\nplan_library = \"plans\"\n",
            dir.path().join("data-token").display()
        ),
    )
    .expect("token config");
    let open = start(&config, &[]);
    let guarded = start(
        &token_config,
        &["--token-file", token_file.to_str().expect("utf-8")],
    );
    let shots = Path::new(env!("CARGO_TARGET_TMPDIR")).join("console-screenshots");
    std::fs::create_dir_all(&shots).expect("screenshot dir");
    let script = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/python/console_browser.py"
    );
    let output = Command::new("python3")
        .arg(script)
        .args([&open.1, &guarded.1, TOKEN])
        .arg(&hil)
        .arg(&shots)
        .arg(chromium())
        .output()
        .expect("python3");
    let stdout = String::from_utf8_lossy(&output.stdout);
    println!("{stdout}");
    assert!(
        output.status.success(),
        "the browser script failed\nstdout:\n{stdout}\nstderr:\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    assert!(stdout.contains("console: all checks passed"), "{stdout}");
    for page in [
        "now",
        "prompts",
        "jobs",
        "job",
        "machine",
        "schedules",
        "login",
        "phone-jobs",
    ] {
        let png = std::fs::read(shots.join(format!("{page}.png"))).expect("screenshot");
        assert!(
            png.starts_with(b"\x89PNG") && png.len() > 5_000,
            "{page}.png"
        );
    }
    println!(
        "screenshots in {}; {:.0} s",
        shots.display(),
        started.elapsed().as_secs_f64()
    );
}

/// `geocal client … --follow` in a terminal ends with a short summary: state, time, where the
/// results, report and session are, the other files, the error, the job's page.
#[test]
fn the_follow_summary_says_state_time_and_where_the_results_are() {
    let job: geocal::serve::api::JobView = serde_json::from_value(serde_json::json!({
        "id": 7, "kind": "multilateration", "type": "run", "state": "succeeded",
        "progress": {"done": 256, "total": 256, "station": null, "eta_s": null, "last_faults": []},
        "submitted_at": "2026-11-28T10:00:00Z", "started_at": "2026-11-28T10:00:01Z",
        "finished_at": "2026-11-28T10:01:13.5Z", "submitted_by": "127.0.0.1:5000",
        "config_sha256": null, "source_job": null, "error": null, "resume": false,
        "files": [
            {"name": "results.json", "bytes": 10, "sha256": "00"},
            {"name": "report.html", "bytes": 10, "sha256": "00"},
            {"name": "job.log", "bytes": 10, "sha256": "00"}
        ]
    }))
    .expect("a job");
    let text = geocal::serve::client::summary(&job, "http://127.0.0.1:7878/");
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(
        lines[0],
        "job 7 succeeded in 1 min 12 s: multilateration run (256/256 points), submitted by 127.0.0.1:5000",
        "{text}"
    );
    assert!(
        text.contains("http://127.0.0.1:7878/v1/jobs/7/results  (geocal client fetch 7 results)")
    );
    assert!(text.contains("http://127.0.0.1:7878/v1/jobs/7/report  (geocal client fetch 7 report)"));
    assert!(!text.contains("session"), "no session was left: {text}");
    assert!(text.contains("files:   job.log"), "{text}");
    assert!(text.contains("http://127.0.0.1:7878/#/jobs/7"), "{text}");
    assert!(lines.len() <= 6, "short: {text}");
}
