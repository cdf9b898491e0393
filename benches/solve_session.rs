//! Whole-pipeline benchmark: a recorded 10 000-point x 16-station session (~1.7 M raw tracer
//! samples) solved as `geocal solve` does it, timed phase by phase with the heap peak of each;
//! then `geocal solve` end to end (wall time, peak RSS) on 1k, 10k and 100k points x 16
//! stations and on a 10x denser recording of the 10k plan, side by side with the Ceres Solver
//! peer (bench/ceres_multilateration.cc, optional) on the same extracted problem.
//!
//! `cargo bench --bench solve_session [-- NAME...]`: only the cases whose name contains one of
//! the NAMEs (`phases`, `1k`, `10k`, `10k-dense`, `100k`). `-- floor`: what reading each 10k
//! file cannot go below, beside the parts of geocal's read and solve.

mod common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use geocal::extract::{extract_points, ExtractOptions, LengthStream, NoiseModel};
use geocal::session::messages::{
    AxisMap, DeviceInfo, MachineInfo, RunEvent, SessionHeader, TargetInfo, TracerSample,
    SESSION_FORMAT,
};
use geocal::session::reader::{read_session, read_session_bytes, stream_session, Session};
use geocal::session::recorder::{Recorder, RecorderOptions};
use geocal::solve::multilateration::{
    best_fit_rigid, initial_stations, solve, MultilaterationProblem, SolveOptions,
};
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use common::{fmt_time, measure, median, mib};

/// The phase table's session: 10 000 points.
const GRID: [usize; 3] = [20, 25, 20];
const STATIONS: usize = 16;
const TRACER: &str = "tracer0";
/// Tracer sample period (20 Hz) and the dwell: 9 settled samples = 0.4 s.
const DT_S: f64 = 0.05;
const DWELL_SAMPLES: usize = 9;
/// Machine feed between points: a short grid step takes 1-2 samples of motion.
const FEED_M_S: f64 = 1.0;
/// Per-sample tracer noise (sigma = a + b*(|station - target| + dead path), the absolute optical
/// path; no dead path here), declared in the header as the session's model.
const NOISE_M: f64 = 1.0e-7;
const NOISE_PPM: f64 = 0.1;
/// Stillstand window in the recorded plan: shorter than the dwell, so every dwell settles.
const WINDOW_S: f64 = 0.3;
const TOLERANCE_M: f64 = 2e-6;
/// Bump when the generator changes, so a stale cached file is not reused.
const DATA_VERSION: u32 = 2;

/// `rate`: the tracer's rate over the base 20 Hz (the same plan, `rate` times the samples).
fn data_path(grid: [usize; 3], rate: usize) -> PathBuf {
    let dense = if rate == 1 {
        String::new()
    } else {
        format!("-r{rate}")
    };
    Path::new(env!("CARGO_MANIFEST_DIR")).join(format!(
        "target/bench-data/session-{}x{STATIONS}{dense}-v{DATA_VERSION}.mcap",
        grid.iter().product::<usize>()
    ))
}

/// Grid points in serpentine visiting order (x fastest, rows and layers alternating), so every
/// move is one grid step; the index in this order is the plan point index, 0 = homing point.
fn plan_points(grid: [usize; 3]) -> Vec<[f64; 3]> {
    let size = [1.4, 2.4, 1.0];
    let coord = |k: usize, i: usize| size[k] * i as f64 / (grid[k] - 1) as f64;
    let mut points = Vec::with_capacity(grid.iter().product());
    for iz in 0..grid[2] {
        for row in 0..grid[1] {
            let iy = if iz % 2 == 0 { row } else { grid[1] - 1 - row };
            for col in 0..grid[0] {
                let ix = if (iz * grid[1] + row) % 2 == 0 {
                    col
                } else {
                    grid[0] - 1 - col
                };
                points.push([coord(0, ix), coord(1, iy), coord(2, iz)]);
            }
        }
    }
    points
}

fn true_stations() -> Vec<Vector3<f64>> {
    (0..STATIONS)
        .map(|k| {
            let a = k as f64 * std::f64::consts::TAU / STATIONS as f64;
            Vector3::new(
                0.7 + 1.8 * a.cos(),
                1.2 + 2.2 * a.sin(),
                -0.3 + 0.4 * (k % 4) as f64,
            )
        })
        .collect()
}

fn header(grid: [usize; 3], rate: usize) -> SessionHeader {
    let dt_s = DT_S / rate as f64;
    SessionHeader {
        format: SESSION_FORMAT.into(),
        session_id: format!("bench-multilateration-{DATA_VERSION}"),
        started_at: "2026-01-01T00:00:00Z".into(),
        kind: "multilateration".into(),
        machine: MachineInfo {
            name: "Bridge CMM 14-24-10 (bench)".into(),
            structure: "FYXZ".into(),
            axes: vec!["x".into(), "y".into(), "z".into()],
            travel_m: BTreeMap::from([
                ("x".into(), [0.0, 1.4]),
                ("y".into(), [0.0, 2.4]),
                ("z".into(), [0.0, 1.0]),
            ]),
            targets: vec![TargetInfo {
                id: "t0".into(),
                offset_m: [0.0, 0.0, 0.0],
            }],
        },
        devices: vec![DeviceInfo {
            id: TRACER.into(),
            kind: "tracer".into(),
            driver: "sim".into(),
            noise_m: Some(NOISE_M),
            noise_ppm: Some(NOISE_PPM),
            dead_path_m: Some(0.0),
            wavelength_m: Some(6.33e-7),
            compensated: Some(true),
            extra: BTreeMap::from([("sample_rate_hz".into(), (1.0 / dt_s).into())]),
        }],
        plan: serde_json::json!({
            "target": "t0",
            "passes": ["forward"],
            "dwell_s": DWELL_SAMPLES as f64 * DT_S,
            "stillstand": {"window_s": WINDOW_S, "tolerance_m": TOLERANCE_M},
            "grid": {"count": grid, "order": "serpentine"},
        }),
    }
}

