//! The daemon under load: a HIL run at the emulated tracer's highest rate submitted over HTTP
//! while a client polls the job's status as fast as it can (status latency, p50/p99/max), the
//! recorder's losses (gaps in the tracer's sequence numbers, messages waiting), the daemon's
//! resident memory over 20 consecutive jobs, and its memory through a 5 kHz recording of a
//! few minutes while solves of a larger session run beside it.
//!
//! `cargo bench --bench serve -- recording` runs only the sections whose name is given
//! (`latency`, `jobs`, `recording`, `flood`: the health latency with the event streams' cap
//! full and 1000 idle connections open, or reconnecting).

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
    submit_as(client, daemon, "application/toml", toml)
}

fn submit_as(client: &Client, daemon: &Daemon, content_type: &str, body: String) -> i64 {
    let r: Value = client
        .post(format!("{}/v1/jobs", daemon.url))
        .header("Content-Type", content_type)
        .body(body)
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
    let wanted: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with("--"))
        .collect();
    let run = |section: &str| wanted.is_empty() || wanted.iter().any(|w| w == section);
    let dir = tempfile::tempdir().expect("tempdir");
    let daemon = start(&dir.path().join("data"));
    let client = Client::new();
    if run("latency") {
        latency(&client, &daemon, dir.path());
    }
    if run("jobs") {
        jobs(&client, &daemon);
    }
    if run("recording") {
        recording(&client, &daemon, dir.path());
    }
    if run("flood") {
        flood(dir.path());
    }
}

/// `GET /v1/health` on a new loopback connection: its latency, seconds.
fn health_s(address: &str) -> f64 {
    use std::io::{Read, Write};
    let started = Instant::now();
    let mut stream = std::net::TcpStream::connect(address).expect("connect");
    stream
        .set_read_timeout(Some(Duration::from_secs(60)))
        .expect("timeout");
    write!(
        stream,
        "GET /v1/health HTTP/1.1\r\nHost: {address}\r\nConnection: close\r\n\r\n"
    )
    .expect("write");
    let mut answer = Vec::new();
    let _ = stream.read_to_end(&mut answer);
    assert!(answer.starts_with(b"HTTP/1.1 200"), "health not answered");
    started.elapsed().as_secs_f64()
}

/// `max_connections = 4` with its 4 event streams open (`max_streams = 4`): the health
/// latency alone, with 1000 idle connections open, and while a peer keeps opening idle ones.
/// Bounded: 5 rounds of 20 requests, then 3 s of reconnecting.
fn flood(dir: &std::path::Path) {
    use std::io::{Read, Write};
    let config = dir.join("flood.toml");
    std::fs::write(&config, "max_connections = 4\nmax_streams = 4\n").expect("config");
    let mut child = Command::new(env!("CARGO_BIN_EXE_geocal"))
        .arg("serve")
        .arg("--config")
        .arg(&config)
        .arg("--data-dir")
        .arg(dir.join("flood-data"))
        .args(["--listen", "127.0.0.1:0", "--live", "off"])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("spawn geocal serve");
    let (url, _) = common::daemon_banner(&mut child);
    let daemon = Daemon { child, url };
    let address = daemon.url.trim_start_matches("http://").to_owned();
    let streams: Vec<std::net::TcpStream> = (0..4)
        .map(|_| {
            let mut s = std::net::TcpStream::connect(&address).expect("connect");
            write!(s, "GET /v1/events HTTP/1.1\r\nHost: {address}\r\n\r\n").expect("write");
            let mut head = [0u8; 12];
            s.read_exact(&mut head).expect("stream answer");
            assert_eq!(&head, b"HTTP/1.1 200");
            s
        })
        .collect();
    let summary = |label: &str, mut t: Vec<f64>| {
        t.sort_by(f64::total_cmp);
        println!(
            "flood: {label}: health p50 {:.1} ms, p99 {:.1} ms, max {:.1} ms ({} requests)",
            percentile(&t, 0.5) * 1e3,
            percentile(&t, 0.99) * 1e3,
            t[t.len() - 1] * 1e3,
            t.len()
        );
    };
    summary(
        "4 streams open",
        (0..100).map(|_| health_s(&address)).collect(),
    );
    let mut flooded = Vec::new();
    for _ in 0..5 {
        let idle: Vec<std::net::TcpStream> = (0..1000)
            .filter_map(|_| std::net::TcpStream::connect(&address).ok())
            .collect();
        assert!(idle.len() >= 900, "{} connections opened", idle.len());
        flooded.extend((0..20).map(|_| health_s(&address)));
    }
    summary("4 streams + 1000 idle connections", flooded);
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let flooder = {
        let (stop, address) = (stop.clone(), address.clone());
        std::thread::spawn(move || {
            let mut held = std::collections::VecDeque::new();
            let mut opened = 0u64;
            while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                if let Ok(s) = std::net::TcpStream::connect(&address) {
                    held.push_back(s);
                    opened += 1;
                }
                if held.len() > 1000 {
                    held.pop_front();
                }
            }
            opened
        })
    };
    let started = Instant::now();
    let mut reconnecting = Vec::new();
    while started.elapsed() < Duration::from_secs(3) {
        reconnecting.push(health_s(&address));
    }
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    let opened = flooder.join().expect("flooder");
    summary(
        &format!("4 streams + a peer opening idle connections ({opened} in 3 s)"),
        reconnecting,
    );
    drop(streams);
}

