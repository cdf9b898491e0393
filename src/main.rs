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
    /// Show no progress (in a terminal one line updated in place; on a pipe a line per
    /// station or per tenth of the work).
    #[arg(long, short, global = true)]
    quiet: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum ReportFormat {
    Html,
    Md,
}

#[derive(Subcommand)]
enum Command {
    /// Run a calibration (live or simulated), record the session, then solve it.
    Run {
        /// The run's configuration (optional with --resume: the run stored it in DIR).
        #[arg(required_unless_present = "resume")]
        config: Option<PathBuf>,
        /// Output directory for session.mcap and results.json.
        #[arg(long, default_value = "geocal-out")]
        out: PathBuf,
        /// Continue the interrupted run recorded in DIR at its first unfinished point
        /// (docs/resume.md); its output goes to DIR.
        #[arg(long, value_name = "DIR", conflicts_with = "out")]
        resume: Option<PathBuf>,
        /// Write the simulated truth (stations, actual points, error functions) as JSON.
        #[arg(long)]
        truth: Option<PathBuf>,
        /// Print the results JSON instead of the text report.
        #[arg(long)]
        json: bool,
        /// Down-weight outlier lengths with a Huber loss beyond this many sigmas (e.g. 3).
        #[arg(long, value_name = "SIGMAS")]
        huber: Option<f64>,
        /// Real runs: read the operator's acknowledgements as lines from stdin even when it
        /// is not a terminal (a supervising program's pipe).
        #[arg(long)]
        yes: bool,
        /// Publish the run live to Foxglove while it records (docs/live-view.md): a port
        /// (loopback) or HOST:PORT; alone, 127.0.0.1:8765.
        #[arg(long, value_name = "ADDR", num_args = 0..=1, default_missing_value = "8765")]
        live: Option<String>,
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
        /// Fit these unmodelled effects (names as `geocal diagnose` gives them, comma
        /// separated, e.g. reversal,station_drift) jointly with the geometry.
        #[arg(long, value_name = "EFFECT,...", value_delimiter = ',')]
        effects: Vec<String>,
    },
    /// The report people read (docs/report.md): one self-contained HTML file (or Markdown with
    /// its plots as SVG files beside it) from a run directory or a results file, with the
    /// session and diagnosis.json found beside the results.
    Report {
        /// A run directory (results.json, session.mcap, diagnosis.json) or a results file.
        #[arg(value_name = "DIR|RESULTS")]
        input: std::path::PathBuf,
        /// The report file (default: report.html or report.md beside the results).
        #[arg(long, value_name = "FILE")]
        out: Option<std::path::PathBuf>,
        /// html (one self-contained file) or md (Markdown, plots as SVG files beside it).
        #[arg(long, value_enum, default_value = "html")]
        format: ReportFormat,
        /// A verification run: the results the tables were made from, instead of the file
        /// named by the `geocal-source.json` beside the tables.
        #[arg(long, value_name = "RESULTS")]
        before: Option<std::path::PathBuf>,
    },
    /// Copy every readable message of a truncated or damaged session into a complete MCAP
    /// file (summary, indexes, CRCs) and print what was lost (docs/repair.md).
    Repair {
        session: PathBuf,
        /// The repaired file (default: SESSION's name with `.repaired.mcap`, beside it).
        #[arg(long, value_name = "FILE")]
        out: Option<PathBuf>,
    },
    /// Where a session departs from the nominal model, which unmodelled effect explains it.
    Diagnose {
        session: PathBuf,
        /// Print geocal-diagnosis/1 JSON instead of the text report.
        #[arg(long)]
        json: bool,
        /// Compare with a twin: a second session, or a config (.toml) to simulate the twin of
        /// this recording from (its stations, the config's machine and noise, effects off).
        #[arg(long, value_name = "SESSION|CONFIG.toml")]
        twin: Option<PathBuf>,
        /// Keep the simulated twin's session in this directory.
        #[arg(long, value_name = "DIR")]
        twin_out: Option<PathBuf>,
        /// Draw each length's residual / sigma against time, one row per station, before and
        /// after the selected effects, to this SVG file.
        #[arg(long, value_name = "FILE.svg")]
        plot: Option<PathBuf>,
    },
    /// Host the configured device emulators (HPI-3D and GRBL on ptys, the Modbus table on
    /// 127.0.0.1) backed by the simulated world, for a run driven from another process;
    /// operator commands (`station <id>`, `target <id>`) on stdin. Stop with Ctrl-C/SIGTERM.
    Simulate {
        config: PathBuf,
        /// Write the simulated truth as JSON (at start and at exit).
        #[arg(long)]
        truth: Option<PathBuf>,
        /// Print the devices as one JSON object.
        #[arg(long)]
        json: bool,
    },
    /// Re-run the sequencer and stillstand detection against a recorded session (replay
    /// drivers), record the replay, solve it and compare it with the recording.
    Replay {
        session: PathBuf,
        /// Deliver the samples at the recorded pace (wall clock) instead of at full speed.
        #[arg(long)]
        realtime: bool,
        /// Output directory for the replayed session.mcap, results.json and comparison.json
        /// (default: `replay` beside SESSION).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Print the comparison (geocal-replay/1 JSON) instead of the text.
        #[arg(long)]
        json: bool,
    },
    /// Connect to one device with its real driver, print its live readings and optionally
    /// record them as a session (kind `monitor`).
    Monitor {
        /// hpi3d:PORT, grbl:PORT, probe:PORT, modbus-rtu:PORT, modbus-tcp:HOST:PORT or
        /// linuxcnc:HOST[:PORT].
        #[arg(long, value_name = "SPEC")]
        device: String,
        /// Stop after this many seconds (default: run until Ctrl-C).
        #[arg(long, value_name = "N")]
        seconds: Option<f64>,
        /// Record the readings to this session file (MCAP).
        #[arg(long, value_name = "FILE")]
        out: Option<PathBuf>,
        /// Driver settings: a TOML file with [hpi3d], [grbl], [linuxcnc], [rotary] or [probe]
        /// (or a run config's [devices.tracer.hpi3d] / [devices.machine.grbl] /
        /// [devices.machine.linuxcnc]).
        #[arg(long, value_name = "FILE")]
        config: Option<PathBuf>,
    },
    /// Write the NC program of a passive run (moves, dwells, operator stops) as ISO G-code.
    ExportNc {
        config: PathBuf,
        /// Write the program here instead of printing it.
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Compensation tables from a multilateration's results (docs/compensation.md): LinuxCNC
    /// joint compensation files with their INI fragment, SINUMERIK $AA_ENC_COMP / $AN_CEC
    /// programs, or the 21 errors as a CSV/JSON table.
    Compensate {
        results: PathBuf,
        /// linuxcnc-type0, linuxcnc-type1, sinumerik, csv or json.
        #[arg(long, value_name = "FORMAT")]
        format: String,
        /// Output directory (LinuxCNC, SINUMERIK: default `compensation`), or the file of a
        /// CSV/JSON table (default: print it).
        #[arg(long, value_name = "PATH")]
        out: Option<PathBuf>,
        /// Table step in metres (e.g. 0.01 for 10 mm); default: the finest step within the
        /// controller's entry limit that keeps the calibrated grid positions on the table.
        #[arg(long, value_name = "METRES")]
        step: Option<f64>,
        /// Axes to export, comma separated.
        #[arg(long, value_delimiter = ',', default_value = "x,y,z")]
        axes: Vec<String>,
        /// SINUMERIK: points per table (MD38000 $MM_ENC_COMP_MAX_POINTS).
        #[arg(long, value_name = "N", default_value_t = 200)]
        max_points: usize,
        /// SINUMERIK: the largest value a table may hold, metres (MD32720 $MA_CEC_MAX_SUM).
        #[arg(long, value_name = "METRES", default_value_t = 1e-3)]
        max_value: f64,
        /// SINUMERIK: machine axis names of x, y, z, comma separated.
        #[arg(long, value_delimiter = ',', default_value = "X1,Y1,Z1")]
        axis_names: Vec<String>,
    },
    /// Has the machine changed between two of its runs? Per parameter the difference, its
    /// combined σ, z and significance after the Holm–Bonferroni correction, and tolerance
    /// exceedance (docs/history.md).
    Compare(geocal::history::cli::CompareArgs),
    /// A machine's parameters over a series of its runs, with steps, drifts and values outside
    /// their tolerance band (docs/history.md).
    Trend(geocal::history::cli::TrendArgs),
    /// Every run's results (and with --raw its tracer samples) as Parquet tables partitioned
    /// by machine and date, for DuckDB, Spark or pandas (docs/fleet.md).
    Export(geocal::export::ExportArgs),
    /// Validate a configuration and predict the uncertainties its plan allows.
    Check {
        config: PathBuf,
        #[arg(long)]
        json: bool,
    },
    /// The acquisition daemon: queue and run jobs, keep them in a catalog that survives
    /// crashes, and serve the HTTP control API (docs/serve.md). Stops cleanly on SIGTERM.
    Serve {
        /// The daemon's configuration (TOML; every key optional).
        #[arg(long, value_name = "FILE")]
        config: Option<PathBuf>,
        /// Jobs, their files and the catalog (overrides the configuration's data_dir).
        #[arg(long, value_name = "DIR")]
        data_dir: Option<PathBuf>,
        /// The API's address (default 127.0.0.1:7878; beyond loopback a token_file is required).
        #[arg(long, value_name = "ADDR")]
        listen: Option<std::net::SocketAddr>,
        /// The bearer token's file (overrides the configuration's token_file).
        #[arg(long, value_name = "FILE")]
        token_file: Option<PathBuf>,
        /// The Foxglove live view's address (PORT or IP:PORT; "off" to disable; default
        /// 127.0.0.1:8765).
        #[arg(long, value_name = "ADDR")]
        live: Option<String>,
    },
    /// Speak to a running daemon: submit a plan, list and follow jobs, acknowledge prompts,
    /// fetch results and sessions.
    Client {
        /// The daemon's URL.
        #[arg(long, env = "GEOCAL_SERVER", default_value = "http://127.0.0.1:7878")]
        server: String,
        /// The bearer token's file (needed when the daemon has one).
        #[arg(long, env = "GEOCAL_TOKEN_FILE", value_name = "FILE")]
        token_file: Option<PathBuf>,
        #[command(subcommand)]
        command: ClientCommand,
    },
}

#[derive(Subcommand)]
enum ClientCommand {
    /// Submit a plan configuration as a run job; print its id (and follow it with --follow).
    Submit {
        config: PathBuf,
        /// Follow the job's progress until it ends; exit non-zero unless it succeeded.
        #[arg(long)]
        follow: bool,
        /// With --follow: print the final job as JSON even in a terminal (on a pipe it is JSON
        /// anyway; in a terminal a short summary).
        #[arg(long)]
        json: bool,
    },
    /// List every job.
    Jobs,
    /// Show one job as JSON.
    Status { id: i64 },
    /// Follow a job until it ends: a short summary in a terminal, the job as JSON on a pipe
    /// or with --json.
    Follow {
        id: i64,
        #[arg(long)]
        json: bool,
    },
    /// Cancel a queued or running job.
    Cancel { id: i64 },
    /// Resume an interrupted or cancelled run.
    Resume { id: i64 },
    /// List the operator prompts waiting.
    Prompts,
    /// Acknowledge an operator prompt.
    Ack { prompt: u64 },
    /// Download a job's `results`, `session`, `report`, or another file it left (by name).
    Fetch {
        id: i64,
        #[arg(default_value = "results")]
        what: String,
        #[arg(long, value_name = "FILE")]
        out: Option<PathBuf>,
    },
}

fn main() -> ExitCode {
    use std::io::IsTerminal;
    let cli = Cli::parse();
    // The daemon logs what it does (info), as JSON lines when a supervisor reads its output.
    let default_level = if matches!(cli.command, Command::Serve { .. }) {
        "info"
    } else {
        "warn"
    };
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default_level));
    // No colour codes in a file or a pipe; a failed write of a log line is dropped (telling
    // of it on the same stderr would fail too).
    let logger = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(std::io::stderr().is_terminal())
        .log_internal_errors(false);
    if matches!(cli.command, Command::Serve { .. }) && !std::io::stderr().is_terminal() {
        logger.json().init();
    } else {
        logger.init();
    }
    geocal::allocator::limit_arenas();
    let progress = geocal::progress::Mode::for_stderr(cli.quiet);
    match dispatch(cli.command, progress) {
        Ok(()) => ExitCode::SUCCESS,
        // The reader of stdout has gone (`geocal check X | head -1`): nothing left to say.
        Err(e) if geocal::console::is_broken_pipe(&e) => ExitCode::SUCCESS,
        Err(e) => {
            geocal::console::write_err(format_args!("{}", geocal::console::error_text(&e)));
            ExitCode::FAILURE
        }
    }
}

