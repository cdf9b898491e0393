//! Reproduces the published four-axis simulation (shared/references/ref2: 12 tracer stations on
//! the rotary table 30° apart + 1 elevated station, 72 points, ±3 µm geometric and ±5" table
//! errors) over several seeds, and prints our residual ranges (estimated − introduced) beside
//! the published ones.
//!
//!     cargo run --release --example rotary_tracer_eval [-- CONFIG [SEEDS]]

use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use geocal::config::Config;
use geocal::kinds::tracer_plan::run::run;
use geocal::run::RunOptions;
use nalgebra::{Matrix3, Rotation3, Vector3};
use serde_json::Value;

const ARCSEC_PER_RAD: f64 = 180.0 * 3600.0 / std::f64::consts::PI;

/// [min, max] accumulator.
#[derive(Clone, Copy)]
struct Range(f64, f64);

impl Range {
    const EMPTY: Range = Range(f64::INFINITY, f64::NEG_INFINITY);
    fn add(&mut self, v: f64) {
        self.0 = self.0.min(v);
        self.1 = self.1.max(v);
    }
    fn merge(&mut self, o: Range) {
        self.add(o.0);
        self.add(o.1);
    }
    fn show(&self) -> String {
        format!("{:+.2} .. {:+.2}", self.0, self.1)
    }
}

/// Ranges of one run: x, y, z point residuals (µm) and the table step residual (arcsec).
#[derive(Clone, Copy)]
struct Row {
    introduced: [Range; 4],
    raw: [Range; 4],
    aligned: [Range; 4],
    sigma_max: [f64; 4],
    /// Largest |residual| / sigma of a table step.
    step_z_max: f64,
}

impl Row {
    fn empty() -> Row {
        Row {
            introduced: [Range::EMPTY; 4],
            raw: [Range::EMPTY; 4],
            aligned: [Range::EMPTY; 4],
            sigma_max: [0.0; 4],
            step_z_max: 0.0,
        }
    }
    fn merge(&mut self, o: &Row) {
        for k in 0..4 {
            self.introduced[k].merge(o.introduced[k]);
            self.raw[k].merge(o.raw[k]);
            self.aligned[k].merge(o.aligned[k]);
            self.sigma_max[k] = self.sigma_max[k].max(o.sigma_max[k]);
        }
        self.step_z_max = self.step_z_max.max(o.step_z_max);
    }
}

fn xyz(v: &Value) -> anyhow::Result<Vector3<f64>> {
    let a = v.as_array().context("expected [x, y, z]")?;
    if a.len() != 3 {
        bail!("expected 3 coordinates");
    }
    let c = |k: usize| a[k].as_f64().context("coordinate is not a number");
    Ok(Vector3::new(c(0)?, c(1)?, c(2)?))
}

/// Rigid motion (R, t) minimising Σ |R a + t − b|² (Kabsch).
fn rigid_fit(a: &[Vector3<f64>], b: &[Vector3<f64>]) -> (Rotation3<f64>, Vector3<f64>) {
    let n = a.len() as f64;
    let ca = a.iter().sum::<Vector3<f64>>() / n;
    let cb = b.iter().sum::<Vector3<f64>>() / n;
    let mut h = Matrix3::zeros();
    for (p, q) in a.iter().zip(b) {
        h += (p - ca) * (q - cb).transpose();
    }
    let svd = h.svd(true, true);
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return (Rotation3::identity(), cb - ca);
    };
    let mut d = Matrix3::identity();
    if (v_t.transpose() * u.transpose()).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    let r = Rotation3::from_matrix_unchecked(v_t.transpose() * d * u.transpose());
    (r, cb - r * ca)
}

