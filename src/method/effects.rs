//! Unmodelled effects in the solve (`geocal solve --effects`): what fitting them changes, and
//! the interface the effect models (the diagnosis's library) offer the solve, so that the
//! methods need not know the models.

use std::collections::BTreeMap;

use nalgebra::DMatrix;

use crate::extract::SettledSession;

/// Effects fitted jointly with the geometry of a session.
pub trait EffectsFit: std::fmt::Debug + Send + Sync {
    /// The effects' names (the diagnosis's vocabulary).
    fn names(&self) -> Vec<&'static str>;
    /// Their joint fit on the session's settled windows: what to take off each length, and
    /// what it adds.
    fn correction(
        &self,
        settled: &SettledSession,
    ) -> Result<EffectCorrection, Box<dyn std::error::Error + Send + Sync>>;
}

/// What modelling the effects changes in the calibration.
#[derive(Debug, Clone)]
pub struct EffectCorrection {
    /// Per recorded length (the extraction's measurement order): the effects' fitted
    /// contribution, to be taken off the measured length (m).
    pub length_correction_m: Vec<f64>,
    /// Effect name → parameter name → value, with `<parameter>.sigma` beside each.
    pub effects: BTreeMap<String, BTreeMap<String, f64>>,
    /// Number of effect parameters fitted (they take degrees of freedom from χ²).
    pub parameters: usize,
    /// Covariance the effects' uncertainty adds to the points (3n x 3n, point-major, in the
    /// points' inner-constraint datum).
    pub point_covariance_m2: DMatrix<f64>,
    /// Covariance the effects' uncertainty adds to the stations (3m x 3m, station-major, in
    /// the same datum): what a method built on the stations (a circle through them) needs.
    pub station_covariance_m2: DMatrix<f64>,
}
