//! Multilateration (DESIGN.md): a laser tracer moved between stations measures lengths to the
//! machine's points; the network solve (`method::multilateration`, shared with the diagnosis
//! and rotary_tracer) gives stations, points and their covariance.

pub mod report;
pub mod uncertainty;

use std::path::Path;

use super::registry::{EvaluatedErrors, Kind, KindCheck, KindRunOutput, RunFlags};
use super::tracer_plan;
use crate::kinds::tracer_plan::simulate::SimulateOptions;
use crate::method::{MethodError, Results, SolveSettings};
use crate::run::RunOptions;
use crate::session::reader::Session;

pub struct Multilateration;

impl Kind for Multilateration {
    fn name(&self) -> &'static str {
        crate::config::PlanKind::Multilateration.as_str()
    }

    fn report(&self, results: &serde_json::Value) -> anyhow::Result<crate::document::KindReport> {
        report::document(results)
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
        Ok(Results::new(crate::method::multilateration::solve(
            session, settings,
        )?))
    }

    fn solve_streamed(
        &self,
        path: &Path,
        settings: &SolveSettings,
    ) -> Option<Result<Results, MethodError>> {
        let solved = crate::method::multilateration::solve_file_streaming(path, settings)?;
        Some(solved.map(Results::new).map_err(MethodError::from))
    }

    fn diagnosable(&self) -> bool {
        true
    }

    fn reports_iso230_2(&self) -> bool {
        true
    }

    fn has_error_functions(&self) -> bool {
        true
    }

    fn evaluated_errors(
        &self,
        results: &serde_json::Value,
        session: &Session,
        config: Option<&crate::config::Config>,
    ) -> anyhow::Result<Option<EvaluatedErrors>> {
        let results: crate::method::multilateration::MultilaterationResults =
            crate::document::results_of(self.name(), results)?;
        let Some(geometric) = results.geometric_errors.clone() else {
            return Ok(None);
        };
        let evaluation = crate::evaluate::tracer::evaluate_session(session, &results, config)?;
        Ok(Some(EvaluatedErrors {
            evaluation,
            geometric,
        }))
    }

    fn uncertainty(
        &self,
        results: &serde_json::Value,
        session: &Session,
        config: Option<&Path>,
    ) -> anyhow::Result<Vec<crate::document::Section>> {
        uncertainty::section(results, session, config)
    }

    fn simulate(&self, path: &Path, options: &SimulateOptions) -> anyhow::Result<()> {
        tracer_plan::simulate(path, options)
    }
}
