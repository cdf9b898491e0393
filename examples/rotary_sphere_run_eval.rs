//! The published rotary-axis check (shared/references/ref3) through the whole pipeline: the
//! example config (config/rotary-sphere.toml) run in the simulated world — table, arm and probe
//! devices, recorded session, solve from the file — for several seeds and probe variants.
//! Prints the share of third-height prediction residuals within 10 µm beside the published
//! ~80 %, the honesty of the reported uncertainties, and the wall time per run.
//!
//!     cargo run --release --example rotary_sphere_run_eval [-- SEEDS]

use std::path::Path;
use std::time::Instant;

use geocal::kinds::rotary_sphere::config::RotarySphereConfig;
use geocal::kinds::rotary_sphere::run::run;
use geocal::run::RunOptions;

const CONFIG: &str = include_str!("../config/rotary-sphere.toml");

fn main() -> anyhow::Result<()> {
    let seeds: u64 = std::env::args()
        .nth(1)
        .map(|s| s.parse())
        .transpose()?
        .unwrap_or(20);
    // (label, probe σ per reading, points per sphere, readings per point)
    let variants: [(&str, f64, usize, usize); 6] = [
        ("27 µm, 5 pts (published)", 27e-6, 5, 1),
        ("27 µm, 5 pts, 3 readings", 27e-6, 5, 3),
        ("10 µm, 5 pts", 10e-6, 5, 1),
        ("5 µm, 5 pts", 5e-6, 5, 1),
        ("1 µm, 5 pts", 1e-6, 5, 1),
        ("27 µm, 25 pts", 27e-6, 25, 1),
    ];
    let dir = tempfile::tempdir()?;
    println!(
        "whole runs of config/rotary-sphere.toml, validation height 229 mm, 36 angles, {seeds} \
         seeds; published: ~80 % of residuals within 10 µm"
    );
    println!(
        "{:28} {:>10} {:>12} {:>10} {:>8} {:>10}",
        "probe", "|r|<=10µm", "coord<=10µm", "in 3σ", "χ²/n", "run [ms]"
    );
    for (label, noise_m, points, readings) in variants {
        let (mut norm, mut coord, mut in3, mut chi2, mut n, mut ms) =
            (0.0, 0.0, 0.0, 0.0, 0usize, 0.0);
        for seed in 0..seeds {
            let text = CONFIG
                .replace("seed = 20240612", &format!("seed = {}", 5000 + seed))
                .replace("noise_m = 2.7e-5", &format!("noise_m = {noise_m:e}"))
                .replace("points = 5 ", &format!("points = {points} "))
                .replace(
                    "readings_per_point = 1 ",
                    &format!("readings_per_point = {readings} "),
                );
            let config = RotarySphereConfig::parse(&text, Path::new("rotary-sphere.toml"))?;
            let start = Instant::now();
            let output = run(
                &config,
                &RunOptions {
                    out_dir: dir.path().join(format!("{label}-{seed}")),
                    truth: None,
                    progress: false,
                    settings: Default::default(),
                    control: Default::default(),
                },
            )?;
            ms += start.elapsed().as_secs_f64() * 1e3;
            let Some(r) = output
                .results
                .get::<geocal::kinds::rotary_sphere::solve::RotarySphereResults>()
            else {
                anyhow::bail!("expected rotary_sphere results");
            };
            let v = &r.validation[0];
            norm += v.share_norm_within_10um;
            coord += v.share_coordinates_within_10um;
            in3 += v.share_within_3_sigma;
            chi2 += v.chi2;
            n += v.count;
        }
        let s = seeds as f64;
        println!(
            "{label:28} {:>9.1}% {:>11.1}% {:>9.1}% {:>8.2} {:>10.0}",
            100.0 * norm / s,
            100.0 * coord / s,
            100.0 * in3 / s,
            chi2 / n as f64,
            ms / s
        );
    }
    Ok(())
}
