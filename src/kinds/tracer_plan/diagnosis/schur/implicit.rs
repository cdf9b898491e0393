//! Sparse columns projected off the structured fit with the projection kept as coefficients:
//! row i of (I − P_X) m is m_i − b_i·z − a_i·q_p (a_i the row's point part, b_i its global
//! entries, p its point), with q_p per point (3 × k) and z over the global columns (g × k).
//! A candidate's projected columns are then never held dense: their rows are made when asked,
//! from its sparse rows and coefficients of the size of the parameters.
//!
//! With s_p = A_pᵀ m_p, the projection off the points gives m_i − a_i·M_p⁺ s_p; its part along
//! B̃ = (I − P_A) B is B̃ z with z = W Wᵀ Bᵀ(I − P_A) m, and B̃ z = B z − A M⁺ Aᵀ B z, so
//! q_p = M_p⁺ (s_p − A_pᵀ B_p z): two walks over the rows, point by point.

use std::ops::Range;
use std::sync::Arc;

use nalgebra::DMatrix;

use crate::diagnose::columns::{ProjectedRows, RowSparse};
use crate::parallel::{self, split_lengths};

use super::{Design, Schur};

/// Points one part of the coefficients' walks takes.
const POINTS_AT_ONCE: usize = 512;
const MAX_COEFFICIENT_THREADS: usize = 2;

/// Each part's points with its columns of qt (k × 3 per point).
fn point_parts<'a>(
    qt: &'a mut DMatrix<f64>,
    parts: &[Range<usize>],
    k: usize,
) -> Vec<(Range<usize>, &'a mut [f64])> {
    let pieces = split_lengths(qt.as_mut_slice(), parts.iter().map(|p| 3 * k * p.len()));
    parts.iter().cloned().zip(pieces).collect()
}

/// Column `j` of a k-row matrix as a slice (contiguous loops over it vectorise; a view's
/// iterator does not).
fn column(m: &DMatrix<f64>, j: usize, k: usize) -> &[f64] {
    &m.as_slice()[j * k..(j + 1) * k]
}

/// Writes the columns' row at a position (with a scratch list of entries).
type RowSource<'a> = dyn Fn(usize, &mut [f64], &mut Vec<(usize, f64)>) + Sync + 'a;

/// The projection's coefficients, transposed so that a row's terms are contiguous: qt (k × 3n,
/// point p's columns 3p..3p + 3) and zt (k × g).
struct Coefficients {
    qt: DMatrix<f64>,
    zt: DMatrix<f64>,
}

/// Sparse whitened columns projected off a structured fit.
struct ImplicitProjection {
    design: Arc<Design>,
    rows: Vec<usize>,
    m: RowSparse,
    coefficients: Coefficients,
}

impl ImplicitProjection {
    /// Row `pos` of the projected columns into `out`: m_i − b_i·z − a_i·q_p.
    fn row_into(&self, pos: usize, out: &mut [f64], entries: &mut Vec<(usize, f64)>) {
        self.m.row_into(pos, out);
        let (d, i, c) = (&self.design, self.rows[pos], &self.coefficients);
        let k = out.len();
        d.global_entries(i, entries);
        for &(col, x) in entries.iter() {
            for (o, z) in out.iter_mut().zip(column(&c.zt, col, k)) {
                *o -= x * z;
            }
        }
        let (p, a) = (d.rows[i].point, d.a(i));
        for (x, &ax) in a.iter().enumerate() {
            for (o, q) in out.iter_mut().zip(column(&c.qt, 3 * p + x, k)) {
                *o -= ax * q;
            }
        }
    }
}

impl ProjectedRows for ImplicitProjection {
    fn nrows(&self) -> usize {
        self.rows.len()
    }

    fn ncols(&self) -> usize {
        self.m.ncols()
    }

