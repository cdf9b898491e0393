//! A whitened design whose local parameters are eliminated group by group: parameters that
//! touch only the rows of one group (a hexapod pose's six, measured by its leg and sensor
//! rows) are factorised block by block, and the global columns (the calibration's and the
//! effects') projected off every block's span are factorised once, so that a fit costs a few
//! small SVDs instead of the SVD of the whole dense design. The same fits as
//! [`WhitenedDesign`]'s (rank, least-squares minimum-norm solution, projection, row space,
//! prediction variances) to rounding; a model that names no local block is fitted dense.

use std::ops::Range;
use std::sync::Arc;

use nalgebra::{DMatrix, DVector};

use super::downdate::HatRows;
use super::engine::{LinearDesign, LinearFit};
use super::stats::{Basis, RANK_TOL};
use super::whitened::{tall_basis, WhitenedDesign, WhitenedFit};
use crate::method::diagnosis::BlockLayout;
pub use crate::method::diagnosis::LocalBlock;
use crate::method::tall_svd::largest_singular_value;

/// The whitened design over all rows with its local blocks (disjoint in rows and columns).
pub struct BlockedDesign {
    design: Arc<DMatrix<f64>>,
    blocks: Arc<Vec<LocalBlock>>,
    /// The columns in no block, in order.
    global: Arc<Vec<usize>>,
    /// Each design row's block, if any.
    row_block: Arc<Vec<Option<usize>>>,
}

impl BlockedDesign {
    /// The blocked design of `design`; None when the blocks are empty, overlap, or a block's
    /// columns are non-zero outside its rows (then the dense design applies).
    pub fn new(design: Arc<DMatrix<f64>>, blocks: Vec<LocalBlock>) -> Option<BlockedDesign> {
        let layout = BlockLayout::of(&design, &blocks)?;
        Some(BlockedDesign {
            design,
            blocks: Arc::new(blocks),
            global: Arc::new(layout.global),
            row_block: Arc::new(layout.row_block),
        })
    }
}

/// One block's part of a fit: its rows among the fit's (positions in the fit's rows and
/// design rows) and the thin SVD of its columns there.
struct BlockFit {
    positions: Vec<usize>,
    rows: Vec<usize>,
    columns: Range<usize>,
    basis: Basis,
}

/// The blocked design's fit on a set of rows.
pub struct BlockedFit {
    design: Arc<DMatrix<f64>>,
    global: Arc<Vec<usize>>,
    /// The fit's rows (design row indices); each design row's block, if any (its fit is
    /// `blocks[b]`, over the block's rows among the fit's).
    rows: Vec<usize>,
    row_block: Arc<Vec<Option<usize>>>,
    blocks: Vec<BlockFit>,
    /// The global columns over the fit's rows, projected off every block's span.
    reduced: Basis,
    /// Orthonormal basis (rows) of the design's null space beyond the blocks' own (a global
    /// direction of the reduced design's null space with the local parameters that follow
    /// it): the minimum-norm solution and the row-space test need it.
    null: DMatrix<f64>,
}

impl BlockFit {
    /// U Uᵀ v over the block's positions, subtracted from `v` (a vector over the fit's rows).
    fn project_off(&self, v: &mut nalgebra::DVectorViewMut<f64>) {
        if self.basis.rank() == 0 {
            return;
        }
        let local = DVector::from_fn(self.positions.len(), |k, _| v[self.positions[k]]);
        let along = &self.basis.u * (self.basis.u.tr_mul(&local));
        for (k, &pos) in self.positions.iter().enumerate() {
            v[pos] -= along[k];
        }
    }
}

impl LinearDesign for BlockedDesign {
    type Fit = BlockedFit;

