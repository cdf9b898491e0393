//! The daemon's machine history: a schedule runs the demo twice, and between the two
//! runs the simulated machine's squareness changes. The second run, compared with the first,
//! raises a `machine_change` event on the SSE stream naming the squareness errors, counts in
//! the Prometheus metrics and is posted to the configured URL (a listener on 127.0.0.1 here);
//! `/v1/machines`, its history and its trend show it.

use crate::common;

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpListener;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use reqwest::blocking::Client;
use reqwest::StatusCode;
use serde_json::Value;

/// Simulated time runs this many times faster than wall time.
const PACE: &str = "\npace = 300.0\n";
/// Long enough for any job here on a loaded 2-core machine.
const TIMEOUT: Duration = Duration::from_secs(600);
const MACHINE: &str = "Bridge CMM 14-24-10 (simulated)";

struct Daemon {
    child: Child,
    url: String,
}

impl Daemon {
    fn start(data_dir: &Path, config: &Path) -> Daemon {
        let mut child = Command::new(env!("CARGO_BIN_EXE_geocal"))
            .arg("serve")
            .arg("--data-dir")
            .arg(data_dir)
            .args(["--listen", "127.0.0.1:0", "--live", "off", "--config"])
            .arg(config)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .expect("spawn geocal serve");
        let (url, _) = common::daemon_banner(&mut child);
        Daemon { child, url }
    }