/// The true points: the plan's plus uniform deviations, the first draws of the generator's
/// random stream (so the truth is known again without the session).
fn truth_points(grid: [usize; 3], rng: &mut ChaCha8Rng) -> Vec<Vector3<f64>> {
    plan_points(grid)
        .iter()
        .map(|p| Vector3::from(*p) + Vector3::from_fn(|_, _| rng.random_range(-4e-6..4e-6)))
        .collect()
}

fn generator_rng() -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(20260101)
}

/// Writes the session as the sequencer would record it: per station a `station_begin`, then
/// per point the motion samples, `point_begin`, the dwell samples, `point_end`.
fn generate(path: &Path, grid: [usize; 3], rate: usize) {
    let t0 = Instant::now();
    let mut rng = generator_rng();
    let nominal = plan_points(grid);
    let truth = truth_points(grid, &mut rng);
    let dt_s = DT_S / rate as f64;
    let dwell_samples = DWELL_SAMPLES * rate;
    let stations = true_stations();
    std::fs::create_dir_all(path.parent().expect("parent")).expect("bench-data dir");
    // Written under another name first: an interrupted run never leaves a cached half file.
    let tmp = path.with_extension("mcap.partial");
    let recorder = Recorder::create(&tmp, RecorderOptions::default()).expect("recorder");
    let h = recorder.handle();
    // 2026-01-01T00:00:00Z, the header's started_at.
    let epoch_ns: u64 = 1_767_225_600_000_000_000;
    // Host reception lags the device clock by a couple of milliseconds.
    let log_ns = |t_s: f64| epoch_ns + (t_s * 1e9).round() as u64 + 2_000_000;
    h.session(&header(grid, rate), epoch_ns);
    let mut seq = 0u64;
    let mut t_s = 0.0;
    let mut samples = 0u64;
    let mut sample = |t_s: f64, length_m: f64, beam_m: f64, rng: &mut ChaCha8Rng| {
        let sigma = NOISE_M + NOISE_PPM * 1e-6 * beam_m;
        let s = TracerSample {
            seq,
            t_s,
            length_m: length_m + sigma * rng.sample::<f64, _>(StandardNormal),
            signal: 0.95,
            tracking: true,
            beam_segment: 0,
        };
        h.tracer(TRACER, &s, log_ns(t_s));
        seq += 1;
        samples += 1;
    };
    let axes = |p: &[f64; 3]| -> AxisMap<f64> { ["x", "y", "z"].into_iter().zip(*p).collect() };
    for (j, station) in stations.iter().enumerate() {
        let id = format!("s{}", j + 1);
        let hint = station + Vector3::from_fn(|_, _| rng.random_range(-0.03..0.03));
        // The operator moves the tracer: minutes pass between stations.
        t_s += 180.0;
        h.event(
            &RunEvent::StationBegin {
                station: id.as_str().into(),
                station_index: j,
                hint_m: Some([hint.x, hint.y, hint.z]),
            },
            log_ns(t_s),
        );
        let home = (station - truth[0]).norm();
        let length = |x: &Vector3<f64>| (station - x).norm() - home;
        let mut approach: AxisMap<i8> = ["x", "y", "z"].into_iter().map(|a| (a, 0)).collect();
        for (i, nom) in nominal.iter().enumerate() {
            if i > 0 {
                let from = truth[i - 1];
                let steps = ((truth[i] - from).norm() / FEED_M_S / dt_s).ceil().max(1.0) as usize;
                for k in 0..steps {
                    t_s += dt_s;
                    let x = from + (truth[i] - from) * (k as f64 / steps as f64);
                    sample(t_s, length(&x), (station - x).norm(), &mut rng);
                }
                for (a, axis) in ["x", "y", "z"].iter().enumerate() {
                    let d = nom[a] - nominal[i - 1][a];
                    if d != 0.0 {
                        approach.insert(*axis, d.signum() as i8);
                    }
                }
            }
            t_s += dt_s;
            h.event(
                &RunEvent::PointBegin {
                    station: id.as_str().into(),
                    point: i,
                    pass: 0,
                    target: "t0".into(),
                    nominal_m: *nom,
                    axes: axes(nom),
                    approach: approach.clone(),
                },
                log_ns(t_s) - 1_000_000,
            );
            let at = length(&truth[i]);
            let beam = (station - truth[i]).norm();
            for k in 0..dwell_samples {
                if k > 0 {
                    t_s += dt_s;
                }
                sample(t_s, at, beam, &mut rng);
            }
            h.event(
                &RunEvent::PointEnd {
                    station: id.as_str().into(),
                    point: i,
                    pass: 0,
                },
                log_ns(t_s) + 1_000_000,
            );
        }
        h.event(
            &RunEvent::StationEnd { station: id.into() },
            log_ns(t_s) + 2_000_000,
        );
    }
    drop(h);
    let stats = recorder.finish().expect("finish session");
    std::fs::rename(&tmp, path).expect("rename session");
    println!(
        "generated {} ({} tracer samples, {} messages, {:.1} MB) in {}",
        path.display(),
        samples,
        stats.messages,
        stats.bytes as f64 / 1e6,
        fmt_time(t0.elapsed())
    );
}