    fn fit(&self, rows: Vec<usize>) -> BlockedFit {
        let x = &self.design;
        let n = x.nrows();
        let mut position = vec![usize::MAX; n];
        for (k, &r) in rows.iter().enumerate() {
            position[r] = k;
        }
        let local_matrix = |block: &LocalBlock| {
            let kept: Vec<usize> = block
                .rows
                .iter()
                .copied()
                .filter(|&r| position[r] != usize::MAX)
                .collect();
            let m = DMatrix::from_fn(kept.len(), block.columns.len(), |i, j| {
                x[(kept[i], block.columns.start + j)]
            });
            (kept, m)
        };
        let locals: Vec<(Vec<usize>, DMatrix<f64>)> =
            self.blocks.iter().map(local_matrix).collect();
        let global_rows = DMatrix::from_fn(rows.len(), self.global.len(), |i, j| {
            x[(rows[i], self.global[j])]
        });
        // The rank cut against the design's largest singular value, taken as the largest of
        // the global columns' and of each block's (within √2 of the design's).
        let reference = locals
            .iter()
            .map(|(_, m)| largest_singular_value(m))
            .fold(largest_singular_value(&global_rows), f64::max);
        let blocks: Vec<BlockFit> = locals
            .into_iter()
            .zip(self.blocks.iter())
            .map(|((kept, m), block)| BlockFit {
                positions: kept.iter().map(|&r| position[r]).collect(),
                rows: kept,
                columns: block.columns.clone(),
                basis: Basis::new(&m, RANK_TOL, reference),
            })
            .collect();
        let mut reduced_columns = global_rows;
        for c in 0..reduced_columns.ncols() {
            let mut column = reduced_columns.column_mut(c);
            for block in &blocks {
                block.project_off(&mut column);
            }
        }
        let (reduced, reduced_null) = basis_with_null(&reduced_columns, reference);
        let mut fit = BlockedFit {
            design: x.clone(),
            global: self.global.clone(),
            rows,
            row_block: self.row_block.clone(),
            blocks,
            reduced,
            null: DMatrix::zeros(0, x.ncols()),
        };
        fit.null = fit.null_space(&reduced_null);
        fit
    }

    fn predict(&self, i: usize, x: &DVector<f64>) -> f64 {
        self.design.row(i).transpose().dot(x)
    }
}

/// The basis of `a` above the rank cut, and an orthonormal basis (rows) of the directions it
/// leaves out (its null space, to the cut).
fn basis_with_null(a: &DMatrix<f64>, reference: f64) -> (Basis, DMatrix<f64>) {
    let basis = tall_basis(a, RANK_TOL, reference);
    let p = a.ncols();
    if basis.rank() == p {
        return (basis, DMatrix::zeros(0, p));
    }
    // The complement of the kept right vectors: eigenvectors of I − VᵀV at eigenvalue 1.
    let complement = DMatrix::identity(p, p) - basis.vt.tr_mul(&basis.vt);
    let eig = complement.symmetric_eigen();
    let keep: Vec<usize> = (0..p).filter(|&j| eig.eigenvalues[j] > 0.5).collect();
    let null = DMatrix::from_fn(keep.len(), p, |k, j| eig.eigenvectors[(j, keep[k])]);
    (basis, null)
}

impl BlockedFit {
    /// The global parameters' least-squares minimum-norm solution's split: the local part
    /// that a global x_G implies, −L⁺ G x_G, block by block, written into `out`.
    fn locals_following(&self, global: &DVector<f64>, out: &mut DVector<f64>) {
        for block in &self.blocks {
            if block.basis.rank() == 0 {
                continue;
            }
            let g_times = DVector::from_fn(block.rows.len(), |k, _| {
                let r = block.rows[k];
                self.global
                    .iter()
                    .zip(global.iter())
                    .map(|(&c, v)| self.design[(r, c)] * v)
                    .sum::<f64>()
            });
            let local = block.basis.solve(&g_times);
            for (j, c) in block.columns.clone().enumerate() {
                out[c] = -local[j];
            }
        }
    }

    /// Orthonormal rows spanning the design's null directions that carry a global part.
    fn null_space(&self, reduced_null: &DMatrix<f64>) -> DMatrix<f64> {
        let p = self.design.ncols();
        let d = reduced_null.nrows();
        if d == 0 {
            return DMatrix::zeros(0, p);
        }
        let mut vectors = DMatrix::zeros(p, d);
        for k in 0..d {
            let z = reduced_null.row(k).transpose();
            let mut v = DVector::zeros(p);
            for (j, &c) in self.global.iter().enumerate() {
                v[c] = z[j];
            }
            self.locals_following(&z, &mut v);
            vectors.set_column(k, &v);
        }
        let q = vectors.qr().q();
        q.transpose()
    }

