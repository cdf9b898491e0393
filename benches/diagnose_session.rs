//! `geocal diagnose` at scale: clean 1 000- and 10 000-point × 16-station sessions (the solve
//! benchmark's plan) diagnosed end to end, each in a fresh child process so that its peak
//! resident memory (VmHWM) is the diagnosis's own: wall time, CPU time, peak RSS, heap peak.
//! The same file is solved the same way beside it, and the diagnosis's ratios to the solve
//! are printed (the goal: ≤ 10× its wall time, ≤ 2× its peak memory).
//!
//! `cargo bench --bench diagnose_session` (sizes: `DIAGNOSE_BENCH_POINTS=1000,10000`;
//! `DIAGNOSE_BENCH_NO_BUDGET=1` runs a size the diagnosis's memory estimate would refuse;
//! `DIAGNOSE_BENCH_MEMORY_LIMIT=BYTES` diagnoses under that limit: 0 shows each size's estimate
//! in its refusal; `DIAGNOSE_BENCH_EFFECTS=NAMES` the effects of the `solve --effects` row,
//! `station_drift` by default (the widest: 3 per station), empty for no such row).
//!
//! `cargo bench --bench diagnose_session -- kinds`: every plan kind's diagnosis against its
//! solve on the outside sessions of `../shared/sessions/` (recorded by another writer), in
//! process (the child modes) and end to end (`geocal solve` and `geocal diagnose`), medians of
//! five runs each.

mod common;

#[path = "../tests/diagnose_scale/session.rs"]
mod session;

use std::path::{Path, PathBuf};
use std::process::Command;

use common::{fmt_time, measure, mib};
use geocal::diagnose::DiagnoseOptions;
use geocal::kinds::diagnosis::diagnose_file;

/// Bump when the generator changes, so a stale cached file is not reused.
const DATA_VERSION: u32 = 1;

fn grid_for(points: usize) -> [usize; 3] {
    match points {
        1000 => [10, 10, 10],
        2016 => [12, 14, 12],
        10000 => [20, 25, 20],
        100000 => [40, 50, 50],
        _ => {
            let side = (points as f64).cbrt().round().max(2.0) as usize;
            [side, side, side]
        }
    }
}

fn data_path(grid: [usize; 3]) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(format!(
        "target/bench-data/diagnose-{}x{}-v{DATA_VERSION}.mcap",
        grid.iter().product::<usize>(),
        session::STATIONS
    ))
}

fn vm_hwm_kib() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
}

fn cpu_seconds_since(cpu0: Option<std::time::Duration>) -> f64 {
    match (cpu0, common::cpu_time()) {
        (Some(a), Some(b)) => b.saturating_sub(a).as_secs_f64(),
        _ => f64::NAN,
    }
}

/// The solve child: solve one file as `geocal solve --effects EFFECTS` does (none: as `geocal
/// solve`), print "wall_s cpu_s heap_peak_bytes vm_hwm_kib".
fn solve_child(path: &Path, effects: &[String]) {
    let cpu0 = common::cpu_time();
    let settings = geocal::kinds::diagnosis::solve_settings(path, effects, Default::default())
        .expect("the effects' names");
    let (results, dt, heap) = measure(|| geocal::kinds::solve_file(path, &settings));
    let cpu = cpu_seconds_since(cpu0);
    results.expect("solve");
    println!(
        "RESULT {} {} {} {}",
        dt.as_secs_f64(),
        cpu,
        heap,
        vm_hwm_kib().unwrap_or(0)
    );
}

/// The child: diagnose one file, print "wall_s cpu_s heap_peak_bytes vm_hwm_kib selected".
fn child(path: &Path) {
    let cpu0 = common::cpu_time();
    let mut options = DiagnoseOptions::default();
    if std::env::var_os("DIAGNOSE_BENCH_NO_BUDGET").is_some() {
        // The peak the diagnosis reaches, whatever its estimate before the work says.
        options.memory_limit_bytes = Some(u64::MAX);
    }
    if let Some(limit) = std::env::var("DIAGNOSE_BENCH_MEMORY_LIMIT")
        .ok()
        .and_then(|v| v.parse().ok())
    {
        options.memory_limit_bytes = Some(limit);
    }
    let (diagnosis, dt, heap) = measure(|| diagnose_file(path, &options));
    let cpu = cpu_seconds_since(cpu0);
    let d = diagnosis.expect("diagnose");
    println!(
        "RESULT {} {} {} {} {} {} {}",
        dt.as_secs_f64(),
        cpu,
        heap,
        vm_hwm_kib().unwrap_or(0),
        d.observations,
        d.gap.chi2_per_dof,
        if d.selected.is_empty() {
            "none".to_string()
        } else {
            d.selected.join(",")
        }
    );
}

