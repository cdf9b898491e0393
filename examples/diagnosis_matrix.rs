//! Validation of `geocal diagnose`: simulated sessions with one effect (or none) switched on,
//! diagnosed; prints the confusion matrix (true effect x first selected), the gap ratios, the
//! held-out RMS after the effect over the clean session's (the same seed's row `none`), the
//! points level before/after, and with `--twin` the diagnosis against the effect-free twin.
//!
//! `cargo run --example diagnosis_matrix -- N [--twin] [--twin-seeds M]`: N seeds per row
//! (default 10); `--twin` also diagnoses each recording against its twin simulated from its
//! config (`geocal diagnose REC --twin CONFIG.toml`) on the first M seeds (default N).

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
        "tracer_eccentricity = { enabled = true, size_m = 4e-6, z_size_m = 2e-6 }",
    ),
    (
        "thermal_drift",
        "thermal_drift = { enabled = true, size = 4e-9 }",
    ),
    ("dead_path", "dead_path = { enabled = true, size = 2.0 }"),
    (
        "thermal_expansion",
        "thermal_expansion = { enabled = true, size = 2e-6 }",
    ),
    (
        "settling",
        "settling = { enabled = true, size_m = 3e-6, tau_s = 0.5 }",
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

use geocal::diagnose::Diagnosis;
use geocal::kinds::tracer_plan::diagnosis::twin::diagnose_file_with_twin;

/// Family-wise level of the diagnosis' tests (its default), for "points level clean after".
const ALPHA: f64 = 0.01;

/// A figure in a fixed-width column: plain below 1000, else in exponent form.
fn fig(v: f64) -> String {
    if v.abs() < 1000.0 {
        format!("{v:.2}")
    } else {
        format!("{v:.1e}")
    }
}

/// The selection's columns, in both tables: (label, width).
const SELECTION_COLUMNS: [(&str, usize); 6] = [
    ("top-1", 7),
    ("unexpl", 7),
    ("confd", 7),
    ("false", 7),
    ("z before", 9),
    ("z after", 9),
];

/// A header line: each label right-aligned in its width.
fn print_header(groups: &[&[(&str, usize)]]) {
    for (label, width) in groups.iter().copied().flatten() {
        print!("{label:>width$}");
    }
    println!();
}

/// Scores of one row over its seeds (`names`: the confusion matrix's columns).
#[derive(Default)]
struct Scores {
    seeds: usize,
    counts: Vec<usize>,
    top1: usize,
    unexplained: usize,
    confounded: usize,
    false_sel: usize,
    z_before: f64,
    z_after: f64,
    /// Points level χ²/dof before and after the selected effects (sums), seeds tested and
    /// seeds whose points level fits the noise model afterwards.
    pts_before: f64,
    pts_after: f64,
    pts_seeds: usize,
    pts_clean: usize,
    /// Against the twin: the recording's points minus the twin's, χ²/dof before and after.
    twin_pts_before: f64,
    twin_pts_after: f64,
    twin_pts_seeds: usize,
    /// Held-out RMS after the selected effects over the clean session's (the same seed and
    /// plan, the row `none`): sum, largest, seeds compared.
    vs_clean: f64,
    vs_clean_max: f64,
    vs_clean_seeds: usize,
}

impl Scores {
    fn add(&mut self, d: &Diagnosis, truth: &str, names: &[&str]) {
        if self.counts.is_empty() {
            self.counts = vec![0; names.len()];
        }
        self.seeds += 1;
        let first = d.selected.first().map_or("none", |s| s.as_str());
        if let Some(k) = names.iter().position(|n| *n == first) {
            self.counts[k] += 1;
        }
        self.top1 += usize::from(first == truth);
        // Every selected effect that is not the one switched on is a false selection.
        self.false_sel += d.selected.iter().filter(|s| *s != truth).count();
        self.confounded += usize::from(d.candidates.iter().any(|c| c.status == "confounded"));
        self.unexplained += usize::from(d.unexplained);
        self.z_before += d.gap.heldout_ratio;
        self.z_after += d.gap_after.heldout_ratio;
        if let (Some(before), Some(after)) = (&d.points_level, &d.points_level_after) {
            self.pts_seeds += 1;
            self.pts_before += before.gap.chi2_per_dof;
            self.pts_after += after.chi2_per_dof;
            self.pts_clean += usize::from(after.p_value >= ALPHA);
        }
        if let Some(t) = &d.twin {
            if let (Some(b), Some(a)) = (&t.points_before, &t.points_after) {
                self.twin_pts_seeds += 1;
                self.twin_pts_before += b.chi2_per_dof;
                self.twin_pts_after += a.chi2_per_dof;
            }
        }
    }

    fn add_vs_clean(&mut self, ratio: f64) {
        self.vs_clean += ratio;
        self.vs_clean_max = self.vs_clean_max.max(ratio);
        self.vs_clean_seeds += 1;
    }

    fn mean(sum: f64, n: usize) -> String {
        if n == 0 {
            "-".into()
        } else {
            fig(sum / n as f64)
        }
    }
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let seeds: u64 = args
        .iter()
        .find(|a| !a.starts_with("--") && a.parse::<u64>().is_ok())
        .and_then(|s| s.parse().ok())
        .unwrap_or(10);
    let twin = args.iter().any(|a| a == "--twin" || a == "--twin-seeds");
    let twin_seeds: u64 = args
        .iter()
        .position(|a| a == "--twin-seeds")
        .and_then(|k| args.get(k + 1))
        .and_then(|s| s.parse().ok())
        .unwrap_or(seeds)
        .min(seeds);
    let one_target = common::diagnose_demo();
    let two_targets = common::two_target_diagnose_demo();
    let names: Vec<&str> = std::iter::once("none")
        .chain(
            geocal::kinds::tracer_plan::diagnosis::effects::LIBRARY
                .iter()
                .map(|k| k.name()),
        )
        .collect();
    let only = std::env::var("ONLY").ok();
    let cases = CASES
        .iter()
        .map(|&(truth, line)| (truth, line, &one_target, ""))
        .chain(
            TWO_TARGET_CASES
                .iter()
                .map(|&(truth, line)| (truth, line, &two_targets, " (2 targets)")),
        );
    let mut rows: Vec<(String, Scores, Scores)> = Vec::new();
    // The clean session's held-out RMS per (plan, seed), from the row `none` run first.
    let mut clean_level: std::collections::HashMap<(&str, u64), f64> = Default::default();
    for (truth, line, base, label) in cases {
        if only
            .as_deref()
            .is_some_and(|o| !o.split(',').any(|o| o == truth))
        {
            continue;
        }
        let (mut alone, mut against) = (Scores::default(), Scores::default());
        for seed in 0..seeds {
            let text = common::with_effects(base, 5000 + seed, line);
            let dir = tempfile::tempdir().expect("tempdir");
            let session = common::record_session(&text, &dir.path().join("rec"));
            let d = geocal::kinds::diagnosis::diagnose_file(&session, &Default::default())
                .expect("diagnose");
            alone.add(&d, truth, &names);
            if truth == "none" {
                clean_level.insert((label, seed), d.gap.heldout_rms_m);
            } else if let Some(clean) = clean_level.get(&(label, seed)) {
                alone.add_vs_clean(d.gap_after.heldout_rms_m / clean);
            }
            if std::env::var("VERBOSE").is_ok() {
                println!("{}", geocal::diagnose::text(&d));
            }
            if twin && seed < twin_seeds {
                // `geocal diagnose REC --twin CONFIG.toml`: the config the recording was made
                // with, its effects switched off by the twin.
                let config = dir.path().join("config.toml");
                std::fs::write(&config, &text).expect("write config");
                let t = diagnose_file_with_twin(
                    &session,
                    &config,
                    Some(&dir.path().join("twin")),
                    &Default::default(),
                )
                .expect("diagnose against the twin");
                against.add(&t, truth, &names);
                if std::env::var("VERBOSE").is_ok() {
                    println!("{}", geocal::diagnose::text(&t));
                }
            }
        }
        rows.push((format!("{truth}{label}"), alone, against));
    }

    println!("rows: true effect; columns: first selected effect; {seeds} seeds each; 5 stations, 27 points, 2 passes");
    print!("{:<26}", "");
    for n in &names {
        print!("{:>8}", &n[..n.len().min(7)]);
    }
    print_header(&[
        &SELECTION_COLUMNS[..],
        &[
            ("pts bef", 9),
            ("pts aft", 9),
            ("pts ok", 7),
            ("/clean", 9),
            ("max", 9),
        ],
    ]);
    for (label, r, _) in &rows {
        print!("{label:<26}");
        for c in &r.counts {
            print!("{c:>8}");
        }
        println!(
            "{:>7}{:>7}{:>7}{:>7}{:>9}{:>9}{:>9}{:>9}{:>7}{:>9}{:>9}",
            r.top1,
            r.unexplained,
            r.confounded,
            r.false_sel,
            Scores::mean(r.z_before, r.seeds),
            Scores::mean(r.z_after, r.seeds),
            Scores::mean(r.pts_before, r.pts_seeds),
            Scores::mean(r.pts_after, r.pts_seeds),
            format!("{}/{}", r.pts_clean, r.pts_seeds),
            Scores::mean(r.vs_clean, r.vs_clean_seeds),
            if r.vs_clean_seeds == 0 {
                "-".into()
            } else {
                fig(r.vs_clean_max)
            },
        );
    }
    if twin {
        println!();
        println!("against the effect-free twin (`geocal diagnose REC --twin CONFIG.toml`), first {twin_seeds} seeds of each row");
        print_header(&[
            &[("", 26), ("seeds", 7)][..],
            &SELECTION_COLUMNS,
            &[("twin bef", 10), ("twin aft", 10)],
        ]);
        for (label, _, t) in &rows {
            println!(
                "{label:<26}{:>7}{:>7}{:>7}{:>7}{:>7}{:>9}{:>9}{:>10}{:>10}",
                t.seeds,
                t.top1,
                t.unexplained,
                t.confounded,
                t.false_sel,
                Scores::mean(t.z_before, t.seeds),
                Scores::mean(t.z_after, t.seeds),
                Scores::mean(t.twin_pts_before, t.twin_pts_seeds),
                Scores::mean(t.twin_pts_after, t.twin_pts_seeds),
            );
        }
    }
}
