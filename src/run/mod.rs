//! What every kind's run shares: its options and output, the runtime its drivers live on,
//! the session file it records into, the truth it writes, its progress bar, and what an
//! interrupted run leaves (`resume`).

pub mod control;
pub mod replay;
pub mod resume;

use std::path::{Path, PathBuf};

use anyhow::Context;

use crate::method::{Results, SolveSettings};
use crate::sequencer::RunSummary;
use crate::session::recorder::{Recorder, RecorderOptions};

pub struct RunOptions {
    pub out_dir: PathBuf,
    /// Write the simulated truth here (simulated runs only).
    pub truth: Option<PathBuf>,
    /// Show a progress bar.
    pub progress: bool,
    pub settings: SolveSettings,
    /// Cancellation, live tap, progress and operator for a run driven by the daemon.
    pub control: crate::run::control::RunControl,
}

pub struct RunOutput {
    pub session_path: PathBuf,
    pub results_path: PathBuf,
    pub summary: RunSummary,
    pub results: Results,
}

/// The runtime a run's drivers, emulators and sequencer live on: the run's own
/// single-threaded one, or the device holder's when the run's real devices are held between
/// runs (their connections outlive the run, so their tasks must too).
pub(crate) enum RunRuntime {
    Own(tokio::runtime::Runtime),
    Holder(tokio::runtime::Handle),
}

impl RunRuntime {
    pub(crate) fn block_on<F: std::future::Future>(&self, future: F) -> F::Output {
        match self {
            RunRuntime::Own(runtime) => runtime.block_on(future),
            RunRuntime::Holder(handle) => handle.block_on(future),
        }
    }
}

/// The runtime for a run; `real_devices`: it connects to devices outside this process.
pub(crate) fn run_runtime(
    control: &crate::run::control::RunControl,
    real_devices: bool,
) -> anyhow::Result<RunRuntime> {
    if let Some(handle) = control
        .devices
        .as_ref()
        .filter(|_| real_devices)
        .and_then(|holder| holder.handle())
    {
        return Ok(RunRuntime::Holder(handle));
    }
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map(RunRuntime::Own)
        .context("starting the async runtime")
}

/// Create the output directory and the session file in it: (its path, its recorder).
pub(crate) fn create_session(options: &RunOptions) -> anyhow::Result<(PathBuf, Recorder)> {
    let out_dir = &options.out_dir;
    std::fs::create_dir_all(out_dir)
        .with_context(|| format!("creating output directory {}", out_dir.display()))?;
    let session_path = out_dir.join(crate::run::resume::SESSION_FILE);
    let recorder_options = RecorderOptions {
        tap: options.control.tap.clone(),
        ..RecorderOptions::default()
    };
    let recorder = Recorder::create(&session_path, recorder_options)
        .with_context(|| format!("creating {}", session_path.display()))?;
    Ok((session_path, recorder))
}

/// Write a simulated world's truth as pretty JSON (`--truth`).
pub(crate) fn write_truth<T: serde::Serialize>(path: &Path, truth: &T) -> anyhow::Result<()> {
    std::fs::write(path, serde_json::to_string_pretty(truth)?)
        .with_context(|| format!("writing truth to {}", path.display()))
}

/// A progress bar on stderr counting `what` (hidden unless `show`).
pub(crate) fn progress_bar(show: bool, what: &str) -> indicatif::ProgressBar {
    if !show {
        return indicatif::ProgressBar::hidden();
    }
    let bar = indicatif::ProgressBar::new(0);
    let template = format!(
        "{{spinner}} [{{elapsed_precise}}] {{bar:40}} {{pos}}/{{len}} {what} ({{eta}} left)"
    );
    if let Ok(style) = indicatif::ProgressStyle::with_template(&template) {
        bar.set_style(style);
    }
    bar
}
