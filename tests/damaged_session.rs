//! Recorded data you always get back: a session with damaged chunks (bytes flipped, a record
//! header broken) still solves, losing only the windows those chunks touched, and `geocal
//! repair` turns damaged, truncated and killed recordings into complete files that the
//! independent Python reader reads to the end, holding exactly the readable messages.

use crate::common;

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::OnceLock;
use std::time::Duration;

use common::{hil_config, small_demo};
use geocal::kinds::registry::solve_session;
use geocal::method::multilateration::MultilaterationResults;
use geocal::method::SolveSettings;
use geocal::session::messages::RunEvent;
use geocal::session::reader::{read_session, read_session_raw, Session};
use geocal::session::{Recorder, RecorderOptions};
use mcap::records::ChunkIndex;

const INSTALL_HINT: &str = "pip install mcap jsonschema";

fn geocal() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_geocal"));
    c.stdin(Stdio::null());
    c
}

/// A small demo run, re-recorded with 16 KiB chunks so that one chunk holds a few windows.
struct Recorded {
    _dir: tempfile::TempDir,
    path: PathBuf,
    bytes: Vec<u8>,
    /// In file order.
    chunks: Vec<ChunkIndex>,
}

fn recorded() -> &'static Recorded {
    static CELL: OnceLock<Recorded> = OnceLock::new();
    CELL.get_or_init(|| {
        let dir = tempfile::tempdir().expect("tempdir");
        let run_dir = dir.path().join("run");
        let config = dir.path().join("demo.toml");
        std::fs::write(&config, small_demo()).expect("config");
        run_config(&config, &run_dir);
        let path = dir.path().join("session.mcap");
        let (bytes, chunks) = rechunked(&run_dir.join("session.mcap"), &path, 16 * 1024);
        assert!(chunks.len() >= 20, "{} chunks", chunks.len());
        Recorded {
            _dir: dir,
            path,
            bytes,
            chunks,
        }
    })
}