/// Ctrl-C (SIGINT) or SIGTERM during `geocal run` cancels the run as the daemon's cancel
/// does: it stops, the machine's controller is left as found and the session is kept for
/// `--resume`. A second signal ends the process at once.
fn cancel_on_interrupt(cancel: tokio_util::sync::CancellationToken) {
    std::thread::spawn(move || {
        let Ok(runtime) = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
        else {
            return;
        };
        runtime.block_on(async {
            use tokio::signal::unix::{signal, SignalKind};
            let Ok(mut term) = signal(SignalKind::terminate()) else {
                return;
            };
            tokio::select! {
                _ = tokio::signal::ctrl_c() => {}
                _ = term.recv() => {}
            }
            geocal::errln!(
                "interrupted: stopping the run, leaving the machine as found and keeping the \
                 session (`geocal run --resume DIR` continues it); again to quit at once"
            );
            cancel.cancel();
            tokio::select! {
                _ = tokio::signal::ctrl_c() => {}
                _ = term.recv() => {}
            }
            std::process::exit(130);
        });
    });
}

fn settings(huber: Option<f64>) -> geocal::method::SolveSettings {
    geocal::method::SolveSettings {
        huber: huber.map(|threshold_sigma| geocal::solve::robust::Huber { threshold_sigma }),
        ..Default::default()
    }
}