    fn rows_at(&self, positions: &[usize]) -> DMatrix<f64> {
        let k = self.m.ncols();
        let mut out = DMatrix::zeros(k, positions.len());
        let mut entries = Vec::new();
        for (mut column, &pos) in out.column_iter_mut().zip(positions) {
            self.row_into(pos, column.as_mut_slice(), &mut entries);
        }
        out.transpose()
    }
}

impl Schur {
    /// `m` (whitened, one row per position among the fit's rows) projected off the design,
    /// the projection kept implicit. Twice, as `project_off` does: the second pass removes
    /// what rounding in the first left in the column space.
    pub fn project_off_implicit(&self, m: RowSparse) -> Box<dyn ProjectedRows> {
        let k = m.ncols();
        let once = self.projection_coefficients(k, &|pos, out, _| m.row_into(pos, out));
        let mut projected = ImplicitProjection {
            design: self.design.clone(),
            rows: self.rows.clone(),
            m,
            coefficients: once,
        };
        let again = self.projection_coefficients(k, &|pos, out, entries| {
            projected.row_into(pos, out, entries)
        });
        projected.coefficients.qt += again.qt;
        projected.coefficients.zt += again.zt;
        Box::new(projected)
    }

    /// The coefficients of the projection of the k columns whose row at a position `row`
    /// writes (with a scratch list of entries). The points in parts on the cores, each
    /// part's sums of Bᵀ(I − P_A)m added in the parts' order: the same on any number of
    /// cores.
    fn projection_coefficients(&self, k: usize, row: &RowSource) -> Coefficients {
        let (n, g) = (self.design.n_points, self.design.n_global());
        let threads = parallel::threads(MAX_COEFFICIENT_THREADS);
        let parts: Vec<Range<usize>> = (0..n)
            .step_by(POINTS_AT_ONCE)
            .map(|first| first..(first + POINTS_AT_ONCE).min(n))
            .collect();
        let mut qt = DMatrix::<f64>::zeros(k, 3 * n);

        // First s_p = A_pᵀ m_p per point (in qt's storage), and Bᵀ(I − P_A) m.
        let sums =
            parallel::in_groups_owned(point_parts(&mut qt, &parts, k), threads, |(points, s)| {
                self.point_sums(points, s, k, row)
            });
        let mut tt = DMatrix::<f64>::zeros(k, g);
        for part in sums {
            tt += part;
        }
        // zᵀ = tᵀ W Wᵀ.
        let zt = (&tt * &self.w_red) * self.w_red.transpose();
        drop(tt);
        // q_p = M_p⁺ (s_p − A_pᵀ B_p z).
        parallel::in_groups_owned(point_parts(&mut qt, &parts, k), threads, |(points, s)| {
            self.point_coefficients(points, s, k, &zt)
        });
        Coefficients { qt, zt }
    }

    /// For the points `points`: s_p = A_pᵀ m_p into `s` (k × 3 per point), and their rows'
    /// Bᵀ(I − P_A) m (k × g, transposed).
    fn point_sums(
        &self,
        points: Range<usize>,
        s: &mut [f64],
        k: usize,
        row: &RowSource,
    ) -> DMatrix<f64> {
        let d = &self.design;
        let first = points.start;
        let mut tt = DMatrix::<f64>::zeros(k, d.n_global());
        let tt_columns = tt.as_mut_slice();
        let mut entries = Vec::new();
        let mut member_rows: Vec<f64> = Vec::new();
        let mut q1 = vec![0.0; 3 * k];
        for p in points {
            let members = self.members(p);
            member_rows.resize(members.len() * k, 0.0);
            for (r, &pos) in member_rows.chunks_mut(k).zip(members) {
                row(pos, r, &mut entries);
            }
            let at = 3 * (p - first);
            let sp = &mut s[at * k..(at + 3) * k];
            for (r, &pos) in member_rows.chunks(k).zip(members) {
                let a = d.a(self.rows[pos]);
                for (x, column) in sp.chunks_exact_mut(k).enumerate() {
                    for (sc, v) in column.iter_mut().zip(r) {
                        *sc += a[x] * v;
                    }
                }
            }
            // M_p⁺ s_p, then each row's part off the point: m_i − a_i·M_p⁺ s_p.
            let mp = self.m_pinv[p];
            for x in 0..3 {
                for c in 0..k {
                    q1[x * k + c] = (0..3).map(|y| mp[(x, y)] * sp[y * k + c]).sum();
                }
            }
            for (r, &pos) in member_rows.chunks_mut(k).zip(members) {
                let i = self.rows[pos];
                let a = d.a(i);
                for (c, v) in r.iter_mut().enumerate() {
                    *v -= (0..3).map(|x| a[x] * q1[x * k + c]).sum::<f64>();
                }
                d.global_entries(i, &mut entries);
                for &(col, x) in &entries {
                    let t = &mut tt_columns[col * k..(col + 1) * k];
                    for (t, v) in t.iter_mut().zip(r.iter()) {
                        *t += x * v;
                    }
                }
            }
        }
        tt
    }

