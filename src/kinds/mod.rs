//! The plan kinds: the registry every command dispatches through (`registry`), and the runs
//! of the kinds with their own configuration layout (`probe_install`, `hexapod`: config ->
//! plan -> simulated devices -> kind sequencer -> recorded session -> solve).

pub mod diagnosis;
pub mod hexapod;
pub mod multilateration;
pub mod probe_install;
pub mod registry;
pub mod rotary_sphere;
pub mod rotary_tracer;
pub mod tracer_plan;

pub use registry::{
    kind_named, kind_of_config, kind_of_run_dir, run_file, solve_file, Kind, KindCheck,
    KindRunOutput, Registry, RunFlags, KINDS,
};

use std::collections::BTreeMap;

use crate::run::{RunOptions, RunOutput};
use crate::session::messages::DeviceInfo;

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

/// Finish the recording, keep the run's error if it failed, let a resumed run's
/// `interruption` check the finished file and delete the interrupted ones, then solve the file
/// as `geocal solve` does and write results.json.
pub(crate) fn finish_and_solve(
    recorder: crate::session::recorder::Recorder,
    summary: Result<crate::sequencer::RunSummary, crate::sequencer::SequencerError>,
    session_path: std::path::PathBuf,
    options: &RunOptions,
    interruption: Option<&crate::run::resume::Interruption>,
) -> anyhow::Result<RunOutput> {
    use anyhow::Context;
    let stats = recorder.finish().context("finishing the session file")?;
    let summary = summary.context("run failed (the session recorded so far is kept)")?;
    if let Some(interruption) = interruption {
        interruption.finished(&session_path)?;
    }
    tracing::info!(
        samples = summary.samples,
        points = summary.points_measured,
        bytes = stats.bytes,
        "run recorded to {}",
        session_path.display()
    );
    let (results, results_path) = crate::kinds::registry::solve_and_write(&session_path, options)?;
    Ok(RunOutput {
        session_path,
        results_path,
        summary,
        results,
    })
}
