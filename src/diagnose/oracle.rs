//! The dense computations the structured ones replaced, kept as the test oracle on a small
//! recorded session: leave-one-station-out, the change-point search and the leverages must
//! agree with them to rounding.

use std::path::Path;
use std::sync::Arc;

use nalgebra::{DMatrix, DVector};

use super::data::Data;
use super::effects::Geometry;
use super::locate;
use super::loso::{self, HeldOutStation};
use super::schur::{Design, Schur};
use super::stats::{chi2_sf, Basis, RANK_TOL};
use crate::session::reader::read_session;
use crate::solve::multilateration::{solve, SolveOptions};

fn dense_leave_one_station_out(
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

fn dense_best_step(
    data: &Data,
    basis: &Basis,
    res_w: &nalgebra::DVector<f64>,
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
        let mut proj = nalgebra::DVector::<f64>::zeros(r);
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

fn close(a: f64, b: f64, what: &str) {
    assert!(
        (a - b).abs() <= 1e-9 * a.abs().max(b.abs()).max(1e-300),
        "{what}: structured {a} vs dense {b}"
    );
}

#[test]
fn structured_matches_the_dense_oracle_on_a_recorded_session() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/outside/outside-clean-7/session.mcap");
    let session = read_session(&path).expect("session");
    let data = Data::from_session(&session).expect("data");
    let solution = solve(&data.problem, &SolveOptions::default()).expect("solve");
    let geom = Geometry::from_solution(&solution);
    let nobs = data.obs.len();
    let design = Arc::new(Design::nominal(&data, &geom));
    let jacobian = geom.jacobian(&data);
    assert!(
        (design.to_dense() - &jacobian).amax() < 1e-12,
        "the design is the Jacobian"
    );

    let (held, skipped) = loso::leave_one_station_out(&data, &design, &solution.residuals_m);
    let (dense, dense_skipped) =
        dense_leave_one_station_out(&data, &jacobian, &solution.residuals_m);
    assert_eq!(skipped, dense_skipped);
    assert_eq!(held.len(), dense.len());
    assert!(!held.is_empty());
    for (s, d) in held.iter().zip(&dense) {
        let HeldOutStation {
            station,
            lengths,
            dof,
            ..
        } = d;
        assert_eq!((&s.station, s.lengths, s.dof), (station, *lengths, *dof));
        close(s.heldout_rms_m, d.heldout_rms_m, "held-out RMS");
        close(s.floor_m, d.floor_m, "floor");
        close(s.ratio, d.ratio, "ratio");
        close(s.p_value, d.p_value, "p");
    }

    let w = DVector::from_iterator(nobs, data.obs.iter().map(|o| 1.0 / o.sigma_m));
    let jw = DMatrix::from_fn(nobs, jacobian.ncols(), |i, c| jacobian[(i, c)] * w[i]);
    let basis = Basis::new(&jw, RANK_TOL, 0.0);
    let fit = Schur::new(design, (0..nobs).collect());
    assert_eq!(fit.rank(), basis.rank());
    for (a, b) in fit.leverages().iter().zip(basis.leverages()) {
        close(*a, b, "leverage");
    }
    let r = DVector::from_fn(nobs, |i, _| solution.residuals_m[i] * w[i]);
    let res_w = basis.project_off_vec(&r);
    for (a, b) in fit.project_off_vec(&r).iter().zip(res_w.iter()) {
        assert!((a - b).abs() <= 1e-9 * res_w.amax(), "residual {a} vs {b}");
    }
    let step = locate::best_step(&data, &fit, &res_w, None).expect("a step");
    let dense_step = dense_best_step(&data, &basis, &res_w, None).expect("a step");
    assert_eq!(
        (step.0, step.1, step.3),
        (dense_step.0, dense_step.1, dense_step.3)
    );
    close(step.2, dense_step.2, "step statistic");
}
