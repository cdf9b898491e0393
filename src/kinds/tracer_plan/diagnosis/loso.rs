//! Leave-one-station-out: each station's lengths predicted from the points the other stations
//! determine (its own position and homing distances refitted), tested against the noise model.

pub use crate::diagnose::lengths::HeldOutStation;

use std::collections::BTreeMap;
use std::sync::Arc;

use nalgebra::{DMatrix, DVector, Vector3};

use crate::diagnose::downdate::apply_blocks;
use crate::parallel;

use super::data::Data;
use super::schur::{Design, Schur};
use super::stats::{Basis, RANK_TOL};

/// Per station, in the linearised nominal model around the full fit (`design`: the nominal
/// design at the full fit; `resid_m` its residuals). Stations whose removal leaves the points
/// undetermined (fewer than four others seeing them) are skipped and named in the second
/// return value.
///
/// The held-out residual's covariance is C = P Q P with Q = I + X_H N⁺ X_Hᵀ (X_H: the held
/// rows on their points' columns, N the training normal matrix) and P the projection off the
/// station's own columns. With the points eliminated Q = E + F Fᵀ, E = I plus each point's
/// small block (a_iᵀ M_p⁺ a_j), F_i = Wᵀ C_pᵀ M_p⁺ a_i (reduced system), so χ² = rᵀ C⁺ r =
/// rᵀQ⁻¹r − (UᵀQ⁻¹r)ᵀ(UᵀQ⁻¹U)⁻¹(UᵀQ⁻¹r) (U: the own columns' basis; Q⁻¹ by Woodbury) and the
/// held rows' covariance is never formed (lengths² entries).
pub fn leave_one_station_out(
    data: &Data,
    design: &Arc<Design>,
    resid_m: &[f64],
) -> (Vec<HeldOutStation>, Vec<String>) {
    let m = data.station_ids.len();
    let w: Vec<f64> = data.obs.iter().map(|o| 1.0 / o.sigma_m).collect();
    // The stations are independent: on the cores, gathered in the stations' order.
    let stations: Vec<usize> = (0..m).collect();
    let per_station = parallel::in_groups(&stations, parallel::threads(2), |&j| {
        held_out_station(data, design, resid_m, &w, j)
    });
    let mut out = Vec::new();
    let mut skipped = Vec::new();
    for (result, id) in per_station.into_iter().zip(&data.station_ids) {
        match result {
            StationOut::Held(held) => out.push(held),
            StationOut::Skipped => skipped.push(id.clone()),
            StationOut::NoLengths => {}
        }
    }
    (out, skipped)
}

/// One station's leave-one-station-out figures.
enum StationOut {
    Held(HeldOutStation),
    /// Its removal leaves the points undetermined.
    Skipped,
    NoLengths,
}

