//! Multilateration solver benchmark: synthetic problems of 100..10 000 points x 5 or 16 stations,
//! timed with heap peak and accuracy, and the same problems solved by SciPy for comparison.

mod common;

use std::path::Path;
use std::process::Command;
use std::time::Duration;

use geocal::solve::multilateration::{
    best_fit_rigid, solve, LengthObservation, MultilaterationProblem, MultilaterationSolution,
    Segment, SolveOptions,
};
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use common::{fmt_time, measure, median, mib};

/// Per-length noise: a settled dwell average of a laser tracer.
const SIGMA_M: f64 = 50e-9;
/// True point deviations from nominal (uniform, per coordinate).
const DEVIATION_M: f64 = 4e-6;
/// How far the station hints (the start) lie from the true stations (uniform, per coordinate).
const HINT_ERROR_M: f64 = 0.03;

struct Synthetic {
    problem: MultilaterationProblem,
    true_points: Vec<Vector3<f64>>,
}

/// Stations around the 1.4 x 2.4 x 1.0 m volume: 5 as a typical CMM set-up (one low in the
/// middle), 16 on a ring at four heights, as in a dense self-calibration.
fn true_stations(m: usize) -> Vec<Vector3<f64>> {
    if m == 5 {
        return vec![
            Vector3::new(-0.4, -0.4, 0.2),
            Vector3::new(1.8, -0.3, 0.9),
            Vector3::new(1.9, 2.8, 0.1),
            Vector3::new(-0.3, 2.9, 1.1),
            Vector3::new(0.7, 1.2, -0.5),
        ];
    }
    (0..m)
        .map(|k| {
            let a = k as f64 * std::f64::consts::TAU / m as f64;
            Vector3::new(
                0.7 + 1.8 * a.cos(),
                1.2 + 2.2 * a.sin(),
                -0.3 + 0.4 * (k % 4) as f64,
            )
        })
        .collect()
}

/// A grid of n = gx*gy*gz points filling the volume; point 0 (a corner) is the homing point.
fn grid_for(n: usize) -> [usize; 3] {
    match n {
        100 => [5, 5, 4],
        1000 => [10, 10, 10],
        10_000 => [20, 25, 20],
        _ => panic!("no grid for {n} points"),
    }
}

fn synthetic(seed: u64, n: usize, m: usize) -> Synthetic {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let grid = grid_for(n);
    let size = [1.4, 2.4, 1.0];
    let mut nominal = Vec::with_capacity(n);
    for iz in 0..grid[2] {
        for iy in 0..grid[1] {
            for ix in 0..grid[0] {
                let f = |i: usize, k: usize| size[k] * i as f64 / (grid[k] - 1) as f64;
                nominal.push(Vector3::new(f(ix, 0), f(iy, 1), f(iz, 2)));
            }
        }
    }
    let true_points: Vec<Vector3<f64>> = nominal
        .iter()
        .map(|p| p + Vector3::from_fn(|_, _| rng.random_range(-DEVIATION_M..DEVIATION_M)))
        .collect();
    let stations = true_stations(m);
    let mut observations = Vec::with_capacity(n * m);
    for (j, pj) in stations.iter().enumerate() {
        // One beam segment per station, its lengths relative to the homing point 0.
        let home = (pj - true_points[0]).norm();
        for (i, x) in true_points.iter().enumerate() {
            let noise = rng.sample::<f64, _>(StandardNormal) * SIGMA_M;
            observations.push(LengthObservation {
                point: i,
                segment: j,
                length_m: (pj - x).norm() - home + noise,
                sigma_m: SIGMA_M,
                path_sigma: None,
            });
        }
    }
    let hints = stations
        .iter()
        .map(|p| Some(p + Vector3::from_fn(|_, _| rng.random_range(-HINT_ERROR_M..HINT_ERROR_M))))
        .collect();
    Synthetic {
        problem: MultilaterationProblem {
            nominal_points: nominal,
            station_hints: hints,
            segments: (0..m).map(|station| Segment { station }).collect(),
            observations,
        },
        true_points,
    }
}

/// The solver's start: points at nominal, stations at their hints, and each homing distance
/// the weighted mean that fits the lengths (what geocal computes before its first iteration).
fn start_distances(p: &MultilaterationProblem) -> Vec<f64> {
    let mut num = vec![0.0; p.segments.len()];
    let mut den = vec![0.0; p.segments.len()];
    for o in &p.observations {
        let j = p.segments[o.segment].station;
        let station = p.station_hints[j].expect("hints are set");
        let w = 1.0 / (o.sigma_m * o.sigma_m);
        num[o.segment] += w * ((station - p.nominal_points[o.point]).norm() - o.length_m);
        den[o.segment] += w;
    }
    num.iter().zip(&den).map(|(a, b)| a / b).collect()
}

