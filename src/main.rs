//! The geocal command line.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "geocal",
    version,
    about = "Geometric calibration of machine tools, CMMs, rotary tables and hexapods"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run a calibration (live or simulated), record the session, then solve it.
    Run {
        config: PathBuf,
        /// Output directory for session.mcap and results.json.
        #[arg(long, default_value = "geocal-out")]
        out: PathBuf,
        /// Write the simulated truth (stations, actual points, error functions) as JSON.
        #[arg(long)]
        truth: Option<PathBuf>,
        /// Print the results JSON instead of the text report.
        #[arg(long)]
        json: bool,
        /// Down-weight outlier lengths with a Huber loss beyond this many sigmas (e.g. 3).
        #[arg(long, value_name = "SIGMAS")]
        huber: Option<f64>,
    },
    /// Re-solve a recorded session (replay): the same results as the live run.
    Solve {
        session: PathBuf,
        /// Print geocal-results/1 JSON instead of the text report.
        #[arg(long)]
        json: bool,
        /// Write the results JSON to this file.
        #[arg(long)]
        out: Option<PathBuf>,
        /// Down-weight outlier lengths with a Huber loss beyond this many sigmas (e.g. 3).
        #[arg(long, value_name = "SIGMAS")]
        huber: Option<f64>,
    },
    /// Where a session departs from the nominal model, which unmodelled effect explains it.
    Diagnose {
        session: PathBuf,
        /// Print geocal-diagnosis/1 JSON instead of the text report.
        #[arg(long)]
        json: bool,
    },
    /// Validate a configuration and predict the uncertainties its plan allows.
    Check {
        config: PathBuf,
        #[arg(long)]
        json: bool,
    },
}

fn main() -> ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn")),
        )
        .with_writer(std::io::stderr)
        .init();
    match dispatch(Cli::parse().command) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn settings(huber: Option<f64>) -> geocal::method::SolveSettings {
    geocal::method::SolveSettings {
        huber: huber.map(|threshold_sigma| geocal::solve::robust::Huber { threshold_sigma }),
    }
}

fn dispatch(command: Command) -> anyhow::Result<()> {
    use std::io::IsTerminal;
    match command {
        Command::Run {
            config,
            out,
            truth,
            json,
            huber,
        } => {
            let options = geocal::run::RunOptions {
                out_dir: out,
                truth,
                progress: std::io::stderr().is_terminal(),
                settings: settings(huber),
            };
            // Kinds with their own configuration layout (probe_install, hexapod) first.
            let output = match geocal::kinds::run_file(&config, &options)? {
                Some(output) => output,
                None => {
                    let cfg = geocal::config::Config::load(&config)?;
                    geocal::run::run(&cfg, &options)?
                }
            };
            if json {
                println!("{}", output.results.to_json_pretty());
            } else {
                print!("{}", geocal::report::text(&output.results));
                println!(
                    "\n  {} samples recorded to {}\n  results in {}",
                    output.summary.samples,
                    output.session_path.display(),
                    output.results_path.display()
                );
            }
        }
        Command::Solve {
            session,
            json,
            out,
            huber,
        } => {
            let results = geocal::run::solve_file(&session, &settings(huber))?;
            if let Some(path) = out {
                std::fs::write(&path, results.to_json_pretty())
                    .map_err(|e| anyhow::anyhow!("writing {}: {e}", path.display()))?;
            }
            if json {
                println!("{}", results.to_json_pretty());
            } else {
                print!("{}", geocal::report::text(&results));
            }
        }
        Command::Diagnose { session, json } => {
            let diagnosis = geocal::diagnose::diagnose_file(&session, &Default::default())?;
            if json {
                println!("{}", serde_json::to_string_pretty(&diagnosis)?);
            } else {
                print!("{}", geocal::diagnose::text(&diagnosis));
            }
        }
        Command::Check { config, json } => {
            if let Some(text) = geocal::kinds::check_file(&config)? {
                print!("{text}");
                return Ok(());
            }
            let cfg = geocal::config::Config::load(&config)?;
            let plan = geocal::plan::Plan::from_config(&cfg);
            let check = geocal::method::plan_check::check(&cfg, &plan)
                .map_err(|e| anyhow::anyhow!("{}: plan check: {e}", config.display()))?;
            if json {
                println!("{}", serde_json::to_string_pretty(&check)?);
            } else {
                println!("{}: valid", config.display());
                print!("{}", geocal::report::plan_check_text(&check));
            }
        }
    }
    Ok(())
}
