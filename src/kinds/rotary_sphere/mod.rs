//! Plan kind `rotary_sphere` (DESIGN.md method 2): its configuration, plan, sequencer,
//! simulated world and HIL table source, run and resume, method and plan check, and the
//! `Kind` the commands call.

pub mod budget;
pub mod check;
pub mod config;
pub mod diagnosis;
pub mod hil_source;
pub mod plan;
pub mod replay;
pub mod report;
pub mod run;
pub mod sequence;
pub mod sim;
pub mod solve;

use std::path::Path;

use crate::kinds::registry::{kind_layout_check, Kind, KindCheck, KindRunOutput, RunFlags};
use crate::method::{MethodError, Results, SolveSettings};
use crate::run::RunOptions;
use crate::session::reader::Session;

fn from_sphere_run(output: run::SphereRunOutput) -> KindRunOutput {
    KindRunOutput {
        recorded: format!("{} probe readings", output.summary.readings),
        session_path: output.session_path,
        results_path: output.results_path,
        results: output.results,
    }
}

/// Plan kind `rotary_sphere`: a rotary table's axis errors from a probed sphere.
pub struct RotarySphere;

impl Kind for RotarySphere {
    fn name(&self) -> &'static str {
        config::KIND
    }

    fn progress_unit(&self) -> &'static str {
        "probed points"
    }

    fn report(&self, results: &serde_json::Value) -> anyhow::Result<crate::document::KindReport> {
        report::document(results)
    }

    fn uncertainty(
        &self,
        _results: &serde_json::Value,
        session: &Session,
        config: Option<&Path>,
    ) -> anyhow::Result<Vec<crate::document::Section>> {
        let declared = match config {
            Some(path) => config::RotarySphereConfig::load(path)?.uncertainty,
            None => Default::default(),
        };
        let section = report::uncertainty(session, &declared).unwrap_or_else(|e| {
            crate::evaluate::budget_section::unavailable("rotary-sphere-uncertainty", &e)
        });
        Ok(vec![section])
    }

    fn check(&self, path: &Path) -> anyhow::Result<KindCheck> {
        let config = config::RotarySphereConfig::load(path)?;
        kind_layout_check(path, check::check(&config))
    }

    fn run(
        &self,
        path: &Path,
        options: &RunOptions,
        _flags: &RunFlags,
    ) -> anyhow::Result<KindRunOutput> {
        let config = config::RotarySphereConfig::load(path)?;
        run::run(&config, options).map(from_sphere_run)
    }

    fn resume(
        &self,
        dir: &Path,
        config: Option<&Path>,
        options: &RunOptions,
    ) -> anyhow::Result<KindRunOutput> {
        run::resume(dir, config, options).map(from_sphere_run)
    }

    fn own_replay(&self) -> Option<crate::run::replay::ReplaySequence> {
        Some(replay::replay)
    }

    fn solve(&self, session: &Session, settings: &SolveSettings) -> Result<Results, MethodError> {
        if !settings.effect_names.is_empty() {
            return solve::solve_with_effects(session, &settings.effect_names)
                .map(Results::new)
                .map_err(|e| MethodError::Kind(e.into()));
        }
        solve::solve(session)
            .map(Results::new)
            .map_err(MethodError::of_kind)
    }

    fn has_residual_model(&self) -> bool {
        true
    }

    fn residual_model(
        &self,
        session: &Session,
    ) -> anyhow::Result<Box<dyn crate::method::diagnosis::ResidualModel>> {
        Ok(Box::new(diagnosis::SphereResidualModel::with_axis(
            session,
        )?))
    }
}