fn held_out_station(
    data: &Data,
    design: &Arc<Design>,
    resid_m: &[f64],
    w: &[f64],
    j: usize,
) -> StationOut {
    let nobs = data.obs.len();
    let m = data.station_ids.len();
    let p = design.geometry_params();
    let id = &data.station_ids[j];
    // The held-out station's own columns: its position and its segments' distances.
    let segments: Vec<usize> = data
        .problem
        .segments
        .iter()
        .enumerate()
        .filter(|(_, s)| s.station == j)
        .map(|(s, _)| s)
        .collect();
    let own_len = 3 + segments.len();
    let train: Vec<usize> = (0..nobs).filter(|&i| data.obs[i].station != j).collect();
    let held: Vec<usize> = (0..nobs).filter(|&i| data.obs[i].station == j).collect();
    if held.is_empty() {
        return StationOut::NoLengths;
    }
    // The training rows never touch the station's own columns.
    let basis = Schur::new(design.clone(), train.clone());
    // The others determine everything but the 6 rigid motions, or the prediction is a guess.
    if basis.rank() + 6 < p - own_len {
        return StationOut::Skipped;
    }
    let rt = DVector::from_fn(train.len(), |r, _| resid_m[train[r]] * w[train[r]]);
    let delta = basis.solve(&rt);
    let nh = held.len();
    let r_dim = basis.reduced_dim();
    let wt = basis.reduced_transpose();
    let mut f = DMatrix::zeros(nh, r_dim);
    let mut ma: Vec<Vector3<f64>> = Vec::with_capacity(nh);
    let mut a: Vec<Vector3<f64>> = Vec::with_capacity(nh);
    let mut z = DVector::zeros(nh);
    for (r, &i) in held.iter().enumerate() {
        let ai = design.point_coefficients(i);
        let point = data.obs[i].point;
        let dp = Vector3::new(delta[3 * point], delta[3 * point + 1], delta[3 * point + 2]);
        z[r] = resid_m[i] * w[i] - ai.dot(&dp);
        let (m_a, f_i) = basis.held_point_covariance(&wt, i);
        f.set_row(r, &f_i.transpose());
        ma.push(m_a);
        a.push(ai);
    }
    // E = I + blockdiag over points of the held rows' a_iᵀ M_p⁺ a_j: its inverse by block.
    let mut by_point: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
    for (r, &i) in held.iter().enumerate() {
        by_point.entry(data.obs[i].point).or_default().push(r);
    }
    let blocks: Vec<(Vec<usize>, DMatrix<f64>, DMatrix<f64>)> = by_point
        .into_values()
        .map(|rows| {
            let e = DMatrix::from_fn(rows.len(), rows.len(), |x, y| {
                f64::from(u8::from(x == y)) + a[rows[x]].dot(&ma[rows[y]])
            });
            let inv = e
                .clone()
                .cholesky()
                .map(|c| c.inverse())
                .unwrap_or_else(|| DMatrix::identity(rows.len(), rows.len()));
            (rows, e, inv)
        })
        .collect();
    let e_apply = |v: &DMatrix<f64>, inverse: bool| {
        apply_blocks(
            blocks.iter().map(|(rows, e, inv)| {
                let mat = if inverse { inv } else { e };
                (rows.as_slice(), mat)
            }),
            v,
        )
    };
    // Q⁻¹ = E⁻¹ − E⁻¹F (I + FᵀE⁻¹F)⁻¹ FᵀE⁻¹ (Woodbury).
    let einv_f = e_apply(&f, true);
    let k = DMatrix::identity(r_dim, r_dim) + f.transpose() * &einv_f;
    let k_inv = k
        .cholesky()
        .map(|c| c.inverse())
        .unwrap_or_else(|| DMatrix::zeros(r_dim, r_dim));
    let q_inv = |v: &DMatrix<f64>| {
        let ev = e_apply(v, true);
        let corr = &einv_f * (&k_inv * (einv_f.transpose() * v));
        ev - corr
    };
    let own = DMatrix::from_fn(nh, own_len, |r, c| {
        let i = held[r];
        if c < 3 {
            -design.point_coefficients(i)[c]
        } else if data.obs[i].segment == segments[c - 3] {
            -w[i]
        } else {
            0.0
        }
    });
    let own_basis = Basis::new(&own, RANK_TOL, 0.0);
    let u = &own_basis.u;
    let rz = &z - u * (u.transpose() * &z);
    let rz_m = DMatrix::from_column_slice(nh, 1, rz.as_slice());
    let qi_rz = q_inv(&rz_m);
    let qi_u = q_inv(u);
    let t = u.transpose() * &qi_rz;
    let g = u.transpose() * &qi_u;
    let correction = g
        .clone()
        .cholesky()
        .map_or(0.0, |c| (t.transpose() * c.solve(&t))[(0, 0)]);
    let stat = (rz_m.transpose() * &qi_rz)[(0, 0)] - correction;
    let dof = nh - own_basis.rank();
    // diag(P Q P) = Q_rr − 2 U_r·(QU)_r + U_rᵀ (UᵀQU) U_r, Q = E + F Fᵀ.
    let qu = e_apply(u, false) + &f * (f.transpose() * u);
    let uqu = u.transpose() * &qu;
    let mut e_diag = vec![0.0; nh];
    for (rows, e, _) in &blocks {
        for (x, &rx) in rows.iter().enumerate() {
            e_diag[rx] = e[(x, x)];
        }
    }
    let c_diag = |r: usize| {
        let q_rr = e_diag[r] + f.row(r).norm_squared();
        let ur = u.row(r);
        q_rr - 2.0 * ur.dot(&qu.row(r)) + (ur * &uqu * ur.transpose())[(0, 0)]
    };
    let ss_m2: f64 = (0..nh).map(|r| (rz[r] / w[held[r]]).powi(2)).sum();
    let floor_m2: f64 = (0..nh).map(|r| c_diag(r) / w[held[r]].powi(2)).sum();
    StationOut::Held(HeldOutStation::from_sums(
        id.clone(),
        nh,
        dof,
        (ss_m2, floor_m2),
        stat,
        m,
    ))
}