struct Phase {
    name: &'static str,
    times: Vec<Duration>,
    cpu: Vec<Duration>,
    peak_bytes: usize,
    heap_after: usize,
    note: String,
}

impl Phase {
    fn new(name: &'static str) -> Self {
        Phase {
            name,
            times: Vec::new(),
            cpu: Vec::new(),
            peak_bytes: 0,
            heap_after: 0,
            note: String::new(),
        }
    }

    fn median_wall(&self) -> Duration {
        median(self.times.clone())
    }

    /// None where the process's CPU time could not be read.
    fn median_cpu(&self) -> Option<Duration> {
        (!self.cpu.is_empty()).then(|| median(self.cpu.clone()))
    }

    /// The median CPU time as a table cell ("-" where it could not be read).
    fn cpu_cell(&self) -> String {
        self.median_cpu().map_or("-".to_string(), fmt_time)
    }

    /// Times `f`; keeps the largest heap peak (above the heap at its start) over the runs.
    fn run<T>(&mut self, f: impl FnOnce() -> T) -> T {
        let cpu0 = common::cpu_time();
        let (v, dt, peak) = measure(f);
        if let (Some(a), Some(b)) = (cpu0, common::cpu_time()) {
            self.cpu.push(b.saturating_sub(a));
        }
        self.times.push(dt);
        self.peak_bytes = self.peak_bytes.max(peak);
        self.heap_after = common::heap_now();
        v
    }
}

/// The cached session of this plan and rate, generated on first use.
fn session_file(grid: [usize; 3], rate: usize) -> PathBuf {
    let path = data_path(grid, rate);
    if !path.exists() {
        println!("no cached session at {}: generating it", path.display());
        generate(&path, grid, rate);
    }
    path
}

fn main() {
    let filters: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with('-'))
        .collect();
    let wanted = |name: &str| filters.is_empty() || filters.iter().any(|f| name.contains(f));
    if wanted("phases") {
        phases();
    }
    if filters.iter().any(|f| f == "floor") {
        floor();
    }
    let cases: Vec<Case> = CASES.iter().copied().filter(|c| wanted(c.name)).collect();
    if !cases.is_empty() {
        compare_with_ceres(&cases);
    }
}

/// The 10k session's phases, each timed with its heap peak.
fn phases() {
    let path = session_file(GRID, 1);
    let file_bytes = std::fs::metadata(&path).map(|m| m.len()).unwrap_or(0);
    let repeats = 3;
    let mut file_read = Phase::new("file read (std::fs::read)");
    let mut decode = Phase::new("decode (read_session_bytes: zstd + JSON)");
    let mut read = Phase::new("read_session (file read + decode)");
    let mut extract = Phase::new("extract_points (stillstand, averaging)");
    let mut build = Phase::new("build problem");
    let mut adjust = Phase::new("solve + covariance (solve::multilateration::solve)");
    let mut method = Phase::new("method::solve_session (extract + build + solve + results)");
    let mut streamed = Phase::new("stream_session + LengthStream (read + extract, streamed)");
    let mut whole = Phase::new("run::solve_file (everything)");
    for _ in 0..repeats {
        let bytes = file_read.run(|| std::fs::read(&path).expect("read file"));
        let session = decode.run(|| read_session_bytes(&bytes).expect("decode"));
        drop(session);
        drop(bytes);
        let session: Session = read.run(|| read_session(&path).expect("read_session"));
        let tracer = session.tracers.keys().next().expect("tracer").clone();
        let samples = session.tracers[&tracer].len();
        read.note = format!(
            "{samples} tracer samples, {} events, {:.1} MB file",
            session.events.len(),
            file_bytes as f64 / 1e6
        );
        let noise = NoiseModel::from_header(&session.header, &tracer);
        let options = ExtractOptions::from_header(&session.header);
        let extraction = extract
            .run(|| extract_points(&session, Some(&tracer), noise, &options).expect("extract"));
        extract.note = format!(
            "{} windows used, {} dropped",
            extraction.measurements.len(),
            extraction.dropped.len()
        );
        let problem =
            build.run(|| geocal::method::multilateration::Problem::build(&extraction).problem);
        let solution = adjust.run(|| solve(&problem, &SolveOptions::default()).expect("solve"));
        adjust.note = format!(
            "n={} m={} obs={} iterations={} chi2/dof={:.3}",
            problem.nominal_points.len(),
            problem.station_hints.len(),
            problem.observations.len(),
            solution.iterations,
            solution.chi2 / solution.dof as f64
        );
        drop((solution, problem, extraction));
        let results = method.run(|| {
            geocal::kinds::registry::solve_session(&session, &Default::default()).expect("method")
        });
        drop(results);
        drop(session);
        let (read_back, lengths, held) = streamed.run(|| {
            let mut sink = LengthStream::new("multilateration");
            let read_back = stream_session(&path, &mut sink).expect("a clean file streams");
            let held = sink.peak_samples;
            (read_back, sink.finish().expect("begun").0, held)
        });
        streamed.note = format!(
            "{} windows used; at most {held} tracer samples, {} messages waiting, {} chunks \
             decoded at once",
            lengths.measurements.len(),
            read_back.peak_held_messages,
            read_back.peak_chunks_in_flight
        );
        drop((read_back, lengths));
        let results = whole
            .run(|| geocal::kinds::solve_file(&path, &Default::default()).expect("solve_file"));
        let r = results.multilateration().expect("tracer results");
        whole.note = format!(
            "residual RMS {:.1} nm, {} points",
            r.residual_rms_m * 1e9,
            r.points.len()
        );
    }
    println!();
    println!(
        "whole pipeline on {} ({:.1} MB), median of {repeats} runs; peak heap = the highest \
         heap above the phase's starting heap; heap after = live heap when it returned; CPU time = \
         user + system of all threads (10 ms resolution)",
        path.display(),
        file_bytes as f64 / 1e6
    );
    println!("| phase | wall time | CPU time | peak heap | heap after | notes |");
    println!("|---|---:|---:|---:|---:|---|");
    for p in [
        &file_read, &decode, &read, &extract, &build, &adjust, &method, &streamed, &whole,
    ] {
        println!(
            "| {} | {} | {} | {:.0} MiB | {:.0} MiB | {} |",
            p.name,
            fmt_time(p.median_wall()),
            p.cpu_cell(),
            mib(p.peak_bytes),
            mib(p.heap_after),
            p.note
        );
    }
    let sum = [&read, &extract, &build, &adjust]
        .iter()
        .map(|p| median(p.times.clone()))
        .sum::<Duration>();
    println!(
        "\nread + extract + build + solve = {} (reference: ~2 s for a C++ bundle adjuster on \
         the extracted problem alone)",
        fmt_time(sum)
    );
}

