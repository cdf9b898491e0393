//! A candidate effect's columns over all rows: a dense matrix, or by rows with a few entries
//! each (an effect with parameters per station touches only that station's in a row), times
//! an optional right factor (a constraint's projector). The sparse form lets a structured fit
//! keep the columns' projection implicit: a large session's candidate is never held dense.

use nalgebra::{DMatrix, DVector};

/// The columns of a candidate effect.
#[derive(Debug, Clone)]
pub enum Columns {
    Dense(DMatrix<f64>),
    Sparse(RowSparse),
}

impl Columns {
    pub fn into_dense(self) -> DMatrix<f64> {
        match self {
            Columns::Dense(m) => m,
            Columns::Sparse(s) => s.to_dense(),
        }
    }

    pub fn ncols(&self) -> usize {
        match self {
            Columns::Dense(m) => m.ncols(),
            Columns::Sparse(s) => s.ncols(),
        }
    }

    /// Row i's (column, value) for every column that may be nonzero, in ascending columns
    /// (a dense matrix: every column).
    pub fn for_row(&self, i: usize, mut f: impl FnMut(usize, f64)) {
        match self {
            Columns::Dense(m) => {
                for c in 0..m.ncols() {
                    f(c, m[(i, c)]);
                }
            }
            Columns::Sparse(s) => s.for_row(i, f),
        }
    }
}

/// Rows with their nonzero entries (compressed rows), times `right` when given.
#[derive(Debug, Clone)]
pub struct RowSparse {
    /// Row i's entries are `entries[starts[i]..starts[i + 1]]`, ascending columns.
    starts: Vec<usize>,
    entries: Vec<(u32, f64)>,
    inner_columns: usize,
    right: Option<DMatrix<f64>>,
}

impl RowSparse {
    /// `inner_columns` columns, no row yet.
    pub fn new(inner_columns: usize, rows_hint: usize, entries_per_row: usize) -> RowSparse {
        let mut starts = Vec::with_capacity(rows_hint + 1);
        starts.push(0);
        RowSparse {
            starts,
            entries: Vec::with_capacity(rows_hint * entries_per_row),
            inner_columns,
            right: None,
        }
    }

    /// Appends a row of (column, value) entries, in ascending columns.
    pub fn push_row(&mut self, entries: impl IntoIterator<Item = (usize, f64)>) {
        self.entries.extend(
            entries
                .into_iter()
                .filter(|&(_, v)| v != 0.0)
                .map(|(c, v)| (c as u32, v)),
        );
        self.starts.push(self.entries.len());
    }

    /// The rows times `right` (inner columns × columns).
    pub fn with_right(mut self, right: DMatrix<f64>) -> RowSparse {
        self.right = Some(match self.right.take() {
            Some(r) => r * right,
            None => right,
        });
        self
    }

    pub fn nrows(&self) -> usize {
        self.starts.len() - 1
    }

    pub fn ncols(&self) -> usize {
        self.right
            .as_ref()
            .map_or(self.inner_columns, |r| r.ncols())
    }

    /// Each row's entries scaled by its weight.
    pub fn scale_rows(&mut self, w: &DVector<f64>) {
        for (i, range) in self.starts.windows(2).enumerate() {
            for e in &mut self.entries[range[0]..range[1]] {
                e.1 *= w[i];
            }
        }
    }

    /// Row i's (column, value) for every column that may be nonzero, in ascending columns
    /// (with a right factor: every column).
    pub fn for_row(&self, i: usize, mut f: impl FnMut(usize, f64)) {
        let entries = &self.entries[self.starts[i]..self.starts[i + 1]];
        match &self.right {
            None => {
                for &(c, v) in entries {
                    f(c as usize, v);
                }
            }
            Some(right) => {
                for c in 0..right.ncols() {
                    f(
                        c,
                        entries
                            .iter()
                            .map(|&(j, v)| v * right[(j as usize, c)])
                            .sum(),
                    );
                }
            }
        }
    }

    /// Row i, dense, into `out` (one entry per column).
    pub fn row_into(&self, i: usize, out: &mut [f64]) {
        out.fill(0.0);
        self.for_row(i, |c, v| out[c] = v);
    }

    pub fn to_dense(&self) -> DMatrix<f64> {
        let (n, k) = (self.nrows(), self.ncols());
        let mut out = DMatrix::zeros(n, k);
        let mut row = vec![0.0; k];
        for i in 0..n {
            self.row_into(i, &mut row);
            for (c, &v) in row.iter().enumerate() {
                out[(i, c)] = v;
            }
        }
        out
    }

    /// The largest column norm.
    pub fn column_norm_max(&self) -> f64 {
        let k = self.ncols();
        let mut sums = vec![0.0; k];
        let mut row = vec![0.0; k];
        for i in 0..self.nrows() {
            self.row_into(i, &mut row);
            for (s, v) in sums.iter_mut().zip(&row) {
                *s += v * v;
            }
        }
        sums.into_iter().fold(0.0, f64::max).sqrt()
    }
}

/// Columns projected off a fit, made a few rows at a time (positions among the fit's rows).
pub trait ProjectedRows: Send + Sync {
    fn nrows(&self) -> usize;
    fn ncols(&self) -> usize;
    /// The rows at `positions`, in that order.
    fn rows_at(&self, positions: &[usize]) -> DMatrix<f64>;
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sparse_rows_times_their_factor_equal_the_dense_product() {
        let mut s = RowSparse::new(4, 3, 2);
        s.push_row([(0, 1.0), (2, -2.0)]);
        s.push_row([]);
        s.push_row([(1, 0.5), (3, 3.0)]);
        let plain = s.to_dense();
        assert_eq!(plain[(0, 2)], -2.0);
        assert_eq!(plain.row(1).amax(), 0.0);
        let right = DMatrix::from_fn(4, 2, |r, c| (r * 2 + c) as f64 - 1.5);
        let s = s.with_right(right.clone());
        assert!((s.to_dense() - &plain * &right).amax() < 1e-15);
        let mut scaled = s.clone();
        scaled.scale_rows(&DVector::from_vec(vec![2.0, 1.0, -1.0]));
        let want =
            DMatrix::from_diagonal(&DVector::from_vec(vec![2.0, 1.0, -1.0])) * &plain * &right;
        assert!((scaled.to_dense() - &want).amax() < 1e-15);
        let norm_max = (0..2).map(|c| want.column(c).norm()).fold(0.0, f64::max);
        assert!((scaled.column_norm_max() - norm_max).abs() < 1e-12);
    }
}
