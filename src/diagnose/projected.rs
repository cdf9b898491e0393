//! A candidate effect's whitened columns projected off a base fit, and their factorisation:
//! from the k × k Gram matrix where that is as accurate as the SVD (time n k², no n × k
//! orthonormal factor, no SVD of a tall matrix), else through the columns' Householder QR and
//! the SVD of its k × k factor (`stats::QrBasis`, as accurate as the SVD of the tall matrix);
//! always by the SVD of the tall matrix when the diagnosis runs as its dense oracle, so that
//! the oracle checks both routes.

use nalgebra::{DMatrix, DVector};

use super::engine::LinearFit;
use super::stats::{gram_factor, Basis, QrBasis, EFFECT_RANK_TOL};

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
    /// Their QR: U = Q U_R.
    Qr(QrBasis),
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
        if let Some((s, vt)) = gram_factor(&columns, EFFECT_RANK_TOL, reference) {
            return Projected {
                s,
                vt,
                left: Left::Columns(columns),
            };
        }
        // A direction the model nearly absorbs: the Gram matrix cannot resolve it.
        let basis = QrBasis::new(columns, EFFECT_RANK_TOL, reference);
        Projected {
            s: basis.s.clone(),
            vt: basis.vt.clone(),
            left: Left::Qr(basis),
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
            Left::Qr(qr) => qr.ut(b),
            Left::U(u) => u.tr_mul(b),
        }
    }

    /// U c over the fit's rows.
    pub fn u_times(&self, c: &DVector<f64>) -> DVector<f64> {
        match &self.left {
            Left::Columns(columns) => columns * self.v_scaled(c),
            Left::Qr(qr) => qr.u_times(c),
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
            Left::Columns(columns) => {
                let scaled = DMatrix::from_fn(self.vt.ncols(), self.vt.nrows(), |c, k| {
                    self.vt[(k, c)] / self.s[k]
                });
                columns * scaled
            }
            Left::Qr(qr) => qr.u(),
            Left::U(u) => u,
        }
    }
}

pub fn column_norm_max(m: &DMatrix<f64>) -> f64 {
    (0..m.ncols())
        .map(|c| m.column(c).norm())
        .fold(0.0, f64::max)
}