/// A sink that drops everything: the streamed read alone, without the extraction.
struct Discard;

impl geocal::session::reader::SessionSink for Discard {
    fn begin(&mut self, _: &SessionHeader, _: &[String], _: usize) -> bool {
        true
    }

    fn batch(
        &mut self,
        _: &mut [Vec<geocal::session::reader::Stamped<TracerSample>>],
        _: &mut Vec<geocal::session::reader::Stamped<RunEvent>>,
    ) -> bool {
        true
    }
}

/// Where a file's compressed pieces are: (offset, stored bytes, compression, uncompressed
/// bytes) of every chunk, from the summary; a file without chunks in 1 MiB pieces (as
/// geocal's reader reads it).
type Piece = (u64, usize, String, usize);

fn compressed_pieces(path: &Path) -> Vec<Piece> {
    let bytes = std::fs::read(path).expect("read session");
    match mcap::Summary::read(&bytes).expect("summary") {
        Some(s) if !s.chunk_indexes.is_empty() => s
            .chunk_indexes
            .iter()
            .map(|c| {
                let start = c.chunk_start_offset + c.chunk_length - c.compressed_size;
                let (stored, uncompressed) = (c.compressed_size, c.uncompressed_size);
                (
                    start,
                    stored as usize,
                    c.compression.clone(),
                    uncompressed as usize,
                )
            })
            .collect(),
        _ => {
            // Runs of whole records from after the magic, each at least 1 MiB.
            let mut pieces = Vec::new();
            let (mut start, mut at) = (8, 8);
            while at + 9 <= bytes.len() {
                let len = u64::from_le_bytes(bytes[at + 1..at + 9].try_into().expect("8 bytes"));
                at += 9 + len as usize;
                if at - start >= 1 << 20 || at + 9 > bytes.len() {
                    pieces.push((start as u64, at - start, String::new(), at - start));
                    start = at;
                }
            }
            pieces
        }
    }
}

/// Converts every JSON number with a fraction or exponent in the messages of `records` (whole
/// MCAP records) to an f64, as any reader of the samples must; returns how many.
fn convert_floats(records: &[u8], sum: &mut f64) -> usize {
    const MESSAGE: u8 = 0x05;
    let mut converted = 0;
    let mut at = 0;
    while at + 9 <= records.len() {
        let len = u64::from_le_bytes(records[at + 1..at + 9].try_into().expect("8 bytes"));
        let end = (at + 9 + len as usize).min(records.len());
        if records[at] == MESSAGE && end >= at + 9 + 22 {
            let data = &records[at + 9 + 22..end];
            let mut i = 0;
            while i < data.len() {
                if data[i] == b':'
                    && data
                        .get(i + 1)
                        .is_some_and(|b| b.is_ascii_digit() || *b == b'-')
                {
                    let number = &data[i + 1..];
                    let n = number
                        .iter()
                        .position(|b| !matches!(b, b'0'..=b'9' | b'.' | b'e' | b'E' | b'-' | b'+'))
                        .unwrap_or(number.len());
                    if number[..n].iter().any(|b| matches!(b, b'.' | b'e' | b'E')) {
                        if let Ok(value) = lexical_core::parse::<f64>(&number[..n]) {
                            *sum += value;
                            converted += 1;
                        }
                    }
                    i += n;
                }
                i += 1;
            }
        }
        at = end;
    }
    converted
}

