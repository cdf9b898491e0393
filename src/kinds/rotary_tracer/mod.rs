//! Rotary tracer (DESIGN.md): the tracer on a rotary table, turned from station to station;
//! the network solve, then a circle through the table stations gives the table's axis and
//! step errors (`solve`).

pub mod budget;
pub mod diagnosis;
pub mod report;
pub mod solve;

use std::path::Path;

use super::registry::{Kind, KindCheck, KindRunOutput, RunFlags};
use super::tracer_plan;
use crate::kinds::tracer_plan::simulate::SimulateOptions;
use crate::method::{MethodError, Results, SolveSettings};
use crate::run::RunOptions;
use crate::session::reader::Session;

pub struct RotaryTracer;

impl Kind for RotaryTracer {
    fn name(&self) -> &'static str {
        crate::config::PlanKind::RotaryTracer.as_str()
    }

    fn diagnosable(&self) -> bool {
        true
    }

    fn reports_iso230_2(&self) -> bool {
        true
    }

    fn tracer_diagnosis(
        &self,
    ) -> Option<&'static dyn crate::method::tracer_effects::TracerNetworkDiagnosis> {
        Some(&diagnosis::DIAGNOSIS)
    }

    fn report(&self, results: &serde_json::Value) -> anyhow::Result<crate::document::KindReport> {
        report::document(results)
    }

    fn uncertainty(
        &self,
        results: &serde_json::Value,
        _session: &Session,
        config: Option<&Path>,
    ) -> anyhow::Result<Vec<crate::document::Section>> {
        let declared = match config {
            Some(path) => crate::config::Config::load(path)?.uncertainty,
            None => None,
        };
        let section = report::uncertainty(results, declared).unwrap_or_else(|e| {
            crate::evaluate::budget_section::unavailable("rotary-tracer-uncertainty", &e)
        });
        Ok(vec![section])
    }

    fn check(&self, path: &Path) -> anyhow::Result<KindCheck> {
        tracer_plan::check(path)
    }

    fn run(
        &self,
        path: &Path,
        options: &RunOptions,
        flags: &RunFlags,
    ) -> anyhow::Result<KindRunOutput> {
        tracer_plan::run(path, options, flags)
    }

    fn resume(
        &self,
        dir: &Path,
        config: Option<&Path>,
        options: &RunOptions,
    ) -> anyhow::Result<KindRunOutput> {
        tracer_plan::resume(dir, config, options)
    }

    fn solve(&self, session: &Session, settings: &SolveSettings) -> Result<Results, MethodError> {
        Ok(Results::new(
            solve::solve(session, settings).map_err(MethodError::of_kind)?,
        ))
    }

    fn solve_streamed(
        &self,
        path: &Path,
        settings: &SolveSettings,
    ) -> Option<Result<Results, MethodError>> {
        let solved = solve::solve_file_streaming(path, settings)?;
        Some(solved.map(Results::new).map_err(MethodError::of_kind))
    }

    fn simulate(&self, path: &Path, options: &SimulateOptions) -> anyhow::Result<()> {
        tracer_plan::simulate(path, options)
    }
}
