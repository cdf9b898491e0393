//! A candidate effect's whitened columns projected off a base fit, and their factorisation:
//! from the k × k Gram matrix where that is as accurate as the SVD (time n k², no n × k
//! orthonormal factor, no SVD of a tall matrix), else by the thin SVD; always by the SVD when
//! the diagnosis runs as its dense oracle, so that the oracle checks the Gram route.

use nalgebra::{DMatrix, DVector};

use super::fit::Fit;
use super::stats::{gram_factor, Basis, EFFECT_RANK_TOL};

pub struct Projected {
    /// The projected columns over the fit's rows (by position).
    columns: DMatrix<f64>,
    /// Singular values and right singular vectors of the kept directions.
    pub s: DVector<f64>,
    pub vt: DMatrix<f64>,
    /// The orthonormal left factor, when the SVD gave it.
    u: Option<DMatrix<f64>>,
}

impl Projected {
    /// `aw`: the candidate's whitened columns over the fit's rows (dropped once projected).
    pub fn new(fit: &Fit, aw: DMatrix<f64>) -> Projected {
        let reference = column_norm_max(&aw);
        let columns = fit.project_off(&aw);
        drop(aw);
        if !fit.is_dense() {
            if let Some((s, vt)) = gram_factor(&columns, EFFECT_RANK_TOL, reference) {
                return Projected {
                    columns,
                    s,
                    vt,
                    u: None,
                };
            }
        }
        let basis = Basis::new(&columns, EFFECT_RANK_TOL, reference);
        Projected {
            columns,
            s: basis.s,
            vt: basis.vt,
            u: Some(basis.u),
        }
    }

    /// Identifiable directions (the projected rank).
    pub fn rank(&self) -> usize {
        self.s.len()
    }

    /// Uᵀ b, b over the fit's rows: S⁻¹ Vᵀ (columnsᵀ b) without U.
    pub fn ut(&self, b: &DVector<f64>) -> DVector<f64> {
        match &self.u {
            Some(u) => u.transpose() * b,
            None => (&self.vt * self.columns.tr_mul(b)).component_div(&self.s),
        }
    }

    /// U c over the fit's rows: columns V S⁻¹ c.
    pub fn u_times(&self, c: &DVector<f64>) -> DVector<f64> {
        match &self.u {
            Some(u) => u * c,
            None => &self.columns * self.v_scaled(c),
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
        match self.u {
            Some(u) => u,
            None => {
                let scaled = DMatrix::from_fn(self.vt.ncols(), self.vt.nrows(), |c, k| {
                    self.vt[(k, c)] / self.s[k]
                });
                &self.columns * scaled
            }
        }
    }
}

pub fn column_norm_max(m: &DMatrix<f64>) -> f64 {
    (0..m.ncols())
        .map(|c| m.column(c).norm())
        .fold(0.0, f64::max)
}
