//! `geocal serve` as outside tools use it: a real HTTP client (reqwest; and Python `requests`
//! as an outside peer) submits plans, follows them on the API and the event stream, cancels,
//! resumes after a kill -9, and fetches what the jobs left; bad requests are clear 4xx that
//! write nothing.

use crate::common;

use std::io::{BufRead, BufReader, Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use reqwest::blocking::Client;
use reqwest::StatusCode;
use serde_json::Value;

/// Simulated time runs this many times faster than wall time: a small demo takes seconds.
const PACE: &str = "\npace = 300.0\n";
/// Long enough for any job here on a loaded 2-core machine.
const JOB_TIMEOUT: Duration = Duration::from_secs(600);

struct Daemon {
    child: Child,
    url: String,
    data_dir: PathBuf,
    /// The Foxglove live view's `ws://` address, when it runs.
    live: Option<String>,
}

impl Daemon {
    fn start(data_dir: &Path, extra: &[&str]) -> Daemon {
        Daemon::start_with_env(data_dir, extra, &[])
    }

    /// With `env`; through a shell that sets WATCHDOG_PID to the daemon's own pid (as systemd
    /// does) and execs it.
    fn start_with_env(data_dir: &Path, extra: &[&str], env: &[(&str, &str)]) -> Daemon {
        let mut command = if env.is_empty() {
            Command::new(env!("CARGO_BIN_EXE_geocal"))
        } else {
            let mut c = Command::new("sh");
            c.args([
                "-c",
                "WATCHDOG_PID=$$ exec \"$0\" \"$@\"",
                env!("CARGO_BIN_EXE_geocal"),
            ]);
            c
        };
        let mut child = command
            .envs(env.iter().copied())
            .arg("serve")
            .arg("--data-dir")
            .arg(data_dir)
            .args(["--listen", "127.0.0.1:0"])
            // Tests run side by side: no fixed live-view port unless a test asks for one.
            .args(if extra.contains(&"--live") {
                &[][..]
            } else {
                &["--live", "off"][..]
            })
            .args(extra)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .expect("spawn geocal serve");
        let (url, live) = common::daemon_banner(&mut child);
        Daemon {
            child,
            url,
            data_dir: data_dir.to_owned(),
            live,
        }
    }

    fn at(&self, path: &str) -> String {
        format!("{}{path}", self.url)
    }

    fn kill_9(&mut self) {
        self.child.kill().expect("SIGKILL");
        self.child.wait().expect("reap");
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A daemon on a fresh data dir, and a client for it.
fn started() -> (tempfile::TempDir, Daemon, Client) {
    let dir = tempfile::tempdir().expect("tempdir");
    let daemon = Daemon::start(&dir.path().join("data"), &[]);
    (dir, daemon, http())
}

fn http() -> Client {
    Client::builder()
        .timeout(None)
        .build()
        .expect("http client")
}

fn submit(client: &Client, daemon: &Daemon, toml: &str) -> i64 {
    let response = client
        .post(daemon.at("/v1/jobs"))
        .header("Content-Type", "application/toml")
        .body(toml.to_owned())
        .send()
        .expect("POST /v1/jobs");
    let status = response.status();
    let body: Value = response.json().expect("json");
    assert_eq!(status, StatusCode::CREATED, "{body}");
    body["id"].as_i64().expect("id")
}

fn job(client: &Client, daemon: &Daemon, id: i64) -> Value {
    client
        .get(daemon.at(&format!("/v1/jobs/{id}")))
        .send()
        .expect("GET job")
        .json()
        .expect("job json")
}

fn wait_for(client: &Client, daemon: &Daemon, id: i64, states: &[&str]) -> Value {
    let start = Instant::now();
    loop {
        let j = job(client, daemon, id);
        if states.contains(&j["state"].as_str().unwrap_or("")) {
            return j;
        }
        assert!(
            start.elapsed() < JOB_TIMEOUT,
            "job {id} never reached {states:?}: {j}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Wait until job `id` has measured at least `done` points.
fn wait_for_progress(client: &Client, daemon: &Daemon, id: i64, done: u64) {
    let start = Instant::now();
    while job(client, daemon, id)["progress"]["done"]
        .as_u64()
        .unwrap_or(0)
        < done
    {
        assert!(
            start.elapsed() < JOB_TIMEOUT,
            "job {id} never reached {done} points"
        );
        std::thread::sleep(Duration::from_millis(10));
    }
}

fn post(client: &Client, daemon: &Daemon, path: &str) -> (StatusCode, Value) {
    let response = client.post(daemon.at(path)).send().expect("POST");
    let status = response.status();
    (status, response.json().unwrap_or(Value::Null))
}

fn fetch(client: &Client, daemon: &Daemon, path: &str) -> Vec<u8> {
    let response = client.get(daemon.at(path)).send().expect("GET");
    assert_eq!(response.status(), StatusCode::OK, "{path}");
    response.bytes().expect("body").to_vec()
}

/// The events on `/v1/events` until a job ends, collected on a thread of its own.
fn follow_events(daemon: &Daemon) -> std::thread::JoinHandle<Vec<(String, Value)>> {
    let response = http()
        .get(daemon.at("/v1/events"))
        .send()
        .expect("GET /v1/events");
    assert_eq!(response.status(), StatusCode::OK);
    std::thread::spawn(move || {
        let mut events = Vec::new();
        let mut name = String::new();
        for line in BufReader::new(response).lines() {
            let Ok(line) = line else { break };
            if let Some(n) = line.strip_prefix("event:") {
                name = n.trim().to_owned();
            } else if let Some(data) = line.strip_prefix("data:") {
                let value: Value = serde_json::from_str(data.trim()).expect("event json");
                let end = name == "job"
                    && ["succeeded", "failed", "cancelled"]
                        .contains(&value["state"].as_str().unwrap_or(""));
                events.push((name.clone(), value));
                if end {
                    break;
                }
            }
        }
        events
    })
}

fn job_dirs(data_dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(data_dir.join("jobs"))
        .map(|d| {
            d.flatten()
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .collect()
        })
        .unwrap_or_default();
    names.sort();
    names
}

fn hil() -> String {
    common::generous_timeouts(&common::hil_config(""))
}

/// Results JSON without what names the moment of the run (session id, start time).
fn without_time(mut results: Value) -> Value {
    fn strip(v: &mut Value) {
        match v {
            Value::Object(map) => {
                map.remove("session_id");
                map.remove("started_at");
                map.values_mut().for_each(strip);
            }
            Value::Array(items) => items.iter_mut().for_each(strip),
            _ => {}
        }
    }
    strip(&mut results);
    results
}

#[test]
fn a_hil_run_submitted_over_http_is_followed_to_the_end_and_its_results_fetched() {
    let (dir, daemon, client) = started();
    let config = hil();
    let events = follow_events(&daemon);
    let id = submit(&client, &daemon, &config);

    // While it runs, the API shows progress and the devices.
    let running = wait_for(&client, &daemon, id, &["running", "succeeded", "failed"]);
    let mut saw_progress = false;
    let mut saw_devices = false;
    while job(&client, &daemon, id)["state"] == "running" {
        let j = job(&client, &daemon, id);
        saw_progress |= j["progress"]["total"].as_u64().unwrap_or(0) > 0;
        let devices: Value = client
            .get(daemon.at("/v1/devices"))
            .send()
            .expect("devices")
            .json()
            .expect("json");
        saw_devices |= devices.as_array().is_some_and(|d| {
            d.iter()
                .any(|d| d["id"] == "tracer0" && d["readings"].as_u64() > Some(0))
        });
        std::thread::sleep(Duration::from_millis(100));
    }
    let done = wait_for(&client, &daemon, id, &["succeeded", "failed"]);
    assert_eq!(done["state"], "succeeded", "{done}");
    assert_eq!(done["kind"], "multilateration");
    assert_eq!(running["type"], "run");
    assert!(
        saw_progress && saw_devices,
        "progress and devices seen while running"
    );
    let total = done["progress"]["total"].as_u64().expect("total");
    assert_eq!(done["progress"]["done"].as_u64(), Some(total));

    // The event stream told the whole story.
    let events = events.join().expect("events thread");
    assert!(
        events.iter().all(|(_, v)| v["id"].as_i64() == Some(id)),
        "{events:?}"
    );
    let events: Vec<(String, Value)> = events
        .into_iter()
        .filter(|(n, v)| !(n == "job" && v["state"] == "queued"))
        .collect();
    let names: Vec<&str> = events.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(
        events.first().map(|e| e.1["state"].clone()),
        Some(Value::from("running")),
        "{names:?}"
    );
    assert!(names.contains(&"station"), "{names:?}");
    let progress: Vec<u64> = events
        .iter()
        .filter(|(n, _)| n == "progress")
        .map(|(_, v)| v["progress"]["done"].as_u64().expect("done"))
        .collect();
    assert_eq!(progress.last(), Some(&total));
    assert!(progress.windows(2).all(|w| w[0] <= w[1]));
    assert_eq!(
        events.last().map(|e| e.1["state"].clone()),
        Some(Value::from("succeeded"))
    );

    // Results and session fetched; the results are what `geocal solve` makes of the session.
    let results: Value =
        serde_json::from_slice(&fetch(&client, &daemon, &format!("/v1/jobs/{id}/results")))
            .expect("results");
    assert_eq!(results["format"], "geocal-results/1");
    let session = dir.path().join("fetched.mcap");
    std::fs::write(
        &session,
        fetch(&client, &daemon, &format!("/v1/jobs/{id}/session")),
    )
    .expect("write");
    let solved = Command::new(env!("CARGO_BIN_EXE_geocal"))
        .args(["solve", "--json"])
        .arg(&session)
        .output()
        .expect("geocal solve");
    assert!(solved.status.success());
    let solved: Value = serde_json::from_slice(&solved.stdout).expect("solve json");
    assert_eq!(
        solved, results,
        "the daemon's results are geocal solve's of its session"
    );
    // The catalog's hashes are the fetched files'.
    let session_entry = done["files"]
        .as_array()
        .and_then(|f| f.iter().find(|f| f["name"] == "session.mcap"))
        .expect("session.mcap listed");
    assert_eq!(
        session_entry["sha256"],
        geocal::serve::catalog::hash_file(&session).expect("hash").1
    );

    // The emulated run recovers the simulated truth like a `geocal run` of the same config.
    let truth: Value = serde_json::from_slice(&fetch(
        &client,
        &daemon,
        &format!("/v1/jobs/{id}/files/truth.json"),
    ))
    .expect("truth");
    let typed: geocal::method::multilateration::MultilaterationResults =
        serde_json::from_value(results).expect("typed results");
    common::assert_recovers_truth(&typed, &truth);
}

#[test]
fn a_simulated_run_through_the_daemon_equals_geocal_run() {
    let (dir, daemon, client) = started();
    let config = common::small_demo();
    let id = submit(&client, &daemon, &config);
    let done = wait_for(&client, &daemon, id, &["succeeded", "failed"]);
    assert_eq!(done["state"], "succeeded", "{done}");
    let from_daemon: Value =
        serde_json::from_slice(&fetch(&client, &daemon, &format!("/v1/jobs/{id}/results")))
            .expect("results");

    let plan = dir.path().join("plan.toml");
    std::fs::write(&plan, &config).expect("plan");
    let out = dir.path().join("direct");
    let run = Command::new(env!("CARGO_BIN_EXE_geocal"))
        .arg("run")
        .arg(&plan)
        .arg("--out")
        .arg(&out)
        .output()
        .expect("geocal run");
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let direct: Value =
        serde_json::from_slice(&std::fs::read(out.join("results.json")).expect("results"))
            .expect("json");
    let session_id = from_daemon["session_id"]
        .as_str()
        .expect("session id")
        .to_owned();
    assert_eq!(without_time(from_daemon), without_time(direct));

    // The report of the run, and of a solve job of its session: geocal report's HTML page.
    let report_of = |job: i64| {
        let response = client
            .get(daemon.at(&format!("/v1/jobs/{job}/report")))
            .send()
            .expect("GET report");
        assert_eq!(response.status(), StatusCode::OK, "job {job}");
        let content_type = response.headers()[reqwest::header::CONTENT_TYPE]
            .to_str()
            .expect("content type")
            .to_owned();
        assert!(content_type.starts_with("text/html"), "{content_type}");
        response.text().expect("report")
    };
    let page = report_of(id);
    assert!(
        page.contains(&session_id) && page.contains("<svg") && page.contains("ISO 230-2"),
        "the run's report"
    );
    let response = client
        .post(daemon.at("/v1/jobs"))
        .header("Content-Type", "application/json")
        .body(format!("{{\"type\": \"solve\", \"session_of\": {id}}}"))
        .send()
        .expect("POST solve");
    assert_eq!(response.status(), StatusCode::CREATED);
    let solve: Value = response.json().expect("json");
    let solve = solve["id"].as_i64().expect("id");
    let done = wait_for(&client, &daemon, solve, &["succeeded", "failed"]);
    assert_eq!(done["state"], "succeeded", "{done}");
    let page = report_of(solve);
    assert!(
        page.contains(&session_id) && page.contains("ISO 230-2"),
        "the solve job's report reads the session it solved"
    );
}

#[test]
fn a_killed_daemon_leaves_an_interrupted_job_that_resumes_through_the_api() {
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path().join("data");
    let mut daemon = Daemon::start(&data, &[]);
    let client = http();
    let id = submit(&client, &daemon, &hil());
    // Kill it once the second station's points have begun: the operator's relocation to it
    // (`relocation_s`, 180 s) was skipped, so the session's log times run ahead of the wall
    // clock, and the resume below comes at once.
    let start = Instant::now();
    loop {
        let j = job(&client, &daemon, id);
        assert_eq!(j["state"], "running", "the run must still be running: {j}");
        if j["progress"]["done"].as_u64().unwrap_or(0) >= 20 {
            break;
        }
        assert!(start.elapsed() < JOB_TIMEOUT);
        std::thread::sleep(Duration::from_millis(20));
    }
    std::thread::sleep(Duration::from_millis(1500));
    daemon.kill_9();
    let job_dir = data.join("jobs").join(id.to_string());
    let killed = dir.path().join("killed.mcap");
    std::fs::copy(job_dir.join("session.mcap"), &killed).expect("copy the killed session");

    let (_, flushed) =
        geocal::session::reader::read_session_raw(&killed).expect("killed file reads");
    let last_log_ns = flushed.iter().map(|m| m.log_time_ns).max().unwrap_or(0);
    let now_ns = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .expect("clock")
        .as_nanos() as u64;
    assert!(
        last_log_ns > now_ns + 60_000_000_000,
        "the killed session's log times run ahead of the wall clock (by {} s)",
        (last_log_ns as f64 - now_ns as f64) * 1e-9
    );

    let daemon = Daemon::start(&data, &[]);
    let interrupted = job(&client, &daemon, id);
    assert_eq!(interrupted["state"], "interrupted", "{interrupted}");
    // Its record shows how far it came and what it left.
    let done_before = interrupted["progress"]["done"].as_u64().unwrap_or(0);
    assert!(done_before >= 20, "{interrupted}");
    assert!(interrupted["progress"]["total"].as_u64().unwrap_or(0) > done_before);
    let names = |j: &Value| -> Vec<String> {
        j["files"]
            .as_array()
            .expect("files")
            .iter()
            .map(|f| f["name"].as_str().unwrap_or_default().to_owned())
            .collect()
    };
    let listed = names(&interrupted);
    for name in ["plan.toml", "session.mcap", "job.log"] {
        assert!(listed.iter().any(|n| n == name), "{name} in {listed:?}");
    }
    let (status, body) = post(&client, &daemon, &format!("/v1/jobs/{id}/resume"));
    assert_eq!(status, StatusCode::ACCEPTED, "{body}");
    let done = wait_for(&client, &daemon, id, &["succeeded", "failed"]);
    assert_eq!(done["state"], "succeeded", "{done}");
    // job.log is the last attempt's; the interrupted one's is kept beside it.
    let log = String::from_utf8(fetch(
        &client,
        &daemon,
        &format!("/v1/jobs/{id}/files/job.log"),
    ))
    .expect("utf-8");
    assert_eq!(log.trim(), "succeeded");
    let earlier = String::from_utf8(fetch(
        &client,
        &daemon,
        &format!("/v1/jobs/{id}/files/job.attempt-1.log"),
    ))
    .expect("utf-8");
    assert!(earlier.starts_with("interrupted"), "{earlier}");
    assert!(
        names(&done).iter().any(|n| n == "job.attempt-1.log"),
        "{done}"
    );

    // Every message flushed before the kill is in the final session, unchanged and in order.
    let (_, before) =
        geocal::session::reader::read_session_raw(&killed).expect("killed file reads");
    let (_, after) = geocal::session::reader::read_session_raw(&job_dir.join("session.mcap"))
        .expect("final file");
    assert!(
        before.len() > 100,
        "the kill came after some data: {}",
        before.len()
    );
    for (a, b) in before.iter().zip(&after) {
        assert_eq!(
            (&a.channel.topic, a.log_time_ns, a.publish_time_ns, &a.data),
            (&b.channel.topic, b.log_time_ns, b.publish_time_ns, &b.data)
        );
    }
    let results: geocal::method::multilateration::MultilaterationResults =
        serde_json::from_slice(&fetch(&client, &daemon, &format!("/v1/jobs/{id}/results")))
            .expect("results");
    let truth: Value =
        serde_json::from_slice(&std::fs::read(job_dir.join("truth.json")).expect("truth"))
            .expect("json");
    common::assert_recovers_truth(&results, &truth);
}

#[test]
fn jobs_wait_their_turn_and_cancel_cleanly() {
    let (dir, daemon, client) = started();
    let paced = format!("{}{PACE}", common::small_demo());
    let first = submit(&client, &daemon, &paced);
    let second = submit(&client, &daemon, &paced);
    let third = submit(&client, &daemon, &paced);
    wait_for(&client, &daemon, first, &["running"]);
    assert_eq!(job(&client, &daemon, second)["state"], "queued");

    // A queued job is cancelled at once and never runs.
    let (status, body) = post(&client, &daemon, &format!("/v1/jobs/{third}/cancel"));
    assert_eq!(
        (status, body["state"].clone()),
        (StatusCode::ACCEPTED, Value::from("cancelled"))
    );

    // A running job stops cleanly: its session is complete and readable, and it resumes.
    wait_for_progress(&client, &daemon, first, 3);
    let (status, _) = post(&client, &daemon, &format!("/v1/jobs/{first}/cancel"));
    assert_eq!(status, StatusCode::ACCEPTED);
    let cancelled = wait_for(
        &client,
        &daemon,
        first,
        &["cancelled", "succeeded", "failed"],
    );
    assert_eq!(cancelled["state"], "cancelled", "{cancelled}");
    let session = dir
        .path()
        .join("data/jobs")
        .join(first.to_string())
        .join("session.mcap");
    let read = geocal::session::read_session(&session).expect("the cancelled session reads");
    assert_eq!(read.completeness, geocal::session::Completeness::Complete);

    // The second runs next; the third never did.
    let second_done = wait_for(&client, &daemon, second, &["succeeded", "failed"]);
    assert_eq!(second_done["state"], "succeeded", "{second_done}");
    assert!(second_done["started_at"].as_str() >= cancelled["finished_at"].as_str());
    let third_now = job(&client, &daemon, third);
    assert_eq!(third_now["state"], "cancelled");
    assert!(third_now["started_at"].is_null());

    let (status, _) = post(&client, &daemon, &format!("/v1/jobs/{first}/resume"));
    assert_eq!(status, StatusCode::ACCEPTED);
    let resumed = wait_for(&client, &daemon, first, &["succeeded", "failed"]);
    assert_eq!(resumed["state"], "succeeded", "{resumed}");
    let results: Value = serde_json::from_slice(&fetch(
        &client,
        &daemon,
        &format!("/v1/jobs/{first}/results"),
    ))
    .expect("results");
    assert_eq!(results["format"], "geocal-results/1");
}

#[test]
fn bad_requests_are_clear_and_write_nothing() {
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path().join("data");
    let serve_config = dir.path().join("serve.toml");
    std::fs::write(&serve_config, "max_body_bytes = 8192\n").expect("config");
    let daemon = Daemon::start(&data, &["--config", serve_config.to_str().expect("utf-8")]);
    let client = http();
    let send = |body: &str, content_type: &str| {
        let r = client
            .post(daemon.at("/v1/jobs"))
            .header("Content-Type", content_type)
            .body(body.to_owned())
            .send()
            .expect("POST");
        let status = r.status();
        (status, r.text().unwrap_or_default())
    };
    let (status, body) = send("kind = \"multilateration\"\n[plan\n", "application/toml");
    assert_eq!(status, StatusCode::BAD_REQUEST, "{body}");
    assert!(body.contains("not TOML"), "{body}");
    let unknown = common::small_demo().replace("[sim]\n", "[sim]\nsead = 3\n");
    let (status, body) = send(&unknown, "application/toml");
    assert_eq!(status, StatusCode::BAD_REQUEST, "{body}");
    assert!(body.contains("sead"), "the error names the key: {body}");
    let (status, body) = send(&"#".repeat(9000), "application/toml");
    assert_eq!(status, StatusCode::PAYLOAD_TOO_LARGE, "{body}");
    let (status, body) = send("{}", "text/plain");
    assert_eq!(status, StatusCode::UNSUPPORTED_MEDIA_TYPE, "{body}");
    let port = common::small_demo().replace(
        "[sim]\n",
        "[devices.tracer.hpi3d]\nport = \"/dev/ttyS0\"\n[sim]\n",
    );
    let (status, body) = send(&port, "application/toml");
    assert_eq!(status, StatusCode::BAD_REQUEST, "{body}");
    assert!(
        body.contains("/dev/ttyS0") && body.contains("allowed_ports"),
        "{body}"
    );
    let (status, body) = send(r#"{"type":"solve","session_of":77}"#, "application/json");
    assert_eq!(status, StatusCode::NOT_FOUND, "{body}");

    let r = client.get(daemon.at("/v1/jobs/12345")).send().expect("GET");
    assert_eq!(r.status(), StatusCode::NOT_FOUND);
    let r = client
        .get(daemon.at("/v1/jobs/..%2F..%2Fetc"))
        .send()
        .expect("GET");
    assert_eq!(r.status(), StatusCode::BAD_REQUEST);
    assert!(
        job_dirs(&data).is_empty(),
        "nothing written: {:?}",
        job_dirs(&data)
    );
    let jobs: Value = client
        .get(daemon.at("/v1/jobs"))
        .send()
        .expect("GET")
        .json()
        .expect("json");
    assert_eq!(jobs, Value::Array(vec![]));

    // A resume of a job that is not interrupted.
    let id = submit(&client, &daemon, &common::small_demo());
    wait_for(&client, &daemon, id, &["succeeded", "failed"]);
    let (status, body) = post(&client, &daemon, &format!("/v1/jobs/{id}/resume"));
    assert_eq!(status, StatusCode::CONFLICT, "{body}");
    assert!(body["error"]
        .as_str()
        .unwrap_or("")
        .contains("only an interrupted, cancelled or failed run"));
    let r = client
        .get(daemon.at(&format!("/v1/jobs/{id}/files/..%2Fcatalog.sqlite")))
        .send()
        .expect("GET");
    assert_eq!(r.status(), StatusCode::NOT_FOUND);
    assert_eq!(job_dirs(&data), vec![id.to_string()]);
}

#[test]
fn a_token_guards_every_route_and_beyond_loopback_one_is_required() {
    let dir = tempfile::tempdir().expect("tempdir");
    let refused = Command::new(env!("CARGO_BIN_EXE_geocal"))
        .arg("serve")
        .arg("--data-dir")
        .arg(dir.path().join("open"))
        .args(["--listen", "0.0.0.0:0"])
        .output()
        .expect("geocal serve");
    assert!(!refused.status.success());
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(stderr.contains("token_file"), "{stderr}");

    let token_file = dir.path().join("token");
    std::fs::write(&token_file, "s3cret-token-0123456789\n").expect("token");
    let loose = Command::new(env!("CARGO_BIN_EXE_geocal"))
        .arg("serve")
        .arg("--data-dir")
        .arg(dir.path().join("loose"))
        .args(["--listen", "0.0.0.0:0", "--token-file"])
        .arg(&token_file)
        .output()
        .expect("geocal serve");
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        if std::fs::metadata(&token_file)
            .expect("meta")
            .permissions()
            .mode()
            & 0o077
            != 0
        {
            assert!(!loose.status.success(), "a readable token file is refused");
        }
        std::fs::set_permissions(&token_file, std::fs::Permissions::from_mode(0o600))
            .expect("chmod");
    }
    let daemon = Daemon::start(
        &dir.path().join("data"),
        &["--token-file", token_file.to_str().expect("utf-8")],
    );
    let client = http();
    let presented = [
        (None, StatusCode::UNAUTHORIZED),
        (Some("s3cret-token-0123456780"), StatusCode::UNAUTHORIZED),
        (Some("s3cret-token-0123456789"), StatusCode::OK),
    ];
    for path in ["/v1/health", "/v1/jobs", "/metrics", "/v1/openapi.json"] {
        for (token, expected) in presented {
            let request = client.get(daemon.at(path));
            let request = match token {
                Some(token) => request.bearer_auth(token),
                None => request,
            };
            let status = request.send().expect("GET").status();
            assert_eq!(status, expected, "{path} with token {token:?}");
        }
    }
    let r = client
        .post(daemon.at("/v1/jobs"))
        .header("Content-Type", "application/toml")
        .body(common::small_demo())
        .send()
        .expect("POST");
    assert_eq!(r.status(), StatusCode::UNAUTHORIZED);
    assert!(job_dirs(&daemon.data_dir).is_empty());
}

#[test]
fn the_openapi_document_health_and_metrics_describe_the_daemon() {
    let (_dir, daemon, client) = started();
    let doc: Value = client
        .get(daemon.at("/v1/openapi.json"))
        .send()
        .expect("GET")
        .json()
        .expect("json");
    assert!(doc["openapi"].as_str().is_some_and(|v| v.starts_with("3.")));
    for path in [
        "/v1/jobs",
        "/v1/jobs/{id}",
        "/v1/jobs/{id}/cancel",
        "/v1/jobs/{id}/resume",
        "/v1/jobs/{id}/results",
        "/v1/jobs/{id}/session",
        "/v1/devices",
        "/v1/prompts",
        "/v1/prompts/{id}/ack",
        "/v1/events",
        "/v1/health",
        "/metrics",
    ] {
        assert!(
            doc["paths"][path].is_object(),
            "{path} in the OpenAPI document"
        );
    }
    let health: Value = client
        .get(daemon.at("/v1/health"))
        .send()
        .expect("GET")
        .json()
        .expect("json");
    assert_eq!(health["status"], "ok");
    let id = submit(&client, &daemon, &common::small_demo());
    wait_for(&client, &daemon, id, &["succeeded"]);
    let metrics = client
        .get(daemon.at("/metrics"))
        .send()
        .expect("GET")
        .text()
        .expect("text");
    assert!(
        metrics.contains("geocal_jobs{state=\"succeeded\"} 1"),
        "{metrics}"
    );
    let samples: u64 = metrics
        .lines()
        .find_map(|l| l.strip_prefix("geocal_samples_recorded_total "))
        .and_then(|v| v.trim().parse().ok())
        .expect("samples metric");
    assert!(samples > 1000, "{samples}");

    // A solve job on the run's session gives the run's results again.
    let r = client
        .post(daemon.at("/v1/jobs"))
        .header("Content-Type", "application/json")
        .body(format!(r#"{{"type":"solve","session_of":{id}}}"#))
        .send()
        .expect("POST");
    assert_eq!(r.status(), StatusCode::CREATED);
    let solve: Value = r.json().expect("json");
    let solve = solve["id"].as_i64().expect("id");
    assert_eq!(
        wait_for(&client, &daemon, solve, &["succeeded", "failed"])["state"],
        "succeeded"
    );
    assert_eq!(
        fetch(&client, &daemon, &format!("/v1/jobs/{solve}/results")),
        fetch(&client, &daemon, &format!("/v1/jobs/{id}/results"))
    );
}

#[test]
fn sigterm_cancels_the_running_job_and_exits_zero() {
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path().join("data");
    let mut daemon = Daemon::start(&data, &[]);
    let client = http();
    let id = submit(&client, &daemon, &format!("{}{PACE}", common::small_demo()));
    wait_for_progress(&client, &daemon, id, 2);
    let pid = daemon.child.id().to_string();
    assert!(Command::new("kill")
        .args(["-TERM", &pid])
        .status()
        .expect("kill")
        .success());
    let start = Instant::now();
    let status = loop {
        if let Some(status) = daemon.child.try_wait().expect("wait") {
            break status;
        }
        assert!(start.elapsed() < JOB_TIMEOUT, "the daemon did not stop");
        std::thread::sleep(Duration::from_millis(20));
    };
    assert!(status.success(), "{status}");
    let daemon = Daemon::start(&data, &[]);
    let stopped = job(&client, &daemon, id);
    assert_eq!(stopped["state"], "cancelled", "{stopped}");
    let (status, _) = post(&client, &daemon, &format!("/v1/jobs/{id}/resume"));
    assert_eq!(status, StatusCode::ACCEPTED);
    assert_eq!(
        wait_for(&client, &daemon, id, &["succeeded", "failed"])["state"],
        "succeeded"
    );
}

#[test]
fn an_outside_python_client_runs_a_hil_job() {
    let dir = tempfile::tempdir().expect("tempdir");
    let daemon = Daemon::start(&dir.path().join("data"), &[]);
    let plan = dir.path().join("plan.toml");
    std::fs::write(&plan, hil()).expect("plan");
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/serve_client.py");
    let output = Command::new("python3")
        .arg(script)
        .arg(&daemon.url)
        .arg(&plan)
        .output()
        .expect("python3 must be installed (pip install requests)");
    assert!(
        output.status.success(),
        "the Python client failed (pip install requests?)\nstdout:\n{}\nstderr:\n{}",
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(stdout.contains("succeeded"), "{stdout}");
}

#[test]
fn operator_prompts_wait_for_an_acknowledgement_over_the_api() {
    let (_dir, daemon, client) = started();
    let config = format!("{}\n[operator]\nrehearse = true\n", hil());
    let id = submit(&client, &daemon, &config);
    let start = Instant::now();
    let mut acknowledged = Vec::new();
    loop {
        let j = job(&client, &daemon, id);
        if j["state"] != "running" && j["state"] != "queued" {
            assert_eq!(j["state"], "succeeded", "{j}");
            break;
        }
        let prompts: Value = client
            .get(daemon.at("/v1/prompts"))
            .send()
            .expect("GET")
            .json()
            .expect("json");
        for prompt in prompts.as_array().expect("array") {
            assert_eq!(prompt["job"].as_i64(), Some(id));
            // Held for a moment: the run must wait for it.
            std::thread::sleep(Duration::from_millis(300));
            assert_eq!(job(&client, &daemon, id)["state"], "running");
            let still: Value = client
                .get(daemon.at("/v1/prompts"))
                .send()
                .expect("GET")
                .json()
                .expect("json");
            assert_eq!(
                still.as_array().map(Vec::len),
                Some(1),
                "the prompt still waits"
            );
            let p = prompt["id"].as_u64().expect("prompt id");
            let r = client
                .post(daemon.at(&format!("/v1/prompts/{p}/ack")))
                .send()
                .expect("POST");
            assert_eq!(r.status(), StatusCode::NO_CONTENT);
            acknowledged.push(prompt["instruction"].as_str().unwrap_or("").to_owned());
        }
        assert!(start.elapsed() < JOB_TIMEOUT);
        std::thread::sleep(Duration::from_millis(20));
    }
    let r = client
        .post(daemon.at("/v1/prompts/9999/ack"))
        .send()
        .expect("POST");
    assert_eq!(r.status(), StatusCode::NOT_FOUND);
    // Four stations and one reflector, mounted at the first station: every change was asked
    // for, in the plan's order.
    let expected = [
        "place the tracer on station s1",
        "mount reflector t0",
        "place the tracer on station s2",
        "place the tracer on station s3",
        "place the tracer on station s4",
    ];
    assert_eq!(acknowledged.len(), expected.len(), "{acknowledged:?}");
    for (text, start) in acknowledged.iter().zip(expected) {
        assert!(text.starts_with(start), "{text} should start with {start}");
    }
}

#[test]
fn systemd_hears_ready_watchdog_and_stopping() {
    use std::os::unix::net::UnixDatagram;
    let dir = tempfile::tempdir().expect("tempdir");
    let socket_path = dir.path().join("notify.sock");
    let socket = UnixDatagram::bind(&socket_path).expect("bind the notify socket");
    socket
        .set_read_timeout(Some(Duration::from_secs(60)))
        .expect("timeout");
    let mut daemon = Daemon::start_with_env(
        &dir.path().join("data"),
        &[],
        &[
            ("NOTIFY_SOCKET", socket_path.to_str().expect("utf-8")),
            ("WATCHDOG_USEC", "200000"),
        ],
    );
    let mut heard = Vec::new();
    let mut buffer = [0u8; 512];
    while !(heard.iter().any(|m: &String| m.contains("READY=1"))
        && heard.iter().filter(|m| m.contains("WATCHDOG=1")).count() >= 2)
    {
        let n = socket
            .recv(&mut buffer)
            .unwrap_or_else(|e| panic!("a notification within 60 s ({e}); heard {heard:?}"));
        heard.push(String::from_utf8_lossy(&buffer[..n]).into_owned());
    }
    let pid = daemon.child.id().to_string();
    assert!(Command::new("kill")
        .args(["-TERM", &pid])
        .status()
        .expect("kill")
        .success());
    loop {
        let n = socket.recv(&mut buffer).expect("STOPPING within 60 s");
        if String::from_utf8_lossy(&buffer[..n]).contains("STOPPING=1") {
            break;
        }
    }
    assert!(daemon.child.wait().expect("wait").success());
}

#[test]
fn schedules_submit_their_plan_and_skip_while_busy() {
    let dir = tempfile::tempdir().expect("tempdir");
    std::fs::write(
        dir.path().join("plan.toml"),
        format!("{}{PACE}", common::small_demo()),
    )
    .expect("plan");
    let serve_config = dir.path().join("serve.toml");
    std::fs::write(
        &serve_config,
        "[[schedule]]\nname = \"often\"\ncron = \"*/2 * * * * *\"\nplan = \"plan.toml\"\n\
         time_zone = \"UTC\"\nwhen_busy = \"skip\"\n",
    )
    .expect("config");
    let daemon = Daemon::start(
        &dir.path().join("data"),
        &["--config", serve_config.to_str().expect("utf-8")],
    );
    let client = http();
    // Two scheduled runs, one after the other: firings while the first runs are skipped.
    let start = Instant::now();
    let jobs = loop {
        let jobs: Value = client
            .get(daemon.at("/v1/jobs"))
            .send()
            .expect("GET")
            .json()
            .expect("json");
        let jobs = jobs.as_array().cloned().unwrap_or_default();
        if jobs.len() >= 2 {
            break jobs;
        }
        assert!(start.elapsed() < JOB_TIMEOUT, "{jobs:?}");
        std::thread::sleep(Duration::from_millis(100));
    };
    assert!(
        jobs.iter().all(|j| j["submitted_by"] == "schedule:often"),
        "{jobs:?}"
    );
    let (first, second) = (
        jobs[1]["id"].as_i64().expect("id"),
        jobs[0]["id"].as_i64().expect("id"),
    );
    let first = wait_for(&client, &daemon, first, &["succeeded", "failed"]);
    assert_eq!(first["state"], "succeeded", "{first}");
    let second = job(&client, &daemon, second);
    // Skipping while busy: the second was submitted only after the first had ended.
    assert!(
        second["submitted_at"].as_str() >= first["finished_at"].as_str(),
        "{first} {second}"
    );

    // A bad expression refuses the start and names the key.
    std::fs::write(
        &serve_config,
        "[[schedule]]\nname = \"bad\"\ncron = \"61 * * * *\"\nplan = \"plan.toml\"\n",
    )
    .expect("config");
    let refused = Command::new(env!("CARGO_BIN_EXE_geocal"))
        .args(["serve", "--listen", "127.0.0.1:0", "--config"])
        .arg(&serve_config)
        .arg("--data-dir")
        .arg(dir.path().join("other"))
        .output()
        .expect("geocal serve");
    assert!(!refused.status.success());
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(stderr.contains("schedule[0].cron"), "{stderr}");
}

#[test]
fn a_foxglove_client_watches_a_hil_run_live() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut daemon = Daemon::start(&dir.path().join("data"), &["--live", "127.0.0.1:0"]);
    let live = daemon
        .live
        .clone()
        .expect("the live view's address on the first line");
    const WANTED: usize = 300;
    let mut watcher = Command::new("python3")
        .arg(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/tests/live_view/client.py"
        ))
        .arg(&live)
        .arg("/tracer/tracer0/range")
        .arg(WANTED.to_string())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("python3 with websockets (pip install websockets)");
    // The run starts publishing only once the client is connected (its first line), however
    // long Python takes to start on a loaded machine.
    let mut lines = BufReader::new(watcher.stdout.take().expect("watcher stdout")).lines();
    let first = lines.next().and_then(Result::ok).unwrap_or_default();
    assert!(
        first.contains("connected"),
        "the Foxglove client: {first:?}"
    );
    // Read as it comes: a client blocked on a full pipe would stop reading its socket.
    let watched = std::thread::spawn(move || lines.map_while(Result::ok).collect::<Vec<_>>());
    // A second viewer, on a raw socket: it must be disconnected when the run ends.
    let live_address = live
        .trim_start_matches("ws://")
        .trim_end_matches('/')
        .to_owned();
    let mut viewer = std::net::TcpStream::connect(&live_address).expect("connect to the live view");
    viewer
        .write_all(
            format!(
                "GET / HTTP/1.1\r\nHost: {live_address}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n\
                 Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\
                 Sec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n"
            )
            .as_bytes(),
        )
        .expect("handshake");
    let mut head = [0u8; 12];
    viewer.read_exact(&mut head).expect("handshake answer");
    assert_eq!(&head, b"HTTP/1.1 101", "{}", String::from_utf8_lossy(&head));
    let (closed, disconnected) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut sink = [0u8; 8192];
        while matches!(viewer.read(&mut sink), Ok(n) if n > 0) {}
        let _ = closed.send(());
    });
    let client = http();
    // The live samples stream: one client that never reads during the run and one that reads
    // every message. (Loopback's socket buffers take a megabyte or so, about what this run
    // sends: how a client that stays behind loses the oldest messages is tested in
    // `serve::samples`.)
    let address = daemon.url.trim_start_matches("http://").to_owned();
    let mut stalled = std::net::TcpStream::connect(&address).expect("connect");
    stalled
        .write_all(
            format!("GET /v1/devices/samples HTTP/1.1\r\nHost: {address}\r\n\r\n").as_bytes(),
        )
        .expect("request");
    let samples = client
        .get(daemon.at("/v1/devices/samples"))
        .send()
        .expect("the samples stream");
    assert_eq!(samples.status(), StatusCode::OK);
    let listening = Instant::now();
    let (event_sender, stream_events) = std::sync::mpsc::channel::<(String, String)>();
    std::thread::spawn(move || {
        // (event, data) pairs until the daemon goes away.
        let mut name = String::new();
        for line in BufReader::new(samples).lines().map_while(Result::ok) {
            if let Some(event) = line.strip_prefix("event: ") {
                name = event.to_owned();
            } else if let Some(data) = line.strip_prefix("data: ") {
                let _ = event_sender.send((std::mem::take(&mut name), data.to_owned()));
            }
        }
    });
    let id = submit(&client, &daemon, &hil());
    let done = wait_for(&client, &daemon, id, &["succeeded", "failed"]);
    assert_eq!(done["state"], "succeeded", "{done}");
    let listened_s = listening.elapsed().as_secs_f64();
    disconnected
        .recv_timeout(Duration::from_secs(120))
        .expect("the live viewer is disconnected once the run has ended");
    let output = watcher.wait_with_output().expect("the watcher ends");
    let stdout = watched.join().expect("the watcher's reader");
    assert!(
        output.status.success(),
        "the Foxglove client failed after {} lines (those without data: {:?}): {}",
        stdout.len(),
        stdout
            .iter()
            .filter(|l| !l.contains("payload_hex"))
            .collect::<Vec<_>>(),
        String::from_utf8_lossy(&output.stderr)
    );
    let received: Vec<(u64, Vec<u8>)> = stdout
        .iter()
        .filter_map(|l| serde_json::from_str::<Value>(l).ok())
        .filter(|v| v.get("payload_hex").is_some())
        .map(|v| {
            let hex = v["payload_hex"].as_str().expect("hex");
            let bytes = (0..hex.len())
                .step_by(2)
                .map(|i| u8::from_str_radix(&hex[i..i + 2], 16).expect("hex digit"))
                .collect();
            (v["log_time_ns"].as_u64().expect("log time"), bytes)
        })
        .collect();
    assert_eq!(received.len(), WANTED);
    // Every sample seen live is the recorded one: same log time, same bytes, in order.
    let session = daemon
        .data_dir
        .join("jobs")
        .join(id.to_string())
        .join("session.mcap");
    let (_, recorded) = geocal::session::reader::read_session_raw(&session).expect("session");
    let recorded: Vec<(u64, Vec<u8>)> = recorded
        .into_iter()
        .filter(|m| m.channel.topic == "/tracer/tracer0/range")
        .map(|m| (m.log_time_ns, m.data))
        .collect();
    let first = recorded
        .iter()
        .position(|r| *r == received[0])
        .expect("the first live sample is in the recording");
    assert_eq!(&recorded[first..first + WANTED], &received[..]);

    // The reading samples client: batches of the tracer's readings, each sample a recorded
    // one, in order, at most 20 messages a second. The run's last reading reaches it before
    // the daemon is killed (on a loaded machine, some time after the job's end is announced).
    let last_recorded_ns = recorded.last().expect("tracer readings recorded").0;
    let mut events = Vec::new();
    let ends_the_run = |data: &str| {
        serde_json::from_str::<Value>(data).is_ok_and(|b| {
            b["device"] == "tracer0"
                && b["t_s"]
                    .as_array()
                    .and_then(|t| t.last())
                    .and_then(Value::as_f64)
                    == Some(last_recorded_ns as f64 * 1e-9)
        })
    };
    while let Ok((name, data)) = stream_events.recv_timeout(Duration::from_secs(60)) {
        let last = name == "samples" && ends_the_run(&data);
        events.push((name, data));
        if last {
            break;
        }
    }
    daemon.kill_9();
    events.extend(stream_events.iter());
    let lagged = events.iter().any(|(name, _)| name == "lagged");
    let batches: Vec<Value> = events
        .iter()
        .filter(|(name, _)| name == "samples")
        .map(|(_, data)| serde_json::from_str(data).expect("a samples message"))
        .filter(|b: &Value| b["device"] == "tracer0")
        .collect();
    let live: Vec<(f64, f64)> = batches
        .iter()
        .flat_map(|b| {
            let t = b["t_s"].as_array().expect("t_s").clone();
            let length = b["fields"]["length_m"]
                .as_array()
                .expect("length_m")
                .clone();
            t.into_iter()
                .zip(length)
                .map(|(t, l)| (t.as_f64().expect("t"), l.as_f64().expect("length")))
        })
        .collect();
    let recorded: Vec<(f64, f64)> = recorded
        .iter()
        .map(|(t, data)| {
            let reading: Value = serde_json::from_slice(data).expect("a recorded reading");
            (
                *t as f64 * 1e-9,
                reading["length_m"].as_f64().expect("length_m"),
            )
        })
        .collect();
    assert!(
        batches.len() as f64 <= 20.0 * listened_s + 5.0,
        "{} tracer messages in {listened_s:.1} s",
        batches.len()
    );
    assert!(
        live.len() >= 10 * batches.len(),
        "{} samples in {} messages: not batched",
        live.len(),
        batches.len()
    );
    assert!(
        batches.iter().all(|b| b["skipped"] == 0),
        "1 kHz is not thinned"
    );
    let start = recorded
        .iter()
        .position(|r| *r == live[0])
        .expect("the first live sample is recorded");
    if lagged {
        let mut rest = recorded[start..].iter();
        assert!(
            live.iter().all(|l| rest.any(|r| r == l)),
            "every live sample is a recorded one, in order"
        );
    } else {
        // Every sample from the first on, to the run's last: the client that never read held
        // up neither the run nor this one.
        assert_eq!(&recorded[start..], &live[..]);
    }
    println!(
        "samples stream: {} tracer samples in {} messages over {listened_s:.1} s (lagged: {lagged})",
        live.len(),
        batches.len()
    );
    drop(stalled);
}

/// The operator's part of a real run through the daemon: every pending prompt of job `id` is
/// carried out on `geocal simulate`'s operator channel, then acknowledged over the API.
/// Returns what was done once the job has ended.
fn operate_through_simulate(
    client: &Client,
    daemon: &Daemon,
    id: i64,
    simulate: &mut common::Simulated,
) -> (Value, Vec<String>) {
    let start = Instant::now();
    let mut steps = Vec::new();
    loop {
        let j = job(client, daemon, id);
        if !["running", "queued"].contains(&j["state"].as_str().unwrap_or("")) {
            return (j, steps);
        }
        let prompts: Value = client
            .get(daemon.at("/v1/prompts"))
            .send()
            .expect("GET")
            .json()
            .expect("json");
        for prompt in prompts.as_array().expect("array") {
            let text = prompt["instruction"].as_str().unwrap_or("");
            let word_after = |prefix: &str| {
                text.strip_prefix(prefix)
                    .and_then(|rest| rest.split_whitespace().next())
                    .map(str::to_owned)
            };
            let command = match (
                word_after("place the tracer on station "),
                word_after("mount reflector "),
            ) {
                (Some(station), _) => format!("station {station}"),
                (_, Some(target)) => format!("target {target}"),
                _ => panic!("unexpected prompt {prompt}"),
            };
            let reply = simulate.operate(&command);
            assert_eq!(reply, format!("ok {command}"), "simulate refused");
            let p = prompt["id"].as_u64().expect("prompt id");
            let (status, _) = post(client, daemon, &format!("/v1/prompts/{p}/ack"));
            assert_eq!(status, StatusCode::NO_CONTENT);
            steps.push(command);
        }
        assert!(start.elapsed() < JOB_TIMEOUT, "job {id} never ended");
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// The held connection of each device id, from `/v1/devices`.
fn connections(client: &Client, daemon: &Daemon) -> std::collections::BTreeMap<String, Value> {
    let devices: Value = client
        .get(daemon.at("/v1/devices"))
        .send()
        .expect("GET /v1/devices")
        .json()
        .expect("json");
    devices
        .as_array()
        .expect("array")
        .iter()
        .filter(|d| !d["connection"].is_null())
        .map(|d| {
            (
                d["id"].as_str().unwrap_or("").to_owned(),
                d["connection"].clone(),
            )
        })
        .collect()
}

#[test]
fn real_devices_stay_connected_between_jobs_and_close_when_idle() {
    let dir = tempfile::tempdir().expect("tempdir");
    // The devices of a machine: geocal simulate hosts the HPI-3D and GRBL emulators on ptys
    // and the Modbus table on 127.0.0.1, outside the daemon's process.
    let sim_cfg = dir.path().join("simulate.toml");
    std::fs::write(&sim_cfg, common::hil_rotary_config("")).expect("write");
    let truth_path = dir.path().join("truth.json");
    let mut simulate =
        common::Simulated::start(env!("CARGO_BIN_EXE_geocal"), &sim_cfg, &truth_path);
    let (tracer, machine, table) = (
        simulate.endpoint("tracer"),
        simulate.endpoint("machine"),
        simulate.endpoint("rotary_table"),
    );
    let plan = format!(
        "{}{}",
        common::rotary_base(),
        common::driver_tables(
            &tracer,
            &machine,
            &format!("{{ kind = \"tcp\", address = \"{table}\" }}")
        )
    );

    // The daemon may reach those ports and that host; idle connections close after 8 s.
    let serve_cfg = dir.path().join("serve.toml");
    let folder = |path: &str| {
        Path::new(path)
            .parent()
            .map(|p| format!("{}/*", p.display()))
            .expect("a folder")
    };
    std::fs::write(
        &serve_cfg,
        format!(
            "allowed_ports = [{:?}, {:?}]\nallowed_hosts = [\"127.0.0.1\"]\n\n\
             [devices]\nrelease_idle_after_s = 8.0\n",
            folder(&tracer),
            folder(&machine)
        ),
    )
    .expect("write");
    let daemon = Daemon::start(
        &dir.path().join("data"),
        &["--config", serve_cfg.to_str().expect("path")],
    );
    let client = http();
    let truth: Value = {
        let text = std::fs::read_to_string(&truth_path).expect("simulate's truth");
        serde_json::from_str(&text).expect("truth json")
    };
    let session_of = |id: i64| {
        let session = dir.path().join(format!("job-{id}.mcap"));
        let bytes = fetch(&client, &daemon, &format!("/v1/jobs/{id}/session"));
        std::fs::write(&session, bytes).expect("write session");
        session
    };
    let judge = |id: i64| {
        let session = session_of(id);
        let results = geocal::kinds::solve_file(&session, &Default::default()).expect("solve");
        let results = results
            .get::<geocal::kinds::rotary_tracer::solve::RotaryTracerResults>()
            .expect("rotary_tracer results");
        common::assert_recovers_truth(&results.multilateration, &truth);
    };
    let held_ids = ["c", "tracer0", "vmc"];
    // A job of the plan, operated through simulate, recovering the truth; then every
    // device's held connection, returned, with the number of connections opened and of
    // jobs served by the current one.
    let mut job_then_connections = |opens: u64, leases: u64| {
        let id = submit(&client, &daemon, &plan);
        let (j, steps) = operate_through_simulate(&client, &daemon, id, &mut simulate);
        assert_eq!(j["state"], "succeeded", "{j}");
        assert_eq!(steps, ["station c01", "target t0", "station s13"]);
        judge(id);
        let held = connections(&client, &daemon);
        println!("after job {id}: {held:?}");
        for device in held_ids {
            let c = &held[device];
            assert_eq!(
                (
                    c["opens"].as_u64(),
                    c["leases"].as_u64(),
                    c["in_use"].as_bool()
                ),
                (Some(opens), Some(leases), Some(false)),
                "{device}: {c}"
            );
        }
        (id, held)
    };

    // First job: the daemon connects the devices and keeps them.
    let (first, after_first) = job_then_connections(1, 1);
    // Second job on the same connections, after a pause: nothing reopened, and no sample of
    // the idle time reaches the run (its results recover the truth as the first job's do).
    std::thread::sleep(Duration::from_millis(1500));
    let (second, after_second) = job_then_connections(1, 2);
    for device in held_ids {
        assert!(
            after_second[device]["connected_s"].as_f64()
                > after_first[device]["connected_s"].as_f64(),
            "{device}: the same connection"
        );
    }
    // The tracer's device clock and the log clock both run in wall time: from the first
    // job's last sample to the second job's first, both advance alike unless the second job
    // was handed samples queued while the device was idle.
    let tracer_samples = |id: i64| {
        let session = geocal::session::reader::read_session(&session_of(id)).expect("session");
        session.tracers["tracer0"]
            .iter()
            .map(|s| (s.log_time_ns, s.msg.t_s))
            .collect::<Vec<_>>()
    };
    let (last, next) = (
        *tracer_samples(first).last().expect("samples"),
        tracer_samples(second)[0],
    );
    let log_gap_s = (next.0 - last.0) as f64 * 1e-9;
    let device_gap_s = next.1 - last.1;
    println!("between the jobs: log {log_gap_s:.3} s, device {device_gap_s:.3} s");
    assert!(
        log_gap_s > 1.5 && (log_gap_s - device_gap_s).abs() < 0.1,
        "log {log_gap_s} s against device {device_gap_s} s: samples from the idle time"
    );

    // Idle: the connections close; the next job connects again.
    let start = Instant::now();
    while !connections(&client, &daemon).is_empty() {
        assert!(start.elapsed() < Duration::from_secs(120), "never released");
        std::thread::sleep(Duration::from_millis(200));
    }
    job_then_connections(2, 1);
}