fn evaluate(config: &Config, out_dir: &Path) -> anyhow::Result<Row> {
    let truth_path = out_dir.join("truth.json");
    let output = run(
        config,
        &RunOptions {
            out_dir: out_dir.to_path_buf(),
            truth: Some(truth_path.clone()),
            progress: false,
            settings: Default::default(),
            control: Default::default(),
        },
    )?;
    let truth: Value = serde_json::from_slice(&std::fs::read(&truth_path)?)?;
    let Some(results) = output
        .results
        .get::<geocal::kinds::rotary_tracer::solve::RotaryTracerResults>()
    else {
        bail!("the configuration is not of kind rotary_tracer");
    };
    let ml = &results.multilateration;
    let truth_points = truth["points"].as_array().context("truth points")?;
    let mut row = Row::empty();
    let mut est = Vec::new();
    let mut actual = Vec::new();
    for p in &ml.points {
        let t = truth_points
            .iter()
            .find(|t| t["point"] == p.point && t["target"] == p.target.as_str())
            .context("point missing from the truth")?;
        let true_actual = xyz(&t["actual_m"])?;
        let nominal = xyz(&t["nominal_m"])?;
        for k in 0..3 {
            let introduced = true_actual[k] - nominal[k];
            row.introduced[k].add(introduced * 1e6);
            row.raw[k].add((p.error_m[k] - introduced) * 1e6);
            row.sigma_max[k] = row.sigma_max[k].max(p.sigma_m[k] * 1e6);
        }
        est.push(Vector3::from(p.actual_m));
        actual.push(true_actual);
    }
    // The datum is a convention (inner constraints relative to the nominal points): remove
    // the rigid motion between the estimated and the true points too, to see the rest.
    let (r, t) = rigid_fit(&est, &actual);
    for (e, a) in est.iter().zip(&actual) {
        let d = r * e + t - a;
        for k in 0..3 {
            row.aligned[k].add(d[k] * 1e6);
        }
    }
    let steps = truth["rotary"]["steps"].as_array().context("truth steps")?;
    let true_error = |k: usize| steps[k]["error_rad"].as_f64().unwrap_or(f64::NAN);
    for (k, step) in results.rotary.steps.iter().enumerate() {
        row.introduced[3].add(true_error(k) * ARCSEC_PER_RAD);
        // Both relative to the first table station: the step angles define no absolute zero.
        let residual = (step.error_rad - (true_error(k) - true_error(0))) * ARCSEC_PER_RAD;
        row.raw[3].add(residual);
        row.aligned[3].add(residual);
        row.sigma_max[3] = row.sigma_max[3].max(step.sigma_rad * ARCSEC_PER_RAD);
        if step.sigma_rad > 0.0 {
            row.step_z_max = row
                .step_z_max
                .max(residual.abs() / (step.sigma_rad * ARCSEC_PER_RAD));
        }
    }
    Ok(row)
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let config_path = PathBuf::from(
        args.first()
            .map_or("config/rotary-tracer.toml", String::as_str),
    );
    let seeds: u64 = match args.get(1) {
        Some(s) => s.parse().context("SEEDS must be a whole number")?,
        None => 5,
    };
    let mut config = Config::load(&config_path)?;
    let base_seed = config.sim.as_ref().map(|s| s.seed).context("needs [sim]")?;
    let work = std::env::temp_dir().join(format!("geocal-rotary-eval-{}", std::process::id()));
    println!(
        "rotary tracer eval: {} ({} seeds from {base_seed})\n",
        config_path.display(),
        seeds
    );
    println!("per seed: residual = estimated - introduced (points raw, in our datum; table steps relative to the first station)");
    println!(
        "{:>10} | {:>16} | {:>16} | {:>16} | {:>16}",
        "seed", "x [µm]", "y [µm]", "z [µm]", "rotary [\"]"
    );
    let mut all = Row::empty();
    for i in 0..seeds {
        let seed = base_seed + i;
        if let Some(sim) = config.sim.as_mut() {
            sim.seed = seed;
        }
        let dir = work.join(format!("seed{seed}"));
        let row = evaluate(&config, &dir)?;
        println!(
            "{:>10} | {:>16} | {:>16} | {:>16} | {:>16}",
            seed,
            row.raw[0].show(),
            row.raw[1].show(),
            row.raw[2].show(),
            row.raw[3].show()
        );
        all.merge(&row);
    }
    let _ = std::fs::remove_dir_all(&work);
    println!("\nover all seeds:");
    println!(
        "{:<34} | {:>16} | {:>16} | {:>16} | {:>16}",
        "", "x [µm]", "y [µm]", "z [µm]", "rotary [\"]"
    );
    let line = |name: &str, r: [Range; 4]| {
        println!(
            "{:<34} | {:>16} | {:>16} | {:>16} | {:>16}",
            name,
            r[0].show(),
            r[1].show(),
            r[2].show(),
            r[3].show()
        );
    };
    line("introduced (ours)", all.introduced);
    line(
        "introduced (published)",
        [
            Range(-2.9, 2.9),
            Range(-3.0, 3.0),
            Range(-3.0, 2.8),
            Range(-5.0, 5.0),
        ],
    );
    line("residual (ours, raw datum)", all.raw);
    line("residual (ours, rigidly aligned)", all.aligned);
    line(
        "residual (published)",
        [
            Range(-0.1, 0.5),
            Range(0.0, 0.8),
            Range(-1.1, 1.4),
            Range(-1.6, 0.2),
        ],
    );
    println!(
        "{:<34} | {:>16.3} | {:>16.3} | {:>16.3} | {:>16.3}",
        "largest reported sigma (ours)",
        all.sigma_max[0],
        all.sigma_max[1],
        all.sigma_max[2],
        all.sigma_max[3]
    );
    println!(
        "largest |table step residual| / its sigma: {:.2}",
        all.step_z_max
    );
    Ok(())
}