    /// For the points `points`: q_p = M_p⁺ (s_p − A_pᵀ B_p z) in place of s_p in `s`.
    fn point_coefficients(&self, points: Range<usize>, s: &mut [f64], k: usize, zt: &DMatrix<f64>) {
        let d = &self.design;
        let first = points.start;
        let mut entries = Vec::new();
        let mut bz = vec![0.0; k];
        for p in points {
            let at = 3 * (p - first);
            let sp = &mut s[at * k..(at + 3) * k];
            for &pos in self.members(p) {
                let i = self.rows[pos];
                d.global_entries(i, &mut entries);
                bz.fill(0.0);
                for &(col, x) in &entries {
                    for (b, z) in bz.iter_mut().zip(column(zt, col, k)) {
                        *b += x * z;
                    }
                }
                let a = d.a(i);
                for (x, column) in sp.chunks_exact_mut(k).enumerate() {
                    for (sc, b) in column.iter_mut().zip(&bz) {
                        *sc -= a[x] * b;
                    }
                }
            }
            let mp = self.m_pinv[p];
            for c in 0..k {
                let v = [sp[c], sp[k + c], sp[2 * k + c]];
                for x in 0..3 {
                    sp[x * k + c] = (0..3).map(|y| mp[(x, y)] * v[y]).sum();
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::tests::small;
    use super::*;

    /// The implicit projection's rows are the dense projection's, with and without a right
    /// factor, over every row and over a subset of the rows.
    #[test]
    fn implicit_rows_equal_the_dense_projection() {
        let design = Arc::new(small(false));
        let n = design.lengths();
        let k = 6;
        let mut m = RowSparse::new(k, n, 2);
        for i in 0..n {
            let s = design.station_of(i);
            m.push_row([
                (s % k, 1.0 + 0.1 * i as f64),
                ((s + 2) % k, -0.3 * (i % 5) as f64),
            ]);
        }
        let right = DMatrix::from_fn(k, 4, |r, c| ((r * 7 + c * 3) % 5) as f64 - 2.0);
        for m in [m.clone(), m.with_right(right)] {
            for rows in [
                (0..n).collect::<Vec<_>>(),
                (0..n).filter(|i| i % 3 != 1).collect(),
            ] {
                let fit = Schur::new(design.clone(), rows.clone());
                let all = m.to_dense();
                let dense = fit.project_off(&all.select_rows(&rows));
                let mut sub = RowSparse::new(all.ncols(), rows.len(), 2);
                for &i in &rows {
                    let mut row = vec![0.0; all.ncols()];
                    row.copy_from_slice(all.row(i).transpose().as_slice());
                    sub.push_row(row.into_iter().enumerate());
                }
                let implicit = fit.project_off_implicit(sub);
                let positions: Vec<usize> = (0..rows.len()).collect();
                let got = implicit.rows_at(&positions);
                let scale = dense.amax().max(1.0);
                assert!(
                    (&got - &dense).amax() <= 1e-12 * scale,
                    "{}",
                    (&got - &dense).amax()
                );
            }
        }
    }
}