fn dispatch(command: Command, progress: geocal::progress::Mode) -> anyhow::Result<()> {
    let kinds = geocal::kinds::Registry::standard();
    match command {
        Command::Run {
            config,
            out,
            truth,
            json,
            huber,
            yes,
            resume,
            live,
        } => {
            let live = match live {
                Some(text) => {
                    let address = geocal::serve::live::parse_address(&text)?;
                    let view = std::sync::Arc::new(geocal::serve::live::LiveView::start(address)?);
                    geocal::errln!(
                        "live view: ws://{} (Foxglove: open connection)",
                        view.address()
                    );
                    Some(view)
                }
                None => None,
            };
            let kind = match (&resume, &config) {
                (Some(dir), config) => kinds.of_run_dir(dir, config.as_deref())?,
                (None, Some(config)) => kinds.of_config(config)?,
                (None, None) => anyhow::bail!("geocal run needs CONFIG or --resume DIR"),
            };
            let shown = geocal::progress::Progress::new(progress, "run", kind.progress_unit());
            let live_tap = match &live {
                Some(view) => geocal::session::tap::Tap::new(view.clone()),
                None => Default::default(),
            };
            // `--yes`: the operator's acknowledgements are lines on stdin, even from a pipe. A
            // flag of this invocation, never written into the run's stored configuration.
            let operator = yes.then(|| {
                std::sync::Arc::new(|| {
                    Box::new(geocal::devices::operator::ConsoleOperator::new(
                        std::io::BufReader::new(std::io::stdin()),
                        Box::new(std::io::stderr()),
                    )) as Box<dyn geocal_drivers::Operator>
                }) as geocal::sequencer::control::OperatorSource
            });
            let cancel = tokio_util::sync::CancellationToken::new();
            cancel_on_interrupt(cancel.clone());
            let control = geocal::run::control::RunControl {
                cancel,
                tap: shown.tap(live_tap),
                progress: Some(shown.sink()),
                operator,
                ..Default::default()
            };
            let options = geocal::run::RunOptions {
                out_dir: resume.clone().unwrap_or(out),
                truth,
                // The kinds' own bars stay off: `shown` draws every kind's progress.
                progress: false,
                settings: settings(huber),
                control,
            };
            let flags = geocal::kinds::RunFlags { assume_yes: yes };
            let output = match (resume, config) {
                (Some(dir), config) => kind.resume(&dir, config.as_deref(), &options),
                (None, Some(config)) => kind.run(&config, &options, &flags),
                (None, None) => anyhow::bail!("geocal run needs CONFIG or --resume DIR"),
            };
            shown.finish();
            let output = output?;
            if let Some(view) = &live {
                view.stop();
            }
            if json {
                geocal::outln!("{}", output.results.to_json_pretty())?;
            } else {
                geocal::out!("{}", output.results.report())?;
                geocal::outln!(
                    "\n  {} recorded to {}\n  results in {}",
                    output.recorded,
                    output.session_path.display(),
                    output.results_path.display()
                )?;
            }
        }
        Command::Solve {
            session,
            json,
            out,
            huber,
            effects,
        } => {
            let settings =
                geocal::kinds::diagnosis::solve_settings(&session, &effects, settings(huber))?;
            let spinner = geocal::progress::spinner(
                progress,
                &format!("solve: reading and solving {}", session.display()),
            );
            let results = geocal::kinds::solve_file(&session, &settings);
            spinner.finish_and_clear();
            let results = results?;
            if let Some(path) = out {
                std::fs::write(&path, results.to_json_pretty())
                    .map_err(|e| anyhow::anyhow!("writing {}: {e}", path.display()))?;
            }
            if json {
                geocal::outln!("{}", results.to_json_pretty())?;
            } else {
                geocal::out!("{}", results.report())?;
            }
        }
        Command::Repair { session, out } => {
            let out = out.unwrap_or_else(|| geocal::session::repair::default_output(&session));
            let report = geocal::session::repair::repair(&session, &out)?;
            geocal::out!("{}", geocal::session::repair::text(&report))?;
        }
        Command::Report {
            input,
            out,
            format,
            before,
        } => {
            let mut inputs = geocal::report::Inputs::read(&input)?;
            inputs.before_results = before;
            let document = geocal::report::build(&inputs, &kinds)?;
            let (format, default_name) = match format {
                ReportFormat::Html => (geocal::report::Format::Html, "report.html"),
                ReportFormat::Md => (geocal::report::Format::Markdown, "report.md"),
            };
            let out = out.unwrap_or_else(|| {
                inputs
                    .results_path
                    .parent()
                    .unwrap_or(std::path::Path::new("."))
                    .join(default_name)
            });
            for path in geocal::report::write(&document, &out, format)? {
                geocal::outln!("{}", path.display())?;
            }
        }
        Command::Diagnose {
            session,
            json,
            twin,
            twin_out,
            plot,
        } => {
            let spinner = geocal::progress::spinner(
                progress,
                &format!(
                    "diagnose: fitting the candidate effects to {}",
                    session.display()
                ),
            );
            let diagnosed = match twin {
                None => {
                    geocal::kinds::diagnosis::diagnose_file_detailed(&session, &Default::default())
                }
                Some(twin) => geocal::kinds::diagnosis::refuse_twin(&session).and_then(|()| {
                    geocal::kinds::tracer_plan::diagnosis::twin::diagnose_file_with_twin_detailed(
                        &session,
                        &twin,
                        twin_out.as_deref(),
                        &Default::default(),
                    )
                }),
            };
            spinner.finish_and_clear();
            let (diagnosis, residuals) = diagnosed?;
            if let Some(path) = plot {
                geocal::diagnose::plot::write_svg(&path, &diagnosis.session_id, &residuals)?;
            }
            if json {
                geocal::outln!("{}", serde_json::to_string_pretty(&diagnosis)?)?;
            } else {
                geocal::out!("{}", geocal::diagnose::text(&diagnosis))?;
            }
        }
        Command::Simulate {
            config,
            truth,
            json,
        } => {
            kinds.of_config(&config)?.simulate(
                &config,
                &geocal::kinds::tracer_plan::simulate::SimulateOptions { truth, json },
            )?;
        }
        Command::Replay {
            session,
            realtime,
            out,
            json,
        } => {
            let out_dir = out.unwrap_or_else(|| {
                session
                    .parent()
                    .unwrap_or(std::path::Path::new("."))
                    .join("replay")
            });
            let output = geocal::replay::replay(
                &session,
                &geocal::replay::ReplayOptions {
                    out_dir,
                    realtime,
                    settings: settings(None),
                    progress: progress == geocal::progress::Mode::Bar,
                },
            )?;
            if json {
                geocal::outln!("{}", serde_json::to_string_pretty(&output.comparison)?)?;
            } else {
                geocal::out!("{}", geocal::replay::text(&output.comparison))?;
            }
            if output.comparison.outcome == geocal::replay::Outcome::Diverged {
                anyhow::bail!("{}", output.comparison.message);
            }
        }
        Command::Monitor {
            device,
            seconds,
            out,
            config,
        } => {
            let summary = geocal::monitor::monitor(&geocal::monitor::MonitorOptions {
                device: device.parse()?,
                seconds,
                out: out.clone(),
                config,
                print_interval_s: 0.2,
            })?;
            let counts: Vec<String> = summary
                .readings
                .iter()
                .map(|(k, n)| format!("{n} {k}"))
                .collect();
            geocal::outln!(
                "{} readings ({}), {} device errors{}",
                summary.readings.values().sum::<u64>(),
                counts.join(", "),
                summary.errors,
                out.map(|p| format!(", recorded to {}", p.display()))
                    .unwrap_or_default()
            )?;
        }
        Command::ExportNc { config, out } => {
            let cfg = geocal::config::Config::load(&config)?;
            let plan = geocal::plan::Plan::from_config(&cfg);
            let title = format!(
                "geocal {} plan from {}: {} stations, {} points, {} passes",
                cfg.kind.as_str(),
                config.display(),
                plan.stations.len(),
                plan.points.len(),
                plan.passes.len()
            );
            let text = geocal::plan::nc::to_gcode(&geocal::plan::nc::program(&cfg, &plan), &title);
            match out {
                Some(path) => std::fs::write(&path, text)
                    .map_err(|e| anyhow::anyhow!("writing {}: {e}", path.display()))?,
                None => geocal::out!("{text}")?,
            }
        }
        Command::Serve {
            config,
            data_dir,
            listen,
            token_file,
            live,
        } => {
            let mut serve_config = match config {
                Some(path) => geocal::serve::ServeConfig::load(&path)?,
                None => geocal::serve::ServeConfig::default(),
            };
            if let Some(dir) = data_dir {
                serve_config.data_dir = dir;
            }
            if let Some(address) = listen {
                serve_config.listen = address;
            }
            if let Some(path) = token_file {
                serve_config.token_file = Some(path);
            }
            if let Some(address) = live {
                serve_config.live = address;
            }
            geocal::serve::serve(serve_config, kinds)?;
        }
        Command::Client {
            server,
            token_file,
            command,
        } => client(&server, token_file.as_deref(), command, progress)?,
        Command::Compensate {
            results,
            format,
            out,
            step,
            axes,
            max_points,
            max_value,
            axis_names,
        } => compensate(CompensateArgs {
            results,
            format,
            out,
            step,
            axes,
            max_points,
            max_value,
            axis_names,
        })?,
        Command::Compare(args) => geocal::history::cli::compare(args)?,
        Command::Trend(args) => {
            geocal::history::cli::trend(args, geocal::serve::machines::catalog_runs)?
        }
        Command::Export(args) => geocal::export::command(&args)?,
        Command::Check { config, json } => {
            let check = kinds.of_config(&config)?.check(&config)?;
            if json {
                geocal::outln!("{}", serde_json::to_string_pretty(&check.json)?)?;
            } else {
                geocal::outln!("{}: valid", config.display())?;
                geocal::out!("{}", check.text)?;
            }
        }
    }
    Ok(())
}