fn main() {
    // The children measure what `geocal solve` and `geocal diagnose` do, arenas included.
    geocal::allocator::limit_arenas();
    let args: Vec<String> = std::env::args().collect();
    if let Some(k) = args.iter().position(|a| a == "--child") {
        child(Path::new(&args[k + 1]));
        return;
    }
    if args.iter().skip(1).any(|a| a == "kinds") {
        kinds_table();
        return;
    }
    if let Some(k) = args.iter().position(|a| a == "--solve-child") {
        solve_child(Path::new(&args[k + 1]), &args[k + 2..]);
        return;
    }
    let effects =
        std::env::var("DIAGNOSE_BENCH_EFFECTS").unwrap_or_else(|_| "station_drift".into());
    let sizes: Vec<usize> = std::env::var("DIAGNOSE_BENCH_POINTS")
        .unwrap_or_else(|_| "1000,10000".into())
        .split(',')
        .filter_map(|s| s.trim().parse().ok())
        .collect();
    println!(
        "| points × stations | lengths | command | wall | CPU | peak RSS | heap peak | chi²/dof | selected | wall / solve | peak RSS / solve |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|");
    for points in sizes {
        let grid = grid_for(points);
        let path = data_path(grid);
        if !path.exists() {
            std::fs::create_dir_all(path.parent().expect("parent")).expect("bench-data dir");
            let tmp = path.with_extension("mcap.partial");
            session::generate(&tmp, grid, 20260101);
            std::fs::rename(&tmp, &path).expect("rename session");
        }
        let size = format!("{} × {}", grid.iter().product::<usize>(), session::STATIONS);
        let solve = match run_child("--solve-child", &path, &[]) {
            Ok(f) => f,
            Err(e) => {
                println!("| {size} | | solve | failed: {e} |");
                continue;
            }
        };
        let num = |f: &[String], k: usize| f[k].parse::<f64>().unwrap_or(f64::NAN);
        println!(
            "| {size} | | solve | {} | {:.1} s | {:.0} MiB | {:.0} MiB | | | | |",
            fmt_time(std::time::Duration::from_secs_f64(num(&solve, 0))),
            num(&solve, 1),
            num(&solve, 3) / 1024.0,
            mib(num(&solve, 2) as usize),
        );
        let f = match run_child("--child", &path, &[]) {
            Ok(f) => f,
            Err(e) => {
                println!("| {size} | | diagnose | failed: {e} |");
                continue;
            }
        };
        println!(
            "| {size} | {} | diagnose | {} | {:.1} s | {:.0} MiB | {:.0} MiB | {:.3} | {} | {:.1}× | {:.2}× |",
            f[4],
            fmt_time(std::time::Duration::from_secs_f64(num(&f, 0))),
            num(&f, 1),
            num(&f, 3) / 1024.0,
            mib(num(&f, 2) as usize),
            num(&f, 5),
            f[6],
            num(&f, 0) / num(&solve, 0),
            num(&f, 3) / num(&solve, 3),
        );
        if effects.is_empty() {
            continue;
        }
        let command = format!("solve --effects {effects}");
        match run_child("--solve-child", &path, &[effects.as_str()]) {
            Ok(f) => println!(
                "| {size} | | {command} | {} | {:.1} s | {:.0} MiB | {:.0} MiB | | | {:.1}× | {:.2}× |",
                fmt_time(std::time::Duration::from_secs_f64(num(&f, 0))),
                num(&f, 1),
                num(&f, 3) / 1024.0,
                mib(num(&f, 2) as usize),
                num(&f, 0) / num(&solve, 0),
                num(&f, 3) / num(&solve, 3),
            ),
            Err(e) => println!("| {size} | | {command} | failed: {e} |"),
        }
    }
}

const KIND_RUNS: usize = 5;