    fn at(&self, path: &str) -> String {
        format!("{}{path}", self.url)
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn get(client: &Client, daemon: &Daemon, path: &str) -> (StatusCode, Value) {
    let response = client.get(daemon.at(path)).send().expect("GET");
    let status = response.status();
    (status, response.json().unwrap_or(Value::Null))
}

/// A one-shot HTTP receiver on 127.0.0.1: every request's body, answered 200.
fn receiver() -> (String, mpsc::Receiver<String>) {
    let listener = TcpListener::bind("127.0.0.1:0").expect("bind");
    let url = format!("http://{}/hook", listener.local_addr().expect("address"));
    let (send, receive) = mpsc::channel();
    std::thread::spawn(move || {
        for stream in listener.incoming() {
            let Ok(mut stream) = stream else { continue };
            let mut reader = BufReader::new(stream.try_clone().expect("clone"));
            let mut length = 0usize;
            loop {
                let mut line = String::new();
                if reader.read_line(&mut line).unwrap_or(0) == 0 {
                    break;
                }
                let lower = line.to_ascii_lowercase();
                if let Some(v) = lower.strip_prefix("content-length:") {
                    length = v.trim().parse().unwrap_or(0);
                }
                if line == "\r\n" {
                    break;
                }
            }
            let mut body = vec![0u8; length];
            if reader.read_exact(&mut body).is_ok() {
                let _ = send.send(String::from_utf8_lossy(&body).into_owned());
            }
            let _ = stream
                .write_all(b"HTTP/1.1 200 OK\r\nContent-Length: 0\r\nConnection: close\r\n\r\n");
        }
    });
    (url, receive)
}

/// The `machine_change` events of the stream, until the first one.
fn first_machine_change(daemon: &Daemon) -> std::thread::JoinHandle<Option<Value>> {
    let response = Client::builder()
        .timeout(None)
        .build()
        .expect("client")
        .get(daemon.at("/v1/events"))
        .send()
        .expect("GET /v1/events");
    assert_eq!(response.status(), StatusCode::OK);
    std::thread::spawn(move || {
        let mut name = String::new();
        for line in BufReader::new(response).lines() {
            let Ok(line) = line else { break };
            if let Some(n) = line.strip_prefix("event:") {
                name = n.trim().to_owned();
            } else if let Some(data) = line.strip_prefix("data:") {
                if name == "machine_change" {
                    return serde_json::from_str(data.trim()).ok();
                }
            }
        }
        None
    })
}

fn wait_for_state(client: &Client, daemon: &Daemon, id: i64) -> Value {
    let start = Instant::now();
    loop {
        let (status, job) = get(client, daemon, &format!("/v1/jobs/{id}"));
        if status == StatusCode::OK
            && ["succeeded", "failed", "cancelled"].contains(&job["state"].as_str().unwrap_or(""))
        {
            return job;
        }
        assert!(start.elapsed() < TIMEOUT, "job {id} never ended: {job}");
        std::thread::sleep(Duration::from_millis(100));
    }
}

#[test]
fn a_scheduled_run_of_a_changed_machine_raises_the_event() {
    let dir = tempfile::tempdir().expect("tempdir");
    let plan = dir.path().join("plan.toml");
    // The demo: the smallest example plan whose grid the 21-error model can use.
    let before = format!("{}{PACE}", common::DEMO);
    let after = before.replace("squareness_rad = 5e-6 }", "squareness_rad = 10e-6 }");
    assert_ne!(before, after, "the demo's squareness size");
    std::fs::write(&plan, &before).expect("plan");
    let (hook, received) = receiver();
    let config = dir.path().join("serve.toml");
    std::fs::write(
        &config,
        format!(
            "[[schedule]]\nname = \"weekly\"\ncron = \"*/2 * * * * *\"\nplan = \"plan.toml\"\n\
             time_zone = \"UTC\"\nwhen_busy = \"skip\"\n\n[history]\nnotify_url = \"{hook}\"\n"
        ),
    )
    .expect("config");
    let daemon = Daemon::start(&dir.path().join("data"), &config);
    let client = Client::builder().timeout(None).build().expect("client");
    let events = first_machine_change(&daemon);
    // The first scheduled run is queued with the plan as it was: change the machine for the
    // next one (submitted only once the first has ended).
    let start = Instant::now();
    loop {
        let (_, jobs) = get(&client, &daemon, "/v1/jobs");
        if jobs.as_array().is_some_and(|j| !j.is_empty()) {
            break;
        }
        assert!(start.elapsed() < TIMEOUT, "no scheduled job");
        std::thread::sleep(Duration::from_millis(50));
    }
    std::fs::write(&plan, &after).expect("changed plan");
    let first = wait_for_state(&client, &daemon, 1);
    assert_eq!(first["state"], "succeeded", "{first}");
    let second = wait_for_state(&client, &daemon, 2);
    assert_eq!(second["state"], "succeeded", "{second}");

    let event = events
        .join()
        .expect("events thread")
        .expect("a machine_change event");
    let change = &event["change"];
    assert_eq!(change["machine"], MACHINE, "{event}");
    assert_eq!(
        (change["job"].as_i64(), change["previous_job"].as_i64()),
        (Some(2), Some(1))
    );
    let significant: Vec<&str> = change["significant"]
        .as_array()
        .expect("significant")
        .iter()
        .filter_map(Value::as_str)
        .collect();
    assert!(!significant.is_empty(), "{event}");
    assert!(
        significant
            .iter()
            .all(|id| ["EC0Y", "EB0Z", "EA0Z"].contains(id)),
        "{significant:?}"
    );

    let body = received
        .recv_timeout(Duration::from_secs(120))
        .expect("the notification");
    let posted: Value = serde_json::from_str(&body).expect("notification JSON");
    assert_eq!(posted["machine"], MACHINE);
    assert_eq!(posted["significant"], change["significant"]);

    let (status, machines) = get(&client, &daemon, "/v1/machines");
    assert_eq!(status, StatusCode::OK);
    let machine = machines
        .as_array()
        .and_then(|m| m.iter().find(|m| m["name"] == MACHINE))
        .unwrap_or_else(|| panic!("{machines}"));
    assert!(machine["runs"].as_u64() >= Some(2), "{machine}");
    let path = format!("/v1/machines/{}", MACHINE.replace(' ', "%20"));
    let (status, history) = get(&client, &daemon, &format!("{path}/history"));
    assert_eq!(status, StatusCode::OK, "{history}");
    let second_run = history["runs"]
        .as_array()
        .and_then(|r| r.iter().find(|r| r["job"] == 2))
        .unwrap_or_else(|| panic!("{history}"));
    assert_eq!(second_run["comparison"]["changed"], true, "{history}");
    assert_eq!(second_run["comparison"]["previous_job"], 1);
    let (status, trend) = get(&client, &daemon, &format!("{path}/trend"));
    assert_eq!(status, StatusCode::OK, "{trend}");
    assert_eq!(trend["format"], "geocal-trend/1");
    let (status, missing) = get(&client, &daemon, "/v1/machines/no%20such%20machine/history");
    assert_eq!(status, StatusCode::NOT_FOUND);
    assert!(missing["error"].as_str().is_some(), "{missing}");

    let metrics = client
        .get(daemon.at("/metrics"))
        .send()
        .expect("GET /metrics")
        .text()
        .expect("text");
    let series = format!("geocal_machine_changes_total{{machine=\"{MACHINE}\",key=\"m-");
    assert!(
        metrics
            .lines()
            .any(|l| l.starts_with(&series) && l.ends_with("\"} 1")),
        "{metrics}"
    );
    let comparison = client
        .get(daemon.at("/v1/jobs/2/files/comparison.json"))
        .send()
        .expect("GET comparison")
        .json::<Value>()
        .expect("json");
    assert_eq!(comparison["format"], "geocal-compare/1");
    // The same history from the command line, read from the daemon's catalog.
    let output = Command::new(env!("CARGO_BIN_EXE_geocal"))
        .args(["trend", "--json", "--catalog"])
        .arg(dir.path().join("data"))
        .output()
        .expect("geocal trend --catalog");
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let trend: Value = serde_json::from_slice(&output.stdout).expect("trend JSON");
    assert_eq!(trend["machine"]["name"], MACHINE);
    assert!(
        trend["runs"].as_array().map(Vec::len) >= Some(2),
        "{}",
        trend["runs"]
    );
}
