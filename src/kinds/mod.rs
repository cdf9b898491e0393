//! The plan kinds: the registry every command dispatches through (`registry`), and the runs
//! of the kinds with their own configuration layout (`probe_install`, `hexapod`: config ->
//! plan -> simulated devices -> kind sequencer -> recorded session -> solve).

pub mod hexapod;
pub mod probe_install;
pub mod registry;
pub mod rotary_sphere;

pub use registry::{
    kind_named, kind_of_config, kind_of_run_dir, run_file, Kind, KindCheck, KindRunOutput,
    Registry, RunFlags, KINDS,
};

use std::collections::BTreeMap;

use crate::clock::Clock;
use crate::run::{RunOptions, RunOutput};
use crate::sequencer::{RunSummary, SequencerError};
use crate::session::messages::{DeviceInfo, SessionHeader};
use crate::session::recorder::RecorderHandle;

pub(crate) fn device(
    id: &str,
    kind: &str,
    driver: &str,
    noise_m: Option<f64>,
    extra: BTreeMap<String, serde_json::Value>,
) -> DeviceInfo {
    DeviceInfo {
        id: id.into(),
        kind: kind.into(),
        driver: driver.into(),
        noise_m,
        noise_ppm: None,
        dead_path_m: None,
        wavelength_m: None,
        compensated: None,
        extra,
    }
}

/// Record a simulated run of a kind and solve it: the session header, the sequencer's run
/// (`run` is given the recorder) on a fresh runtime, the truth (`--truth`), then the file is
/// finished and solved as `geocal solve` does.
pub(crate) fn record_and_solve<Fut, T>(
    header: &SessionHeader,
    clock: &dyn Clock,
    options: &RunOptions,
    run: impl FnOnce(RecorderHandle) -> Fut,
    truth: impl FnOnce() -> anyhow::Result<T>,
) -> anyhow::Result<RunOutput>
where
    Fut: std::future::Future<Output = Result<RunSummary, SequencerError>>,
    T: serde::Serialize,
{
    let (session_path, recorder) = crate::run::create_session(&options.out_dir)?;
    let handle = recorder.handle();
    handle.session(header, clock.now_ns());
    let summary = crate::run::run_runtime()?.block_on(run(handle));
    if let Some(path) = &options.truth {
        crate::run::write_truth(path, &truth()?)?;
    }
    finish_and_solve(recorder, summary, session_path, options)
}

/// Finish the recording, keep the run's error if it failed, then solve the file as `geocal
/// solve` does and write results.json.
pub(crate) fn finish_and_solve(
    recorder: crate::session::recorder::Recorder,
    summary: Result<crate::sequencer::RunSummary, crate::sequencer::SequencerError>,
    session_path: std::path::PathBuf,
    options: &RunOptions,
) -> anyhow::Result<RunOutput> {
    use anyhow::Context;
    let stats = recorder.finish().context("finishing the session file")?;
    let summary = summary.context("run failed (the session recorded so far is kept)")?;
    tracing::info!(
        samples = summary.samples,
        points = summary.points_measured,
        bytes = stats.bytes,
        "run recorded to {}",
        session_path.display()
    );
    let (results, results_path) = crate::run::solve_and_write(&session_path, options)?;
    Ok(RunOutput {
        session_path,
        results_path,
        summary,
        results,
    })
}