/// `geocal run CONFIG --out DIR`, which must succeed.
fn run_config(config: &Path, out_dir: &Path) {
    let out = geocal()
        .arg("run")
        .arg(config)
        .arg("--out")
        .arg(out_dir)
        .output()
        .expect("run geocal");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// The session at `source` written again to `dest` with chunks of `chunk_size` bytes: its
/// bytes and its chunk index in file order.
fn rechunked(source: &Path, dest: &Path, chunk_size: u64) -> (Vec<u8>, Vec<ChunkIndex>) {
    let (_, messages) = read_session_raw(source).expect("raw read");
    let rec = Recorder::create(
        dest,
        RecorderOptions {
            chunk_size,
            flush_interval: Duration::from_secs(3600),
            ..RecorderOptions::default()
        },
    )
    .expect("recorder");
    let h = rec.handle();
    for m in messages {
        h.raw(m);
    }
    rec.finish().expect("finish");
    let bytes = std::fs::read(dest).expect("read back");
    let summary = mcap::Summary::read(&bytes)
        .expect("summary")
        .expect("summary");
    let mut chunks = summary.chunk_indexes.clone();
    chunks.sort_by_key(|c| c.chunk_start_offset);
    (bytes, chunks)
}

/// Flips 8 bytes in the middle of chunk `i`'s compressed data.
fn flip_chunk(bytes: &mut [u8], chunk: &ChunkIndex) {
    let mid = (chunk.chunk_start_offset + chunk.chunk_length / 2) as usize;
    for b in &mut bytes[mid..mid + 8] {
        *b ^= 0xA5;
    }
}

/// Breaks chunk `i`'s record header: its length now runs far past the end of the file.
fn break_header(bytes: &mut [u8], chunk: &ChunkIndex) {
    bytes[chunk.chunk_start_offset as usize + 8] ^= 0x40;
}

/// The file without summary and footer: the reader must go the linear way.
fn without_summary(bytes: &[u8], chunks: &[ChunkIndex]) -> Vec<u8> {
    let last = chunks.last().expect("chunks");
    // The last chunk's message indexes follow it; keep them, cut before DataEnd.
    let mut end = (last.chunk_start_offset + last.chunk_length) as usize;
    while bytes[end] == mcap::records::op::MESSAGE_INDEX {
        let len = u64::from_le_bytes(bytes[end + 1..end + 9].try_into().expect("8 bytes"));
        end += 9 + len as usize;
    }
    bytes[..end].to_vec()
}

/// `geocal solve FILE --json` on these bytes.
fn solve_cli(bytes: &[u8], dir: &Path, name: &str) -> (MultilaterationResults, String) {
    let path = dir.join(name);
    std::fs::write(&path, bytes).expect("write");
    let out = geocal()
        .arg("solve")
        .arg(&path)
        .arg("--json")
        .output()
        .expect("geocal solve");
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(out.status.success(), "{name}: {stderr}");
    let results = serde_json::from_slice(&out.stdout).expect("results JSON");
    (results, stderr)
}

/// The undamaged session with every window removed whose point_begin..point_end overlaps
/// one of the chunks' log-time ranges, solved.
fn solve_without_windows(chunks: &[&ChunkIndex]) -> (MultilaterationResults, usize) {
    let mut session: Session = read_session(&recorded().path).expect("session");
    let touched = |from: u64, to: u64| {
        chunks
            .iter()
            .any(|c| c.message_start_time <= to && from <= c.message_end_time)
    };
    let mut kept = Vec::new();
    let mut open: Option<usize> = None;
    let mut removed = 0;
    for (i, e) in session.events.iter().enumerate() {
        match e.msg {
            RunEvent::PointBegin { .. } => open = Some(i),
            RunEvent::PointEnd { .. } => {
                if let Some(b) = open.take() {
                    if touched(session.events[b].log_time_ns, e.log_time_ns) {
                        removed += 1;
                        continue;
                    }
                    kept.push(session.events[b].clone());
                }
            }
            _ => {}
        }
        if !matches!(e.msg, RunEvent::PointBegin { .. }) {
            kept.push(e.clone());
        }
    }
    session.events = kept;
    let results = solve_session(&session, &SolveSettings::default()).expect("solve");
    let results = results.multilateration().expect("multilateration").clone();
    (results, removed)
}

fn assert_same_solution(damaged: &MultilaterationResults, expected: &MultilaterationResults) {
    assert_eq!(
        damaged.extraction.windows_used,
        expected.extraction.windows_used
    );
    assert_eq!(damaged.dof, expected.dof);
    assert_eq!(damaged.stations, expected.stations);
    assert_eq!(damaged.points, expected.points);
    assert_eq!(damaged.residual_rms_m, expected.residual_rms_m);
}

/// Damages `which` chunks with `how`, solves through the summary and linearly, compares with
/// the windows-removed solve; returns (windows used, all windows).
fn check_damaged(which: &[usize], how: fn(&mut [u8], &ChunkIndex)) -> (usize, usize) {
    let r = recorded();
    let dir = tempfile::tempdir().expect("tempdir");
    let mut bytes = r.bytes.clone();
    for &i in which {
        how(&mut bytes, &r.chunks[i]);
    }
    let chunks: Vec<&ChunkIndex> = which.iter().map(|&i| &r.chunks[i]).collect();
    let (expected, removed) = solve_without_windows(&chunks);
    let (all, _) = solve_cli(&r.bytes, dir.path(), "intact.mcap");
    assert!(removed > 0, "the damaged chunks touch no window");
    for (name, file) in [
        ("indexed.mcap", bytes.clone()),
        ("linear.mcap", without_summary(&bytes, &r.chunks)),
    ] {
        let (got, stderr) = solve_cli(&file, dir.path(), name);
        let damaged = &got.extraction.damaged_chunks;
        assert_eq!(damaged.len(), which.len(), "{name}: {damaged:?}");
        for (d, c) in damaged.iter().zip(&chunks) {
            assert_eq!(d.byte_offset, c.chunk_start_offset, "{name}");
            assert_eq!(d.byte_length, c.chunk_length, "{name}");
            let times = (d.start_log_time_ns, d.end_log_time_ns);
            if name == "indexed.mcap" {
                // The summary's chunk index: exact.
                assert_eq!(d.time_source, "chunk_index", "{name}");
                assert_eq!(times, (c.message_start_time, c.message_end_time), "{name}");
            } else {
                // No summary: from the chunks around it, which hold the lost span.
                assert_eq!(d.time_source, "neighbours", "{name}");
                assert!(
                    times.0 <= c.message_start_time && c.message_end_time <= times.1,
                    "{name}: {times:?}"
                );
            }
            assert!(d.messages.is_some_and(|n| n > 0), "{name}");
            assert!(
                stderr.contains(&format!("skipped bytes {}..", c.chunk_start_offset)),
                "{name}: {stderr}"
            );
        }
        assert!(stderr.contains("geocal repair"), "{stderr}");
        assert!(
            got.extraction.windows_used >= all.extraction.windows_used - removed,
            "{name}"
        );
        assert_same_solution(&got, &expected);
    }
    (
        expected.extraction.windows_used,
        all.extraction.windows_used,
    )
}

/// The first chunk from `near` on whose log times overlap a dwell window (most chunks hold
/// only moves).
fn chunk_in_a_window(near: usize) -> usize {
    let r = recorded();
    let session = read_session(&r.path).expect("session");
    let mut windows = Vec::new();
    let mut begin = None;
    for e in &session.events {
        match e.msg {
            RunEvent::PointBegin { .. } => begin = Some(e.log_time_ns),
            RunEvent::PointEnd { .. } => windows.extend(begin.take().map(|b| (b, e.log_time_ns))),
            _ => {}
        }
    }
    (near..r.chunks.len())
        .find(|&i| {
            let c = &r.chunks[i];
            windows
                .iter()
                .any(|&(b, e)| c.message_start_time <= e && b <= c.message_end_time)
        })
        .expect("a chunk inside a window")
}

#[test]
fn one_damaged_chunk_costs_only_its_windows() {
    let n = recorded().chunks.len();
    let (used, all) = check_damaged(&[chunk_in_a_window(n / 2)], flip_chunk);
    println!("one damaged chunk: {used} of {all} windows used");
}

#[test]
fn three_damaged_chunks_spread_over_the_file() {
    let n = recorded().chunks.len();
    let (used, all) = check_damaged(
        &[
            chunk_in_a_window(n / 4),
            chunk_in_a_window(n / 2),
            chunk_in_a_window(3 * n / 4),
        ],
        flip_chunk,
    );
    println!("three damaged chunks: {used} of {all} windows used");
}

#[test]
fn damaged_record_header_resyncs_at_the_next_record() {
    let n = recorded().chunks.len();
    let (used, all) = check_damaged(&[chunk_in_a_window(n / 3)], break_header);
    println!("damaged record header: {used} of {all} windows used");
}

/// Windows a session file's solve uses, or its error: in-process, as `geocal solve` does.
fn solve_file(path: &Path) -> Result<usize, String> {
    let session = read_session(path).map_err(|e| e.to_string())?;
    let results = solve_session(&session, &SolveSettings::default()).map_err(|e| e.to_string())?;
    let results = results.multilateration().ok_or("not multilateration")?;
    Ok(results.extraction.windows_used)
}

/// The windows of the damaged file (or its error), equal to its repaired copy's; an error
/// when they differ.
fn damaged_and_repaired(
    bytes: &[u8],
    dir: &Path,
    name: &str,
) -> Result<Result<usize, String>, String> {
    let damaged = dir.join(format!("{name}.mcap"));
    let repaired = dir.join(format!("{name}.repaired.mcap"));
    std::fs::write(&damaged, bytes).expect("write");
    let from_damaged = solve_file(&damaged);
    let repaired_windows = match geocal::session::repair::repair(&damaged, &repaired) {
        Ok(report) if report.has_header => solve_file(&repaired),
        Ok(_) => Err("no header".into()),
        Err(e) => Err(e.to_string()),
    };
    let verdict = match (&from_damaged, &repaired_windows) {
        (Ok(a), Ok(b)) if a == b => Ok(from_damaged),
        // Neither solves (the session header, or every window, was lost): the same either way.
        (Err(_), Err(_)) => Ok(from_damaged),
        _ => {
            let damage: Vec<String> = read_session(&damaged)
                .map(|s| s.damaged.iter().map(|d| d.describe()).collect())
                .unwrap_or_default();
            Err(format!(
                "{name}: damaged {from_damaged:?}, repaired {repaired_windows:?}: {damage:#?}"
            ))
        }
    };
    // Sixty seeds' copies would otherwise pile up in the temporary folder.
    let _ = std::fs::remove_file(&damaged);
    let _ = std::fs::remove_file(&repaired);
    verdict
}

/// Random damage anywhere, the summary and footer included: a few to 200 bytes set at random
/// in a random stretch of the file. The damaged file solves with exactly the windows of its
/// `geocal repair`ed copy: the skipped spans' times never come from the damaged bytes.
#[test]
fn random_damage_solves_like_the_repaired_copy() {
    use rand::{Rng, SeedableRng};
    let r = recorded();
    let dir = tempfile::tempdir().expect("tempdir");
    let n = r.bytes.len();
    let summary_start = r
        .chunks
        .last()
        .map_or(n, |c| (c.chunk_start_offset + c.chunk_length) as usize);
    let intact = solve_file(&r.path).expect("intact solve");
    let (mut solved, mut fewer, mut differ) = (0, 0, Vec::new());
    for seed in 0..60u64 {
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        // Every sixth seed damages only the summary section (indexes, statistics, footer).
        let (from, to) = if seed % 6 == 0 {
            (summary_start, n)
        } else {
            let span = rng.random_range(16..=n / 5);
            let from = rng.random_range(mcap::MAGIC.len()..n - span);
            (from, from + span)
        };
        let mut bytes = r.bytes.clone();
        for _ in 0..rng.random_range(1..=200) {
            bytes[rng.random_range(from..to)] = rng.random();
        }
        match damaged_and_repaired(&bytes, dir.path(), &format!("seed{seed}")) {
            Ok(Ok(w)) => {
                solved += 1;
                fewer += usize::from(w < intact);
            }
            Ok(Err(_)) => {}
            Err(why) => differ.push(why),
        }
    }
    assert!(differ.is_empty(), "{differ:#?}");
    println!("random damage: {solved} of 60 solved, {fewer} with fewer windows than {intact}");
    assert!(
        solved >= 40 && fewer >= 20,
        "{solved} solved, {fewer} lost windows"
    );
}

/// The demo session with 200 bytes set at random in its middle fifth: the solve skips the
/// damaged chunks and keeps what the repaired copy keeps, most of the 1000 windows. The
/// session is rechunked first: the recorder cuts chunks by time as well as size, so the same
/// bytes would hit other messages in every run.
#[test]
fn demo_session_with_a_damaged_middle_fifth() {
    use rand::{Rng, SeedableRng};
    let dir = tempfile::tempdir().expect("tempdir");
    let config = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/demo-multilateration.toml");
    run_config(&config, &dir.path().join("run"));
    let (mut bytes, _) = rechunked(
        &dir.path().join("run/session.mcap"),
        &dir.path().join("rechunked.mcap"),
        256 * 1024,
    );
    let n = bytes.len();
    let mut rng = rand::rngs::StdRng::seed_from_u64(23);
    for _ in 0..200 {
        bytes[rng.random_range(2 * n / 5..3 * n / 5)] = rng.random();
    }
    let windows = damaged_and_repaired(&bytes, dir.path(), "demo")
        .expect("the same windows")
        .expect("the damaged demo solves");
    println!("damaged demo: {windows} of 1000 windows used");
    assert!((700..1000).contains(&windows), "{windows} windows");
}

/// Every message as the Python `mcap` reader sees it: (topic, log time, publish time, data).
type Message = (String, u64, u64, Vec<u8>);

fn python_messages(path: &Path) -> Vec<Message> {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/check_session.py");
    let dump = path.with_extension("dump");
    let out = Command::new("python3")
        .arg(&script)
        .arg(path)
        .arg("--dump")
        .arg(&dump)
        .output()
        .unwrap_or_else(|e| {
            panic!("cannot run python3 ({e}); install Python 3 and {INSTALL_HINT}")
        });
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_ne!(out.status.code(), Some(3), "{INSTALL_HINT}\n{stderr}");
    assert!(
        out.status.success(),
        "check_session.py on {}: {stderr}",
        path.display()
    );
    let text = std::fs::read_to_string(&dump).expect("dump");
    text.lines()
        .map(|line| {
            let f: Vec<&str> = line.split('\t').collect();
            let data = (0..f[3].len())
                .step_by(2)
                .map(|i| u8::from_str_radix(&f[3][i..i + 2], 16).expect("hex"))
                .collect();
            (
                f[0].to_owned(),
                f[1].parse().expect("log time"),
                f[2].parse().expect("publish time"),
                data,
            )
        })
        .collect()
}

/// The messages of an intact file's chunks, by the mcap crate, skipping chunks `lost`.
fn chunk_messages(bytes: &[u8], keep: impl Fn(&ChunkIndex) -> bool) -> Vec<Message> {
    let summary = mcap::Summary::read(bytes)
        .expect("summary")
        .expect("summary");
    let mut chunks = summary.chunk_indexes.clone();
    chunks.sort_by_key(|c| c.chunk_start_offset);
    let mut out = Vec::new();
    for c in chunks.iter().filter(|c| keep(c)) {
        for m in summary.stream_chunk(bytes, c).expect("chunk") {
            let m = m.expect("message");
            out.push((
                m.channel.topic.clone(),
                m.log_time,
                m.publish_time,
                m.data.into_owned(),
            ));
        }
    }
    out
}

/// `geocal repair FILE --out OUT`; returns its stdout.
fn repair(input: &Path, output: &Path) -> String {
    let out = geocal()
        .arg("repair")
        .arg(input)
        .arg("--out")
        .arg(output)
        .output()
        .expect("geocal repair");
    assert!(
        out.status.success(),
        "repair {}: {}",
        input.display(),
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

#[test]
fn repair_of_a_damaged_file_keeps_every_readable_message() {
    let r = recorded();
    let dir = tempfile::tempdir().expect("tempdir");
    let n = r.chunks.len();
    let mut bytes = without_summary(&r.bytes, &r.chunks);
    flip_chunk(&mut bytes, &r.chunks[n / 2]);
    break_header(&mut bytes, &r.chunks[n / 5]);
    let input = dir.path().join("damaged.mcap");
    std::fs::write(&input, &bytes).expect("write");
    let output = dir.path().join("repaired.mcap");
    let report = repair(&input, &output);
    let lost = [
        r.chunks[n / 5].chunk_start_offset,
        r.chunks[n / 2].chunk_start_offset,
    ];
    for offset in lost {
        assert!(
            report.contains(&format!("damaged bytes {offset}..")),
            "{report}"
        );
    }
    let expected = chunk_messages(&r.bytes, |c| !lost.contains(&c.chunk_start_offset));
    // Every readable message, and one `data_lost` event per lost chunk.
    let (losses, copied): (Vec<Message>, Vec<Message>) = python_messages(&output)
        .into_iter()
        .partition(|(topic, _, _, data)| {
            topic == "/run/event" && String::from_utf8_lossy(data).contains("\"data_lost\"")
        });
    assert_eq!(copied, expected);
    assert_eq!(losses.len(), lost.len());
    // And geocal reads it as complete and undamaged, with what its original lost recorded.
    let s = read_session(&output).expect("repaired session");
    assert!(s.completeness.is_complete() && s.damaged.is_empty());
    let mut recorded: Vec<u64> = s.lost_before_repair.iter().map(|d| d.byte_offset).collect();
    recorded.sort_unstable();
    let mut lost = lost.to_vec();
    lost.sort_unstable();
    assert_eq!(recorded, lost);
}

#[test]
fn repair_of_a_truncated_file_keeps_its_complete_chunks() {
    let r = recorded();
    let dir = tempfile::tempdir().expect("tempdir");
    let cut_chunk = &r.chunks[r.chunks.len() * 2 / 3];
    let cut = (cut_chunk.chunk_start_offset + cut_chunk.chunk_length / 3) as usize;
    let input = dir.path().join("cut.mcap");
    std::fs::write(&input, &r.bytes[..cut]).expect("write");
    let output = dir.path().join("repaired.mcap");
    let report = repair(&input, &output);
    assert!(report.contains("the cut end of the file"), "{report}");
    let expected = chunk_messages(&r.bytes, |c| {
        (c.chunk_start_offset + c.chunk_length) as usize <= cut
    });
    assert_eq!(python_messages(&output), expected);
}

/// What the mcap crate itself reads of a file cut short: every message up to its cut.
fn readable_messages(bytes: &[u8]) -> Vec<Message> {
    let mut out = Vec::new();
    let Ok(stream) =
        mcap::MessageStream::new_with_options(bytes, mcap::read::Options::IgnoreEndMagic.into())
    else {
        return out;
    };
    for m in stream {
        let Ok(m) = m else { break };
        out.push((
            m.channel.topic.clone(),
            m.log_time,
            m.publish_time,
            m.data.into_owned(),
        ));
    }
    out
}

#[test]
fn repair_of_a_killed_hil_run() {
    let dir = tempfile::tempdir().expect("tempdir");
    let config = dir.path().join("hil.toml");
    std::fs::write(&config, hil_config("")).expect("config");
    let out = dir.path().join("run");
    let mut child = geocal()
        .arg("run")
        .arg(&config)
        .arg("--out")
        .arg(&out)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("spawn geocal");
    // Killed mid-run once a few hundred messages are on disk: waiting on data, not on time,
    // holds on a loaded machine.
    let killed = out.join("session.mcap");
    let deadline = std::time::Instant::now() + Duration::from_secs(180);
    while readable_messages(&std::fs::read(&killed).unwrap_or_default()).len() < 300 {
        assert!(
            child.try_wait().expect("status").is_none(),
            "the run ended before the kill"
        );
        assert!(
            std::time::Instant::now() < deadline,
            "no 300 messages on disk after 180 s"
        );
        std::thread::sleep(Duration::from_millis(200));
    }
    child.kill().expect("SIGKILL");
    child.wait().expect("reap");
    let bytes = std::fs::read(&killed).expect("killed file");
    let expected = readable_messages(&bytes);
    assert!(
        expected.len() > 100,
        "{} messages before the kill",
        expected.len()
    );
    let output = dir.path().join("repaired.mcap");
    repair(&killed, &output);
    assert_eq!(python_messages(&output), expected);
    let s = read_session(&output).expect("repaired session");
    assert!(s.completeness.is_complete());
}

/// A kind's session from its example config, re-recorded with chunks of `chunk_size` bytes.
fn rechunked_kind_session(config: &str, dir: &Path, chunk_size: u64) -> (PathBuf, Vec<ChunkIndex>) {
    let run_dir = dir.join("run");
    let config = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("config")
        .join(config);
    run_config(&config, &run_dir);
    let path = dir.join("rechunked.mcap");
    let (_, chunks) = rechunked(&run_dir.join("session.mcap"), &path, chunk_size);
    (path, chunks)
}

/// A measurement window of the kinds that are not multilateration: its begin and end events
/// (indexes into `Session::events`) and their log times.
#[derive(Clone, Copy)]
struct KindWindow {
    begin_event: usize,
    end_event: usize,
    begin_ns: u64,
    end_ns: u64,
}

impl KindWindow {
    fn touched_by(&self, chunk: &ChunkIndex) -> bool {
        self.begin_ns <= chunk.message_end_time && chunk.message_start_time <= self.end_ns
    }

    /// Whether the chunk lies inside the window (its begin and end events survive) and holds
    /// some of its sensor readings, not all.
    fn cuts_inside(&self, chunk: &ChunkIndex, session: &Session) -> bool {
        let readings = session.probes.values().flatten().map(|r| r.log_time_ns);
        let messages = session.topics.values().flatten().map(|m| m.log_time_ns);
        let inside: Vec<bool> = readings
            .chain(messages)
            .filter(|t| self.begin_ns <= *t && *t <= self.end_ns)
            .map(|t| chunk.message_start_time <= t && t <= chunk.message_end_time)
            .collect();
        self.begin_ns < chunk.message_start_time
            && chunk.message_end_time < self.end_ns
            && inside.iter().any(|i| *i)
            && inside.iter().any(|i| !*i)
    }
}

fn kind_windows(session: &Session) -> Vec<KindWindow> {
    let mut open = None;
    let mut out = Vec::new();
    for (i, e) in session.events.iter().enumerate() {
        match e.msg {
            RunEvent::PoseBegin { .. }
            | RunEvent::ProbeBegin { .. }
            | RunEvent::ProbePointBegin { .. } => open = Some((i, e.log_time_ns)),
            RunEvent::PoseEnd { .. }
            | RunEvent::ProbeEnd { .. }
            | RunEvent::ProbePointEnd { .. } => {
                if let Some((begin_event, begin_ns)) = open.take() {
                    out.push(KindWindow {
                        begin_event,
                        end_event: i,
                        begin_ns,
                        end_ns: e.log_time_ns,
                    });
                }
            }
            _ => {}
        }
    }
    out
}

/// The session without `removed` windows: their begin and end events and every sensor reading
/// inside them.
fn without_windows(session: &Session, removed: &[KindWindow]) -> Session {
    let outside = |t: u64| !removed.iter().any(|w| w.begin_ns <= t && t <= w.end_ns);
    let mut out = session.clone();
    for readings in out.probes.values_mut() {
        readings.retain(|r| outside(r.log_time_ns));
    }
    for messages in out.topics.values_mut() {
        messages.retain(|m| outside(m.log_time_ns));
    }
    let bounds: std::collections::BTreeSet<usize> = removed
        .iter()
        .flat_map(|w| [w.begin_event, w.end_event])
        .collect();
    out.events = (out.events.into_iter().enumerate())
        .filter(|(i, _)| !bounds.contains(i))
        .map(|(_, e)| e)
        .collect();
    out
}

/// How many windows a kind's results used.
fn windows_used(results: &geocal::method::Results) -> usize {
    let json: serde_json::Value =
        serde_json::from_str(&results.to_json_pretty()).expect("results json");
    match json["kind"].as_str() {
        Some("hexapod") => json["poses"].as_u64().expect("poses") as usize,
        Some("probe_install") => json["points"].as_u64().expect("points") as usize,
        Some("rotary_sphere") => json["spheres"]
            .as_array()
            .expect("spheres")
            .iter()
            .map(|s| s["points"].as_u64().expect("points") as usize)
            .sum(),
        other => panic!("unexpected kind {other:?}"),
    }
}

#[test]
fn other_kinds_drop_the_windows_of_a_damaged_chunk_whole() {
    for config in ["hexapod.toml", "probe-install.toml", "rotary-sphere.toml"] {
        let dir = tempfile::tempdir().expect("tempdir");
        let (path, chunks) = rechunked_kind_session(config, dir.path(), 1);
        assert!(chunks.len() >= 6, "{config}: {} chunks", chunks.len());
        let intact = read_session(&path).expect("intact session");
        let all = windows_used(&solve_session(&intact, &SolveSettings::default()).expect("solve"));
        assert_eq!(
            all,
            kind_windows(&intact).len(),
            "{config}: every window used"
        );

        let windows = kind_windows(&intact);
        // Late in the run (the hexapod's reference pose 0 comes first), inside a window: its
        // begin and end survive with part of its readings, which must not be used. A kind
        // with one reading per window cannot be cut so; any window's chunk will do there.
        let late: Vec<(&ChunkIndex, Vec<KindWindow>)> = chunks[chunks.len() * 2 / 3..]
            .iter()
            .map(|c| {
                (
                    c,
                    windows
                        .iter()
                        .copied()
                        .filter(|w| w.touched_by(c))
                        .collect(),
                )
            })
            .collect();
        let (chunk, touched) = late
            .iter()
            .find(|(c, touched)| touched.iter().any(|w| w.cuts_inside(c, &intact)))
            .or_else(|| late.iter().find(|(_, touched)| !touched.is_empty()))
            .unwrap_or_else(|| panic!("{config}: no late chunk holds a window"));
        let mut bytes = std::fs::read(&path).expect("read");
        flip_chunk(&mut bytes, chunk);
        let damaged_path = dir.path().join("damaged.mcap");
        std::fs::write(&damaged_path, &bytes).expect("write");
        let damaged = read_session(&damaged_path).expect("damaged session reads");
        assert_eq!(
            damaged.damaged.len(),
            1,
            "{config}: one damaged chunk reported"
        );
        let results = solve_session(&damaged, &SolveSettings::default())
            .unwrap_or_else(|e| panic!("{config}: solve of the damaged session: {e}"));
        let expected = solve_session(
            &without_windows(&intact, touched),
            &SolveSettings::default(),
        )
        .expect("solve without the touched windows");
        assert!(
            windows_used(&results) <= all - touched.len(),
            "{config}: {} of {all} windows used, {} touched the chunk",
            windows_used(&results),
            touched.len()
        );
        assert_eq!(
            results.to_json_pretty(),
            expected.to_json_pretty(),
            "{config}: the damaged session solves as the session without the touched windows"
        );
    }
}

#[test]
fn results_written_before_damaged_chunks_existed_still_parse() {
    let (results, _) = solve_without_windows(&[]);
    let mut json = serde_json::to_value(&results).expect("to json");
    let extraction = json["extraction"].as_object_mut().expect("extraction");
    assert!(extraction.remove("damaged_chunks").is_some());
    let parsed: MultilaterationResults =
        serde_json::from_value(json).expect("results without damaged_chunks parse");
    assert_eq!(parsed, results);
}