/// Every outside session's diagnosis against its solve: in process (the child modes: the
/// work alone) and end to end (the `geocal` commands, process start and output included).
fn kinds_table() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/sessions");
    let mut sessions: Vec<PathBuf> = std::fs::read_dir(&dir)
        .map(|entries| {
            entries
                .filter_map(Result::ok)
                .map(|e| e.path().join("session.mcap"))
                .filter(|p| p.exists())
                .collect()
        })
        .unwrap_or_default();
    sessions.sort();
    if sessions.is_empty() {
        println!("no outside sessions under {}", dir.display());
        return;
    }
    println!(
        "| session | kind | rows | solve | diagnose | wall / solve | `geocal solve` | `geocal diagnose` | wall / solve, end to end | peak RSS solve / diagnose | peak RSS / solve |"
    );
    println!("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for path in sessions {
        let name = path
            .parent()
            .and_then(Path::file_name)
            .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
        let kind = geocal::session::reader::read_session(&path)
            .map(|s| s.header.kind)
            .unwrap_or_else(|e| format!("unreadable: {e}"));
        let (mut solve, mut diagnose) = (Vec::new(), Vec::new());
        let (mut solve_cli, mut diagnose_cli) = (Vec::new(), Vec::new());
        let (mut solve_rss, mut diagnose_rss, mut rows) = (0.0f64, 0.0f64, String::new());
        for _ in 0..KIND_RUNS {
            let parts = (
                run_child("--solve-child", &path, &[]),
                run_child("--child", &path, &[]),
            );
            let (Ok(s), Ok(d)) = parts else {
                println!("| {name} | {kind} | failed: {parts:?} |");
                break;
            };
            let num = |f: &[String], k: usize| f[k].parse::<f64>().unwrap_or(f64::NAN);
            solve.push(num(&s, 0));
            diagnose.push(num(&d, 0));
            solve_rss = solve_rss.max(num(&s, 3));
            diagnose_rss = diagnose_rss.max(num(&d, 3));
            rows.clone_from(&d[4]);
            solve_cli.push(end_to_end("solve", &path));
            diagnose_cli.push(end_to_end("diagnose", &path));
        }
        if solve.is_empty() {
            continue;
        }
        let (s, d) = (median(&mut solve), median(&mut diagnose));
        let (sc, dc) = (median(&mut solve_cli), median(&mut diagnose_cli));
        println!(
            "| {name} | {kind} | {rows} | {:.1} ms | {:.1} ms | {:.1}× | {:.1} ms | {:.1} ms | {:.1}× | {:.1} / {:.1} MiB | {:.2}× |",
            1e3 * s,
            1e3 * d,
            d / s,
            1e3 * sc,
            1e3 * dc,
            dc / sc,
            solve_rss / 1024.0,
            diagnose_rss / 1024.0,
            diagnose_rss / solve_rss,
        );
    }
}

/// Wall seconds of `geocal COMMAND --json PATH` (NaN when it fails).
fn end_to_end(command: &str, path: &Path) -> f64 {
    let started = std::time::Instant::now();
    let ok = Command::new(env!("CARGO_BIN_EXE_geocal"))
        .args([command, "--json"])
        .arg(path)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    if ok {
        started.elapsed().as_secs_f64()
    } else {
        f64::NAN
    }
}

fn median(values: &mut [f64]) -> f64 {
    values.sort_by(f64::total_cmp);
    values.get(values.len() / 2).copied().unwrap_or(f64::NAN)
}

/// Runs this benchmark as a child in `mode` on `path` (then `extra`); its RESULT line's fields.
fn run_child(mode: &str, path: &Path, extra: &[&str]) -> Result<Vec<String>, String> {
    let exe = std::env::current_exe().map_err(|e| e.to_string())?;
    let out = Command::new(exe)
        .arg(mode)
        .arg(path)
        .args(extra)
        .output()
        .map_err(|e| e.to_string())?;
    let stdout = String::from_utf8_lossy(&out.stdout);
    match stdout.lines().find_map(|l| l.strip_prefix("RESULT ")) {
        Some(line) => Ok(line.split_whitespace().map(str::to_string).collect()),
        None => Err(String::from_utf8_lossy(&out.stderr).trim().to_string()),
    }
}
