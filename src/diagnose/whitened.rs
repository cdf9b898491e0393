//! A small whitened design held whole (hundreds to thousands of rows, tens to a few hundred
//! parameters), fitted by the thin SVD of its rows: the [`LinearDesign`] of the residual
//! models the kinds hand over (`method::diagnosis::ResidualModel`).

use std::sync::Arc;

use nalgebra::{DMatrix, DVector};

use super::engine::{LinearDesign, LinearFit};
use super::stats::{Basis, RANK_TOL};

/// The whitened design over all rows; its residuals are whitened too.
#[derive(Clone)]
pub struct WhitenedDesign(pub Arc<DMatrix<f64>>);

/// Its fit on a set of rows.
pub struct WhitenedFit {
    design: Arc<DMatrix<f64>>,
    pub basis: Basis,
}

fn rows_of(m: &DMatrix<f64>, rows: &[usize]) -> DMatrix<f64> {
    DMatrix::from_fn(rows.len(), m.ncols(), |r, c| m[(rows[r], c)])
}

impl LinearDesign for WhitenedDesign {
    type Fit = WhitenedFit;

    fn fit(&self, rows: Vec<usize>) -> WhitenedFit {
        WhitenedFit {
            basis: Basis::new(&rows_of(&self.0, &rows), RANK_TOL, 0.0),
            design: self.0.clone(),
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
        let row: Vec<f64> = self.design.row(i).iter().copied().collect();
        let norm2: f64 = row.iter().map(|v| v * v).sum();
        let inside: f64 = (0..self.basis.rank())
            .map(|k| {
                (0..row.len())
                    .map(|j| self.basis.vt[(k, j)] * row[j])
                    .sum::<f64>()
                    .powi(2)
            })
            .sum();
        norm2 == 0.0 || norm2 - inside <= 1e-12 * norm2
    }

    fn prediction_variances(&self, held: &[usize]) -> Vec<f64> {
        held.iter()
            .map(|&h| {
                let row: Vec<f64> = self.design.row(h).iter().copied().collect();
                self.basis.prediction_variance(&row)
            })
            .collect()
    }

    fn factorises_by_svd(&self) -> bool {
        true
    }
}
