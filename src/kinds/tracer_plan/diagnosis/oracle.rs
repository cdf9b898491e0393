//! The dense computations the structured ones replaced, kept as the test oracle on a small
//! recorded session: leave-one-station-out, the change-point search and the leverages must
//! agree with them to rounding.

use std::path::Path;
use std::sync::Arc;

use nalgebra::{DMatrix, DVector};

use super::data::Data;
use super::dense;
use super::effects::Geometry;
use super::fit::Fit;
use super::locate;
use super::loso::{self, HeldOutStation};
use super::schur::{Design, Schur};
use super::stats::{Basis, RANK_TOL};
use crate::session::reader::read_session;
use crate::solve::multilateration::{solve, SolveOptions};

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
        dense::leave_one_station_out(&data, &jacobian, &solution.residuals_m);
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
    let fit = Schur::new(design.clone(), (0..nobs).collect());
    assert_eq!(fit.rank(), basis.rank());
    for (a, b) in fit.leverages().iter().zip(basis.leverages()) {
        close(*a, b, "leverage");
    }
    let r = DVector::from_fn(nobs, |i, _| solution.residuals_m[i] * w[i]);
    let res_w = basis.project_off_vec(&r);
    for (a, b) in fit.project_off_vec(&r).iter().zip(res_w.iter()) {
        assert!((a - b).abs() <= 1e-9 * res_w.amax(), "residual {a} vs {b}");
    }
    let step = locate::best_step(&data, &Fit::Structured(fit), &res_w, None).expect("a step");
    let dense_step = dense::best_step(&data, &basis, &res_w, None).expect("a step");
    assert_eq!(
        (step.0, step.1, step.3),
        (dense_step.0, dense_step.1, dense_step.3)
    );
    close(step.2, dense_step.2, "step statistic");
}