fn write_problem_json(p: &MultilaterationProblem, path: &Path) -> std::io::Result<()> {
    let flat = |v: &[Vector3<f64>]| v.iter().flat_map(|p| [p.x, p.y, p.z]).collect::<Vec<_>>();
    let stations: Vec<Vector3<f64>> = p.station_hints.iter().map(|h| h.expect("hint")).collect();
    let json = serde_json::json!({
        "format": "geocal-bench-multilateration/1",
        "nominal_m": flat(&p.nominal_points),
        "start_stations_m": flat(&stations),
        "start_distances_m": start_distances(p),
        "segment_station": p.segments.iter().map(|s| s.station).collect::<Vec<_>>(),
        "obs_point": p.observations.iter().map(|o| o.point).collect::<Vec<_>>(),
        "obs_segment": p.observations.iter().map(|o| o.segment).collect::<Vec<_>>(),
        "obs_length_m": p.observations.iter().map(|o| o.length_m).collect::<Vec<_>>(),
        "obs_sigma_m": p.observations.iter().map(|o| o.sigma_m).collect::<Vec<_>>(),
        "fixed": common::gauge_coordinates(&p.nominal_points).iter().map(|&(i, a)| [i, a]).collect::<Vec<_>>(),
    });
    std::fs::write(path, serde_json::to_vec(&json)?)
}

/// Σ (r/σ)² at the common start, to check that both solvers begin from the same point.
fn start_chi2(p: &MultilaterationProblem) -> f64 {
    let d = start_distances(p);
    p.observations
        .iter()
        .map(|o| {
            let station = p.station_hints[p.segments[o.segment].station].expect("hint");
            let r = o.length_m - ((station - p.nominal_points[o.point]).norm() - d[o.segment]);
            (r / o.sigma_m).powi(2)
        })
        .sum()
}

struct SciPyResult {
    time: Duration,
    chi2: f64,
    chi2_start: f64,
    nfev: u64,
    status: i64,
}

const SCRIPT: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/bench/scipy_multilateration.py"
);

fn scipy_available() -> bool {
    Command::new("python3")
        .args(["-c", "import scipy, numpy"])
        .output()
        .map(|o| o.status.success())
        .unwrap_or(false)
}

fn run_scipy(p: &MultilaterationProblem) -> Result<SciPyResult, String> {
    let dir = tempfile::tempdir().map_err(|e| e.to_string())?;
    let path = dir.path().join("problem.json");
    write_problem_json(p, &path).map_err(|e| e.to_string())?;
    let out = Command::new("python3")
        .arg(SCRIPT)
        .arg(&path)
        .output()
        .map_err(|e| e.to_string())?;
    if !out.status.success() {
        return Err(String::from_utf8_lossy(&out.stderr).into_owned());
    }
    let stdout = String::from_utf8_lossy(&out.stdout);
    let line = stdout.lines().last().ok_or("no output")?;
    let v: serde_json::Value = serde_json::from_str(line).map_err(|e| e.to_string())?;
    let num = |k: &str| v[k].as_f64().ok_or(format!("no `{k}` in {line}"));
    Ok(SciPyResult {
        time: Duration::from_secs_f64(num("time_s")?),
        chi2: num("chi2")?,
        chi2_start: num("chi2_start")?,
        nfev: v["nfev"].as_u64().unwrap_or(0),
        status: v["status"].as_i64().unwrap_or(0),
    })
}

/// RMS per coordinate of the point errors after the rigid fit onto the truth, and the RMS the
/// solver's covariances predict.
fn accuracy(sol: &MultilaterationSolution, truth: &[Vector3<f64>]) -> (f64, f64) {
    let (r, t) = best_fit_rigid(&sol.points, truth).expect("rigid fit");
    let n3 = 3.0 * truth.len() as f64;
    let err = sol
        .points
        .iter()
        .zip(truth)
        .map(|(x, y)| (r * x + t - y).norm_squared())
        .sum::<f64>()
        / n3;
    let pred = sol.point_covariance.iter().map(|q| q.trace()).sum::<f64>() / n3;
    (err.sqrt(), pred.sqrt())
}

