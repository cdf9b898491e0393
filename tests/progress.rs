//! What a person sees while a job runs: `geocal client submit --follow` of the demo, its
//! stderr a pseudo-terminal (as in a terminal) and a pipe (as in a script or a log). In the
//! terminal the progress is one line redrawn in place (carriage returns, a handful of line
//! feeds, not one per point); on the pipe a line per station or per tenth, at most 15.

use crate::common;

use std::io::Read;
use std::os::fd::{FromRawFd, OwnedFd};
use std::path::Path;
use std::process::{Child, Command, Stdio};

/// The demo's points (5 stations × 100 points × 2 passes).
const DEMO_POINTS: usize = 1000;
/// The most lines the piped progress of the demo may take (docs/report.md, "Progress").
const PIPED_MAX_LINES: usize = 15;

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

/// A daemon on `data_dir`, its log (JSON lines: stderr is not a terminal) into `log`.
fn daemon(data_dir: &Path, log: &Path) -> Daemon {
    let log = std::fs::File::create(log).expect("daemon log");
    let mut child = Command::new(env!("CARGO_BIN_EXE_geocal"))
        .arg("serve")
        .arg("--data-dir")
        .arg(data_dir)
        .args(["--listen", "127.0.0.1:0", "--live", "off"])
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(log)
        .spawn()
        .expect("spawn geocal serve");
    let (url, _) = common::daemon_banner(&mut child);
    Daemon { child, url }
}

/// A pseudo-terminal pair (master, slave) of 100 columns.
fn pty() -> (OwnedFd, OwnedFd) {
    let mut master = -1;
    let mut slave = -1;
    let size = libc::winsize {
        ws_row: 30,
        ws_col: 100,
        ws_xpixel: 0,
        ws_ypixel: 0,
    };
    // SAFETY: openpty writes two descriptors into the integers given; null name and termios
    // take the defaults.
    let rc = unsafe {
        libc::openpty(
            &mut master,
            &mut slave,
            std::ptr::null_mut(),
            std::ptr::null(),
            &size,
        )
    };
    assert_eq!(rc, 0, "openpty: {}", std::io::Error::last_os_error());
    // SAFETY: both descriptors were just opened and are owned by nobody else.
    unsafe { (OwnedFd::from_raw_fd(master), OwnedFd::from_raw_fd(slave)) }
}

fn submit(daemon: &Daemon, config: &Path, stderr: Stdio) -> Child {
    Command::new(env!("CARGO_BIN_EXE_geocal"))
        .args(["client", "--server", &daemon.url, "submit"])
        .arg(config)
        .arg("--follow")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(stderr)
        .spawn()
        .expect("spawn geocal client")
}

#[test]
fn a_followed_demo_shows_one_line_in_a_terminal_and_few_on_a_pipe() {
    let dir = tempfile::tempdir().expect("tempdir");
    let log = dir.path().join("daemon.log");
    let daemon = daemon(&dir.path().join("data"), &log);
    let config = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/demo-multilateration.toml");

    // In a terminal.
    let (master, slave) = pty();
    let mut child = submit(&daemon, &config, Stdio::from(slave));
    let mut reader = std::fs::File::from(master);
    let mut seen = Vec::new();
    let mut buffer = [0u8; 4096];
    // The master reads until the client (the slave's last holder) exits: then EIO.
    loop {
        match reader.read(&mut buffer) {
            Ok(0) | Err(_) => break,
            Ok(n) => seen.extend_from_slice(&buffer[..n]),
        }
    }
    let status = child.wait().expect("client exit");
    let text = String::from_utf8_lossy(&seen);
    assert!(status.success(), "the followed job failed: {text}");
    // The terminal turns each line feed into CR LF: a redraw is a CR not before a LF.
    let redraws = text.matches('\r').count() - text.matches("\r\n").count();
    let line_feeds = text.matches('\n').count();
    let drawn = text.matches(&format!("/{DEMO_POINTS} points")).count();
    let tail: String = text
        .chars()
        .rev()
        .take(300)
        .collect::<Vec<_>>()
        .into_iter()
        .rev()
        .collect();
    eprintln!(
        "terminal: {redraws} redraws, {line_feeds} line feeds, {} bytes, ending {tail:?}",
        seen.len()
    );
    assert!(
        drawn >= 3 && redraws >= 3,
        "no progress line redrawn in place ({drawn} draws, {redraws} redraws): {text:?}"
    );
    assert!(
        line_feeds <= 5,
        "{line_feeds} line feeds in the terminal (state lines only): {text:?}"
    );
    assert!(text.contains("succeeded"), "{text:?}");

    // On a pipe.
    let child = submit(&daemon, &config, Stdio::piped());
    let out = child.wait_with_output().expect("client output");
    let text = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "the piped job failed: {text}");
    let lines: Vec<&str> = text.lines().collect();
    eprintln!("piped:\n{text}");
    assert!(
        lines.len() <= PIPED_MAX_LINES,
        "{} lines on the pipe, at most {PIPED_MAX_LINES}:\n{text}",
        lines.len()
    );
    assert!(!text.contains('\r'), "carriage returns on a pipe: {text:?}");
    // A line at each tenth: the last one says all points are done.
    assert!(
        text.contains(&format!("{DEMO_POINTS}/{DEMO_POINTS} points (100 %)")),
        "{text}"
    );
    assert!(
        lines.iter().filter(|l| l.contains("points (")).count() >= 10,
        "fewer than a line per tenth:\n{text}"
    );

    // --quiet: nothing on stderr (the job as JSON on stdout, the exit status).
    let quiet = Command::new(env!("CARGO_BIN_EXE_geocal"))
        .args(["--quiet", "client", "--server", &daemon.url, "submit"])
        .arg(&config)
        .arg("--follow")
        .stdin(Stdio::null())
        .output()
        .expect("quiet client");
    assert!(quiet.status.success());
    let text = String::from_utf8_lossy(&quiet.stderr);
    assert!(text.trim().is_empty(), "--quiet writes to stderr: {text}");

    // The daemon's log: per job a record per tenth and per station, never per point.
    let log = std::fs::read_to_string(&log).expect("daemon log");
    for job in 1..=3 {
        let records: Vec<&str> = log
            .lines()
            .filter(|l| l.contains(&format!("\"job\":{job},")))
            .filter(|l| l.contains("\"progress\"") || l.contains("station begins"))
            .collect();
        let tenths = records
            .iter()
            .filter(|l| l.contains("\"progress\""))
            .count();
        assert_eq!(tenths, 10, "job {job}: {records:#?}");
        assert!(records.len() <= PIPED_MAX_LINES, "job {job}: {records:#?}");
    }
}
