//! Fuzzing with byte mutations (proptest; cargo-fuzz needs a nightly toolchain CI lacks): the
//! session reader, the HPI-3D, GRBL and ASCII-probe codecs and the Modbus register maps are
//! fed mutated seeds from `fuzz/corpus/<target>/`. Any panic, a case slower than
//! `SLOW_CASE` (a hang) or an allocation above `MAX_ALLOCATION` fails; a failing input goes
//! to `fuzz/regressions/<target>/`, which every run replays first.
//!
//! CI runs each target for `GEOCAL_FUZZ_SECONDS` (default 3) or `PROPTEST_CASES` cases
//! (default 2000), whichever ends first. A longer run (docs/repair.md, "Fuzzing"):
//! `GEOCAL_FUZZ_SECONDS=600 PROPTEST_CASES=1000000 cargo test --release --test fuzz`.

use std::alloc::{GlobalAlloc, Layout, System};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use proptest::prelude::*;
use proptest::test_runner::{Config, TestCaseError, TestRunner};

/// Records the largest single allocation, so that a size read from the input cannot make a
/// small input allocate gigabytes unnoticed.
struct Largest;

static LARGEST: AtomicUsize = AtomicUsize::new(0);

unsafe impl GlobalAlloc for Largest {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        LARGEST.fetch_max(layout.size(), Ordering::Relaxed);
        System.alloc(layout)
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        System.dealloc(ptr, layout)
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        LARGEST.fetch_max(new_size, Ordering::Relaxed);
        System.realloc(ptr, layout, new_size)
    }
}

#[global_allocator]
static ALLOCATOR: Largest = Largest;

/// The session reader bounds a chunk's claimed size at 1024x its stored size + 1 MiB; inputs
/// here are at most a few hundred KiB.
const MAX_ALLOCATION: usize = 512 << 20;
const SLOW_CASE: Duration = Duration::from_secs(10);

fn fuzz_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz")
}

fn files(dir: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    let mut out: Vec<_> = std::fs::read_dir(dir)
        .map(|rd| rd.filter_map(Result::ok).map(|e| e.path()).collect())
        .unwrap_or_default();
    out.sort();
    out.into_iter()
        .filter_map(|p| std::fs::read(&p).ok().map(|b| (p, b)))
        .collect()
}

