//! The `geocal compare` and `geocal trend` commands: their arguments and what they print and
//! write.

use std::path::{Path, PathBuf};

use anyhow::Context;

use super::compare::{self, CompareOptions, Tolerances};
use super::load::{self, Run};
use super::trend::{self, TrendOptions};

/// Tolerances on the command line, by unit.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct ToleranceArgs {
    /// Allowed change of a parameter in metres (e.g. 2e-6).
    #[arg(long, value_name = "METRES")]
    pub tolerance_m: Option<f64>,
    /// Allowed change of a parameter in radians (e.g. 5e-6).
    #[arg(long, value_name = "RADIANS")]
    pub tolerance_rad: Option<f64>,
    /// Allowed change of a parameter whose results state no unit.
    #[arg(long, value_name = "VALUE")]
    pub tolerance_other: Option<f64>,
}

impl ToleranceArgs {
    fn tolerances(&self) -> Tolerances {
        Tolerances {
            m: self.tolerance_m,
            rad: self.tolerance_rad,
            other: self.tolerance_other,
        }
    }
}

/// `geocal compare A B`.
#[derive(Debug, Clone, clap::Args)]
pub struct CompareArgs {
    /// The earlier run: a run folder (results.json, run-config.toml, session.mcap) or a
    /// results file.
    #[arg(value_name = "A")]
    pub a: PathBuf,
    /// The later run, of the same machine, kind and plan.
    #[arg(value_name = "B")]
    pub b: PathBuf,
    /// Print geocal-compare/1 JSON instead of the text.
    #[arg(long)]
    pub json: bool,
    /// Family-wise significance level (Holm–Bonferroni over the parameters compared).
    #[arg(long, default_value_t = 0.05)]
    pub alpha: f64,
    #[command(flatten)]
    pub tolerances: ToleranceArgs,
    /// Write the report (difference curves with ±2σ bands) to this HTML file.
    #[arg(long, value_name = "FILE.html")]
    pub html: Option<PathBuf>,
}

/// `geocal trend`.
#[derive(Debug, Clone, clap::Args)]
pub struct TrendArgs {
    /// A folder of run folders of one machine.
    #[arg(value_name = "DIR", required_unless_present = "catalog")]
    pub dir: Option<PathBuf>,
    /// The daemon's data dir: its catalog's succeeded runs instead of a folder.
    #[arg(long, value_name = "DATA_DIR", conflicts_with = "dir")]
    pub catalog: Option<PathBuf>,
    /// The machine (its key, declared id, configured name or serial) when the runs are of several.
    #[arg(long, value_name = "NAME")]
    pub machine: Option<String>,
    /// Print geocal-trend/1 JSON instead of the text.
    #[arg(long)]
    pub json: bool,
    /// Family-wise false-alarm level of the whole series.
    #[arg(long, default_value_t = 0.05)]
    pub alpha: f64,
    #[command(flatten)]
    pub tolerances: ToleranceArgs,
    /// How many of the first runs make the baseline (the band's centre, and its width when no
    /// tolerance is set).
    #[arg(long, value_name = "N", default_value_t = 5)]
    pub baseline_runs: usize,
    /// Write the HTML trend report (SVG plots) to this file.
    #[arg(long, value_name = "FILE.html")]
    pub html: Option<PathBuf>,
}

fn write_html(document: &crate::document::Document, path: &Path) -> anyhow::Result<()> {
    std::fs::write(path, crate::document::html::render(document))
        .with_context(|| format!("writing {}", path.display()))?;
    crate::console::write_err(format_args!("wrote {}\n", path.display()));
    Ok(())
}

/// Run `geocal compare`.
pub fn compare(args: CompareArgs) -> anyhow::Result<()> {
    let a = Run::load(&args.a)?;
    let b = Run::load(&args.b)?;
    let options = CompareOptions {
        alpha: args.alpha,
        tolerances: args.tolerances.tolerances(),
    };
    let comparison = compare::compare(&a, &b, &options)?;
    if let Some(path) = &args.html {
        write_html(&compare::document(&comparison)?, path)?;
    }
    if args.json {
        crate::console::write_out(format_args!(
            "{}\n",
            serde_json::to_string_pretty(&comparison)?
        ))?;
    } else {
        crate::console::write_out(format_args!("{}", compare::text(&comparison)))?;
    }
    Ok(())
}

/// The runs of the machine `wanted` among `runs` (all of them when they are of one machine):
/// machines told apart by their key (docs/fleet.md, "One machine").
pub fn runs_of_machine(runs: Vec<Run>, wanted: Option<&str>) -> anyhow::Result<Vec<Run>> {
    let mut machines: Vec<String> = runs
        .iter()
        .map(|r| format!("{}: {}", r.machine.label(), r.machine.key()))
        .collect();
    machines.sort();
    machines.dedup();
    match wanted {
        Some(key) => {
            let kept = load::runs_of_machine(runs, key, |r| &r.machine)?;
            if kept.is_empty() {
                anyhow::bail!(
                    "no run of machine \"{key}\" (machines found: {})",
                    machines.join("; ")
                );
            }
            Ok(kept)
        }
        None if machines.len() > 1 => anyhow::bail!(
            "the runs are of {} machines ({}): choose one with --machine NAME or KEY",
            machines.len(),
            machines.join("; ")
        ),
        None => Ok(runs),
    }
}

/// Run `geocal trend`; `catalog_runs` reads the daemon's catalog (the daemon's module).
pub fn trend(
    args: TrendArgs,
    catalog_runs: fn(&Path) -> anyhow::Result<Vec<Run>>,
) -> anyhow::Result<()> {
    let runs = match (&args.dir, &args.catalog) {
        (Some(dir), _) => load::load_series(dir)?,
        (None, Some(data_dir)) => catalog_runs(data_dir)?,
        (None, None) => anyhow::bail!("geocal trend needs DIR or --catalog DATA_DIR"),
    };
    let runs = runs_of_machine(runs, args.machine.as_deref())?;
    let options = TrendOptions {
        alpha: args.alpha,
        tolerances: args.tolerances.tolerances(),
        baseline_runs: args.baseline_runs,
    };
    let result = trend::trend(&runs, &options)?;
    if let Some(path) = &args.html {
        write_html(&trend::document(&result)?, path)?;
    }
    if args.json {
        crate::console::write_out(format_args!("{}\n", serde_json::to_string_pretty(&result)?))?;
    } else {
        crate::console::write_out(format_args!("{}", trend::text(&result)))?;
    }
    Ok(())
}