/// Every piece of `path` read from the file and decompressed on `threads` threads into a
/// buffer each thread reuses, nothing else: what any reader of the file spends at least; with
/// `floats`, also every float of its messages converted. Returns the bytes decompressed and
/// the floats converted.
fn read_and_decompress(
    path: &Path,
    pieces: &[Piece],
    threads: usize,
    floats: bool,
) -> (usize, usize) {
    use std::os::unix::fs::FileExt;
    use std::sync::atomic::{AtomicUsize, Ordering};
    let file = std::fs::File::open(path).expect("open session");
    let next = AtomicUsize::new(0);
    let total = AtomicUsize::new(0);
    let converted = AtomicUsize::new(0);
    std::thread::scope(|scope| {
        for _ in 0..threads {
            scope.spawn(|| {
                let mut stored = Vec::new();
                let mut out = Vec::new();
                let mut zstd = zstd::bulk::Decompressor::new().expect("zstd");
                loop {
                    let i = next.fetch_add(1, Ordering::Relaxed);
                    let Some((at, n, compression, uncompressed)) = pieces.get(i) else {
                        break;
                    };
                    // Zeroed only where they grow, as the reader's buffers.
                    if stored.len() < *n {
                        stored.resize(*n, 0);
                    }
                    file.read_exact_at(&mut stored[..*n], *at)
                        .expect("read chunk");
                    if out.len() < *uncompressed && !compression.is_empty() {
                        out.resize(*uncompressed, 0);
                    }
                    let (stored, out) = (&stored[..*n], &mut out[..]);
                    let wrote = match compression.as_str() {
                        "zstd" => zstd
                            .decompress_to_buffer(stored, &mut out[..*uncompressed])
                            .expect("zstd chunk"),
                        "lz4" => {
                            let mut lz4 = lz4::Decoder::new(stored).expect("lz4 chunk");
                            std::io::Read::read_exact(&mut lz4, &mut out[..*uncompressed])
                                .expect("lz4 chunk");
                            *uncompressed
                        }
                        _ => stored.len(),
                    };
                    total.fetch_add(wrote, Ordering::Relaxed);
                    if floats {
                        let records = if compression.is_empty() {
                            stored
                        } else {
                            &out[..wrote]
                        };
                        let mut sum = 0.0;
                        converted.fetch_add(convert_floats(records, &mut sum), Ordering::Relaxed);
                        std::hint::black_box(sum);
                    }
                }
            });
        }
    });
    (total.into_inner(), converted.into_inner())
}

/// The 10k files' floor beside geocal's parts, each the median of five runs on this process:
/// reading and decompressing alone (two threads), the same converting every float of the
/// messages, geocal's streamed read dropping what it reads, the read with the extraction, the
/// solve with its covariance. The floor of `geocal solve` end to end is the decompression and
/// the floats plus the solve (any reader must decompress every chunk and convert the samples'
/// numbers, and the solve needs every length before it starts), and never less than their CPU
/// time spread over both cores.
fn floor() {
    let repeats = 5;
    println!(
        "\nfloor of the 10k files (median of {repeats} runs, wall / CPU of all threads; two \
         cores): every chunk read and decompressed on two threads and nothing else, beside \
         geocal's own parts"
    );
    println!(
        "| file | decompressed | floats | read + decompress | + convert every float | geocal \
         read, nothing kept | geocal read + extraction | solve + covariance | floor: \
         decompress + floats + solve, wall (their CPU / 2) |"
    );
    println!("|---|---:|---:|---:|---:|---:|---:|---:|---:|");
    for case in CASES
        .iter()
        .filter(|c| c.name.starts_with("10k") && c.rate == 1)
    {
        let path = case.session_file();
        let mut decompress = Phase::new("decompress");
        let mut with_floats = Phase::new("decompress + floats");
        let mut read = Phase::new("read");
        let mut extract = Phase::new("extract");
        let mut adjust = Phase::new("solve");
        let pieces = compressed_pieces(&path);
        let (mut bytes, mut floats) = (0, 0);
        for _ in 0..repeats {
            bytes = decompress
                .run(|| read_and_decompress(&path, &pieces, 2, false))
                .0;
            floats = with_floats
                .run(|| read_and_decompress(&path, &pieces, 2, true))
                .1;
            read.run(|| stream_session(&path, &mut Discard).expect("a clean file streams"));
            let lengths = extract.run(|| {
                let mut sink = LengthStream::new("multilateration");
                stream_session(&path, &mut sink).expect("a clean file streams");
                sink.finish().expect("begun").0
            });
            let problem = geocal::method::multilateration::Problem::of_lengths(&lengths).problem;
            adjust.run(|| solve(&problem, &SolveOptions::default()).expect("solve"));
        }
        let cell = |p: &Phase| format!("{} / {}", fmt_time(p.median_wall()), p.cpu_cell());
        let cpu_of = |p: &Phase| p.median_cpu().unwrap_or_default();
        println!(
            "| {} | {:.0} MB | {:.2} M | {} | {} | {} | {} | {} | {} ({}) |",
            case.name,
            bytes as f64 / 1e6,
            floats as f64 / 1e6,
            cell(&decompress),
            cell(&with_floats),
            cell(&read),
            cell(&extract),
            cell(&adjust),
            fmt_time(with_floats.median_wall() + adjust.median_wall()),
            fmt_time((cpu_of(&with_floats) + cpu_of(&adjust)) / 2)
        );
    }
}

#[derive(Clone, Copy)]
struct Case {
    name: &'static str,
    grid: [usize; 3],
    rate: usize,
    layout: Layout,
}

/// Who laid the file out: geocal's own recorder, or the Python `mcap` writer rewriting the
/// same messages (bench/rewrite_session.py) as an independent recorder does.
#[derive(Clone, Copy)]
enum Layout {
    Own,
    /// `compression`: zstd, lz4 or none; `chunk_bytes`: None writes no chunks.
    Python {
        compression: &'static str,
        chunk_bytes: Option<usize>,
    },
}