fn gaps_in(session: &std::path::Path) -> (usize, u64) {
    let read = geocal::session::read_session(session).expect("session");
    let samples: Vec<u64> = read.tracers.values().flatten().map(|s| s.msg.seq).collect();
    let gaps: u64 = samples
        .windows(2)
        .map(|w| w[1].saturating_sub(w[0]).saturating_sub(1))
        .sum();
    (samples.len(), gaps)
}

fn latency(client: &Client, daemon: &Daemon, dir: &std::path::Path) {
    println!("## Status latency and recorder losses during a HIL run\n");
    println!("| tracer rate | status calls | p50 | p99 | max | tracer samples | sequence gaps | recorder queue max | job |");
    println!("|---|---|---|---|---|---|---|---|---|");
    for rate_hz in [1000.0, 5000.0] {
        let config = common::generous_timeouts(&common::hil_config("")).replace(
            "sample_rate_hz = 1000.0",
            &format!("sample_rate_hz = {rate_hz:.1}"),
        );
        let id = submit(client, daemon, config);
        let mut latencies_ms = Vec::new();
        let end_state = loop {
            let t = Instant::now();
            let s = state(client, daemon, id);
            latencies_ms.push(t.elapsed().as_secs_f64() * 1e3);
            if s != "queued" && s != "running" {
                break s;
            }
        };
        latencies_ms.sort_by(f64::total_cmp);
        let session = dir
            .join("data/jobs")
            .join(id.to_string())
            .join("session.mcap");
        let (samples, gaps) = gaps_in(&session);
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
            samples,
        );
    }
}

