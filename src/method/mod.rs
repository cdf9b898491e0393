//! Methods: each wires the session reader, point extraction, a model and a solver into
//! results for one plan kind. `solve_session` picks the method from the session's kind.

pub mod multilateration;
pub mod plan_check;
pub mod plan_check_kinds;
pub mod rotary_tracer;

use serde::Serialize;

#[derive(Debug, thiserror::Error)]
pub enum MethodError {
    #[error("session kind `{0}` has no solver (known: {1})")]
    UnknownKind(String, String),
    #[error(transparent)]
    Multilateration(#[from] multilateration::MultilaterationError),
    #[error(transparent)]
    RotaryTracer(#[from] rotary_tracer::RotaryTracerError),
    #[error(transparent)]
    RotarySphere(#[from] crate::kinds::rotary_sphere::solve::RotarySphereMethodError),
    #[error(transparent)]
    ProbeInstall(#[from] crate::kinds::probe_install::solve::ProbeInstallMethodError),
    #[error(transparent)]
    Hexapod(#[from] crate::kinds::hexapod::solve::HexapodMethodError),
}

/// Results of any method, serialised as geocal-results/1.
// One value per solve: the size difference between variants costs nothing worth a Box.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone, Serialize)]
#[serde(untagged)]
pub enum Results {
    Multilateration(multilateration::MultilaterationResults),
    RotaryTracer(rotary_tracer::RotaryTracerResults),
    RotarySphere(Box<crate::kinds::rotary_sphere::solve::RotarySphereResults>),
    ProbeInstall(Box<crate::kinds::probe_install::solve::ProbeInstallResults>),
    Hexapod(Box<crate::kinds::hexapod::solve::HexapodResults>),
}

impl Results {
    pub fn to_json_pretty(&self) -> String {
        serde_json::to_string_pretty(self).unwrap_or_else(|e| format!("{{\"error\": \"{e}\"}}"))
    }

    /// The stations and points every tracer method has (None for methods without a tracer).
    pub fn multilateration(&self) -> Option<&multilateration::MultilaterationResults> {
        match self {
            Results::Multilateration(r) => Some(r),
            Results::RotaryTracer(r) => Some(&r.multilateration),
            Results::RotarySphere(_) | Results::ProbeInstall(_) | Results::Hexapod(_) => None,
        }
    }
}

/// Choices a user makes when solving; a replay with the same settings gives the same results.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SolveSettings {
    /// Down-weight outlier lengths with a Huber loss (threshold in sigmas).
    pub huber: Option<crate::solve::robust::Huber>,
    /// Unmodelled effects (the diagnosis's names) fitted jointly with the geometry.
    pub effects: Vec<crate::diagnose::effects::EffectKind>,
}

/// Solve a session with the method of its kind.
pub use crate::kinds::registry::solve_session;