impl Case {
    /// The case's session file: the own recorder's, generated on first use, or its rewrite.
    fn session_file(&self) -> PathBuf {
        let own = session_file(self.grid, self.rate);
        let Layout::Python {
            compression,
            chunk_bytes,
        } = self.layout
        else {
            return own;
        };
        let chunks = chunk_bytes.map_or("unchunked".to_string(), |b| format!("chunk{b}"));
        let path = own.with_extension(format!("py-{compression}-{chunks}.mcap"));
        if !path.exists() {
            let mut command = Command::new("python3");
            command
                .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("bench/rewrite_session.py"))
                .arg(&own)
                .arg(&path)
                .arg("--compression")
                .arg(compression);
            match chunk_bytes {
                Some(b) => command.arg("--chunk-size").arg(b.to_string()),
                None => command.arg("--unchunked"),
            };
            let status = command.status().expect("python3 runs");
            assert!(
                status.success(),
                "bench/rewrite_session.py failed ({status}): pip install mcap"
            );
        }
        path
    }
}

const FOUR_MIB: usize = 4 * 1024 * 1024;

const CASES: [Case; 7] = [
    Case {
        name: "1k",
        grid: [10, 10, 10],
        rate: 1,
        layout: Layout::Own,
    },
    Case {
        name: "10k",
        grid: GRID,
        rate: 1,
        layout: Layout::Own,
    },
    Case {
        name: "10k-python-zstd-4MiB",
        grid: GRID,
        rate: 1,
        layout: Layout::Python {
            compression: "zstd",
            chunk_bytes: Some(FOUR_MIB),
        },
    },
    Case {
        name: "10k-python-lz4-4MiB",
        grid: GRID,
        rate: 1,
        layout: Layout::Python {
            compression: "lz4",
            chunk_bytes: Some(FOUR_MIB),
        },
    },
    Case {
        name: "10k-python-unchunked",
        grid: GRID,
        rate: 1,
        layout: Layout::Python {
            compression: "none",
            chunk_bytes: None,
        },
    },
    Case {
        name: "10k-dense",
        grid: GRID,
        rate: 10,
        layout: Layout::Own,
    },
    Case {
        name: "100k",
        grid: [50, 50, 40],
        rate: 1,
        layout: Layout::Own,
    },
];

/// One end-to-end `geocal solve` as a user runs it: wall time and peak resident memory (from
/// `/usr/bin/time`, the child's maximum RSS).
struct EndToEnd {
    wall: Duration,
    cpu: Duration,
    peak_rss_kib: u64,
}

fn run_geocal_solve(session: &Path, out: &Path) -> Result<EndToEnd, String> {
    let time_file = out.with_extension("time");
    let status = Command::new("/usr/bin/time")
        .arg("-f")
        .arg("%e %U %S %M")
        .arg("-o")
        .arg(&time_file)
        .arg(env!("CARGO_BIN_EXE_geocal"))
        .arg("solve")
        .arg(session)
        .arg("--out")
        .arg(out)
        .stdout(std::process::Stdio::null())
        .status()
        .map_err(|e| format!("cannot run /usr/bin/time: {e}"))?;
    if !status.success() {
        return Err(format!(
            "geocal solve {} failed: {status}",
            session.display()
        ));
    }
    let text = std::fs::read_to_string(&time_file).map_err(|e| e.to_string())?;
    let fields: Vec<f64> = text
        .lines()
        .last()
        .unwrap_or_default()
        .split_whitespace()
        .filter_map(|f| f.parse().ok())
        .collect();
    let [wall, user, system, rss] = fields[..] else {
        return Err(format!("unexpected /usr/bin/time output: {text}"));
    };
    Ok(EndToEnd {
        wall: Duration::from_secs_f64(wall),
        cpu: Duration::from_secs_f64(user + system),
        peak_rss_kib: rss as u64,
    })
}

/// The Ceres peer, built by bench/build_ceres_peer.sh; Err says why it is skipped.
fn ceres_peer() -> Result<PathBuf, String> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let exe = root.join("target/bench-data/ceres_multilateration");
    let output = Command::new("sh")
        .arg(root.join("bench/build_ceres_peer.sh"))
        .arg(&exe)
        .output()
        .map_err(|e| format!("cannot run bench/build_ceres_peer.sh: {e}"))?;
    if !output.status.success() {
        return Err(String::from_utf8_lossy(&output.stderr).trim().to_string());
    }
    Ok(exe)
}

struct CeresRun {
    solve_time: Duration,
    /// Ceres's own Solver::Summary times: total and linear solver.
    summary_total: Duration,
    summary_linear: Duration,
    iterations: u64,
    chi2: f64,
    points: Vec<Vector3<f64>>,
}

/// The peer's first trust region radius beside Ceres's default (1e4): from this problem's
/// start Ceres then takes Gauss–Newton steps and converges in 3 iterations instead of 9–14
/// (any radius from 1e10 up does; 1e8 still takes 10).
const CERES_GAUSS_NEWTON_RADIUS: f64 = 1e12;

