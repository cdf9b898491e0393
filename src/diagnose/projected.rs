//! A candidate effect's whitened columns projected off a base fit, and their factorisation:
//! the singular values and right vectors from the k × k Gram matrix where that is as accurate
//! as the SVD (time n k², no n × k orthonormal factor, no SVD of a tall matrix), else from the
//! SVD of the columns' QR factor R (`stats::qr_right_factor`, as accurate as the SVD of the
//! tall matrix); U = columns V S⁻¹ is never formed whole, only a fold's rows of it at a time.
//! Always by the SVD of the tall matrix when the diagnosis runs as its dense oracle, so that
//! the oracle checks both routes.

use nalgebra::{DMatrix, DVector};

use super::engine::LinearFit;
use super::stats::{gram_factor, qr_right_factor, Basis, EFFECT_RANK_TOL};

pub struct Projected {
    /// Singular values and right singular vectors of the kept directions.
    pub s: DVector<f64>,
    pub vt: DMatrix<f64>,
    left: Left,
}

/// What gives the left factor U.
enum Left {
    /// The projected columns over the fit's rows (by position): U = columns V S⁻¹.
    Columns(DMatrix<f64>),
    /// U itself (the dense oracle's SVD).
    U(DMatrix<f64>),
}

impl Projected {
    /// `aw`: the candidate's whitened columns over the fit's rows (projected in place).
    pub fn new<F: LinearFit + ?Sized>(fit: &F, aw: DMatrix<f64>) -> Projected {
        let reference = column_norm_max(&aw);
        let columns = fit.project_off_owned(aw);
        if fit.factorises_by_svd() {
            let basis = Basis::new(&columns, EFFECT_RANK_TOL, reference);
            return Projected {
                s: basis.s,
                vt: basis.vt,
                left: Left::U(basis.u),
            };
        }
        // Else a direction the model nearly absorbs: the Gram matrix cannot resolve it.
        let (s, vt) = gram_factor(&columns, EFFECT_RANK_TOL, reference)
            .unwrap_or_else(|| qr_right_factor(&columns, EFFECT_RANK_TOL, reference));
        Projected {
            s,
            vt,
            left: Left::Columns(columns),
        }
    }

    /// Identifiable directions (the projected rank).
    pub fn rank(&self) -> usize {
        self.s.len()
    }

    /// Uᵀ b, b over the fit's rows (for the Gram route S⁻¹ Vᵀ (columnsᵀ b), without U).
    pub fn ut(&self, b: &DVector<f64>) -> DVector<f64> {
        match &self.left {
            Left::Columns(columns) => (&self.vt * columns.tr_mul(b)).component_div(&self.s),
            Left::U(u) => u.tr_mul(b),
        }
    }

    /// U c over the fit's rows.
    pub fn u_times(&self, c: &DVector<f64>) -> DVector<f64> {
        match &self.left {
            Left::Columns(columns) => columns * self.v_scaled(c),
            Left::U(u) => u * c,
        }
    }

    /// V S⁻¹ c.
    fn v_scaled(&self, c: &DVector<f64>) -> DVector<f64> {
        self.vt.tr_mul(&c.component_div(&self.s))
    }

    /// Minimum-norm least-squares θ of columns θ ≈ b.
    pub fn solve(&self, b: &DVector<f64>) -> DVector<f64> {
        self.v_scaled(&self.ut(b))
    }

    /// The orthonormal basis U of the projected columns' span.
    pub fn into_u(self) -> DMatrix<f64> {
        match self.left {
            Left::Columns(ref columns) => columns * self.v_over_s(),
            Left::U(u) => u,
        }
    }

    /// Rows of U (positions among the fit's rows).
    pub fn u_rows(&self, rows: &[usize]) -> DMatrix<f64> {
        match &self.left {
            Left::Columns(columns) => columns.select_rows(rows) * self.v_over_s(),
            Left::U(u) => u.select_rows(rows),
        }
    }

    /// V S⁻¹ (k × rank).
    fn v_over_s(&self) -> DMatrix<f64> {
        DMatrix::from_fn(self.vt.ncols(), self.vt.nrows(), |c, k| {
            self.vt[(k, c)] / self.s[k]
        })
    }
}

pub fn column_norm_max(m: &DMatrix<f64>) -> f64 {
    (0..m.ncols())
        .map(|c| m.column(c).norm())
        .fold(0.0, f64::max)
}