fn env_or<T: std::str::FromStr>(name: &str, default: T) -> T {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

#[derive(Debug, Clone)]
enum Mutation {
    Flip(usize, u8),
    Set(usize, u8),
    Insert(usize, Vec<u8>),
    Remove(usize, usize),
    Truncate(usize),
    /// Copies a range of the input over another place (duplicated records, shifted lengths).
    Splice(usize, usize, usize),
}

fn mutation() -> impl Strategy<Value = Mutation> {
    prop_oneof![
        (any::<usize>(), 1..=255u8).prop_map(|(i, b)| Mutation::Flip(i, b)),
        (
            any::<usize>(),
            prop_oneof![Just(0u8), Just(0xFF), Just(0x7F), Just(0x80), any::<u8>()]
        )
            .prop_map(|(i, b)| Mutation::Set(i, b)),
        (any::<usize>(), prop::collection::vec(any::<u8>(), 1..16))
            .prop_map(|(i, v)| Mutation::Insert(i, v)),
        (any::<usize>(), 1..64usize).prop_map(|(i, n)| Mutation::Remove(i, n)),
        any::<usize>().prop_map(Mutation::Truncate),
        (any::<usize>(), any::<usize>(), 1..256usize)
            .prop_map(|(a, b, n)| Mutation::Splice(a, b, n)),
    ]
}

fn apply(seed: &[u8], mutations: &[Mutation]) -> Vec<u8> {
    let mut b = seed.to_vec();
    for m in mutations {
        let len = b.len().max(1);
        match m {
            Mutation::Flip(i, x) => {
                if let Some(v) = b.get_mut(i % len) {
                    *v ^= x;
                }
            }
            Mutation::Set(i, x) => {
                if let Some(v) = b.get_mut(i % len) {
                    *v = *x;
                }
            }
            Mutation::Insert(i, v) => {
                let at = i % (b.len() + 1);
                b.splice(at..at, v.iter().copied());
            }
            Mutation::Remove(i, n) => {
                let at = i % len;
                let end = (at + n).min(b.len());
                if at < end {
                    b.drain(at..end);
                }
            }
            Mutation::Truncate(i) => b.truncate(i % (b.len() + 1)),
            Mutation::Splice(from, to, n) => {
                if !b.is_empty() {
                    let from = from % b.len();
                    let n = (*n).min(b.len() - from);
                    let piece = b[from..from + n].to_vec();
                    let to = to % b.len();
                    let end = (to + n).min(b.len());
                    b.splice(to..end, piece);
                }
            }
        }
    }
    b
}

/// Runs `target` on every regression input, then on mutated seeds for the time budget.
fn fuzz(name: &str, target: fn(&[u8])) {
    let check = |input: &[u8]| -> Result<(), String> {
        LARGEST.store(0, Ordering::Relaxed);
        let started = Instant::now();
        let result = std::panic::catch_unwind(|| target(input));
        let elapsed = started.elapsed();
        let largest = LARGEST.load(Ordering::Relaxed);
        match result {
            Err(_) => Err("panicked".into()),
            Ok(()) if elapsed > SLOW_CASE => Err(format!("took {elapsed:?}")),
            Ok(()) if largest > MAX_ALLOCATION => Err(format!("allocated {largest} bytes at once")),
            Ok(()) => Ok(()),
        }
    };
    let regressions = fuzz_dir().join("regressions").join(name);
    for (path, input) in files(&regressions) {
        if let Err(why) = check(&input) {
            panic!("{name}: regression input {} {why}", path.display());
        }
    }
    let seeds: Vec<Vec<u8>> = files(&fuzz_dir().join("corpus").join(name))
        .into_iter()
        .map(|(_, b)| b)
        .collect();
    assert!(!seeds.is_empty(), "{name}: no seeds in fuzz/corpus/{name}");
    let budget = Duration::from_secs_f64(env_or("GEOCAL_FUZZ_SECONDS", 3.0));
    let cases = env_or("PROPTEST_CASES", 2000u32);
    let mut runner = TestRunner::new(Config {
        cases,
        failure_persistence: None,
        ..Config::default()
    });
    let deadline = Instant::now() + budget;
    let strategy = (0..seeds.len(), prop::collection::vec(mutation(), 1..8));
    let ran = std::cell::Cell::new(0u64);
    let result = runner.run(&strategy, |(seed, mutations)| {
        if Instant::now() > deadline {
            return Ok(());
        }
        ran.set(ran.get() + 1);
        let input = apply(&seeds[seed], &mutations);
        check(&input).map_err(TestCaseError::fail)
    });
    if let Err(failure) = result {
        // Keep the (shrunk) input as a regression test.
        let message = failure.to_string();
        let _ = std::fs::create_dir_all(&regressions);
        if let proptest::test_runner::TestError::Fail(_, (seed, mutations)) = &failure {
            let input = apply(&seeds[*seed], mutations);
            let path = regressions.join(format!("found-{}", input.len()));
            let _ = std::fs::write(&path, &input);
            panic!("{name}: {message}; input kept in {}", path.display());
        }
        panic!("{name}: {message}");
    }
    println!("{name}: {} mutated inputs, no finding", ran.get());
}

#[test]
fn fuzz_session_reader() {
    fuzz("session_reader", |b| {
        let _ = geocal::session::read_session_bytes(b);
    });
}

#[test]
fn fuzz_hpi3d_codec() {
    use geocal_drivers::hpi3d::{codec, DeviceDecoder, HostDecoder};
    fuzz("hpi3d_codec", |b| {
        let _ = DeviceDecoder::new().feed(b);
        let _ = HostDecoder::new().feed(b);
        let _ = codec::decode_device(b);
        let _ = codec::decode_host(b);
    });
}

#[test]
fn fuzz_grbl_codec() {
    use geocal_drivers::grbl::codec::{parse_block, parse_controller_line, Framed, LineFramer};
    fuzz("grbl_codec", |b| {
        for framer in [LineFramer::new(256), LineFramer::with_realtime(256)] {
            let mut framer = framer;
            for item in framer.push(b) {
                if let Framed::Line(line) = item {
                    let _ = parse_controller_line(&line);
                    let _ = parse_block(&line);
                }
            }
        }
    });
}

#[test]
fn fuzz_probe_codec() {
    use geocal_drivers::probe::codec::ProbeProtocol;
    let protocol = ProbeProtocol::new(
        "M0\r",
        r"^M0,(?P<value>[+-]?\d+(?:\.\d+)?)$",
        Some(r"^ER,\w+,(?P<code>\d+)$"),
        1e-3,
    )
    .expect("the default probe protocol");
    static PROTOCOL: std::sync::OnceLock<ProbeProtocol> = std::sync::OnceLock::new();
    let _ = PROTOCOL.set(protocol);
    fuzz("probe_codec", |b| {
        let protocol = PROTOCOL.get().expect("set above");
        for line in String::from_utf8_lossy(b).split(['\r', '\n']) {
            let _ = protocol.parse_line(line);
        }
    });
}

/// A map as TOML text (the config a table or hexapod is driven by), then register words.
fn map_input(b: &[u8]) -> (String, Vec<u16>) {
    let split = b.iter().position(|&x| x == 0).unwrap_or(b.len());
    let text = String::from_utf8_lossy(&b[..split]).into_owned();
    let words = b[split.saturating_add(1).min(b.len())..]
        .chunks(2)
        .map(|c| u16::from_le_bytes([c[0], *c.get(1).unwrap_or(&0)]))
        .collect();
    (text, words)
}

#[test]
fn fuzz_modbus_table_map() {
    use geocal_drivers::modbus_table::map::RegisterMap;
    fuzz("modbus_table_map", |b| {
        let (text, words) = map_input(b);
        let Ok(map) = toml::from_str::<RegisterMap>(&text) else {
            return;
        };
        if map.validate().is_err() {
            return;
        }
        for register in [&map.target, &map.actual] {
            let n = usize::from(register.words());
            for w in words.chunks(n) {
                if let Some(angle) = register.decode_rad(w) {
                    // A decoded angle encodes back to the same words.
                    if w.len() == n && angle.is_finite() {
                        if let Ok(back) = register.encode_rad(angle) {
                            assert_eq!(back, w, "{text}");
                        }
                    }
                }
            }
        }
        let _ = words.first().map(|&w| map.acknowledged(w));
    });
}

#[test]
fn fuzz_modbus_hexapod_map() {
    use geocal_drivers::modbus_hexapod::HexapodRegisterMap;
    fuzz("modbus_hexapod_map", |b| {
        let (text, words) = map_input(b);
        let Ok(map) = toml::from_str::<HexapodRegisterMap>(&text) else {
            return;
        };
        if map.validate().is_err() {
            return;
        }
        let _ = map.pose_target.decode(&words);
        let _ = map.legs.decode(&words);
        let n = usize::from(map.legs.block_words());
        if let Some(lengths) = words.get(..n).and_then(|w| map.legs.decode(w)) {
            let _ = map.legs.encode(&lengths);
        }
    });
}

/// Writes the seeds: `cargo test --test integration fuzz::write_seeds -- --ignored`.
#[test]
#[ignore = "regenerates fuzz/corpus"]
fn write_seeds() {
    let corpus = fuzz_dir().join("corpus");
    let put = |target: &str, name: &str, bytes: &[u8]| {
        let dir = corpus.join(target);
        std::fs::create_dir_all(&dir).expect("corpus dir");
        std::fs::write(dir.join(name), bytes).expect("seed");
    };
    // A small session: header, events and samples over several small chunks.
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("s.mcap");
    let rec = geocal::session::Recorder::create(
        &path,
        geocal::session::RecorderOptions {
            chunk_size: 1024,
            flush_interval: Duration::from_secs(3600),
            ..Default::default()
        },
    )
    .expect("recorder");
    let h = rec.handle();
    let header: geocal::session::messages::SessionHeader = serde_json::from_value(
        serde_json::json!({"format": "geocal-session/1", "session_id": "seed", "started_at": "2026-11-01T10:00:00Z",
            "kind": "multilateration", "machine": {"name": "m", "structure": "FYXZ", "axes": ["x","y","z"],
            "travel_m": {}, "targets": []}, "devices": [], "plan": {}}),
    )
    .expect("header");
    h.session(&header, 1);
    for i in 0..120u64 {
        let s = geocal::session::messages::TracerSample {
            seq: i,
            t_s: i as f64 * 1e-3,
            length_m: 0.1 + i as f64 * 1e-6,
            signal: 0.9,
            tracking: true,
            beam_segment: 0,
        };
        h.tracer("t0", &s, 10 + i);
        if i % 40 == 0 {
            h.event(
                &geocal::session::messages::RunEvent::StationBegin {
                    station: "s1".into(),
                    station_index: 0,
                    hint_m: None,
                },
                10 + i,
            );
        }
    }
    rec.finish().expect("finish");
    put(
        "session_reader",
        "small.mcap",
        &std::fs::read(&path).expect("seed"),
    );
    use geocal_drivers::hpi3d::{codec, DeviceFrame, Distance, HostCommand, HostFrame, Status};
    let mut stream = Vec::new();
    for i in 0..6i64 {
        stream.extend(codec::encode_device(&DeviceFrame::Distance(Distance {
            position_counts: i * 1_234_567 - 3_000_000,
            spare: [0, 0],
            status: Status::default(),
        })));
    }
    stream.extend(codec::encode_device(&DeviceFrame::Ack {
        command: HostCommand::Home,
        data: [0; 12],
    }));
    for command in HostCommand::KNOWN {
        stream.extend(codec::encode_host(&HostFrame::new(command)));
    }
    put("hpi3d_codec", "frames.bin", &stream);
    put(
        "grbl_codec",
        "lines.txt",
        b"Grbl 1.1h ['$' for help]\r\nok\r\n<Idle|MPos:10.000,-2.500,0.000|FS:0,0>\r\n\
          error:9\r\nALARM:1\r\n[MSG:Reset to continue]\r\nG1 X10.5 Y-3 F600\r\nG4 P0.5\r\n?~!\x18\n",
    );
    put(
        "probe_codec",
        "replies.txt",
        b"M0,+012.345\r\nM0,-000.001\r\nER,M0,01\r\nM0,abc\r\n",
    );
    put(
        "modbus_table_map",
        "map.toml",
        b"unit_id = 1\ntarget = { address = 100, width_bits = 32, word_order = \"big\", counts_per_rad = 57295.78 }\n\
          actual = { address = 200, kind = \"input\", width_bits = 16, word_order = \"little\", signed = false, rad_per_count = 1e-4 }\n\
          status = { address = 300, kind = \"input\", in_position_bit = 0, moving_bit = 1, fault_bit = 2 }\n\
          command = { address = 110, go_value = 1, clear_value = 0 }\nack = { bit = 3 }\n\
          fault_code = { address = 301, kind = \"input\" }\n\x00\x10\x27\xff\xff\x00\x80\x01\x00",
    );
    put(
        "modbus_hexapod_map",
        "map.toml",
        b"pose_target = { address = 100, counts_per_m = 1e7, counts_per_rad = 1e7 }\n\
          legs = { address = 200, kind = \"input\", m_per_count = 1e-7 }\n\
          status = { address = 300, kind = \"input\", in_position_bit = 0, moving_bit = 1, fault_bit = 2 }\n\
          command = { address = 120, go_value = 1, clear_value = 0 }\nack = { bit = 3 }\n\
          \x00\x01\x00\x02\x00\x03\x00\x04\x00\x05\x00\x06\x00\x07\x00\x08\x00\x09\x00\x0a\x00\x0b\x00\x0c\x00",
    );
}
