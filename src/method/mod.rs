//! Methods: each wires the session reader, point extraction, a model and a solver into
//! results for one plan kind. `solve_session` picks the method from the session's kind.

pub mod multilateration;
pub mod plan_check;

use serde::Serialize;

use crate::session::reader::Session;

#[derive(Debug, thiserror::Error)]
pub enum MethodError {
    #[error("session kind `{0}` has no solver yet (known: multilateration)")]
    UnknownKind(String),
    #[error(transparent)]
    Multilateration(#[from] multilateration::MultilaterationError),
}

/// Results of any method, serialised as geocal-results/1.
#[derive(Debug, Clone, Serialize)]
#[serde(untagged)]
pub enum Results {
    Multilateration(multilateration::MultilaterationResults),
}

impl Results {
    pub fn to_json_pretty(&self) -> String {
        serde_json::to_string_pretty(self).unwrap_or_else(|e| format!("{{\"error\": \"{e}\"}}"))
    }
}

/// Choices a user makes when solving; a replay with the same settings gives the same results.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SolveSettings {
    /// Down-weight outlier lengths with a Huber loss (threshold in sigmas).
    pub huber: Option<crate::solve::robust::Huber>,
}

pub fn solve_session(session: &Session, settings: &SolveSettings) -> Result<Results, MethodError> {
    match session.header.kind.as_str() {
        "multilateration" => Ok(Results::Multilateration(multilateration::solve(
            session, settings,
        )?)),
        other => Err(MethodError::UnknownKind(other.to_string())),
    }
}
