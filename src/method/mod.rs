//! Methods: each wires the session reader, point extraction, a model and a solver into
//! results for one plan kind (`kinds::registry::solve_session` picks it from the session's kind).

pub mod blocked_lsq;
pub mod diagnosis;
pub mod effects;
pub mod multilateration;
pub mod plan_check;
pub mod plan_check_kinds;
pub mod report;
pub mod report_document;
pub mod tall_svd;
pub mod tracer_effects;

use std::any::Any;

#[derive(Debug, thiserror::Error)]
pub enum MethodError {
    #[error("session kind `{0}` has no solver (known: {1})")]
    UnknownKind(String, String),
    #[error(transparent)]
    Multilateration(#[from] multilateration::MultilaterationError),
    /// A kind's own solve failed: its error, as it says it.
    #[error(transparent)]
    Kind(Box<dyn std::error::Error + Send + Sync>),
}

impl MethodError {
    /// A kind's own error (`solve(session).map_err(MethodError::of_kind)`).
    pub fn of_kind(e: impl std::error::Error + Send + Sync + 'static) -> Self {
        MethodError::Kind(Box::new(e))
    }
}

/// What every kind's results offer the commands: their results.json, their text report and,
/// for kinds that measure with a tracer, the tracer network solved (stations and points).
pub trait KindResults: ResultsValue {
    /// The report an engineer reads at the end of a run.
    fn report(&self) -> String;
    fn tracer_network(&self) -> Option<&multilateration::MultilaterationResults> {
        None
    }
}

/// What any serialisable results type gives by itself: its JSON and a copy.
pub trait ResultsValue: Any + std::fmt::Debug + Send + Sync {
    /// geocal-results/1, pretty-printed.
    fn to_json_pretty(&self) -> String;
    fn to_json_value(&self) -> serde_json::Result<serde_json::Value>;
    fn clone_boxed(&self) -> Box<dyn KindResults>;
}

impl<T> ResultsValue for T
where
    T: KindResults + serde::Serialize + Clone + std::fmt::Debug + Send + Sync + 'static,
{
    fn to_json_pretty(&self) -> String {
        serde_json::to_string_pretty(self).unwrap_or_else(|e| format!("{{\"error\": \"{e}\"}}"))
    }

    fn to_json_value(&self) -> serde_json::Result<serde_json::Value> {
        serde_json::to_value(self)
    }

    fn clone_boxed(&self) -> Box<dyn KindResults> {
        Box::new(self.clone())
    }
}

/// How many σ the text output lists, scaled, beside the misfit warning.
const MISFIT_TEXT_ROWS: usize = 24;

/// Results of any kind's method.
#[derive(Debug)]
pub struct Results(Box<dyn KindResults>);

impl Clone for Results {
    fn clone(&self) -> Self {
        Results(self.0.clone_boxed())
    }
}

impl Results {
    pub fn new(results: impl KindResults) -> Self {
        Results(Box::new(results))
    }

    /// The results as the kind's own type, if they are of type `T`.
    pub fn get<T: KindResults>(&self) -> Option<&T> {
        let any: &dyn Any = self.0.as_ref();
        any.downcast_ref::<T>()
    }

    pub fn to_json_pretty(&self) -> String {
        self.0.to_json_pretty()
    }

    pub fn to_json_value(&self) -> serde_json::Result<serde_json::Value> {
        self.0.to_json_value()
    }

    /// The kind's text report, and the misfit warning with the scaled σ when the fit is flagged.
    pub fn report(&self) -> String {
        let mut text = self.0.report();
        if let Some((misfit, json)) = self.misfit() {
            text.push_str(&misfit.text(&json, MISFIT_TEXT_ROWS));
        }
        text
    }

    /// The results' `misfit` when the fit is flagged, with the results as JSON.
    pub fn misfit(&self) -> Option<(crate::solve::misfit::Misfit, serde_json::Value)> {
        let json = self.to_json_value().ok()?;
        let misfit = serde_json::from_value(json.get("misfit")?.clone()).ok()?;
        Some((misfit, json))
    }

    /// The stations and points every tracer method has (None for methods without a tracer).
    pub fn multilateration(&self) -> Option<&multilateration::MultilaterationResults> {
        self.0.tracer_network()
    }
}

/// Choices a user makes when solving; a replay with the same settings gives the same results.
#[derive(Debug, Clone, Default)]
pub struct SolveSettings {
    /// Down-weight outlier lengths with a Huber loss (threshold in sigmas).
    pub huber: Option<crate::solve::robust::Huber>,
    /// Unmodelled effects fitted jointly with the geometry (the diagnosis's models:
    /// `kinds::tracer_plan::diagnosis::correct::parse_effects`); None: none.
    pub effects: Option<std::sync::Arc<dyn effects::EffectsFit>>,
    /// Effects of the kind's own library (kinds with a residual model, `diagnosis`), fitted
    /// jointly with its calibration; empty: none.
    pub effect_names: Vec<String>,
    /// Told how much of the session file is read (bytes done of its size) while it is read;
    /// no bearing on the results.
    pub read_progress: Option<crate::session::reader::ReadProgress>,
}

impl PartialEq for SolveSettings {
    fn eq(&self, other: &Self) -> bool {
        let names = |s: &SolveSettings| s.effects.as_ref().map(|e| e.names());
        self.huber == other.huber
            && names(self) == names(other)
            && self.effect_names == other.effect_names
    }
}
