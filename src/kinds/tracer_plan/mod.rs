//! What the kinds on the tracer plan layout share (multilateration, rotary_tracer): one
//! configuration (`config::Config`), one plan, the generic sequencer and simulated world, the
//! tracer run (`run`), its resume and its emulator hosting. A kind's `Kind` implementation
//! calls these; only its solve and report are its own.

pub mod resume;
pub mod run;
pub mod simulate;

use std::path::Path;

use super::registry::{from_run, KindCheck, KindRunOutput, RunFlags};
use crate::config::Config;
use crate::run::RunOptions;
use simulate::SimulateOptions;

/// The configuration at `path`; `--yes` answers the operator's prompts from a pipe.
fn load(path: &Path, flags: &RunFlags) -> anyhow::Result<Config> {
    let mut config = Config::load(path)?;
    if flags.assume_yes {
        config
            .operator
            .get_or_insert_with(Default::default)
            .piped_stdin = true;
    }
    Ok(config)
}

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
    flags: &RunFlags,
) -> anyhow::Result<KindRunOutput> {
    run::run(&load(path, flags)?, options).map(from_run)
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