fn jobs(client: &Client, daemon: &Daemon) {
    println!("\n## Daemon memory over 20 consecutive jobs (small simulated demo)\n");
    println!("| job | RSS |");
    println!("|---|---|");
    let pid = daemon.child.id();
    let mut rss = Vec::new();
    for i in 1..=20 {
        let id = submit(client, daemon, common::small_demo());
        let s = wait(client, daemon, id);
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

/// A HIL run of a few minutes with the tracer at 5 kHz (the demo's grid, 4 stations, both
/// passes), while solves of a larger simulated session (the full demo with a 100 Hz tracer)
/// run back to back beside it; the daemon's RSS read every second from the run's first point
/// to its last.
fn recording(client: &Client, daemon: &Daemon, dir: &std::path::Path) {
    println!("\n## Daemon memory through a 5 kHz recording while solves run beside it\n");
    let pid = daemon.child.id();
    let larger = common::DEMO.replace("sample_rate_hz = 25.0", "sample_rate_hz = 100.0");
    let source = submit(client, daemon, larger);
    assert_eq!(wait(client, daemon, source), "succeeded");
    let solve_body = format!(r#"{{"type": "solve", "session_of": {source}}}"#);
    let config = common::generous_timeouts(&common::hil_config(""))
        .replace("sample_rate_hz = 1000.0", "sample_rate_hz = 5000.0")
        .replace(
            "passes = [\"forward\"]",
            "passes = [\"forward\", \"backward\"]",
        )
        .replace(
            "x = { from = 0.1, to = 1.3, count = 3 }",
            "x = { from = 0.1, to = 1.3, count = 5 }",
        )
        .replace(
            "y = { from = 0.2, to = 2.2, count = 3 }",
            "y = { from = 0.2, to = 2.2, count = 5 }",
        )
        .replace(
            "z = { from = 0.15, to = 0.95, count = 2 }",
            "z = { from = 0.15, to = 0.95, count = 4 }",
        );
    let rss_before = rss_kib(pid);
    let id = submit(client, daemon, config);
    let started = Instant::now();
    let mut solves = Vec::new();
    let mut readings: Vec<(f64, u64)> = Vec::new();
    let mut heap: Vec<(f64, f64)> = Vec::new();
    let end_state = loop {
        let job: Value = client
            .get(format!("{}/v1/jobs/{id}", daemon.url))
            .send()
            .expect("status")
            .json()
            .expect("json");
        let s = job["state"].as_str().unwrap_or("").to_owned();
        if s != "queued" && s != "running" {
            break s;
        }
        let done = job["progress"]["done"].as_u64().unwrap_or(0);
        let total = job["progress"]["total"].as_u64().unwrap_or(0);
        let recording = s == "running" && done >= 1 && done < total;
        if solves.last().is_none_or(|&last| {
            !matches!(state(client, daemon, last).as_str(), "queued" | "running")
        }) {
            // Between two solves: the heap the daemon and the run hold.
            if recording {
                heap.push((
                    started.elapsed().as_secs_f64(),
                    common::heap_in_use_bytes(client, &daemon.url) as f64 / 1024.0,
                ));
            }
            solves.push(submit_as(
                client,
                daemon,
                "application/json",
                solve_body.clone(),
            ));
        }
        if recording {
            readings.push((started.elapsed().as_secs_f64(), rss_kib(pid)));
        }
        std::thread::sleep(Duration::from_secs(1));
    };
    let solved = solves
        .iter()
        .filter(|&&s| wait(client, daemon, s) == "succeeded")
        .count();
    let session = dir
        .join("data/jobs")
        .join(id.to_string())
        .join("session.mcap");
    let (samples, gaps) = gaps_in(&session);
    let mib = |kib: f64| kib / 1024.0;
    let at = |fraction: f64| {
        let i = ((readings.len() - 1) as f64 * fraction).round() as usize;
        mib(readings[i].1 as f64)
    };
    let duration = readings[readings.len() - 1].0 - readings[0].0;
    // The trend over the last three quarters: the first quarter holds the allocator's
    // warm-up (the first solves' and the recorder's buffers).
    let later: Vec<(f64, f64)> = readings[readings.len() / 4..]
        .iter()
        .map(|r| (r.0, r.1 as f64))
        .collect();
    let max = readings.iter().map(|r| r.1).max().unwrap_or(0);
    println!("| recording | tracer samples | sequence gaps | solves beside it | RSS before | RSS at 10 % | 50 % | 100 % | max | RSS trend, last 3/4 | heap between solves, first / last | heap trend | job |");
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    println!(
        "| {duration:.0} s | {samples} | {gaps} | {solved} of {} | {:.1} MiB | {:.1} MiB | {:.1} MiB | {:.1} MiB | {:.1} MiB | {:+.2} MiB/min | {:.1} / {:.1} MiB | {:+.2} MiB/min | {end_state} |",
        solves.len(),
        mib(rss_before as f64),
        at(0.1),
        at(0.5),
        at(1.0),
        mib(max as f64),
        mib(slope(&later) * 60.0),
        mib(heap[0].1),
        mib(heap[heap.len() - 1].1),
        mib(slope(&heap) * 60.0),
    );
}

/// Least-squares slope of (x, y).
fn slope(points: &[(f64, f64)]) -> f64 {
    let n = points.len() as f64;
    let mx = points.iter().map(|p| p.0).sum::<f64>() / n;
    let my = points.iter().map(|p| p.1).sum::<f64>() / n;
    let sxy: f64 = points.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
    let sxx: f64 = points.iter().map(|p| (p.0 - mx).powi(2)).sum();
    sxy / sxx
}
