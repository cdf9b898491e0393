//! Whole runs through the real LinuxCNC with faults injected from outside geocal, as an
//! operator or a network would: E-stop pressed by another linuxcncrsh client in the middle
//! of a run (the run stops: the operator owns the E-stop), the driver's connection torn down
//! (`ss -K` in LinuxCNC's namespace), and linuxcncrsh killed. The run recovers or stops with
//! a clear message; no recorded sample is lost; `geocal run --resume DIR` finishes a stopped
//! run and the results recover the truth. Skips without LinuxCNC or root (saying why), fails
//! when `CI` is set.

use crate::common;

use std::io::{BufRead, BufReader, Write};
use std::net::TcpStream;
use std::os::fd::AsRawFd;
use std::path::Path;
use std::sync::mpsc;
use std::time::Duration;

use common::{assert_recovers_truth, faults, resume_cli};
use geocal::config::Config;
use geocal::kinds::tracer_plan::run::run;
use geocal::run::RunOptions;
use geocal::session::messages::RunEvent;
use geocal::session::reader::{read_session, read_session_raw, Session};

/// The example real-controller HIL configuration (the small demo, 4 stations x 18 points),
/// with a short reconnect window so that a linuxcncrsh that is gone stops the run soon.
fn config_text() -> String {
    let text = include_str!("../../../config/linuxcnc/hil.toml");
    let table = "[devices.machine.linuxcnc]\n";
    assert!(text.contains("driver = \"linuxcnc\"") && text.contains(table));
    text.replace(table, &format!("{table}reconnect_timeout_s = 5.0\n"))
}

/// The pid of the `linuxcncrsh` this test process started (through geocal's launcher):
/// one whose ancestors include this process, so another test's instance is never touched.
fn our_linuxcncrsh() -> Option<u32> {
    let me = std::process::id();
    let parent = |pid: u32| -> Option<u32> {
        let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
        // "pid (comm) state ppid ...": comm may hold spaces, so split after its ')'.
        let rest = &stat[stat.rfind(')')? + 1..];
        rest.split_whitespace().nth(1)?.parse().ok()
    };
    std::fs::read_dir("/proc").ok()?.find_map(|entry| {
        let pid: u32 = entry.ok()?.file_name().to_str()?.parse().ok()?;
        let comm = std::fs::read_to_string(format!("/proc/{pid}/comm")).ok()?;
        if comm.trim() != "linuxcncrsh" {
            return None;
        }
        let mut p = pid;
        for _ in 0..32 {
            p = parent(p)?;
            if p == me {
                return Some(pid);
            }
            if p <= 1 {
                return None;
            }
        }
        None
    })
}

/// Connect to linuxcncrsh from a thread inside `pid`'s network namespace.
fn connect_in_namespace_of(pid: u32) -> std::io::Result<TcpStream> {
    let ns = std::fs::File::open(format!("/proc/{pid}/ns/net"))?;
    std::thread::spawn(move || {
        // SAFETY: setns affects this thread only; `ns` is an open namespace file.
        if unsafe { libc::setns(ns.as_raw_fd(), libc::CLONE_NEWNET) } != 0 {
            return Err(std::io::Error::last_os_error());
        }
        let address = std::net::SocketAddr::from(([127, 0, 0, 1], geocal::sim::linuxcnc::RSH_PORT));
        TcpStream::connect_timeout(&address, Duration::from_secs(10))
    })
    .join()
    .map_err(|_| std::io::Error::other("the namespace thread panicked"))?
}

