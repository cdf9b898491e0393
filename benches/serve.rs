//! The daemon under load: a HIL run at the emulated tracer's highest rate submitted over HTTP
//! while a client polls the job's status as fast as it can (status latency, p50/p99/max), the
//! recorder's losses (gaps in the tracer's sequence numbers, messages waiting), and the
//! daemon's resident memory over 20 consecutive jobs.

#[path = "../tests/common/mod.rs"]
mod common;

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use reqwest::blocking::Client;
use serde_json::Value;

struct Daemon {
    child: Child,
    url: String,
}

impl Drop for Daemon {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn start(data: &std::path::Path) -> Daemon {
    let mut child = Command::new(env!("CARGO_BIN_EXE_geocal"))
        .arg("serve")
        .arg("--data-dir")
        .arg(data)
        .args(["--listen", "127.0.0.1:0", "--live", "127.0.0.1:0"])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("spawn geocal serve");
    let mut line = String::new();
    BufReader::new(child.stdout.take().expect("stdout"))
        .read_line(&mut line)
        .expect("first line");
    let url = line
        .split_whitespace()
        .find(|w| w.starts_with("http://"))
        .expect("address")
        .trim_end_matches(',')
        .to_owned();
    Daemon { child, url }
}

fn submit(client: &Client, daemon: &Daemon, toml: String) -> i64 {
    let r: Value = client
        .post(format!("{}/v1/jobs", daemon.url))
        .header("Content-Type", "application/toml")
        .body(toml)
        .send()
        .expect("submit")
        .json()
        .expect("json");
    r["id"].as_i64().unwrap_or_else(|| panic!("{r}"))
}

fn state(client: &Client, daemon: &Daemon, id: i64) -> String {
    let j: Value = client
        .get(format!("{}/v1/jobs/{id}", daemon.url))
        .send()
        .expect("status")
        .json()
        .expect("json");
    j["state"].as_str().unwrap_or("").to_owned()
}

fn wait(client: &Client, daemon: &Daemon, id: i64) -> String {
    loop {
        let s = state(client, daemon, id);
        if s != "queued" && s != "running" {
            return s;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

fn rss_kib(pid: u32) -> u64 {
    std::fs::read_to_string(format!("/proc/{pid}/status"))
        .ok()
        .and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix("VmRSS:"))
                .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        })
        .unwrap_or(0)
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    let i = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

fn main() {
    let dir = tempfile::tempdir().expect("tempdir");
    let daemon = start(&dir.path().join("data"));
    let client = Client::new();

    println!("## Status latency and recorder losses during a HIL run\n");
    println!("| tracer rate | status calls | p50 | p99 | max | tracer samples | sequence gaps | recorder queue max | job |");
    println!("|---|---|---|---|---|---|---|---|---|");
    for rate_hz in [1000.0, 5000.0] {
        let config = common::generous_timeouts(&common::hil_config("")).replace(
            "sample_rate_hz = 1000.0",
            &format!("sample_rate_hz = {rate_hz:.1}"),
        );
        let id = submit(&client, &daemon, config);
        let mut latencies_ms = Vec::new();
        let end_state = loop {
            let t = Instant::now();
            let s = state(&client, &daemon, id);
            latencies_ms.push(t.elapsed().as_secs_f64() * 1e3);
            if s != "queued" && s != "running" {
                break s;
            }
        };
        latencies_ms.sort_by(f64::total_cmp);
        let session = dir
            .path()
            .join("data/jobs")
            .join(id.to_string())
            .join("session.mcap");
        let read = geocal::session::read_session(&session).expect("session");
        let samples: Vec<u64> = read.tracers.values().flatten().map(|s| s.msg.seq).collect();
        let gaps: u64 = samples
            .windows(2)
            .map(|w| w[1].saturating_sub(w[0]).saturating_sub(1))
            .sum();
        let metrics = client
            .get(format!("{}/metrics", daemon.url))
            .send()
            .expect("metrics")
            .text()
            .expect("text");
        let queue_max = metrics
            .lines()
            .find_map(|l| l.strip_prefix("geocal_recorder_queue_depth_max "))
            .unwrap_or("?")
            .to_owned();
        println!(
            "| {rate_hz:.0} Hz | {} | {:.2} ms | {:.2} ms | {:.2} ms | {} | {gaps} | {queue_max} | {end_state} |",
            latencies_ms.len(),
            percentile(&latencies_ms, 0.5),
            percentile(&latencies_ms, 0.99),
            latencies_ms.last().copied().unwrap_or(0.0),
            samples.len(),
        );
    }

    println!("\n## Daemon memory over 20 consecutive jobs (small simulated demo)\n");
    println!("| job | RSS |");
    println!("|---|---|");
    let pid = daemon.child.id();
    let mut rss = Vec::new();
    for i in 1..=20 {
        let id = submit(&client, &daemon, common::small_demo());
        let s = wait(&client, &daemon, id);
        assert_eq!(s, "succeeded");
        let kib = rss_kib(pid);
        rss.push(kib);
        if i == 1 || i % 5 == 0 {
            println!("| {i} | {:.1} MiB |", kib as f64 / 1024.0);
        }
    }
    let first_half: f64 = rss[..10].iter().sum::<u64>() as f64 / 10.0;
    let second_half: f64 = rss[10..].iter().sum::<u64>() as f64 / 10.0;
    println!(
        "\nmean RSS jobs 1-10 {:.1} MiB, jobs 11-20 {:.1} MiB",
        first_half / 1024.0,
        second_half / 1024.0
    );
}
