//! Validation of `geocal diagnose`: simulated sessions with one effect (or none) switched on,
//! diagnosed; prints the confusion matrix (true effect x first selected) and the gap ratios.

#[path = "../tests/common/mod.rs"]
mod common;

/// (true effect, the `[sim.effects]` line that switches it on at a realistic size).
const CASES: [(&str, &str); 7] = [
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
        "periodic_nonlinearity",
        "periodic_nonlinearity = { enabled = true, size_m = 3e-7, period_m = 0.05 }",
    ),
];

fn main() {
    let seeds: u64 = std::env::args()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(10);
    let base = common::diagnose_demo();
    let names = [
        "none",
        "station_drift",
        "reversal",
        "length_step",
        "air_refraction",
        "tracer_eccentricity",
    ];
    println!("rows: true effect; columns: first selected effect; {seeds} seeds each; 5 stations, 27 points, 2 passes");
    print!("{:<22}", "");
    for n in names {
        print!("{:>12}", &n[..n.len().min(11)]);
    }
    println!(
        "{:>12}{:>12}{:>14}",
        "unexplained", "both-sel", "heldout z-rms"
    );
    let only = std::env::var("ONLY").ok();
    for (truth, line) in CASES {
        if only.as_deref().is_some_and(|o| o != truth) {
            continue;
        }
        let mut counts = [0usize; 6];
        let mut unexplained = 0;
        let mut ratio_sum = 0.0;
        let mut extra = 0;
        for seed in 0..seeds {
            let d = common::run_and_diagnose(&common::with_effects(&base, 5000 + seed, line));
            let first = d.selected.first().map_or("none", |s| s.as_str());
            if let Some(k) = names.iter().position(|n| *n == first) {
                counts[k] += 1;
            }
            if d.selected.len() > 1 {
                extra += 1;
            }
            unexplained += usize::from(d.unexplained);
            ratio_sum += d.gap_after.heldout_ratio;
            if std::env::var("VERBOSE").is_ok() {
                println!("{}", geocal::diagnose::text(&d));
            }
        }
        print!("{truth:<22}");
        for c in counts {
            print!("{c:>12}");
        }
        println!(
            "{unexplained:>12}{extra:>12}{:>14.2}",
            ratio_sum / seeds as f64
        );
    }
}
