//! The dense computations the structured ones (`schur`) replaced, kept as their oracle: the
//! whole design (lengths × parameters) and its thin SVD. Small sessions only; the diagnosis
//! uses them when run under [`super::fit::dense_oracle`], which the tests do to check that
//! the structured diagnosis reports the same figures.

use std::sync::Arc;

use nalgebra::{DMatrix, DVector};

use super::data::Data;
use super::loso::HeldOutStation;
use super::schur::Design;
use super::stats::{Basis, RANK_TOL};

/// The least-squares fit of a design on a set of its rows by the dense thin SVD.
pub struct DenseFit {
    design: Arc<Design>,
    /// The unwhitened dense design (all lengths).
    dense: DMatrix<f64>,
    basis: Basis,
}

impl DenseFit {
    pub fn new(design: Arc<Design>, rows: &[usize]) -> DenseFit {
        let dense = design.to_dense();
        let whitened = DMatrix::from_fn(rows.len(), dense.ncols(), |r, c| {
            dense[(rows[r], c)] * design.weight(rows[r])
        });
        DenseFit {
            basis: Basis::new(&whitened, RANK_TOL, 0.0),
            design,
            dense,
        }
    }

    pub fn design(&self) -> &Design {
        &self.design
    }

    pub fn basis(&self) -> &Basis {
        &self.basis
    }

    pub fn rank(&self) -> usize {
        self.basis.rank()
    }

    pub fn solve(&self, y: &DVector<f64>) -> DVector<f64> {
        self.basis.solve(y)
    }

    pub fn project_off_vec(&self, y: &DVector<f64>) -> DVector<f64> {
        self.basis.project_off_vec(y)
    }

    pub fn project_off(&self, m: &DMatrix<f64>) -> DMatrix<f64> {
        self.basis.project_off(m)
    }

    fn row(&self, i: usize) -> DVector<f64> {
        self.dense.row(i).transpose()
    }

    /// Design row i lies in the fit's row space (its part outside is rounding, ~1e-12).
    pub fn in_row_space(&self, i: usize) -> bool {
        let row = self.row(i);
        let inside = &self.basis.vt * &row;
        row.norm_squared() - inside.norm_squared() <= 1e-12 * row.norm_squared()
    }

    pub fn prediction_variances(&self, held: &[usize]) -> Vec<f64> {
        held.iter()
            .map(|&i| {
                let row: Vec<f64> = self.row(i).iter().copied().collect();
                self.basis.prediction_variance(&row)
            })
            .collect()
    }

    pub fn leverages(&self) -> Vec<f64> {
        self.basis.leverages()
    }

    /// Entries of the normal matrix's pseudo-inverse V S⁻² Vᵀ on `cols`.
    pub fn pinv_block(&self, cols: &[usize]) -> DMatrix<f64> {
        let b = &self.basis;
        DMatrix::from_fn(cols.len(), cols.len(), |x, y| {
            (0..b.rank())
                .map(|k| b.vt[(k, cols[x])] * b.vt[(k, cols[y])] / b.s[k].powi(2))
                .sum()
        })
    }
}

/// `loso::leave_one_station_out` on the dense Jacobian (rows: lengths; columns: points,
/// stations, segments).
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
        out.push(HeldOutStation::from_sums(
            id.clone(),
            nh,
            dof,
            (ss_m2, floor_m2),
            stat,
            m,
        ));
    }
    (out, skipped)
}

/// `locate::best_step` with the column space's dense orthonormal basis (the fit's rows: every
/// length, in order).
pub fn best_step(
    data: &Data,
    basis: &Basis,
    res_w: &DVector<f64>,
    station: Option<usize>,
) -> Option<(usize, usize, f64, usize)> {
    let w: Vec<f64> = data.obs.iter().map(|o| 1.0 / o.sigma_m).collect();
    let r = basis.rank();
    let mut best: Option<(usize, usize, f64)> = None;
    let mut tried = 0;
    for (g, members) in data.passes.iter().enumerate() {
        if station.is_some_and(|s| data.obs[members[0]].station != s) {
            continue;
        }
        // Walk the split from the end: the step column is the suffix indicator (whitened).
        let mut proj = DVector::<f64>::zeros(r);
        let (mut cc, mut cr) = (0.0, 0.0);
        for k in (1..members.len()).rev() {
            let i = members[k];
            for c in 0..r {
                proj[c] += w[i] * basis.u[(i, c)];
            }
            cc += w[i] * w[i];
            cr += w[i] * res_w[i];
            tried += 1;
            let perp = cc - proj.norm_squared();
            // A step that the nominal model absorbs (e.g. the whole pass) is not a candidate.
            if perp <= 1e-6 * cc {
                continue;
            }
            let stat = cr * cr / perp;
            if best.is_none_or(|b| stat > b.2) {
                best = Some((g, k, stat));
            }
        }
    }
    best.map(|(g, k, s)| (g, k, s, tried))
}
