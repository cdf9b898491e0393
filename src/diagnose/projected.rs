//! A candidate effect's whitened columns projected off a base fit, and their factorisation:
//! the singular values and right vectors from the k × k Gram matrix where that is as accurate
//! as the SVD (time n k², no n × k orthonormal factor, no SVD of a tall matrix), else from the
//! SVD of the columns' QR factor R (`stats::qr_right_factor`, as accurate as the SVD of the
//! tall matrix); U = columns V S⁻¹ is never formed whole, only a fold's rows of it at a time.
//! Always by the SVD of the tall matrix when the diagnosis runs as its dense oracle, so that
//! the oracle checks both routes.

use nalgebra::{DMatrix, DVector};

use super::columns::ProjectedRows;
use super::engine::LinearFit;
use super::stats::{
    factor_gram, gram_and_cross, gram_factor, qr_right_factor, Basis, EFFECT_RANK_TOL,
};
use crate::parallel;

/// Rows of implicit projected columns made at once when they are walked whole.
const ROWS_AT_ONCE: usize = 2048;
/// Threads such a walk runs on.
const MAX_ROW_THREADS: usize = 2;

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
    /// The projected columns made from the fit when asked: U = rows V S⁻¹.
    Rows(Box<dyn ProjectedRows>),
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
        let (s, vt) = right_factor(
            columns.shape(),
            &|start, len| columns.rows(start, len).into_owned(),
            reference,
        );
        Projected {
            s,
            vt,
            left: Left::Columns(columns),
        }
    }

    /// From columns already projected and kept implicit by the fit (`reference`: the largest
    /// norm of the columns before their projection), with Uᵀ b: on the Gram route from the
    /// same walk over the rows as the Gram matrix (the rows are made again at each walk).
    pub fn from_rows(
        rows: Box<dyn ProjectedRows>,
        reference: f64,
        b: &DVector<f64>,
    ) -> (Projected, DVector<f64>) {
        let shape = (rows.nrows(), rows.ncols());
        // Uᵀb = S⁻¹ Vᵀ (Aᵀb) on the Gram route; the QR route walks the rows again for it.
        let (s, vt, ut) = {
            let block = |start, len| rows.rows_at(&(start..start + len).collect::<Vec<_>>());
            let (gram, cross) = gram_and_cross(shape, &block, b);
            match factor_gram(gram, shape.0, EFFECT_RANK_TOL, reference) {
                Some((s, vt)) => {
                    let ut = (&vt * cross).component_div(&s);
                    (s, vt, Some(ut))
                }
                None => {
                    let (s, vt) = qr_right_factor(shape, &block, EFFECT_RANK_TOL, reference);
                    (s, vt, None)
                }
            }
        };
        let projected = Projected {
            s,
            vt,
            left: Left::Rows(rows),
        };
        let ut = ut.unwrap_or_else(|| projected.ut(b));
        (projected, ut)
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
            Left::Rows(rows) => {
                let parts = in_blocks(rows.nrows(), |positions| {
                    rows.rows_at(positions).tr_mul(&b.select_rows(positions))
                });
                let mut t = DVector::zeros(rows.ncols());
                for part in parts {
                    t += part;
                }
                (&self.vt * t).component_div(&self.s)
            }
        }
    }

    /// U c over the fit's rows.
    pub fn u_times(&self, c: &DVector<f64>) -> DVector<f64> {
        match &self.left {
            Left::Columns(columns) => columns * self.v_scaled(c),
            Left::U(u) => u * c,
            Left::Rows(rows) => {
                let v = self.v_scaled(c);
                let v = DMatrix::from_column_slice(v.len(), 1, v.as_slice());
                rows_times(&**rows, &v).column(0).into_owned()
            }
        }
    }

    /// V S⁻¹ c.
    pub fn v_scaled(&self, c: &DVector<f64>) -> DVector<f64> {
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
            Left::Rows(ref rows) => rows_times(&**rows, &self.v_over_s()),
        }
    }

    /// Rows of U (positions among the fit's rows).
    pub fn u_rows(&self, rows: &[usize]) -> DMatrix<f64> {
        match &self.left {
            Left::Columns(columns) => columns.select_rows(rows) * self.v_over_s(),
            Left::U(u) => u.select_rows(rows),
            Left::Rows(projected) => projected.rows_at(rows) * self.v_over_s(),
        }
    }

    /// V S⁻¹ (k × rank).
    fn v_over_s(&self) -> DMatrix<f64> {
        DMatrix::from_fn(self.vt.ncols(), self.vt.nrows(), |c, k| {
            self.vt[(k, c)] / self.s[k]
        })
    }
}

/// Singular values and Vᵀ of projected columns given a block of rows at a time: from the
/// Gram matrix, else (a direction the model nearly absorbs, which the Gram matrix cannot
/// resolve) from the QR factor R.
fn right_factor(
    shape: (usize, usize),
    block: &(dyn Fn(usize, usize) -> DMatrix<f64> + Sync),
    reference: f64,
) -> (DVector<f64>, DMatrix<f64>) {
    gram_factor(shape, block, EFFECT_RANK_TOL, reference)
        .unwrap_or_else(|| qr_right_factor(shape, block, EFFECT_RANK_TOL, reference))
}

/// `job` on each block of positions 0..n, the blocks on the cores; the results in the blocks'
/// order.
fn in_blocks<R: Send>(n: usize, job: impl Fn(&[usize]) -> R + Sync) -> Vec<R> {
    let blocks: Vec<Vec<usize>> = parallel::position_blocks(n, ROWS_AT_ONCE).collect();
    parallel::in_groups(&blocks, parallel::threads(MAX_ROW_THREADS), |b| job(b))
}

/// The projected columns' rows times `m`, a block of rows at a time on the cores.
fn rows_times(rows: &dyn ProjectedRows, m: &DMatrix<f64>) -> DMatrix<f64> {
    let parts = in_blocks(rows.nrows(), |positions| rows.rows_at(positions) * m);
    let mut out = DMatrix::zeros(rows.nrows(), m.ncols());
    let mut at = 0;
    for part in parts {
        out.rows_mut(at, part.nrows()).copy_from(&part);
        at += part.nrows();
    }
    out
}

pub fn column_norm_max(m: &DMatrix<f64>) -> f64 {
    (0..m.ncols())
        .map(|c| m.column(c).norm())
        .fold(0.0, f64::max)
}
