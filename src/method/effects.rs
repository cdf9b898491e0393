//! Unmodelled effects in the solve (`geocal solve --effects`): what fitting them changes, and
//! the interface the effect models (the diagnosis's library) offer the solve, so that the
//! methods need not know the models.

use std::collections::BTreeMap;

use nalgebra::{DMatrix, Matrix3};

use crate::extract::SettledDwells;

/// Effects fitted jointly with the geometry of a session.
pub trait EffectsFit: std::fmt::Debug + Send + Sync {
    /// The effects' names (the diagnosis's vocabulary).
    fn names(&self) -> Vec<&'static str>;
    /// Their joint fit on the session's settled windows (their raw samples are not read): what
    /// to take off each length, and what it adds.
    fn correction(
        &self,
        settled: &SettledDwells,
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
    /// How each effect parameter moves the points (3n x parameters, point-major, in the
    /// points' inner-constraint datum): with `parameter_covariance`, the covariance the
    /// effects' uncertainty adds to the points, R Θ Rᵀ, kept as its factors (the 3n x 3n
    /// product would not fit in memory for a large plan).
    pub point_response: DMatrix<f64>,
    /// Covariance of the effect parameters, Θ (parameters x parameters).
    pub parameter_covariance: DMatrix<f64>,
    /// Covariance the effects' uncertainty adds to the stations (3m x 3m, station-major, in
    /// the same datum): what a method built on the stations (a circle through them) needs.
    pub station_covariance_m2: DMatrix<f64>,
}

impl EffectCorrection {
    /// The covariance the effects add to point `i` (3 x 3, m²).
    pub fn point_covariance_block(&self, i: usize) -> Matrix3<f64> {
        let rows = self.point_response.rows(3 * i, 3);
        let block = rows * &self.parameter_covariance * rows.transpose();
        Matrix3::from_fn(|r, c| block[(r, c)])
    }

    /// The covariance the effects add to all points (3n x 3n, m²): for plans small enough to
    /// hold it.
    pub fn point_covariance_m2(&self) -> DMatrix<f64> {
        &self.point_response * &self.parameter_covariance * self.point_response.transpose()
    }
}
