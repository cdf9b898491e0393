//! Whole-pipeline benchmark: a recorded 10 000-point x 16-station session (~1.7 M raw tracer
//! samples) solved as `geocal solve` does it, timed phase by phase with the heap peak of each.

mod common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use geocal::extract::{extract_points, ExtractOptions, NoiseModel};
use geocal::session::messages::{
    DeviceInfo, MachineInfo, RunEvent, SessionHeader, TargetInfo, TracerSample, SESSION_FORMAT,
};
use geocal::session::reader::{read_session, read_session_bytes, Session};
use geocal::session::recorder::{Recorder, RecorderOptions};
use geocal::solve::multilateration::{solve, SolveOptions};
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use common::{fmt_time, measure, median, mib};

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

fn data_path() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(format!(
        "target/bench-data/session-{}x{STATIONS}-v{DATA_VERSION}.mcap",
        GRID.iter().product::<usize>()
    ))
}

/// Grid points in serpentine visiting order (x fastest, rows and layers alternating), so every
/// move is one grid step; the index in this order is the plan point index, 0 = homing point.
fn plan_points() -> Vec<[f64; 3]> {
    let size = [1.4, 2.4, 1.0];
    let coord = |k: usize, i: usize| size[k] * i as f64 / (GRID[k] - 1) as f64;
    let mut points = Vec::with_capacity(GRID.iter().product());
    for iz in 0..GRID[2] {
        for row in 0..GRID[1] {
            let iy = if iz % 2 == 0 { row } else { GRID[1] - 1 - row };
            for col in 0..GRID[0] {
                let ix = if (iz * GRID[1] + row) % 2 == 0 {
                    col
                } else {
                    GRID[0] - 1 - col
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

fn header() -> SessionHeader {
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
            extra: BTreeMap::from([("sample_rate_hz".into(), (1.0 / DT_S).into())]),
        }],
        plan: serde_json::json!({
            "target": "t0",
            "passes": ["forward"],
            "dwell_s": DWELL_SAMPLES as f64 * DT_S,
            "stillstand": {"window_s": WINDOW_S, "tolerance_m": TOLERANCE_M},
            "grid": {"count": GRID, "order": "serpentine"},
        }),
    }
}

/// Writes the session as the sequencer would record it: per station a `station_begin`, then
/// per point the motion samples, `point_begin`, the dwell samples, `point_end`.
fn generate(path: &Path) {
    let t0 = Instant::now();
    let mut rng = ChaCha8Rng::seed_from_u64(20260101);
    let nominal = plan_points();
    let truth: Vec<Vector3<f64>> = nominal
        .iter()
        .map(|p| Vector3::from(*p) + Vector3::from_fn(|_, _| rng.random_range(-4e-6..4e-6)))
        .collect();
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
    h.session(&header(), epoch_ns);
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
    let axes = |p: &[f64; 3]| -> BTreeMap<String, f64> {
        ["x", "y", "z"]
            .iter()
            .zip(p)
            .map(|(a, v)| (a.to_string(), *v))
            .collect()
    };
    for (j, station) in stations.iter().enumerate() {
        let id = format!("s{}", j + 1);
        let hint = station + Vector3::from_fn(|_, _| rng.random_range(-0.03..0.03));
        // The operator moves the tracer: minutes pass between stations.
        t_s += 180.0;
        h.event(
            &RunEvent::StationBegin {
                station: id.clone(),
                station_index: j,
                hint_m: Some([hint.x, hint.y, hint.z]),
            },
            log_ns(t_s),
        );
        let home = (station - truth[0]).norm();
        let length = |x: &Vector3<f64>| (station - x).norm() - home;
        let mut approach: BTreeMap<String, i8> =
            ["x", "y", "z"].iter().map(|a| (a.to_string(), 0)).collect();
        for (i, nom) in nominal.iter().enumerate() {
            if i > 0 {
                let from = truth[i - 1];
                let steps = ((truth[i] - from).norm() / FEED_M_S / DT_S).ceil().max(1.0) as usize;
                for k in 0..steps {
                    t_s += DT_S;
                    let x = from + (truth[i] - from) * (k as f64 / steps as f64);
                    sample(t_s, length(&x), (station - x).norm(), &mut rng);
                }
                for (a, axis) in ["x", "y", "z"].iter().enumerate() {
                    let d = nom[a] - nominal[i - 1][a];
                    if d != 0.0 {
                        approach.insert(axis.to_string(), d.signum() as i8);
                    }
                }
            }
            t_s += DT_S;
            h.event(
                &RunEvent::PointBegin {
                    station: id.clone(),
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
            for k in 0..DWELL_SAMPLES {
                if k > 0 {
                    t_s += DT_S;
                }
                sample(t_s, at, beam, &mut rng);
            }
            h.event(
                &RunEvent::PointEnd {
                    station: id.clone(),
                    point: i,
                    pass: 0,
                },
                log_ns(t_s) + 1_000_000,
            );
        }
        h.event(
            &RunEvent::StationEnd { station: id },
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

fn main() {
    let path = data_path();
    if !path.exists() {
        println!("no cached session at {}: generating it", path.display());
        generate(&path);
    }
    let file_bytes = std::fs::metadata(&path).map(|m| m.len()).unwrap_or(0);
    let repeats = 3;
    let mut file_read = Phase::new("file read (std::fs::read)");
    let mut decode = Phase::new("decode (read_session_bytes: zstd + JSON)");
    let mut read = Phase::new("read_session (file read + decode)");
    let mut extract = Phase::new("extract_points (stillstand, averaging)");
    let mut build = Phase::new("build problem");
    let mut adjust = Phase::new("solve + covariance (solve::multilateration::solve)");
    let mut method = Phase::new("method::solve_session (extract + build + solve + results)");
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
        &file_read, &decode, &read, &extract, &build, &adjust, &method, &whole,
    ] {
        let cpu = if p.cpu.is_empty() {
            "-".to_string()
        } else {
            fmt_time(median(p.cpu.clone()))
        };
        println!(
            "| {} | {} | {} | {:.0} MiB | {:.0} MiB | {} |",
            p.name,
            fmt_time(median(p.times.clone())),
            cpu,
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