/// Writes the extracted problem as the peer reads it: the same input as geocal's (points at
/// nominal, stations at their hints, homing distances fitted; geocal's own resection of the
/// stations is part of its timed solve), the σ geocal weighed each
/// length with at its solution (fixed for Ceres), six point coordinates held as the gauge.
fn write_peer_problem(
    problem: &MultilaterationProblem,
    sigmas_m: &[f64],
    path: &Path,
) -> std::io::Result<()> {
    use std::fmt::Write as _;
    let stations = initial_stations(problem).expect("start stations");
    let mut num = vec![0.0; problem.segments.len()];
    let mut den = vec![0.0; problem.segments.len()];
    for (o, sigma) in problem.observations.iter().zip(sigmas_m) {
        let j = problem.segments[o.segment].station;
        let w = 1.0 / (sigma * sigma);
        num[o.segment] += w * ((stations[j] - problem.nominal_points[o.point]).norm() - o.length_m);
        den[o.segment] += w;
    }
    let mut text = String::new();
    let p = problem;
    let _ = writeln!(
        text,
        "{} {} {} {}",
        p.nominal_points.len(),
        stations.len(),
        p.segments.len(),
        p.observations.len()
    );
    for x in &p.nominal_points {
        let _ = writeln!(text, "{:e} {:e} {:e}", x.x, x.y, x.z);
    }
    for x in &stations {
        let _ = writeln!(text, "{:e} {:e} {:e}", x.x, x.y, x.z);
    }
    for (s, seg) in p.segments.iter().enumerate() {
        let _ = writeln!(text, "{:e} {}", num[s] / den[s], seg.station);
    }
    for (o, sigma) in p.observations.iter().zip(sigmas_m) {
        let _ = writeln!(
            text,
            "{} {} {:e} {:e}",
            o.point, o.segment, o.length_m, sigma
        );
    }
    for (i, a) in common::gauge_coordinates(&p.nominal_points) {
        let _ = writeln!(text, "{i} {a}");
    }
    std::fs::write(path, text)
}

/// The peer on `problem_file` with 2 threads, from Ceres's default first trust region or
/// from `radius`.
fn run_ceres(exe: &Path, problem_file: &Path, radius: Option<f64>) -> Result<CeresRun, String> {
    let points_file = problem_file.with_extension("points");
    let mut command = Command::new(exe);
    command.arg(problem_file).arg(&points_file).arg("2");
    if let Some(radius) = radius {
        command.arg(format!("{radius:e}"));
    }
    let output = command
        .output()
        .map_err(|e| format!("cannot run {}: {e}", exe.display()))?;
    let stdout = String::from_utf8_lossy(&output.stdout);
    let line = stdout.lines().last().unwrap_or_default();
    let v: serde_json::Value = serde_json::from_str(line).map_err(|e| {
        format!(
            "Ceres peer printed {line:?} ({e}); stderr {}",
            String::from_utf8_lossy(&output.stderr)
        )
    })?;
    let points = std::fs::read_to_string(&points_file)
        .map_err(|e| e.to_string())?
        .lines()
        .map(|l| {
            let c: Vec<f64> = l
                .split_whitespace()
                .filter_map(|f| f.parse().ok())
                .collect();
            Vector3::new(c[0], c[1], c[2])
        })
        .collect();
    Ok(CeresRun {
        solve_time: Duration::from_secs_f64(v["time_s"].as_f64().unwrap_or(f64::NAN)),
        summary_total: Duration::from_secs_f64(v["ceres_total_s"].as_f64().unwrap_or(0.0)),
        summary_linear: Duration::from_secs_f64(v["ceres_linear_solver_s"].as_f64().unwrap_or(0.0)),
        iterations: v["iterations"].as_u64().unwrap_or(0),
        chi2: v["chi2"].as_f64().unwrap_or(f64::NAN),
        points,
    })
}

/// RMS distance of the points from the truth after the best rigid fit onto it.
fn rms_error(points: &[Vector3<f64>], truth: &[Vector3<f64>]) -> f64 {
    let Some((r, t)) = best_fit_rigid(points, truth) else {
        return f64::NAN;
    };
    let sum: f64 = points
        .iter()
        .zip(truth)
        .map(|(p, q)| (r * p + t - q).norm_squared())
        .sum();
    (sum / points.len() as f64).sqrt()
}

