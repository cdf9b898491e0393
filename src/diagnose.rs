//! Sim-to-real gap diagnosis (`geocal diagnose`), the part every plan kind shares: the
//! geocal-diagnosis/1 document, the engine and forward selection over a linearised model, the
//! statistics, the residual-model client, the text and the residual plot. Each kind's model
//! and effect library sit in its own folder under `kinds/`; `kinds::diagnosis` picks the one
//! that reads a session.

pub mod blocked;
pub mod columns;
pub mod downdate;
pub mod engine;
pub mod forward;
pub mod lengths;
pub mod plot;
pub mod progress;
pub mod projected;
pub mod residual_model;
pub mod selection;
pub mod stats;
mod text;
pub mod whitened;

pub use text::{
    details, key_parameters, summary, text, verdict, SUMMARY_MAX_LINES, TABLE_MAX_ROWS,
};

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use serde_json::Value;

use lengths::{HeldOutStation, PointsGap, PointsLevel};

pub const DIAGNOSIS_FORMAT: &str = "geocal-diagnosis/1";

/// Settings of the tests; the defaults are the documented ones.
#[derive(Debug, Clone, PartialEq)]
pub struct DiagnoseOptions {
    /// Family-wise false-alarm level of each round of selection and of the `where` tests.
    pub alpha: f64,
    /// Minimum number of cross-validation folds (a multilateration session's selection uses at
    /// least its number of stations, and its reported gaps finer folds where points have few
    /// stations to spare).
    pub folds: usize,
    /// Memory the diagnosis may use (bytes); None: the machine's available memory
    /// (`MemAvailable` in /proc/meminfo). A diagnosis estimated to need more is refused
    /// before any work (`budget`).
    pub memory_limit_bytes: Option<u64>,
    /// Called as (done, total) while the diagnosis works: the total is fixed at the start,
    /// done only grows and ends at the total (`progress::Counter`).
    pub progress: Option<crate::progress_sink::ProgressSink>,
}

impl Default for DiagnoseOptions {
    fn default() -> Self {
        Self {
            alpha: 0.01,
            folds: 5,
            memory_limit_bytes: None,
            progress: None,
        }
    }
}

/// Two candidates are confounded when their projected column spaces are this close (largest
/// principal angle cosine) and the data do not prefer one strongly (BIC difference below 10,
/// "very strong evidence" on the Kass–Raftery scale).
pub const CONFOUNDED_COSINE: f64 = 0.95;
pub const DECISIVE_BIC: f64 = 10.0;

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct Gap {
    pub rms_m: f64,
    pub heldout_rms_m: f64,
    pub chi2_per_dof: f64,
    /// Held-out RMS expected from the noise model alone (noise plus prediction uncertainty).
    pub heldout_floor_m: f64,
    /// RMS of the held-out residuals each in units of its own predicted standard deviation
    /// (noise and prediction): 1 when the model holds. Steadier than the ratio of RMS values,
    /// which a few high-leverage lengths dominate.
    pub heldout_ratio: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct Candidate {
    pub effect: String,
    pub params: BTreeMap<String, Value>,
    pub rms_after_m: f64,
    pub heldout_rms_after_m: f64,
    pub bic_delta: f64,
    pub p_value: f64,
    /// Selection round (0 = against the nominal model) of this evaluation.
    pub round: usize,
    /// Identifiable parameters (projected rank) and the χ² drop when added.
    pub df: usize,
    pub chi2_drop: f64,
    /// selected | rejected (why) | confounded.
    pub status: String,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub confounded_with: Vec<String>,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct Diagnosis {
    pub format: String,
    pub session_id: String,
    pub noise_floor_m: f64,
    pub gap: Gap,
    #[serde(rename = "where")]
    pub where_: Vec<WhereEntry>,
    pub candidates: Vec<Candidate>,
    pub selected: Vec<String>,
    pub gap_after: Gap,
    pub unexplained: bool,
    /// The declared noise model is off by a common scale: residuals uniformly too large (or
    /// small) with no group structure beyond it. A statement about the noise declaration,
    /// kept apart from the effects; `unexplained` is then decided on the rescaled residuals.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub noise_scale: Option<NoiseScale>,
    /// The calibration with the selected effects modelled (`geocal solve --effects`) and how
    /// far its points moved from the nominal model's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub corrected: Option<CorrectedCalibration>,
    /// The points level (solved points against the quasi-rigid 21-error model) of the nominal
    /// model; absent when the session's points cannot be tested (the reason is in `notes`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub points_level: Option<PointsLevel>,
    /// The points level after the selected effects: the lengths minus their fitted
    /// contribution re-solved and fitted again (with `target_offset` selected, χ², dof, rank
    /// and p with its shifts fitted; `rms_m` and `floor_m` without them).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub points_level_after: Option<PointsGap>,
    /// Each station's lengths predicted from the points of the others (nominal model).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub leave_one_station_out: Vec<HeldOutStation>,
    /// The twin comparison, when the diagnosis is of a recording against its twin.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub twin: Option<lengths::TwinReport>,
    /// Observations used and what the tests assumed.
    pub observations: usize,
    pub notes: Vec<String>,
    /// For a kind with a residual model: its kind, residual units, coordinates, library and
    /// the parameters with the effects fitted.
    #[serde(default, flatten, skip_serializing_if = "Option::is_none")]
    pub model: Option<residual_model::ModelDiagnosis>,
}

/// The `noise_scale` finding: the declared per-length σ times `k` fits the residuals.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct NoiseScale {
    /// √(χ²/dof) of the final model, and its two-sided confidence interval.
    pub k: f64,
    pub k_low: f64,
    pub k_high: f64,
    /// Confidence level of [k_low, k_high] (e.g. 0.95).
    pub confidence: f64,
    /// Degrees of freedom of the χ² that k comes from.
    pub dof: usize,
    /// "the declared noise model is k× too small|large".
    pub statement: String,
}

/// The calibration re-solved with the selected effects modelled.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct CorrectedCalibration {
    /// The command that gives it, e.g. `geocal solve SESSION --effects reversal`.
    pub command: String,
    pub effects: Vec<String>,
    /// RMS over points and coordinates of (corrected − nominal-model) point positions, in
    /// metres and in units of the corrected points' σ.
    pub points_moved_rms_m: f64,
    pub points_moved_rms_sigma: f64,
}

/// Each length's residual in units of its σ, before (nominal model) and after the final model
/// (the selected effects and any confounded group fitted): what `geocal diagnose --plot` draws.
/// Not part of geocal-diagnosis/1.
#[derive(Debug, Clone, PartialEq)]
pub struct StandardisedResiduals {
    pub station_ids: Vec<String>,
    pub lengths: Vec<StandardisedResidual>,
    /// The effects in the final model; empty when it is the nominal model (`after` = `before`).
    pub final_effects: Vec<String>,
    /// The x axis when it is not time (a kind's residual model: its coordinate), and then
    /// `station_ids` are the plot's rows (legs, directions, ...).
    pub x_axis: Option<String>,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StandardisedResidual {
    /// Index into `station_ids`.
    pub station: usize,
    /// Seconds since the session's first settled length.
    pub t_s: f64,
    pub before: f64,
    pub after: f64,
}

/// A group of residuals tested against the noise model (`where`).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct WhereEntry {
    pub level: String,
    pub group: String,
    pub key: String,
    /// Share of the residual sum of squares (m²) in this group.
    pub share: f64,
    pub rms_m: f64,
    /// Bonferroni-corrected P(χ² ≥ observed) of the group under the noise model.
    pub p_value: f64,
}
