//! The diagnosis's least-squares fits: structured (`schur`, points eliminated block by block)
//! always, or dense (`dense`, the whole design's SVD) when the diagnosis runs as its own
//! oracle under [`dense_oracle`], which the tests use to check the structured figures.

use std::cell::Cell;
use std::sync::Arc;

use nalgebra::{DMatrix, DVector};

use super::data::Data;
use super::dense::{self, DenseFit};
use super::engine::{LinearDesign, LinearFit};
use super::loso::{self, HeldOutStation};
use super::schur::{Design, Schur};
use crate::diagnose::columns::{ProjectedRows, RowSparse};
use crate::diagnose::downdate::HatRows;

thread_local! {
    static DENSE_ORACLE: Cell<bool> = const { Cell::new(false) };
}

/// Run `f` with every fit of the diagnosis made dense (thin SVD of the whole design): the
/// oracle of the structured diagnosis, for small sessions in tests. The dense design needs
/// lengths × parameters × 8 bytes several times over.
#[doc(hidden)]
pub fn dense_oracle<T>(f: impl FnOnce() -> T) -> T {
    struct Restore(bool);
    impl Drop for Restore {
        fn drop(&mut self) {
            DENSE_ORACLE.with(|d| d.set(self.0));
        }
    }
    let _restore = Restore(DENSE_ORACLE.with(|d| d.replace(true)));
    f()
}

fn dense_mode() -> bool {
    DENSE_ORACLE.with(Cell::get)
}

pub enum Fit {
    Structured(Schur),
    Dense(DenseFit),
}

impl Fit {
    /// The fit of `design` on `rows` (whitened by the design's weights).
    pub fn new(design: Arc<Design>, rows: Vec<usize>) -> Fit {
        if dense_mode() {
            Fit::Dense(DenseFit::new(design, &rows))
        } else {
            Fit::Structured(Schur::new(design, rows))
        }
    }

    /// Whether this is the dense oracle's fit (thin SVD of the whole design).
    pub fn is_dense(&self) -> bool {
        matches!(self, Fit::Dense(_))
    }

    pub fn rank(&self) -> usize {
        match self {
            Fit::Structured(s) => s.rank(),
            Fit::Dense(d) => d.rank(),
        }
    }

    pub fn design(&self) -> &Design {
        match self {
            Fit::Structured(s) => s.design(),
            Fit::Dense(d) => d.design(),
        }
    }

    /// Least-squares minimum-norm x of X x ≈ y over the fit's rows (y whitened, by position).
    pub fn solve(&self, y: &DVector<f64>) -> DVector<f64> {
        match self {
            Fit::Structured(s) => s.solve(y),
            Fit::Dense(d) => d.solve(y),
        }
    }

    /// [`Fit::solve`] of every column of `y` (structured: together, one walk over the rows
    /// per step, the refinement's residuals in `y`'s place).
    pub fn solve_columns(&self, y: DMatrix<f64>) -> DMatrix<f64> {
        match self {
            Fit::Structured(s) => s.solve_columns_owned(y),
            Fit::Dense(d) => {
                let columns: Vec<DVector<f64>> =
                    y.column_iter().map(|c| d.solve(&c.into_owned())).collect();
                DMatrix::from_columns(&columns)
            }
        }
    }

    /// y minus its projection on the design's column space (over the fit's rows).
    pub fn project_off_vec(&self, y: &DVector<f64>) -> DVector<f64> {
        match self {
            Fit::Structured(s) => s.project_off_vec(y),
            Fit::Dense(d) => d.project_off_vec(y),
        }
    }

    pub fn project_off(&self, m: &DMatrix<f64>) -> DMatrix<f64> {
        match self {
            Fit::Structured(s) => s.project_off(m),
            Fit::Dense(d) => d.project_off(m),
        }
    }

    /// [`Fit::project_off`] in place of `m` (structured: no copy of it).
    pub fn project_off_owned(&self, m: DMatrix<f64>) -> DMatrix<f64> {
        match self {
            Fit::Structured(s) => s.project_off_owned(m),
            Fit::Dense(d) => d.project_off(&m),
        }
    }

    /// Whether design row i lies in the row space of the fit (its length is predictable).
    pub fn in_row_space(&self, i: usize) -> bool {
        match self {
            Fit::Structured(s) => s.in_row_space(i),
            Fit::Dense(d) => d.in_row_space(i),
        }
    }

    /// Variance of each held row's prediction under unit whitened noise.
    pub fn prediction_variances(&self, held: &[usize]) -> Vec<f64> {
        match self {
            Fit::Structured(s) => s.prediction_variances(held),
            Fit::Dense(d) => d.prediction_variances(held),
        }
    }

    /// Diagonal of the hat matrix over the fit's rows (by position).
    pub fn leverages(&self) -> Vec<f64> {
        match self {
            Fit::Structured(s) => s.leverages(),
            Fit::Dense(d) => d.leverages(),
        }
    }

    /// Entries (full parameter order) of the normal matrix's pseudo-inverse on `cols`.
    pub fn pinv_block(&self, cols: &[usize]) -> DMatrix<f64> {
        match self {
            Fit::Structured(s) => s.pinv_block(cols),
            Fit::Dense(d) => d.pinv_block(cols),
        }
    }
}

impl LinearFit for Fit {
    fn rank(&self) -> usize {
        Fit::rank(self)
    }

    fn solve(&self, y: &DVector<f64>) -> DVector<f64> {
        Fit::solve(self, y)
    }

    fn project_off_vec(&self, y: &DVector<f64>) -> DVector<f64> {
        Fit::project_off_vec(self, y)
    }

    fn project_off_owned(&self, m: DMatrix<f64>) -> DMatrix<f64> {
        Fit::project_off_owned(self, m)
    }

    fn in_row_space(&self, i: usize) -> bool {
        Fit::in_row_space(self, i)
    }

    fn prediction_variances(&self, held: &[usize]) -> Vec<f64> {
        Fit::prediction_variances(self, held)
    }

    fn factorises_by_svd(&self) -> bool {
        self.is_dense()
    }

    /// Structured only: the dense oracle projects the columns whole.
    fn project_off_implicit(&self, m: RowSparse) -> Result<Box<dyn ProjectedRows>, RowSparse> {
        match self {
            Fit::Structured(s) => Ok(s.project_off_implicit(m)),
            Fit::Dense(_) => Err(m),
        }
    }

    /// Structured only: the dense oracle refits every fold, and so checks the downdates.
    fn hat_rows(&self, sets: &[&[usize]]) -> Option<Vec<HatRows>> {
        match self {
            Fit::Structured(s) => Some(s.hat_rows(sets)),
            Fit::Dense(_) => None,
        }
    }
}

impl LinearDesign for Arc<Design> {
    type Fit = Fit;

    fn fit(&self, rows: Vec<usize>) -> Fit {
        Fit::new(self.clone(), rows)
    }

    /// The dense oracle is chosen per thread ([`dense_oracle`]): its fits stay on the caller's.
    fn fits_on_any_thread(&self) -> bool {
        !dense_mode()
    }

    fn predict(&self, i: usize, x: &DVector<f64>) -> f64 {
        Design::predict(self, i, x)
    }
}

/// Leave-one-station-out on the nominal design (`loso`), dense under [`dense_oracle`].
pub fn leave_one_station_out(
    data: &Data,
    design: &Arc<Design>,
    resid_m: &[f64],
) -> (Vec<HeldOutStation>, Vec<String>) {
    if dense_mode() {
        dense::leave_one_station_out(data, &design.to_dense(), resid_m)
    } else {
        loso::leave_one_station_out(data, design, resid_m)
    }
}
