//! Plan kind `hexapod` (DESIGN.md method 5): its configuration, plan, sequencer, simulated
//! world and HIL source, devices, run and resume, method, plan check and report, and the
//! `Kind` the commands call.

pub mod budget;
pub mod check;
pub mod config;
pub mod devices;
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

use crate::kinds::registry::{
    from_run, kind_layout_check, Kind, KindCheck, KindRunOutput, RunFlags,
};
use crate::method::{MethodError, Results, SolveSettings};
use crate::run::RunOptions;
use crate::session::reader::Session;

/// Plan kind `hexapod`: the hinge coordinates of a Stewart platform from its leg lengths.
pub struct Hexapod;

impl Kind for Hexapod {
    fn name(&self) -> &'static str {
        config::KIND
    }

    fn progress_unit(&self) -> &'static str {
        "poses"
    }

    fn report(&self, results: &serde_json::Value) -> anyhow::Result<crate::document::KindReport> {
        report::document(results)
    }

    fn uncertainty(
        &self,
        results: &serde_json::Value,
        session: &Session,
        config: Option<&Path>,
    ) -> anyhow::Result<Vec<crate::document::Section>> {
        let declared = match config {
            Some(path) => config::HexapodConfig::load(path)?.uncertainty,
            None => Default::default(),
        };
        let section = report::uncertainty(results, session, &declared).unwrap_or_else(|e| {
            crate::evaluate::budget_section::unavailable("hexapod-uncertainty", &e)
        });
        Ok(vec![section])
    }

    fn check(&self, path: &Path) -> anyhow::Result<KindCheck> {
        let config = config::HexapodConfig::load(path)?;
        kind_layout_check(path, check::check(&config))
    }

    fn run(
        &self,
        path: &Path,
        options: &RunOptions,
        _flags: &RunFlags,
    ) -> anyhow::Result<KindRunOutput> {
        let config = config::HexapodConfig::load(path)?;
        run::run(&config, options).map(from_run)
    }

    fn resume(
        &self,
        dir: &Path,
        config: Option<&Path>,
        options: &RunOptions,
    ) -> anyhow::Result<KindRunOutput> {
        run::resume(dir, config, options).map(from_run)
    }

    fn own_replay(&self) -> Option<crate::run::replay::ReplaySequence> {
        Some(replay::replay)
    }

    fn solve(&self, session: &Session, settings: &SolveSettings) -> Result<Results, MethodError> {
        if !settings.effect_names.is_empty() {
            return solve::solve_with_effects(session, &settings.effect_names)
                .map(Results::new)
                .map_err(MethodError::Kind);
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
        let nominal = solve::solve(session)?;
        Ok(Box::new(diagnosis::HexapodResidualModel::new(
            session, &nominal,
        )?))
    }
}