/// Another linuxcncrsh client (an operator's GUI) takes control and presses E-stop, then
/// watches LinuxCNC until it shuts down (the run's end): once the E-stop shows, every
/// reading must show it still pressed and the commanded position unchanged (nothing
/// released it, no move was sent). Says how many readings it took.
fn press_estop_and_watch(pid: u32) -> Result<String, String> {
    let mut s = connect_in_namespace_of(pid).map_err(|e| format!("connect: {e}"))?;
    s.set_read_timeout(Some(Duration::from_secs(30)))
        .map_err(|e| e.to_string())?;
    let mut r = BufReader::new(s.try_clone().map_err(|e| e.to_string())?);
    // The reply to `line`, or None once LinuxCNC closed the connection.
    let mut ask = |line: &str| -> Result<Option<String>, String> {
        if s.write_all(format!("{line}\r\n").as_bytes()).is_err() {
            return Ok(None);
        }
        let mut reply = String::new();
        while reply.trim().is_empty() || reply.trim().eq_ignore_ascii_case(line) {
            reply.clear();
            match r.read_line(&mut reply) {
                Ok(0) | Err(_) => return Ok(None),
                Ok(_) => {}
            }
        }
        Ok(Some(reply.trim().to_string()))
    };
    for line in [
        "hello EMC faults 1.0",
        "set verbose on",
        "set enable EMCTOO",
        "set estop on",
    ] {
        match ask(line)? {
            Some(reply) if reply.contains("ACK") && !reply.contains("NAK") => {}
            other => return Err(format!("{line}: {other:?}")),
        }
    }
    let mut readings = 0;
    let mut seen = Vec::new();
    let mut stopped_at: Option<String> = None;
    while let (Some(estop), Some(position)) = (ask("get estop")?, ask("get abs_act_pos")?) {
        seen.push(estop.clone());
        if estop == "ESTOP OFF" && readings == 0 {
            // linuxcncrsh shows the E-stop a few cycles late; the run stops as soon as it
            // shows, and its end shuts LinuxCNC down: watch closely.
            std::thread::sleep(Duration::from_millis(2));
            continue;
        }
        if estop != "ESTOP ON" {
            return Err(format!("the E-stop was released: {estop}"));
        }
        match &stopped_at {
            None => stopped_at = Some(position),
            Some(p) if *p != position => {
                return Err(format!("moved in E-stop: from {p} to {position}"))
            }
            Some(_) => {}
        }
        readings += 1;
        std::thread::sleep(Duration::from_millis(10));
    }
    if readings == 0 {
        // The run stops as soon as the driver sees the E-stop, and its end shuts this
        // LinuxCNC down at once: this client may see it go before the E-stop shows to it.
        return Ok(format!(
            "LinuxCNC shut down before the E-stop showed to this client (readings {seen:?})"
        ));
    }
    Ok(format!(
        "E-stop on and the position unchanged in all {readings} readings until LinuxCNC shut down"
    ))
}

/// Tear down every client connection to linuxcncrsh in `pid`'s namespace (the kernel's
/// SOCK_DESTROY, as a firewall or a network fault would: the driver reads an error).
fn cut_connections(pid: u32) -> Result<String, String> {
    let out = std::process::Command::new("nsenter")
        .arg(format!("--net=/proc/{pid}/ns/net"))
        .args(["ss", "-K", "dport", "=", "5007"])
        .output()
        .map_err(|e| format!("nsenter ss -K: {e}"))?;
    let listed = String::from_utf8_lossy(&out.stdout);
    if !listed.contains(":5007") {
        return Err(format!(
            "ss -K found no connection to cut: {listed} {}",
            String::from_utf8_lossy(&out.stderr)
        ));
    }
    Ok(String::new())
}

/// What a test does at a point of the run: after `points` points are done, `inject` (what
/// it saw, or why it failed).
type Injection = (u64, Box<dyn FnOnce(u32) -> Result<String, String> + Send>);

/// `geocal run` (in this process) of `config` into `dir`, with `injections` done from a
/// thread of their own as the run's progress reaches them. The run's result, and each
/// injection's outcome.
fn run_with_injections(
    config: &str,
    dir: &Path,
    injections: Vec<Injection>,
) -> (anyhow::Result<geocal::run::RunOutput>, Vec<String>) {
    let config = Config::parse(config, Path::new("linuxcnc-faults.toml")).expect("config");
    let (progress_tx, progress_rx) = mpsc::channel::<u64>();
    let progress_tx = std::sync::Mutex::new(progress_tx);
    let control = geocal::run::control::RunControl {
        progress: Some(geocal::progress_sink::ProgressSink::new(
            move |done, _total| {
                let _ = progress_tx.lock().map(|tx| tx.send(done));
            },
        )),
        ..Default::default()
    };
    let injector = std::thread::spawn(move || {
        let mut outcomes = Vec::new();
        for (at, inject) in injections {
            let reached = loop {
                match progress_rx.recv() {
                    Ok(done) if done >= at => break true,
                    Ok(_) => {}
                    Err(_) => break false,
                }
            };
            if !reached {
                outcomes.push(format!("the run ended before point {at}"));
                continue;
            }
            let outcome = match our_linuxcncrsh() {
                Some(pid) => inject(pid).map(|seen| format!("done at point {at}: {seen}")),
                None => Err("no linuxcncrsh of this test's LinuxCNC".to_string()),
            };
            outcomes.push(outcome.unwrap_or_else(|e| format!("FAILED at point {at}: {e}")));
        }
        outcomes
    });
    let result = run(
        &config,
        &RunOptions {
            out_dir: dir.to_path_buf(),
            truth: Some(dir.join("truth.json")),
            progress: false,
            settings: Default::default(),
            control,
        },
    );
    let outcomes = injector.join().expect("injector thread");
    (result, outcomes)
}