    /// The design row i as a vector.
    fn row(&self, i: usize) -> DVector<f64> {
        self.design.row(i).transpose()
    }

    /// The design row's parts: the global entries and, in a block of the fit, the block's
    /// index and local entries.
    fn split_row(&self, i: usize) -> (DVector<f64>, Option<(usize, DVector<f64>)>) {
        let global = DVector::from_fn(self.global.len(), |j, _| self.design[(i, self.global[j])]);
        let local = self.row_block[i].map(|b| {
            let block = &self.blocks[b];
            (
                b,
                DVector::from_fn(block.columns.len(), |j, _| {
                    self.design[(i, block.columns.start + j)]
                }),
            )
        });
        (global, local)
    }

    /// The squared part of row i's local entries outside its block's row space (a row in no
    /// block has none: the blocks' columns are zero there).
    fn local_out_of_row_space(&self, i: usize) -> f64 {
        let Some((b, l)) = self.split_row(i).1 else {
            return 0.0;
        };
        let inside = &self.blocks[b].basis.vt * &l;
        (l.norm_squared() - inside.norm_squared()).max(0.0)
    }

    /// Diagonal of the hat matrix over the fit's rows (leverages), by position.
    pub fn leverages(&self) -> Vec<f64> {
        let mut h: Vec<f64> = (0..self.rows.len())
            .map(|k| self.reduced.u.row(k).norm_squared())
            .collect();
        for block in &self.blocks {
            for (k, &pos) in block.positions.iter().enumerate() {
                h[pos] += block.basis.u.row(k).norm_squared();
            }
        }
        h
    }

    fn project_off_view(&self, mut v: nalgebra::DVectorViewMut<f64>) {
        for block in &self.blocks {
            block.project_off(&mut v);
        }
        let along = &self.reduced.u * self.reduced.u.tr_mul(&v);
        v -= along;
    }
}

impl LinearFit for BlockedFit {
    fn rank(&self) -> usize {
        self.reduced.rank() + self.blocks.iter().map(|b| b.basis.rank()).sum::<usize>()
    }

    fn solve(&self, y: &DVector<f64>) -> DVector<f64> {
        let p = self.design.ncols();
        let mut projected = y.clone();
        for block in &self.blocks {
            block.project_off(&mut projected.column_mut(0));
        }
        let global = self.reduced.solve(&projected);
        let mut x = DVector::zeros(p);
        for (j, &c) in self.global.iter().enumerate() {
            x[c] = global[j];
        }
        // Each block's parameters fit what the global ones leave of its rows.
        for block in &self.blocks {
            if block.basis.rank() == 0 {
                continue;
            }
            let left = DVector::from_fn(block.rows.len(), |k, _| {
                let r = block.rows[k];
                y[block.positions[k]]
                    - self
                        .global
                        .iter()
                        .zip(global.iter())
                        .map(|(&c, v)| self.design[(r, c)] * v)
                        .sum::<f64>()
            });
            let local = block.basis.solve(&left);
            for (j, c) in block.columns.clone().enumerate() {
                x[c] = local[j];
            }
        }
        // The minimum-norm solution: no part along the null directions with a global part
        // (the blocks' own null directions are left out by their pseudo-inverses).
        if self.null.nrows() > 0 {
            let along = &self.null * &x;
            x -= self.null.tr_mul(&along);
        }
        x
    }

    fn project_off_vec(&self, y: &DVector<f64>) -> DVector<f64> {
        let mut out = y.clone();
        self.project_off_view(out.column_mut(0));
        out
    }

    fn project_off_owned(&self, mut m: DMatrix<f64>) -> DMatrix<f64> {
        for c in 0..m.ncols() {
            self.project_off_view(m.column_mut(c));
        }
        m
    }

    /// Inside the training rows' span to 1e-12 of the row's squared norm, as the dense fit.
    fn in_row_space(&self, i: usize) -> bool {
        let row = self.row(i);
        let norm2 = row.norm_squared();
        let outside = self.local_out_of_row_space(i) + (&self.null * &row).norm_squared();
        norm2 == 0.0 || outside <= 1e-12 * norm2
    }

