//! Durability: a simulated run (paced to 300x real time) is killed with SIGKILL at a seeded
//! random moment, then `geocal run --resume DIR` completes it. The killed file must still
//! read; every message it holds must appear unchanged in the final file; the results must
//! recover the truth as an unbroken run does, and agree with the unbroken run's. A run
//! cancelled through its control (the daemon's cancel, a progress callback's) stops at the
//! point it was cancelled at, for every kind, simulated devices included.

mod common;

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::Duration;

use common::{assert_recovers_truth, run_with_truth, small_demo};
use geocal::method::multilateration::MultilaterationResults;
use geocal::session::messages::RunEvent;
use geocal::session::reader::{read_session, read_session_raw, Completeness, Session};
use rand::{Rng, SeedableRng};

const PACE: &str = "\npace = 300.0\n";

fn geocal() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_geocal"));
    c.stdout(Stdio::null()).stderr(Stdio::piped());
    c
}

/// Start `geocal` with `args` and SIGKILL it after `after`.
fn run_and_kill(args: &[&str], after: Duration) {
    let mut child = geocal().args(args).spawn().expect("spawn geocal");
    std::thread::sleep(after);
    match child.try_wait().expect("child status") {
        Some(status) => panic!("geocal finished ({status}) before the kill at {after:?}"),
        None => child.kill().expect("SIGKILL"),
    }
    child.wait().expect("reap");
}

fn resume(dir: &Path) {
    let out = geocal()
        .args(["run", "--resume"])
        .arg(dir)
        .arg("--truth")
        .arg(dir.join("truth.json"))
        .output()
        .expect("resume");
    assert!(
        out.status.success(),
        "resume failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// The killed file (read linearly, up to its last complete chunk) is a prefix of the final
/// file: same messages, payloads and times, in the same order.
fn assert_prefix(killed: &Path, final_session: &Session, final_path: &Path) -> u64 {
    let truncated = read_session(killed).expect("the killed file reads");
    let Completeness::Truncated { messages_read, .. } = truncated.completeness else {
        panic!("a killed run's file cannot be complete");
    };
    // Decoded by the session reader (indexed for the finished file).
    for (id, samples) in &truncated.tracers {
        assert_eq!(
            &final_session.tracers[id][..samples.len()],
            &samples[..],
            "tracer {id}"
        );
    }
    for (id, samples) in &truncated.env {
        assert_eq!(
            &final_session.env[id][..samples.len()],
            &samples[..],
            "env {id}"
        );
    }
    let n = truncated.events.len();
    assert_eq!(&final_session.events[..n], &truncated.events[..]);
    // Byte for byte, in file order.
    let (_, raw_killed) = read_session_raw(killed).expect("raw");
    let (_, raw_final) = read_session_raw(final_path).expect("raw");
    assert_eq!(raw_killed.len() as u64, messages_read);
    for (a, b) in raw_killed.iter().zip(&raw_final) {
        assert_eq!(
            (&a.channel.topic, a.log_time_ns, a.publish_time_ns, &a.data),
            (&b.channel.topic, b.log_time_ns, b.publish_time_ns, &b.data)
        );
    }
    messages_read
}

/// Points and stations of two solutions differ by no more than their combined sigmas allow.
fn assert_agree(a: &MultilaterationResults, b: &MultilaterationResults) -> (f64, f64) {
    let mut z = vec![];
    for (p, q) in a.points.iter().zip(&b.points) {
        assert_eq!((p.point, &p.target), (q.point, &q.target));
        for k in 0..3 {
            z.push((p.actual_m[k] - q.actual_m[k]) / p.sigma_m[k].hypot(q.sigma_m[k]));
        }
    }
    for (s, t) in a.stations.iter().zip(&b.stations) {
        assert_eq!(s.id, t.id);
        for k in 0..3 {
            z.push((s.position_m[k] - t.position_m[k]) / s.sigma_m[k].hypot(t.sigma_m[k]));
        }
    }
    let rms = (z.iter().map(|v| v * v).sum::<f64>() / z.len() as f64).sqrt();
    let max = z.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    // Independent solutions would give standard normal z; these share the samples recorded
    // before the kill. The z are strongly correlated (a station's error moves all its
    // points), worth about 10 independent values: RMS > 2 has p ~ 2e-5 (chi2, 10 dof), and
    // 4.5 sigma anywhere p < 1e-3. A mishandled resume is off by micrometres, 10-50 sigma.
    assert!(
        rms <= 2.0 && max <= 4.5,
        "RMS {rms:.2} sigma, max {max:.2} sigma"
    );
    (rms, max)
}

#[test]
fn killed_runs_resume_and_match_an_unbroken_run() {
    let config = format!("{}{PACE}", small_demo());
    let unbroken_dir = tempfile::tempdir().expect("tempdir");
    // Pacing changes nothing but wall time: the unbroken reference runs unpaced, in-process.
    let (unbroken, truth) = run_with_truth(&small_demo(), unbroken_dir.path());
    let unbroken = unbroken
        .results
        .multilateration()
        .expect("tracer results")
        .clone();
    assert_recovers_truth(&unbroken, &truth);

    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(4);
    for round in 0..3 {
        let dir = tempfile::tempdir().expect("tempdir");
        let config_path = dir.path().join("in.toml");
        std::fs::write(&config_path, &config).expect("config");
        let out = dir.path().join("run");
        let out_s = out.to_str().expect("utf-8 path");
        // The paced run takes ~3.3 s of wall time.
        let kill_at = Duration::from_secs_f64(rng.random_range(0.4..2.8));
        run_and_kill(
            &["run", config_path.to_str().expect("path"), "--out", out_s],
            kill_at,
        );
        let killed = dir.path().join("killed.mcap");
        std::fs::copy(out.join("session.mcap"), &killed).expect("copy the killed file");
        let mut killed_files = vec![killed];
        if round == 2 {
            // Kill the resumed run too: the second resume must pick up both.
            let again = Duration::from_secs_f64(rng.random_range(0.3..1.0));
            run_and_kill(&["run", "--resume", out_s], again);
            let killed2 = dir.path().join("killed2.mcap");
            let current = out.join("session.mcap");
            if read_session(&current).is_ok() {
                std::fs::copy(&current, &killed2).expect("copy");
                killed_files.push(killed2);
            }
        }
        resume(&out);

        let final_path = out.join("session.mcap");
        let session = read_session(&final_path).expect("final session");
        assert!(session.completeness.is_complete());
        let kept: Vec<u64> = killed_files
            .iter()
            .map(|k| assert_prefix(k, &session, &final_path))
            .collect();
        let resumes: Vec<u64> = session
            .events
            .iter()
            .filter_map(|e| match e.msg {
                RunEvent::Resume { messages_kept, .. } => Some(messages_kept),
                _ => None,
            })
            .collect();
        assert_eq!(
            resumes.first(),
            kept.first(),
            "first resume kept every message"
        );
        let leftovers: Vec<_> = std::fs::read_dir(&out)
            .expect("dir")
            .filter_map(|e| e.ok())
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .filter(|n| n.contains("interrupted"))
            .collect();
        assert!(leftovers.is_empty(), "{leftovers:?}");

        let results = geocal::kinds::solve_file(&final_path, &Default::default()).expect("solve");
        let resumed = results.multilateration().expect("tracer results");
        let truth: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.join("truth.json")).expect("truth"))
                .expect("truth json");
        assert_recovers_truth(resumed, &truth);
        assert_eq!(
            resumed.extraction.windows_used,
            unbroken.extraction.windows_used
        );
        let (rms, max) = assert_agree(resumed, &unbroken);
        let samples = session.tracers.values().map(Vec::len).sum::<usize>();
        println!(
            "round {round}: killed at {kill_at:?}, kept {kept:?} messages, resumes {resumes:?}, \
             {samples} samples, windows repeated {}, vs unbroken: RMS {rms:.2} sigma, max {max:.2} sigma",
            resumed.extraction.windows_repeated
        );
    }
}