fn events(session: &Session) -> Vec<RunEvent> {
    session.events.iter().map(|e| e.msg.clone()).collect()
}

/// No sample lost: the tracer's seq runs without a gap within each run's stream (a resumed
/// run starts a new stream, whose seq starts again), and no `frames_lost` fault.
fn assert_tracer_streams_whole(session: &Session) {
    let samples = &session.tracers["tracer0"];
    assert!(!samples.is_empty(), "tracer samples recorded");
    let mut restarts = 0;
    for pair in samples.windows(2) {
        let (a, b) = (pair[0].msg.seq, pair[1].msg.seq);
        if b == a + 1 {
            continue;
        }
        assert!(b < a, "tracer seq jumps from {a} to {b}: samples lost");
        restarts += 1;
    }
    assert!(restarts <= 1, "{restarts} restarts of the tracer stream");
    assert!(
        faults(&events(session), "frames_lost").is_empty(),
        "frames lost"
    );
}

/// The driver's connection cut at point 4 (`ss -K` in LinuxCNC's namespace): the driver
/// reconnects (`disconnect`/`reconnect` faults), the run completes, every sample is
/// recorded and the results recover the truth.
pub fn linuxcnc_run_reconnects_after_a_cut_connection() {
    if !common::linuxcnc_available() {
        return;
    }
    let dir = tempfile::tempdir().expect("tempdir");
    let started = std::time::Instant::now();
    let (result, outcomes) = run_with_injections(
        &config_text(),
        dir.path(),
        vec![(4, Box::new(cut_connections))],
    );
    println!(
        "LinuxCNC run with a cut connection: {:.1} s, injections {outcomes:?}",
        started.elapsed().as_secs_f64()
    );
    let output = result.unwrap_or_else(|e| panic!("the run did not recover: {e:#}"));
    assert!(
        outcomes[0].starts_with("done"),
        "injection: {}",
        outcomes[0]
    );
    let session = read_session(&output.session_path).expect("session");
    let events = events(&session);
    for e in &events {
        if let RunEvent::Fault { .. } = e {
            println!("{e:?}");
        }
    }
    assert!(
        !faults(&events, "disconnect").is_empty(),
        "disconnect recorded"
    );
    assert!(
        !faults(&events, "reconnect").is_empty(),
        "reconnect recorded"
    );
    assert_tracer_streams_whole(&session);
    let results = output.results.multilateration().expect("tracer results");
    assert_eq!(results.points.len(), 18);
    let truth: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("truth.json")).expect("truth"))
            .expect("truth json");
    assert_recovers_truth(results, &truth);
}

/// E-stop pressed by another client at point 4: the run stops (geocal does not release an
/// E-stop it did not cause) with a message that names it and says how to go on, the session
/// kept; LinuxCNC stays in E-stop with its position unchanged until the run's end shuts it
/// down; the E-stop is recorded as an `alarm` fault. `geocal run --resume DIR` (a fresh
/// LinuxCNC: the HIL's controller is the run's own) finishes it with no sample lost, every
/// message of the stopped session unchanged, and the results recover the truth.
pub fn linuxcnc_run_stopped_by_an_estop_resumes() {
    if !common::linuxcnc_available() {
        return;
    }
    let dir = tempfile::tempdir().expect("tempdir");
    let started = std::time::Instant::now();
    let (result, outcomes) = run_with_injections(
        &config_text(),
        dir.path(),
        vec![(4, Box::new(press_estop_and_watch))],
    );
    println!(
        "LinuxCNC run with an E-stop: {:.1} s, injections {outcomes:?}, result {:?}",
        started.elapsed().as_secs_f64(),
        result.as_ref().map(|_| ()).map_err(|e| format!("{e:#}"))
    );
    assert!(
        outcomes[0].starts_with("done"),
        "injection: {}",
        outcomes[0]
    );
    let error = match result {
        Ok(_) => panic!("the run went on through an E-stop it did not cause"),
        Err(e) => format!("{e:#}"),
    };
    println!("the run stopped: {error}");
    assert!(
        error.contains("in E-stop")
            && error.contains("geocal run --resume")
            && error.contains("session recorded so far is kept"),
        "the message names LinuxCNC's E-stop and the way on: {error}"
    );
    let session_path = dir.path().join("session.mcap");
    let first = read_session(&session_path).expect("the session reads");
    let alarms: Vec<String> = faults(&events(&first), "alarm")
        .iter()
        .map(|(d, m)| format!("{d}: {m}"))
        .collect();
    println!("alarms: {alarms:?}");
    assert!(
        alarms.len() == 1 && alarms[0].starts_with("cmm: ") && alarms[0].contains("E-stop"),
        "the E-stop is recorded as one alarm, named once settled: {alarms:?}"
    );
    assert_tracer_streams_whole(&first);
    let results = resume_and_check_prefix(dir.path());
    let ml = results.multilateration().expect("tracer results");
    assert_eq!(ml.points.len(), 18);
    let truth: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("truth.json")).expect("truth"))
            .expect("truth json");
    assert_recovers_truth(ml, &truth);
}

