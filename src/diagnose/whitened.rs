//! A small whitened design held whole (hundreds to thousands of rows, tens to a few hundred
//! parameters), fitted by the thin SVD of its rows (through their QR when they are many more
//! than the columns, `method::tall_svd`): the [`LinearDesign`] of the residual models the
//! kinds hand over (`method::diagnosis::ResidualModel`).

use std::sync::Arc;

use nalgebra::{DMatrix, DVector};

use super::downdate::HatRows;
use super::engine::{LinearDesign, LinearFit};
use super::stats::{accurate_svd, Basis, RANK_TOL};
use crate::method::tall_svd::thin_svd;

/// The whitened design over all rows; its residuals are whitened too.
#[derive(Clone)]
pub struct WhitenedDesign(pub Arc<DMatrix<f64>>);

/// Its fit on a set of rows.
pub struct WhitenedFit {
    design: Arc<DMatrix<f64>>,
    /// The fit's rows (design rows), by position in the basis.
    rows: Vec<usize>,
    pub basis: Basis,
}

/// [`Basis::new`] of `a`, its SVD through the QR when `a` is tall.
pub fn tall_basis(a: &DMatrix<f64>, tol: f64, reference: f64) -> Basis {
    let (n, p) = a.shape();
    if n == 0 || p == 0 {
        return Basis::new(a, tol, reference);
    }
    Basis::from_svd(thin_svd(a, accurate_svd), n, p, tol, reference)
}

fn rows_of(m: &DMatrix<f64>, rows: &[usize]) -> DMatrix<f64> {
    DMatrix::from_fn(rows.len(), m.ncols(), |r, c| m[(rows[r], c)])
}

impl LinearDesign for WhitenedDesign {
    type Fit = WhitenedFit;

    fn fit(&self, rows: Vec<usize>) -> WhitenedFit {
        WhitenedFit {
            basis: tall_basis(&rows_of(&self.0, &rows), RANK_TOL, 0.0),
            design: self.0.clone(),
            rows,
        }
    }

    fn predict(&self, i: usize, x: &DVector<f64>) -> f64 {
        self.0.row(i).transpose().dot(x)
    }
}

impl LinearFit for WhitenedFit {
    fn rank(&self) -> usize {
        self.basis.rank()
    }

    fn solve(&self, y: &DVector<f64>) -> DVector<f64> {
        self.basis.solve(y)
    }

    fn project_off_vec(&self, y: &DVector<f64>) -> DVector<f64> {
        self.basis.project_off_vec(y)
    }

    fn project_off_owned(&self, m: DMatrix<f64>) -> DMatrix<f64> {
        self.basis.project_off(&m)
    }

    /// Inside the training rows' span to 1e-12 of the row's squared norm.
    fn in_row_space(&self, i: usize) -> bool {
        let row = self.design.row(i).transpose();
        let norm2 = row.norm_squared();
        let inside = (&self.basis.vt * &row).norm_squared();
        norm2 == 0.0 || norm2 - inside <= 1e-12 * norm2
    }

    /// |S⁻¹ Vᵀ row|² of every held row at once.
    fn prediction_variances(&self, held: &[usize]) -> Vec<f64> {
        let rows = rows_of(&self.design, held);
        let mut along = &self.basis.vt * rows.transpose();
        for (k, mut direction) in along.row_iter_mut().enumerate() {
            direction /= self.basis.s[k];
        }
        along.column_iter().map(|c| c.norm_squared()).collect()
    }

    fn factorises_by_svd(&self) -> bool {
        true
    }

    /// H = U Uᵀ: no blocks, L the sets' rows of U. None if a set's row is not the fit's.
    fn hat_rows(&self, sets: &[&[usize]]) -> Option<Vec<HatRows>> {
        let mut position = vec![usize::MAX; self.design.nrows()];
        for (k, &i) in self.rows.iter().enumerate() {
            position[i] = k;
        }
        sets.iter()
            .map(|set| {
                let positions = set
                    .iter()
                    .map(|&i| position.get(i).copied().filter(|&k| k != usize::MAX))
                    .collect::<Option<Vec<usize>>>()?;
                Some(HatRows {
                    groups: (0..set.len())
                        .map(|k| (vec![k], DMatrix::zeros(1, 1)))
                        .collect(),
                    low: Box::new(self.basis.u.select_rows(&positions)),
                })
            })
            .collect()
    }
}
