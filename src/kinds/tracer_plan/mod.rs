//! What the kinds on the tracer plan layout share (multilateration, rotary_tracer): one
//! configuration (`config::Config`), one plan, the generic sequencer and simulated world, the
//! tracer run (`run`), its resume and its emulator hosting. A kind's `Kind` implementation
//! calls these; only its solve and report are its own.

pub mod diagnosis;
pub mod resume;
pub mod run;
pub mod simulate;

use std::path::Path;

use super::registry::{from_run, KindCheck, KindRunOutput, RunFlags};
use crate::config::Config;
use crate::run::RunOptions;
use simulate::SimulateOptions;

/// `geocal check`: the tracer plan's predicted uncertainties.
pub(crate) fn check(path: &Path) -> anyhow::Result<KindCheck> {
    let config = Config::load(path)?;
    let plan = crate::plan::Plan::from_config(&config);
    let check = crate::method::plan_check::check(&config, &plan)
        .map_err(|e| anyhow::anyhow!("{}: plan check: {e}", path.display()))?;
    Ok(KindCheck {
        json: serde_json::to_value(&check)?,
        text: crate::method::report::plan_check_text(&check),
    })
}

pub(crate) fn run(
    path: &Path,
    options: &RunOptions,
    _flags: &RunFlags,
) -> anyhow::Result<KindRunOutput> {
    // `--yes` reaches the run as its operator (`RunControl::operator`), not as configuration.
    run::run(&Config::load(path)?, options).map(from_run)
}

pub(crate) fn resume(
    dir: &Path,
    config: Option<&Path>,
    options: &RunOptions,
) -> anyhow::Result<KindRunOutput> {
    resume::resume(dir, config, options).map(from_run)
}

pub(crate) fn simulate(path: &Path, options: &SimulateOptions) -> anyhow::Result<()> {
    simulate::simulate(&Config::load(path)?, options)
}
