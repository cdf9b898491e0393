//! The sections of geocal-diagnosis/1 that a diagnosis of measured lengths adds: the points
//! level, each station held out, and the comparison with a twin.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

/// The points level's fit against the noise model.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct PointsGap {
    /// Σ of the whitened residuals squared and its degrees of freedom (3·points − rank).
    pub chi2: f64,
    pub dof: usize,
    pub chi2_per_dof: f64,
    pub p_value: f64,
    /// RMS of the residual components (m), and the RMS the noise model expects of them.
    pub rms_m: f64,
    pub floor_m: f64,
    /// Points fitted (per target, plan point and pass) and identifiable model parameters.
    pub points: usize,
    pub rank: usize,
}

/// One point whose residual fails the noise model (Bonferroni over the points).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct PointDeparture {
    pub target: String,
    pub point: usize,
    pub pass: usize,
    pub nominal_m: [f64; 3],
    pub residual_m: [f64; 3],
    /// χ² of its 3 residual components under their covariance, and the corrected p-value.
    pub chi2: f64,
    pub p_value: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct PointsLevel {
    pub gap: PointsGap,
    /// Points failing the noise model, largest χ² first.
    #[serde(default)]
    pub departures: Vec<PointDeparture>,
    /// The `target_offset` candidate at this level (plans with two or more targets).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub target_offset: Option<TargetOffsetTest>,
}

/// The `target_offset` candidate at the points level: a constant error in the offset of each
/// reflector after the first shifts that target's points by a constant, which the quasi-rigid
/// model cannot express (the lengths level cannot see it: every point is free there, and with
/// one target the shift is the gauge's). Score test of the shifts projected off the model.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct TargetOffsetTest {
    /// Identifiable shift parameters (projected rank) and the χ² drop when they are added.
    pub df: usize,
    pub chi2_drop: f64,
    pub p_value: f64,
    /// BIC change when added (negative: better).
    pub bic_delta: f64,
    /// χ² of the points level and its degrees of freedom with the shifts fitted.
    pub chi2_after: f64,
    pub dof_after: usize,
    /// The fitted offset error of each target relative to the first (m): its identifiable part
    /// (minimum norm; with two targets the component along o₂ − o₁), and its standard
    /// deviation per component.
    pub offsets_m: BTreeMap<String, [f64; 3]>,
    #[serde(default)]
    pub offsets_sigma_m: BTreeMap<String, [f64; 3]>,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct HeldOutStation {
    pub station: String,
    /// Held-out lengths and the degrees of freedom left after refitting the station's own
    /// position and homing distances (lengths − 3 − segments).
    pub lengths: usize,
    pub dof: usize,
    /// RMS of the held-out residuals (m) and the RMS the noise model predicts for them (noise
    /// plus the uncertainty of the points fitted without this station).
    pub heldout_rms_m: f64,
    pub floor_m: f64,
    /// sqrt(χ²/dof) of the held-out residuals under their predicted covariance: 1 when the
    /// station agrees with the others, its sampling spread about sqrt(1/(2·dof)).
    pub ratio: f64,
    /// P(χ² ≥ observed), Bonferroni over the stations.
    pub p_value: f64,
}

impl HeldOutStation {
    /// A station's figures from its held-out sums: the residuals' and the predicted floor's
    /// sums of squares (m²), χ² with `dof`, Bonferroni over `stations`.
    pub fn from_sums(
        station: String,
        lengths: usize,
        dof: usize,
        (ss_m2, floor_m2): (f64, f64),
        chi2: f64,
        stations: usize,
    ) -> HeldOutStation {
        HeldOutStation {
            station,
            lengths,
            dof,
            heldout_rms_m: (ss_m2 / lengths as f64).sqrt(),
            floor_m: (floor_m2 / lengths as f64).sqrt(),
            ratio: (chi2 / dof.max(1) as f64).sqrt(),
            p_value: (super::stats::chi2_sf(chi2, dof as f64) * stations as f64).min(1.0),
        }
    }
}

/// The recording's points minus the twin's (per pass), whitened by both covariances.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct TwinPointsGap {
    pub chi2: f64,
    pub dof: usize,
    pub chi2_per_dof: f64,
    pub p_value: f64,
    /// RMS of the difference components (m) and the RMS both noise models predict.
    pub rms_m: f64,
    pub floor_m: f64,
    pub points: usize,
}

/// `twin` in geocal-diagnosis/1 (an extension): what the recording was compared with.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct TwinReport {
    pub session_id: String,
    /// `session` (a second recording) or `config` (simulated here).
    pub source: String,
    /// Recorded lengths with a twin length at the same station, target, point, pass and
    /// occurrence; the others are diagnosed against the model alone.
    pub matched_lengths: usize,
    pub unmatched_lengths: usize,
    /// Points before and after removing the selected effects' fitted contribution.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub points_before: Option<TwinPointsGap>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub points_after: Option<TwinPointsGap>,
    /// Points of the recording that depart from the twin's, largest χ² first.
    #[serde(default)]
    pub departures: Vec<PointDeparture>,
}