/// `geocal run --resume DIR` of a stopped run: it records more, keeps every message of the
/// stopped session unchanged and loses no sample; the final session's results.
fn resume_and_check_prefix(dir: &Path) -> geocal::method::Results {
    let session_path = dir.join("session.mcap");
    let stopped = read_session(&session_path).expect("the stopped session reads");
    let points_done = events(&stopped)
        .iter()
        .filter(|e| matches!(e, RunEvent::PointEnd { .. }))
        .count();
    println!("the stopped session holds {points_done} finished points");
    assert!(points_done >= 4, "the points before the fault are kept");
    let (_, stopped_raw) = read_session_raw(&session_path).expect("raw stopped session");

    let started = std::time::Instant::now();
    resume_cli(env!("CARGO_BIN_EXE_geocal"), dir);
    println!("resume: {:.1} s", started.elapsed().as_secs_f64());
    let (_, final_raw) = read_session_raw(&session_path).expect("raw final session");
    assert!(
        final_raw.len() > stopped_raw.len(),
        "the resume recorded more"
    );
    for (i, (a, b)) in stopped_raw.iter().zip(&final_raw).enumerate() {
        assert_eq!(
            (&a.channel.topic, a.log_time_ns, &a.data),
            (&b.channel.topic, b.log_time_ns, &b.data),
            "message {i} of the stopped session changed"
        );
    }
    let finished = read_session(&session_path).expect("final session");
    assert!(finished.completeness.is_complete());
    assert_tracer_streams_whole(&finished);
    let kept: Vec<u64> = finished
        .events
        .iter()
        .filter_map(|e| match e.msg {
            RunEvent::Resume { messages_kept, .. } => Some(messages_kept),
            _ => None,
        })
        .collect();
    assert_eq!(
        kept,
        [stopped_raw.len() as u64],
        "the resume kept every message"
    );
    geocal::kinds::solve_file(&session_path, &Default::default()).expect("solve")
}

/// linuxcncrsh killed at point 6: it never comes back (the driver has no other way in), so
/// the run stops with a message naming the lost connection, the session kept; `geocal run
/// --resume DIR` starts a fresh LinuxCNC and finishes the plan with every message kept, and
/// the results recover the truth.
pub fn linuxcnc_run_stopped_by_a_killed_linuxcncrsh_resumes() {
    if !common::linuxcnc_available() {
        return;
    }
    let dir = tempfile::tempdir().expect("tempdir");
    let kill = |pid: u32| -> Result<String, String> {
        // SAFETY: kill(2) of the linuxcncrsh this test started (found by ancestry).
        if unsafe { libc::kill(pid as i32, libc::SIGKILL) } != 0 {
            return Err(std::io::Error::last_os_error().to_string());
        }
        Ok(String::new())
    };
    let started = std::time::Instant::now();
    let (result, outcomes) =
        run_with_injections(&config_text(), dir.path(), vec![(6, Box::new(kill))]);
    println!(
        "LinuxCNC run with linuxcncrsh killed: {:.1} s, injections {outcomes:?}",
        started.elapsed().as_secs_f64()
    );
    assert!(
        outcomes[0].starts_with("done"),
        "injection: {}",
        outcomes[0]
    );
    let error = match result {
        Ok(_) => panic!("the run cannot complete without linuxcncrsh"),
        Err(e) => format!("{e:#}"),
    };
    println!("the run stopped: {error}");
    assert!(
        error.contains("linuxcncrsh") && error.contains("session recorded so far is kept"),
        "the message names the lost linuxcncrsh: {error}"
    );
    let results = resume_and_check_prefix(dir.path());
    let ml = results.multilateration().expect("tracer results");
    assert_eq!(ml.points.len(), 18);
    let truth: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("truth.json")).expect("truth"))
            .expect("truth json");
    assert_recovers_truth(ml, &truth);
}
