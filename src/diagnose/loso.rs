//! Leave-one-station-out: each station's lengths predicted from the points the other stations
//! determine (its own position and homing distances refitted), tested against the noise model.

use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

use super::data::Data;
use super::stats::{chi2_sf, Basis, RANK_TOL};

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

/// Per station, in the linearised nominal model around the full fit (`jacobian` rows:
/// observations; columns: points, stations, segments as `Geometry::jacobian`; `resid_m` the
/// full fit's residuals). Stations whose removal leaves the points undetermined (fewer than
/// four others seeing them) are skipped and named in the second return value.
pub fn leave_one_station_out(
    data: &Data,
    jacobian: &DMatrix<f64>,
    resid_m: &[f64],
) -> (Vec<HeldOutStation>, Vec<String>) {
    let nobs = data.obs.len();
    let n_points = data.problem.nominal_points.len();
    let m = data.station_ids.len();
    let p = jacobian.ncols();
    let w: Vec<f64> = data.obs.iter().map(|o| 1.0 / o.sigma_m).collect();
    let mut out = Vec::new();
    let mut skipped = Vec::new();
    for (j, id) in data.station_ids.iter().enumerate() {
        // The held-out station's own columns: its position and its segments' distances.
        let mut own: Vec<usize> = (0..3).map(|a| 3 * n_points + 3 * j + a).collect();
        own.extend(
            data.problem
                .segments
                .iter()
                .enumerate()
                .filter(|(_, s)| s.station == j)
                .map(|(s, _)| 3 * n_points + 3 * m + s),
        );
        let is_own = |c: usize| own.contains(&c);
        let train: Vec<usize> = (0..nobs).filter(|&i| data.obs[i].station != j).collect();
        let held: Vec<usize> = (0..nobs).filter(|&i| data.obs[i].station == j).collect();
        if held.is_empty() {
            continue;
        }
        let xt = DMatrix::from_fn(train.len(), p, |r, c| {
            if is_own(c) {
                0.0
            } else {
                jacobian[(train[r], c)] * w[train[r]]
            }
        });
        let basis = Basis::new(&xt, RANK_TOL, 0.0);
        // The others determine everything but the 6 rigid motions, or the prediction is a guess.
        if basis.rank() + 6 < p - own.len() {
            skipped.push(id.clone());
            continue;
        }
        let rt = DVector::from_fn(train.len(), |r, _| resid_m[train[r]] * w[train[r]]);
        let delta = basis.solve(&rt);
        let nh = held.len();
        // Whitened held-out design of the other columns, and its prediction: G = X_H V S⁻¹.
        let xh = DMatrix::from_fn(nh, p, |r, c| {
            if is_own(c) {
                0.0
            } else {
                jacobian[(held[r], c)] * w[held[r]]
            }
        });
        let z = DVector::from_fn(nh, |r, _| resid_m[held[r]] * w[held[r]]) - &xh * &delta;
        let mut g = &xh * basis.vt.transpose();
        for (k, mut col) in g.column_iter_mut().enumerate() {
            col /= basis.s[k];
        }
        let cov_z = DMatrix::identity(nh, nh) + &g * g.transpose();
        let a = DMatrix::from_fn(nh, own.len(), |r, c| {
            jacobian[(held[r], own[c])] * w[held[r]]
        });
        let own_basis = Basis::new(&a, RANK_TOL, 0.0);
        let proj = DMatrix::identity(nh, nh) - &own_basis.u * own_basis.u.transpose();
        let rz = &proj * z;
        let c = &proj * cov_z * &proj;
        let eigen = c.clone().symmetric_eigen();
        let largest = eigen.eigenvalues.amax();
        let (mut stat, mut dof) = (0.0, 0usize);
        for (k, &lambda) in eigen.eigenvalues.iter().enumerate() {
            if lambda > 1e-9 * largest && lambda > 0.0 {
                stat += eigen.eigenvectors.column(k).dot(&rz).powi(2) / lambda;
                dof += 1;
            }
        }
        let ss_m2: f64 = (0..nh).map(|r| (rz[r] / w[held[r]]).powi(2)).sum();
        let floor_m2: f64 = (0..nh).map(|r| c[(r, r)] / w[held[r]].powi(2)).sum();
        out.push(HeldOutStation {
            station: id.clone(),
            lengths: nh,
            dof,
            heldout_rms_m: (ss_m2 / nh as f64).sqrt(),
            floor_m: (floor_m2 / nh as f64).sqrt(),
            ratio: (stat / dof.max(1) as f64).sqrt(),
            p_value: (chi2_sf(stat, dof as f64) * m as f64).min(1.0),
        });
    }
    (out, skipped)
}
