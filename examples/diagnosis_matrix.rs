//! Validation of `geocal diagnose`: simulated sessions with one effect (or none) switched on,
//! diagnosed; prints the confusion matrix (true effect x first selected) and the gap ratios.

#[path = "../tests/common/mod.rs"]
mod common;

/// (true effect, the `[sim.effects]` line that switches it on at a realistic size).
const CASES: [(&str, &str); 12] = [
    ("none", ""),
    (
        "station_drift",
        "station_drift = { enabled = true, size = 5e-9 }",
    ),
    ("reversal", "reversal = { enabled = true, size = 1e-6 }"),
    (
        "length_step",
        "length_step = { enabled = true, size = 1e-6 }",
    ),
    (
        "air_refraction",
        "air_refraction = { enabled = true, size = 1.0 }",
    ),
    (
        "tracer_eccentricity",
        "tracer_eccentricity = { enabled = true, size_m = 2e-6, z_size_m = 1e-6 }",
    ),
    (
        "thermal_drift",
        "thermal_drift = { enabled = true, size = 4e-9 }",
    ),
    ("dead_path", "dead_path = { enabled = true, size = 1.0 }"),
    (
        "thermal_expansion",
        "thermal_expansion = { enabled = true, size = 2e-6 }",
    ),
    (
        "settling",
        "settling = { enabled = true, size_m = 1.5e-6, tau_s = 0.5 }",
    ),
    (
        "target_offset",
        "target_offset = { enabled = true, size_m = 1e-3 }",
    ),
    (
        "periodic_nonlinearity",
        "periodic_nonlinearity = { enabled = true, size_m = 3e-7, period_m = 0.05 }",
    ),
];

/// Cases on the two-target plan (the points-level `target_offset` test needs two reflectors).
const TWO_TARGET_CASES: [(&str, &str); 2] = [
    ("none", ""),
    (
        "target_offset",
        "target_offset = { enabled = true, size_m = 2e-5 }",
    ),
];

fn main() {
    let seeds: u64 = std::env::args()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(10);
    let one_target = common::diagnose_demo();
    let two_targets = common::two_target_diagnose_demo();
    let names: Vec<&str> = std::iter::once("none")
        .chain(geocal::diagnose::effects::LIBRARY.iter().map(|k| k.name()))
        .collect();
    println!("rows: true effect; columns: first selected effect; {seeds} seeds each; 5 stations, 27 points, 2 passes");
    print!("{:<26}", "");
    for n in &names {
        print!("{:>8}", &n[..n.len().min(7)]);
    }
    println!(
        "{:>7}{:>7}{:>7}{:>7}{:>9}{:>9}",
        "top-1", "unexpl", "confd", "false", "z before", "z after"
    );
    let only = std::env::var("ONLY").ok();
    let cases = CASES
        .iter()
        .map(|&(truth, line)| (truth, line, &one_target, ""))
        .chain(
            TWO_TARGET_CASES
                .iter()
                .map(|&(truth, line)| (truth, line, &two_targets, " (2 targets)")),
        );
    for (truth, line, base, label) in cases {
        if only.as_deref().is_some_and(|o| o != truth) {
            continue;
        }
        let mut counts = vec![0usize; names.len()];
        let (mut top1, mut unexplained, mut confounded, mut false_sel) = (0, 0, 0, 0);
        let (mut before, mut after) = (0.0, 0.0);
        for seed in 0..seeds {
            let d = common::run_and_diagnose(&common::with_effects(base, 5000 + seed, line));
            let first = d.selected.first().map_or("none", |s| s.as_str());
            if let Some(k) = names.iter().position(|n| *n == first) {
                counts[k] += 1;
            }
            top1 += usize::from(first == truth);
            // Every selected effect that is not the one switched on is a false selection.
            false_sel += d.selected.iter().filter(|s| *s != truth).count();
            confounded += usize::from(d.candidates.iter().any(|c| c.status == "confounded"));
            unexplained += usize::from(d.unexplained);
            before += d.gap.heldout_ratio;
            after += d.gap_after.heldout_ratio;
            if std::env::var("VERBOSE").is_ok() {
                println!("{}", geocal::diagnose::text(&d));
            }
        }
        print!("{:<26}", format!("{truth}{label}"));
        for c in counts {
            print!("{c:>8}");
        }
        println!(
            "{top1:>7}{unexplained:>7}{confounded:>7}{false_sel:>7}{:>9.2}{:>9.2}",
            before / seeds as f64,
            after / seeds as f64
        );
    }
}