#[test]
fn a_cancelled_run_stops_at_the_point_it_was_cancelled_at_for_every_kind() {
    use std::sync::{Arc, Mutex};

    use geocal::kinds::Registry;
    use geocal::run::control::RunControl;
    use geocal::run::RunOptions;

    let configs = Path::new(env!("CARGO_MANIFEST_DIR")).join("config");
    let mut kinds = Vec::new();
    for entry in std::fs::read_dir(&configs).expect("config/") {
        let config = entry.expect("entry").path();
        if config.extension().is_none_or(|e| e != "toml") {
            continue;
        }
        let dir = tempfile::tempdir().expect("tempdir");
        let reported = Arc::new(Mutex::new(Vec::new()));
        let cancel = tokio_util::sync::CancellationToken::new();
        let (seen, token) = (reported.clone(), cancel.clone());
        let control = RunControl {
            cancel: cancel.clone(),
            progress: Some(geocal::progress_sink::ProgressSink::new(
                move |done: u64, _total: u64| {
                    seen.lock().expect("progress").push(done);
                    if done == 3 {
                        token.cancel();
                    }
                },
            )),
            ..Default::default()
        };
        let options = RunOptions {
            out_dir: dir.path().join("run"),
            truth: None,
            progress: false,
            settings: Default::default(),
            control,
        };
        let kind = Registry::standard().of_config(&config).expect("kind");
        let outcome = kind.run(&config, &options, &Default::default());
        let error = match outcome {
            Ok(_) => panic!("{}: ran to its end after a cancel", config.display()),
            Err(e) => format!("{e:#}"),
        };
        assert!(
            error.contains("run cancelled"),
            "{}: {error}",
            config.display()
        );
        let reported = reported.lock().expect("progress").clone();
        assert_eq!(reported, [1, 2, 3], "{}", config.display());
        assert!(dir.path().join("run/session.mcap").is_file());
        kinds.push(kind.name());
    }
    kinds.sort_unstable();
    assert_eq!(
        kinds,
        [
            "hexapod",
            "multilateration",
            "probe_install",
            "rotary_sphere",
            "rotary_tracer"
        ]
    );
}