fn client(
    server: &str,
    token_file: Option<&std::path::Path>,
    command: ClientCommand,
    progress: geocal::progress::Mode,
) -> anyhow::Result<()> {
    use geocal::serve::client::{default_fetch_path, job_line, Client};
    let client = Client::new(server, token_file)?;
    let follow = |id: i64, json: bool| -> anyhow::Result<()> {
        let shown = geocal::progress::Progress::new(progress, &format!("job {id}"), "points");
        let job = client.follow_events(id, |event, value| {
            geocal::serve::client::show_event(&shown, event, value)
        });
        shown.finish();
        let job = job?;
        // A person reads a summary; a program (a pipe, or --json) the whole record.
        if json || !std::io::IsTerminal::is_terminal(&std::io::stdout()) {
            geocal::outln!("{}", serde_json::to_string_pretty(&job)?)?;
        } else {
            geocal::outln!("{}", geocal::serve::client::summary(&job, server))?;
        }
        if job.state != geocal::serve::catalog::JobState::Succeeded {
            anyhow::bail!("job {id} ended {}", job.state.as_str());
        }
        Ok(())
    };
    match command {
        ClientCommand::Submit {
            config,
            follow: and_follow,
            json,
        } => {
            let id = client.submit(&config)?;
            geocal::outln!("{id}")?;
            if and_follow {
                follow(id, json)?;
            }
        }
        ClientCommand::Jobs => {
            for job in client.jobs()? {
                geocal::outln!("{}", job_line(&job))?;
            }
        }
        ClientCommand::Status { id } => {
            geocal::outln!("{}", serde_json::to_string_pretty(&client.job(id)?)?)?
        }
        ClientCommand::Follow { id, json } => follow(id, json)?,
        ClientCommand::Cancel { id } => client.cancel(id)?,
        ClientCommand::Resume { id } => client.resume(id)?,
        ClientCommand::Prompts => {
            for prompt in client.prompts()? {
                geocal::outln!(
                    "{:>4}  job {:<5} {}",
                    prompt.id,
                    prompt.job,
                    prompt.instruction
                )?;
            }
        }
        ClientCommand::Ack { prompt } => client.ack(prompt)?,
        ClientCommand::Fetch { id, what, out } => {
            let out = out.unwrap_or_else(|| default_fetch_path(id, &what));
            let bytes = client.fetch(id, &what, &out)?;
            geocal::outln!("{bytes} bytes to {}", out.display())?;
        }
    }
    Ok(())
}