struct Row {
    n: usize,
    m: usize,
    obs: usize,
    time: Duration,
    repeats: usize,
    iterations: usize,
    peak_bytes: usize,
    chi2: f64,
    dof: usize,
    rms_err_m: f64,
    rms_pred_m: f64,
    scipy: Option<Result<SciPyResult, String>>,
    start_chi2: f64,
}

fn main() {
    // `cargo bench` passes `--bench`; a name filter (any other argument) selects cases by "nxm".
    let filter: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with("--"))
        .collect();
    let with_scipy = std::env::var_os("GEOCAL_BENCH_NO_SCIPY").is_none() && scipy_available();
    if !with_scipy {
        println!(
            "SciPy comparison skipped: python3 with scipy and numpy not importable \
             (install with `pip install scipy numpy`) or GEOCAL_BENCH_NO_SCIPY set."
        );
    }
    let options = SolveOptions::default();
    let mut rows = Vec::new();
    for &n in &[100, 1000, 10_000] {
        for &m in &[5, 16] {
            let name = format!("{n}x{m}");
            if !filter.is_empty() && !filter.iter().any(|f| name.contains(f.as_str())) {
                continue;
            }
            let syn = synthetic(1000 + n as u64 + m as u64, n, m);
            let obs = syn.problem.observations.len();
            // Small cases are noisy: the median of several runs; the first run gives the memory.
            let repeats = if obs <= 20_000 { 7 } else { 3 };
            let mut times = Vec::with_capacity(repeats);
            let mut first = None;
            for _ in 0..repeats {
                let (sol, dt, peak) = measure(|| solve(&syn.problem, &options));
                let sol = sol.unwrap_or_else(|e| panic!("{name}: {e}"));
                times.push(dt);
                first.get_or_insert((sol, peak));
            }
            let (sol, peak_bytes) = first.expect("at least one run");
            let (rms_err_m, rms_pred_m) = accuracy(&sol, &syn.true_points);
            let scipy = with_scipy.then(|| run_scipy(&syn.problem));
            let row = Row {
                n,
                m,
                obs,
                time: median(times),
                repeats,
                iterations: sol.iterations,
                peak_bytes,
                chi2: sol.chi2,
                dof: sol.dof,
                rms_err_m,
                rms_pred_m,
                scipy,
                start_chi2: start_chi2(&syn.problem),
            };
            eprintln!("done {name}: {}", fmt_time(row.time));
            rows.push(row);
        }
    }
    print_tables(&rows);
}

fn print_tables(rows: &[Row]) {
    println!();
    println!("geocal multilateration (sparse LM, Schur complement; includes the covariance)");
    println!(
        "| n | m | observations | wall time (median of k) | iterations | peak heap | chi2 | chi2/dof | point RMS error | predicted RMS |"
    );
    println!("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for r in rows {
        println!(
            "| {} | {} | {} | {} (k={}) | {} | {:.2} MiB | {:.1} | {:.3} | {:.1} nm | {:.1} nm |",
            r.n,
            r.m,
            r.obs,
            fmt_time(r.time),
            r.repeats,
            r.iterations,
            mib(r.peak_bytes),
            r.chi2,
            r.chi2 / r.dof as f64,
            r.rms_err_m * 1e9,
            r.rms_pred_m * 1e9,
        );
    }
    if rows.iter().all(|r| r.scipy.is_none()) {
        return;
    }
    println!();
    println!(
        "SciPy least_squares (trf, lsmr, x_scale='jac', analytic sparse Jacobian) from the same start"
    );
    println!(
        "| n | m | geocal time | scipy time | time ratio scipy/geocal | nfev | geocal chi2 | scipy chi2 | cost ratio scipy/geocal | start chi2 agrees |"
    );
    println!("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|");
    for r in rows {
        match &r.scipy {
            None => {}
            Some(Err(e)) => println!("| {} | {} | scipy failed: {} |", r.n, r.m, e.trim()),
            Some(Ok(s)) => {
                let agrees = ((s.chi2_start - r.start_chi2) / r.start_chi2).abs() < 1e-9;
                println!(
                    "| {} | {} | {} | {} | {:.1} | {} | {:.3} | {:.3} | {:.9} | {} |",
                    r.n,
                    r.m,
                    fmt_time(r.time),
                    fmt_time(s.time),
                    s.time.as_secs_f64() / r.time.as_secs_f64(),
                    s.nfev,
                    r.chi2,
                    s.chi2,
                    s.chi2 / r.chi2,
                    if agrees {
                        format!("yes (status {})", s.status)
                    } else {
                        format!("NO: {:.6e} vs {:.6e}", s.chi2_start, r.start_chi2)
                    },
                );
            }
        }
    }
}