    /// rowᵀ (XᵀX)⁻ row by the Schur complement: the block's part |S⁻¹ Vᵀ l|², then the global
    /// entries less what the block's least squares carries of them, through the reduced
    /// design's. Exact for rows in the row space (any generalised inverse gives the same).
    fn prediction_variances(&self, held: &[usize]) -> Vec<f64> {
        held.iter()
            .map(|&h| {
                let (mut global, local) = self.split_row(h);
                let mut var = 0.0;
                if let Some((b, l)) = local {
                    let block = &self.blocks[b];
                    let a = DVector::from_fn(block.basis.rank(), |k, _| {
                        block.basis.vt.row(k).transpose().dot(&l) / block.basis.s[k]
                    });
                    var += a.norm_squared();
                    if block.basis.rank() > 0 {
                        // G_kᵀ U_k a over the block's rows.
                        let ua = &block.basis.u * &a;
                        for (k, &r) in block.rows.iter().enumerate() {
                            for (j, &c) in self.global.iter().enumerate() {
                                global[j] -= self.design[(r, c)] * ua[k];
                            }
                        }
                    }
                }
                var + self.reduced.prediction_variance(global.as_slice())
            })
            .collect()
    }

    fn factorises_by_svd(&self) -> bool {
        true
    }
}

/// The residual models' design: blocked when the model names local blocks that hold, else
/// dense.
pub enum ModelDesign {
    Dense(WhitenedDesign),
    Blocked(BlockedDesign),
}

impl ModelDesign {
    pub fn new(design: DMatrix<f64>, blocks: Vec<LocalBlock>) -> ModelDesign {
        let design = Arc::new(design);
        match BlockedDesign::new(design.clone(), blocks) {
            Some(blocked) => ModelDesign::Blocked(blocked),
            None => ModelDesign::Dense(WhitenedDesign(design)),
        }
    }
}

pub enum ModelFit {
    Dense(WhitenedFit),
    Blocked(BlockedFit),
}

impl ModelFit {
    /// Diagonal of the hat matrix over the fit's rows (leverages).
    pub fn leverages(&self) -> Vec<f64> {
        match self {
            ModelFit::Dense(f) => f.basis.leverages(),
            ModelFit::Blocked(f) => f.leverages(),
        }
    }
}

impl LinearDesign for ModelDesign {
    type Fit = ModelFit;

    fn fit(&self, rows: Vec<usize>) -> ModelFit {
        match self {
            ModelDesign::Dense(d) => ModelFit::Dense(d.fit(rows)),
            ModelDesign::Blocked(d) => ModelFit::Blocked(d.fit(rows)),
        }
    }

    fn predict(&self, i: usize, x: &DVector<f64>) -> f64 {
        match self {
            ModelDesign::Dense(d) => d.predict(i, x),
            ModelDesign::Blocked(d) => d.predict(i, x),
        }
    }
}

macro_rules! both {
    ($self:ident, $f:ident => $e:expr) => {
        match $self {
            ModelFit::Dense($f) => $e,
            ModelFit::Blocked($f) => $e,
        }
    };
}

impl LinearFit for ModelFit {
    fn rank(&self) -> usize {
        both!(self, f => f.rank())
    }
    fn solve(&self, y: &DVector<f64>) -> DVector<f64> {
        both!(self, f => f.solve(y))
    }
    fn project_off_vec(&self, y: &DVector<f64>) -> DVector<f64> {
        both!(self, f => f.project_off_vec(y))
    }
    fn project_off_owned(&self, m: DMatrix<f64>) -> DMatrix<f64> {
        both!(self, f => f.project_off_owned(m))
    }
    fn in_row_space(&self, i: usize) -> bool {
        both!(self, f => f.in_row_space(i))
    }
    fn prediction_variances(&self, held: &[usize]) -> Vec<f64> {
        both!(self, f => f.prediction_variances(held))
    }
    fn factorises_by_svd(&self) -> bool {
        both!(self, f => f.factorises_by_svd())
    }
    fn hat_rows(&self, sets: &[&[usize]]) -> Option<Vec<HatRows>> {
        match self {
            ModelFit::Dense(f) => f.hat_rows(sets),
            ModelFit::Blocked(_) => None,
        }
    }
}