struct CompensateArgs {
    results: PathBuf,
    format: String,
    out: Option<PathBuf>,
    step: Option<f64>,
    axes: Vec<String>,
    max_points: usize,
    max_value: f64,
    axis_names: Vec<String>,
}

fn compensate(a: CompensateArgs) -> anyhow::Result<()> {
    use geocal::compensate::{self, sinumerik::SinumerikOptions, TableFormat, AXES};
    let format = TableFormat::parse(&a.format).ok_or_else(|| {
        anyhow::anyhow!(
            "--format {}: expected one of {}",
            a.format,
            TableFormat::NAMES.join(", ")
        )
    })?;
    let axes = a
        .axes
        .iter()
        .map(|name| {
            AXES.iter()
                .position(|x| x == name)
                .ok_or_else(|| anyhow::anyhow!("--axes: expected x, y or z, found `{name}`"))
        })
        .collect::<anyhow::Result<Vec<usize>>>()?;
    let axis_names: [String; 3] = a.axis_names.clone().try_into().map_err(|_| {
        anyhow::anyhow!(
            "--axis-names: expected three names (x, y, z), found {}",
            a.axis_names.len()
        )
    })?;
    let calibration = compensate::Calibration::load(&a.results)?;
    let options = compensate::ExportOptions {
        step_m: a.step,
        axes,
        ..Default::default()
    };
    let sinumerik = SinumerikOptions {
        axis_names,
        max_points: a.max_points,
        max_value_m: a.max_value,
    };
    let export = compensate::export(&calibration, format, &options, &sinumerik)?;
    for s in &export.steps {
        geocal::errln!(
            "axis {}: {} entries, step {:.4} mm, interpolation error {:.4} µm (calibration σ {:.4} µm)",
            s.axis,
            s.entries,
            s.step_m * 1e3,
            s.interpolation_error_m * 1e6,
            s.sigma_m * 1e6
        );
    }
    for w in export.warnings() {
        geocal::errln!("warning: {w}");
    }
    let write = |path: &std::path::Path, text: &str| {
        std::fs::write(path, text).map_err(|e| anyhow::anyhow!("writing {}: {e}", path.display()))
    };
    match (format, &a.out) {
        (TableFormat::Csv | TableFormat::Json, None) => {
            for f in &export.files {
                geocal::out!("{}", f.text)?;
            }
        }
        (TableFormat::Csv | TableFormat::Json, Some(path)) => {
            for f in &export.files {
                write(path, &f.text)?;
                geocal::errln!("wrote {}", path.display());
            }
        }
        (_, out) => {
            let dir = out.clone().unwrap_or_else(|| PathBuf::from("compensation"));
            std::fs::create_dir_all(&dir)
                .map_err(|e| anyhow::anyhow!("creating {}: {e}", dir.display()))?;
            for f in &export.files {
                let path = dir.join(&f.name);
                write(&path, &f.text)?;
                geocal::errln!("wrote {}", path.display());
            }
            // Beside the tables: the results they came from, for a verification run's report.
            let source = compensate::source::Source::new(&calibration, format, &export.steps);
            let path = dir.join(compensate::source::SOURCE_FILE);
            write(&path, &source.to_json())?;
            geocal::errln!("wrote {}", path.display());
        }
    }
    Ok(())
}
