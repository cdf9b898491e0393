//! `geocal diagnose` at scale: clean 1 000- and 10 000-point × 16-station sessions (the solve
//! benchmark's plan) diagnosed end to end, each in a fresh child process so that its peak
//! resident memory (VmHWM) is the diagnosis's own: wall time, CPU time, peak RSS, heap peak.
//!
//! `cargo bench --bench diagnose_session` (sizes: `DIAGNOSE_BENCH_POINTS=1000,10000`).

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

/// The child: diagnose one file, print "wall_s cpu_s heap_peak_bytes vm_hwm_kib selected".
fn child(path: &Path) {
    let cpu0 = common::cpu_time();
    let (diagnosis, dt, heap) = measure(|| diagnose_file(path, &DiagnoseOptions::default()));
    let cpu = match (cpu0, common::cpu_time()) {
        (Some(a), Some(b)) => b.saturating_sub(a).as_secs_f64(),
        _ => f64::NAN,
    };
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
    let args: Vec<String> = std::env::args().collect();
    if let Some(k) = args.iter().position(|a| a == "--child") {
        child(Path::new(&args[k + 1]));
        return;
    }
    let sizes: Vec<usize> = std::env::var("DIAGNOSE_BENCH_POINTS")
        .unwrap_or_else(|_| "1000,10000".into())
        .split(',')
        .filter_map(|s| s.trim().parse().ok())
        .collect();
    println!(
        "| points × stations | lengths | wall | CPU | peak RSS | heap peak | chi²/dof | selected |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    for points in sizes {
        let grid = grid_for(points);
        let path = data_path(grid);
        if !path.exists() {
            std::fs::create_dir_all(path.parent().expect("parent")).expect("bench-data dir");
            let tmp = path.with_extension("mcap.partial");
            session::generate(&tmp, grid, 20260101);
            std::fs::rename(&tmp, &path).expect("rename session");
        }
        let exe = std::env::current_exe().expect("bench executable");
        let out = Command::new(exe)
            .arg("--child")
            .arg(&path)
            .output()
            .expect("run the child");
        let stdout = String::from_utf8_lossy(&out.stdout);
        let Some(line) = stdout.lines().find_map(|l| l.strip_prefix("RESULT ")) else {
            println!(
                "| {} × {} | failed: {} |",
                grid.iter().product::<usize>(),
                session::STATIONS,
                String::from_utf8_lossy(&out.stderr).trim()
            );
            continue;
        };
        let f: Vec<&str> = line.split_whitespace().collect();
        let num = |k: usize| f[k].parse::<f64>().unwrap_or(f64::NAN);
        println!(
            "| {} × {} | {} | {} | {:.1} s | {:.0} MiB | {:.0} MiB | {:.3} | {} |",
            grid.iter().product::<usize>(),
            session::STATIONS,
            f[4],
            fmt_time(std::time::Duration::from_secs_f64(num(0))),
            num(1),
            num(3) / 1024.0,
            mib(num(2) as usize),
            num(5),
            f[6]
        );
    }
}