fn compare_with_ceres(cases: &[Case]) {
    let peer = ceres_peer();
    if let Err(why) = &peer {
        println!("Ceres comparison skipped: {why}");
    }
    let repeats = 3;
    let mut rows = Vec::new();
    for case in cases {
        let path = case.session_file();
        let file_mb = std::fs::metadata(&path).map_or(0.0, |m| m.len() as f64 / 1e6);
        // The extracted problem, as `geocal solve` builds it.
        let session = read_session(&path).expect("read_session");
        let tracer = session.tracers.keys().next().expect("tracer").clone();
        let samples = session.tracers[&tracer].len();
        let noise = NoiseModel::from_header(&session.header, &tracer);
        let options = ExtractOptions::from_header(&session.header);
        let extraction = extract_points(&session, Some(&tracer), noise, &options).expect("extract");
        drop(session);
        let problem = geocal::method::multilateration::Problem::build(&extraction).problem;
        drop(extraction);
        let solution = solve(&problem, &SolveOptions::default()).expect("solve");
        let truth = truth_points(case.grid, &mut generator_rng());
        let geocal_rms = rms_error(&solution.points, &truth);
        let problem_file = path.with_extension("ceres.txt");
        if peer.is_ok() {
            write_peer_problem(&problem, &solution.sigmas_m, &problem_file).expect("problem file");
        }
        let out = path.with_extension("results.json");
        // Side by side: each repeat runs geocal end to end, then Ceres on the same problem.
        let mut geocal_runs = Vec::new();
        let mut ceres_runs = Vec::new();
        let mut gauss_newton_runs = Vec::new();
        for _ in 0..repeats {
            match run_geocal_solve(&path, &out) {
                Ok(run) => geocal_runs.push(run),
                Err(e) => println!("{}: {e}", case.name),
            }
            if let Ok(exe) = &peer {
                for (radius, runs) in [
                    (None, &mut ceres_runs),
                    (Some(CERES_GAUSS_NEWTON_RADIUS), &mut gauss_newton_runs),
                ] {
                    match run_ceres(exe, &problem_file, radius) {
                        Ok(run) => runs.push(run),
                        Err(e) => println!("{}: Ceres failed: {e}", case.name),
                    }
                }
            }
        }
        let best_geocal = geocal_runs.iter().min_by_key(|r| r.wall);
        let best_ceres = ceres_runs.iter().min_by_key(|r| r.solve_time);
        let best_gauss_newton = gauss_newton_runs.iter().min_by_key(|r| r.solve_time);
        let peer_best = |run: Option<&CeresRun>| {
            run.map(|c| PeerBest {
                solve_time: c.solve_time,
                summary_total: c.summary_total,
                summary_linear: c.summary_linear,
                iterations: c.iterations,
                chi2: c.chi2,
                point_rms_m: rms_error(&c.points, &truth),
            })
        };
        rows.push(Row {
            name: case.name,
            samples,
            lengths: problem.observations.len(),
            file_mb,
            geocal: best_geocal.map(|r| (r.wall, r.cpu, r.peak_rss_kib)),
            iterations: solution.iterations,
            chi2: solution.chi2,
            point_rms_m: geocal_rms,
            ceres: peer_best(best_ceres),
            gauss_newton: peer_best(best_gauss_newton),
        });
    }
    println!();
    println!(
        "geocal solve end to end (read, extract, solve, covariance, results; best of {repeats}, \
         /usr/bin/time) vs the Ceres peer's solve alone (DENSE_SCHUR, 2 threads, best of \
         {repeats}), side by side: from Ceres's default first trust region (1e4) and from \
         {CERES_GAUSS_NEWTON_RADIUS:e} (Gauss–Newton steps); point error = RMS vs the truth \
         after a rigid fit"
    );
    println!(
        "| case | tracer samples | lengths | file | geocal wall | geocal CPU | peak RSS | \
         iterations | Ceres solve, default radius (summary total / linear solver), iterations | \
         ratio | Ceres solve, radius {CERES_GAUSS_NEWTON_RADIUS:e}, iterations | ratio | \
         point error geocal | point error Ceres (both) | chi2 geocal | chi2 Ceres (both) |"
    );
    println!("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for row in rows {
        let (wall, cpu, rss) = match row.geocal {
            Some((w, c, r)) => (
                fmt_time(w),
                fmt_time(c),
                format!("{:.0} MiB", r as f64 / 1024.0),
            ),
            None => ("-".into(), "-".into(), "-".into()),
        };
        let ratio = |peer: &Option<PeerBest>| match (peer, row.geocal) {
            (Some(c), Some((w, _, _))) => {
                format!("{:.2}", w.as_secs_f64() / c.solve_time.as_secs_f64())
            }
            _ => "-".into(),
        };
        let either = |f: &dyn Fn(&PeerBest) -> String| {
            [&row.ceres, &row.gauss_newton]
                .iter()
                .map(|c| c.as_ref().map_or("-".into(), f))
                .collect::<Vec<_>>()
                .join(" / ")
        };
        let default_peer = row.ceres.as_ref().map_or("-".into(), |c| {
            format!(
                "{} ({} / {}), {}",
                fmt_time(c.solve_time),
                fmt_time(c.summary_total),
                fmt_time(c.summary_linear),
                c.iterations
            )
        });
        let gauss_newton_peer = row.gauss_newton.as_ref().map_or("-".into(), |c| {
            format!("{}, {}", fmt_time(c.solve_time), c.iterations)
        });
        println!(
            "| {} | {} | {} | {:.0} MB | {wall} | {cpu} | {rss} | {} | {default_peer} | {} | \
             {gauss_newton_peer} | {} | {:.3} µm | {} | {:.1} | {} |",
            row.name,
            row.samples,
            row.lengths,
            row.file_mb,
            row.iterations,
            ratio(&row.ceres),
            ratio(&row.gauss_newton),
            row.point_rms_m * 1e6,
            either(&|c| format!("{:.3} µm", c.point_rms_m * 1e6)),
            row.chi2,
            either(&|c| format!("{:.1}", c.chi2)),
        );
    }
}

/// The best of a Ceres peer's runs on one case.
struct PeerBest {
    solve_time: Duration,
    summary_total: Duration,
    summary_linear: Duration,
    iterations: u64,
    chi2: f64,
    point_rms_m: f64,
}

/// One case of the comparison.
struct Row {
    name: &'static str,
    samples: usize,
    lengths: usize,
    file_mb: f64,
    /// geocal's best wall, its CPU and peak RSS (KiB).
    geocal: Option<(Duration, Duration, u64)>,
    iterations: usize,
    chi2: f64,
    point_rms_m: f64,
    ceres: Option<PeerBest>,
    gauss_newton: Option<PeerBest>,
}
