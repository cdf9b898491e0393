//! The diagnosis's linear algebra on the structure of the multilateration design, as the solve
//! exploits it: each length sees one point (3 columns), its station (3) and its beam segment
//! (1), plus a few dense effect columns. The points are eliminated block by block (3 × 3); what
//! remains is the reduced (Schur complement) system of the stations, segments and effects,
//! whose size does not grow with the points. Every projection, least-squares solve, leverage,
//! prediction variance and null-space test the diagnosis needs comes from these blocks; the
//! dense design (lengths × parameters) is never built.
//!
//! With A the points' columns and B the rest (whitened), the column space of [A B] is
//! col(A) ⊕ col(B̃), B̃ = (I − P_A) B, and the reduced matrix S = B̃ᵀB̃ = Σ_p (B_pᵀB_p −
//! C_pᵀ M_p⁺ C_p) with M_p = A_pᵀA_p and C_p = A_pᵀB_p summed over point p's rows.

use std::collections::BTreeMap;
use std::sync::Arc;

use nalgebra::{DMatrix, DVector, Matrix3, Vector3};

use crate::diagnose::columns::Columns;
use crate::diagnose::downdate::{HatRows, LowRank};
use crate::parallel::{self, in_parallel, split_lengths};

use super::data::Data;
use super::effects::Geometry;

mod implicit;

/// Below this many entries (rows × columns) a projection runs on one thread: threads would
/// cost more than they save.
const THREADED_PROJECTION_ENTRIES: usize = 200_000;
const MAX_PROJECTION_THREADS: usize = 8;
/// Rows whose leverages one thread computes at a time.
const LEVERAGE_ROWS_AT_ONCE: usize = 4096;
/// Columns of a pseudo-inverse block solved together (each group holds a few parameter-long
/// columns).
const PINV_SOLVED_TOGETHER: usize = 8;
/// Points whose C_pᵀ M_p⁺ are gathered for one product by Wᵀ in [`Schur::reduced`]: a dense
/// product instead of one per point, in a buffer of global columns × 3 × this (~1 MB).
const REDUCED_CHUNK_POINTS: usize = 512;

/// Relative eigenvalue below which a direction of a point's 3 × 3 block or of the reduced
/// system is not identifiable. Eigenvalues are squared singular values: 1e-12 is a singular
/// value 1e-6 of the largest, far above the rounding that the gauge directions are left with
/// after the elimination (eigenvalues ~1e-16 of the largest) and far below the real directions
/// (condition < 1e4 in singular value, eigenvalues above 1e-8 of the largest) once the reduced
/// system is equilibrated (columns of unit norm, whatever their units): the same rank as the
/// dense SVD's cut (`stats::RANK_TOL`) on these designs (`tests/diagnose_oracle.rs`).
pub const EIGEN_TOL: f64 = 1e-12;

/// One length's place in the linearised model.
#[derive(Debug, Clone, Copy)]
struct Row {
    point: usize,
    station: usize,
    segment: usize,
    /// Unit vector from the point to the station.
    u: Vector3<f64>,
    /// Whitening weight 1/σ.
    w: f64,
}

/// The linearised design around a geometry, columns in the order of
/// `Geometry::jacobian` (points, stations, segments) followed by the effect columns.
#[derive(Debug, Clone)]
pub struct Design {
    n_points: usize,
    n_stations: usize,
    n_segments: usize,
    rows: Vec<Row>,
    /// Unwhitened effect columns (metres per unit parameter, one row per length): blocks side
    /// by side, each dense or by rows (an effect per station touches a few columns of a row).
    effects: Vec<Columns>,
}

impl Design {
    /// The nominal model's design at `geom`, weighted by the lengths' declared σ.
    pub fn nominal(data: &Data, geom: &Geometry) -> Design {
        Design::with_points(data, geom, |i| data.obs[i].point)
    }

    /// [`Design::nominal`] with length i on `geom`'s point `point_of(i)` (the points level's
    /// one point per plan point and pass).
    pub fn with_points(data: &Data, geom: &Geometry, point_of: impl Fn(usize) -> usize) -> Design {
        let rows = data
            .obs
            .iter()
            .enumerate()
            .map(|(i, o)| {
                let point = point_of(i);
                Row {
                    point,
                    station: o.station,
                    segment: o.segment,
                    u: geom.beam_between(o.station, point).0,
                    w: 1.0 / o.sigma_m,
                }
            })
            .collect();
        Design {
            n_points: geom.points.len(),
            n_stations: geom.stations.len(),
            n_segments: geom.distances_m.len(),
            rows,
            effects: Vec::new(),
        }
    }

    /// The same design with `effects` (unwhitened, one row per length) as its extra columns.
    #[cfg(test)]
    pub fn with_effects(&self, effects: DMatrix<f64>) -> Design {
        self.with_effect_blocks(vec![Columns::Dense(effects)])
    }

    /// The same design with the `blocks` of effect columns side by side as its extra columns.
    pub fn with_effect_blocks(&self, blocks: Vec<Columns>) -> Design {
        Design {
            effects: blocks,
            n_points: self.n_points,
            n_stations: self.n_stations,
            n_segments: self.n_segments,
            rows: self.rows.clone(),
        }
    }

    pub fn n_points(&self) -> usize {
        self.n_points
    }

    pub fn lengths(&self) -> usize {
        self.rows.len()
    }

    /// Columns of the geometry: 3 per point, 3 per station, 1 per segment.
    pub fn geometry_params(&self) -> usize {
        3 * self.n_points + 3 * self.n_stations + self.n_segments
    }

    pub fn n_params(&self) -> usize {
        3 * self.n_points + self.n_global()
    }

    /// Columns after the points': stations, segments, effects.
    pub fn n_global(&self) -> usize {
        3 * self.n_stations + self.n_segments + self.effect_columns()
    }

    pub fn effect_columns(&self) -> usize {
        self.effects.iter().map(Columns::ncols).sum()
    }

    /// Row i's effect columns, unwhitened, into `out` (one entry per effect column).
    pub fn effect_row_into(&self, i: usize, out: &mut [f64]) {
        out.fill(0.0);
        self.for_effect_entry(i, |c, v| out[c] = v);
    }

    /// Row i's unwhitened (effect column, value) for every effect column that may be nonzero.
    fn for_effect_entry(&self, i: usize, mut f: impl FnMut(usize, f64)) {
        let mut first = 0;
        for block in &self.effects {
            block.for_row(i, |c, v| f(first + c, v));
            first += block.ncols();
        }
    }

    pub fn point_of(&self, i: usize) -> usize {
        self.rows[i].point
    }

    pub fn station_of(&self, i: usize) -> usize {
        self.rows[i].station
    }

    /// Global columns (index after the points') of row i's station and segment.
    pub fn own_columns(&self, station: usize, segments: &[usize]) -> Vec<usize> {
        let mut own: Vec<usize> = (0..3).map(|a| 3 * station + a).collect();
        own.extend(segments.iter().map(|s| 3 * self.n_stations + s));
        own
    }

    /// Whitened coefficients of row i on its point's columns.
    pub fn point_coefficients(&self, i: usize) -> Vector3<f64> {
        self.a(i)
    }

    fn a(&self, i: usize) -> Vector3<f64> {
        let r = &self.rows[i];
        -r.u * r.w
    }

    /// Whitened station and segment entries of row i (global column, value).
    fn sparse(&self, i: usize) -> [(usize, f64); 4] {
        let r = &self.rows[i];
        let s = 3 * r.station;
        [
            (s, r.u.x * r.w),
            (s + 1, r.u.y * r.w),
            (s + 2, r.u.z * r.w),
            (3 * self.n_stations + r.segment, -r.w),
        ]
    }

    /// Row i's whitened global entries (stations, segment, then every effect column).
    fn global_entries(&self, i: usize, out: &mut Vec<(usize, f64)>) {
        out.clear();
        out.extend_from_slice(&self.sparse(i));
        let first = 3 * self.n_stations + self.n_segments;
        let w = self.rows[i].w;
        // Every effect column, zero or not: each row has the same number of entries.
        let start = out.len();
        out.extend((0..self.effect_columns()).map(|c| (first + c, 0.0)));
        let row = &mut out[start..];
        self.for_effect_entry(i, |c, v| row[c].1 = v * w);
    }

    /// Whitened row i's global part as a dense vector.
    fn global_dense(&self, i: usize) -> DVector<f64> {
        let mut v = DVector::zeros(self.n_global());
        let mut entries = Vec::new();
        self.global_entries(i, &mut entries);
        for (c, x) in entries {
            v[c] += x;
        }
        v
    }

    pub fn weight(&self, i: usize) -> f64 {
        self.rows[i].w
    }

    /// Unwhitened row i times x (full parameter order): the linearised predicted length.
    pub fn predict(&self, i: usize, x: &DVector<f64>) -> f64 {
        let r = &self.rows[i];
        let g = 3 * self.n_points;
        let mut sum = 0.0;
        for a in 0..3 {
            sum += -r.u[a] * x[3 * r.point + a] + r.u[a] * x[g + 3 * r.station + a];
        }
        sum -= x[g + 3 * self.n_stations + r.segment];
        let first = g + 3 * self.n_stations + self.n_segments;
        self.for_effect_entry(i, |c, v| sum += v * x[first + c]);
        sum
    }

    /// The dense unwhitened design (test oracle on small problems).
    pub fn to_dense(&self) -> DMatrix<f64> {
        let mut x = DMatrix::zeros(self.rows.len(), self.n_params());
        let g = 3 * self.n_points;
        for (i, r) in self.rows.iter().enumerate() {
            for a in 0..3 {
                x[(i, 3 * r.point + a)] = -r.u[a];
            }
            for (c, v) in self.sparse(i) {
                x[(i, g + c)] = v / r.w;
            }
            let first = g + 3 * self.n_stations + self.n_segments;
            self.for_effect_entry(i, |c, v| x[(i, first + c)] = v);
        }
        x
    }
}

/// A symmetric 3 × 3 block's pseudo-inverse with the relative eigenvalue cut.
struct PseudoInverse3 {
    inv: Matrix3<f64>,
    /// F with inv = Fᵀ F (a row per kept direction, zero rows for the cut ones).
    factor: Matrix3<f64>,
    /// The directions cut.
    null: Vec<Vector3<f64>>,
}

fn pinv3(m: &Matrix3<f64>) -> PseudoInverse3 {
    let eig = m.symmetric_eigen();
    let top = eig.eigenvalues.amax();
    let mut inv = Matrix3::zeros();
    let mut factor = Matrix3::zeros();
    let mut null = Vec::new();
    for k in 0..3 {
        let v = eig.eigenvectors.column(k).into_owned();
        let l = eig.eigenvalues[k];
        if l > EIGEN_TOL * top && l > 0.0 {
            inv += v * v.transpose() / l;
            factor.set_row(k, &(v.transpose() / l.sqrt()));
        } else {
            null.push(v);
        }
    }
    PseudoInverse3 { inv, factor, null }
}

/// The reduced system S = Σ_p (D_p − C_pᵀ M_p⁺ C_p) (D_p = Σ b bᵀ over point p's rows, C_p =
/// Σ a bᵀ) summed point by point: each point's term is formed whole over its touched columns
/// (ascending) before it is added, so the sum holds only what each point leaves (not the large
/// D_p and C_pᵀM⁺C_p that cancel); the terms of consecutive points on the same columns are
/// summed over those columns and go into S when the columns change. The terms are symmetric:
/// only their lower triangles are formed.
struct ReducedSum {
    /// Columns of the running sum and of the point's term (ascending).
    cols: Vec<usize>,
    /// The running sum and the point's term, column-major over `cols`.
    sum: Vec<f64>,
    term: Vec<f64>,
    /// F_p C_p's three rows over the touched columns.
    fc: [Vec<f64>; 3],
}

impl ReducedSum {
    fn new() -> ReducedSum {
        ReducedSum {
            cols: Vec::new(),
            sum: Vec::new(),
            term: Vec::new(),
            fc: [Vec::new(), Vec::new(), Vec::new()],
        }
    }

    /// Starts a point's term over `cols` (ascending), the running sum moved into `s` first
    /// when its columns are others.
    fn begin_point(&mut self, cols: &[usize], s: &mut DMatrix<f64>) {
        let k = cols.len();
        if self.cols != cols {
            self.flush(s);
            self.cols.clear();
            self.cols.extend_from_slice(cols);
            self.sum.clear();
            self.sum.resize(k * k, 0.0);
        }
        self.term.clear();
        self.term.resize(k * k, 0.0);
    }

    /// D_p's part from one row: its entries by slot (ascending).
    fn add_row(&mut self, entries: &[(usize, f64)]) {
        let k = self.cols.len();
        for (n, &(x, vx)) in entries.iter().enumerate() {
            for &(y, vy) in &entries[n..] {
                self.term[x * k + y] += vx * vy;
            }
        }
    }

    /// Ends the point: its term less (F C)ᵀ(F C) (F: M_p⁺ = FᵀF; `c` per slot), then added.
    fn end_point(&mut self, factor: &Matrix3<f64>, c: &[Vector3<f64>]) {
        let k = c.len();
        for row in &mut self.fc {
            row.clear();
        }
        for cj in c {
            let fc = factor * cj;
            for (row, v) in self.fc.iter_mut().zip(fc.iter()) {
                row.push(*v);
            }
        }
        let [f0, f1, f2] = &self.fc;
        for (x, column) in self.term.chunks_exact_mut(k).enumerate() {
            let (a0, a1, a2) = (f0[x], f1[x], f2[x]);
            let below = column[x..]
                .iter_mut()
                .zip(&f0[x..])
                .zip(&f1[x..])
                .zip(&f2[x..]);
            for (((t, &b0), &b1), &b2) in below {
                *t -= a0 * b0 + a1 * b1 + a2 * b2;
            }
        }
        for (x, (sum, term)) in self
            .sum
            .chunks_exact_mut(k)
            .zip(self.term.chunks_exact(k))
            .enumerate()
        {
            for (s, t) in sum[x..].iter_mut().zip(&term[x..]) {
                *s += t;
            }
        }
    }

    /// The running sum into S (both triangles).
    fn flush(&mut self, s: &mut DMatrix<f64>) {
        let k = self.cols.len();
        for (x, &cx) in self.cols.iter().enumerate() {
            for (y, &cy) in self.cols.iter().enumerate().skip(x) {
                let v = self.sum[x * k + y];
                s[(cy, cx)] += v;
                if cy != cx {
                    s[(cx, cy)] += v;
                }
            }
        }
        self.sum.fill(0.0);
    }
}

/// The least-squares fit of a design on a set of its rows, points eliminated: what the dense
/// `stats::Basis` (thin SVD) gave, from the blocks.
pub struct Schur {
    design: Arc<Design>,
    /// The fit's rows; vectors "over the rows" are indexed by position in this list.
    rows: Vec<usize>,
    /// Positions of each point's rows (CSR: point p's are `point_rows[point_start[p]..point_start[p + 1]]`).
    point_start: Vec<usize>,
    point_rows: Vec<usize>,
    /// M_p⁺ per point.
    m_pinv: Vec<Matrix3<f64>>,
    point_rank: usize,
    /// The reduced system's kept eigenvectors over √eigenvalue: S⁺ = W Wᵀ.
    w_red: DMatrix<f64>,
    /// Orthonormal basis of the design's null space over these rows (full parameter order):
    /// the reduced system's null directions with the points' response, and the points' own
    /// null directions (a point no row of the fit sees, or sees from one line only).
    null_dense: DMatrix<f64>,
    point_null: Vec<(usize, Vector3<f64>)>,
}

/// Per point of a fit: C_pᵀ y for a 3-vector y is Σ_rows b_i (a_i · y); these helpers walk a
/// point's rows once.
impl Schur {
    pub fn new(design: Arc<Design>, rows: Vec<usize>) -> Schur {
        let n = design.n_points;
        let g = design.n_global();
        let mut point_start = vec![0usize; n + 1];
        for &i in &rows {
            point_start[design.rows[i].point + 1] += 1;
        }
        for p in 0..n {
            point_start[p + 1] += point_start[p];
        }
        let mut fill = point_start.clone();
        let mut point_rows = vec![0usize; rows.len()];
        for (pos, &i) in rows.iter().enumerate() {
            let p = design.rows[i].point;
            point_rows[fill[p]] = pos;
            fill[p] += 1;
        }
        let mut m_pinv = Vec::with_capacity(n);
        let mut point_null = Vec::new();
        let mut point_rank = 0;
        let mut s = DMatrix::<f64>::zeros(g, g);
        // Squared norm of each global column before the elimination: the scale of the
        // reduced system's equilibration.
        let mut column_norm2 = vec![0.0; g];
        let mut entries = Vec::new();
        // Per member row of the current point: its entries by slot, and its a.
        let mut row_entries: Vec<(usize, f64)> = Vec::new();
        let mut row_starts: Vec<usize> = Vec::new();
        // Local column slots of the current point's touched global columns.
        let mut slot = vec![usize::MAX; g];
        let mut cols: Vec<usize> = Vec::new();
        let mut c_local: Vec<Vector3<f64>> = Vec::new();
        let mut reduced = ReducedSum::new();
        for p in 0..n {
            let members = &point_rows[point_start[p]..point_start[p + 1]];
            let mut m = Matrix3::zeros();
            cols.clear();
            row_entries.clear();
            row_starts.clear();
            for &pos in members {
                let i = rows[pos];
                let a = design.a(i);
                m += a * a.transpose();
                design.global_entries(i, &mut entries);
                row_starts.push(row_entries.len());
                for &(cx, vx) in &entries {
                    column_norm2[cx] += vx * vx;
                    if slot[cx] == usize::MAX {
                        slot[cx] = 0;
                        cols.push(cx);
                    }
                    row_entries.push((cx, vx));
                }
            }
            row_starts.push(row_entries.len());
            cols.sort_unstable();
            for (k, &c) in cols.iter().enumerate() {
                slot[c] = k;
            }
            // Slots follow the global columns' order, so each row's entries stay ascending.
            for entry in &mut row_entries {
                entry.0 = slot[entry.0];
            }
            reduced.begin_point(&cols, &mut s);
            c_local.clear();
            c_local.resize(cols.len(), Vector3::zeros());
            for (r, &pos) in members.iter().enumerate() {
                let a = design.a(rows[pos]);
                let entries = &row_entries[row_starts[r]..row_starts[r + 1]];
                reduced.add_row(entries);
                for &(x, vx) in entries {
                    c_local[x] += a * vx;
                }
            }
            let PseudoInverse3 { inv, factor, null } = pinv3(&m);
            point_rank += 3 - null.len();
            point_null.extend(null.into_iter().map(|v| (p, v)));
            reduced.end_point(&factor, &c_local);
            for &c in &cols {
                slot[c] = usize::MAX;
            }
            m_pinv.push(inv);
        }
        reduced.flush(&mut s);
        // Symmetrise against the rounding of the two triangles' sums, and equilibrate: Ŝ =
        // D⁻¹ S D⁻¹ with D the columns' norms, so that the rank cut does not depend on the
        // columns' units. An effect column whose whitened entries are ~1e-7 of a station's
        // (air refraction: dn·L ≈ 1e-7 m per unit) has an eigenvalue ~1e-14 of the stations'
        // in S, under any cut that the normal equations' rounding allows, while the dense SVD
        // (cut 1e-9 in singular value) keeps it. Columns no row touches keep the scale 1.
        let scale: Vec<f64> = column_norm2
            .iter()
            .map(|&n2| if n2 > 0.0 { n2.sqrt() } else { 1.0 })
            .collect();
        let s = DMatrix::from_fn(g, g, |r, c| {
            0.5 * (s[(r, c)] + s[(c, r)]) / (scale[r] * scale[c])
        });
        let eig = s.symmetric_eigen();
        let top = eig.eigenvalues.amax();
        let keep: Vec<usize> = (0..g)
            .filter(|&k| eig.eigenvalues[k] > EIGEN_TOL * top && eig.eigenvalues[k] > 0.0)
            .collect();
        let null_red: Vec<usize> = (0..g).filter(|k| !keep.contains(k)).collect();
        // S's generalised inverse D⁻¹ Ŝ⁺ D⁻¹ = W Wᵀ: every use (projections, estimable
        // predictions, solves whose null part is removed) is the same for any of them.
        let w_red = DMatrix::from_fn(g, keep.len(), |r, k| {
            eig.eigenvectors[(r, keep[k])] / eig.eigenvalues[keep[k]].sqrt() / scale[r]
        });
        let mut fit = Schur {
            design,
            rows,
            point_start,
            point_rows,
            m_pinv,
            point_rank,
            w_red,
            null_dense: DMatrix::zeros(0, 0),
            point_null,
        };
        // Null directions of the whole design: (−M_p⁺ C_p v, v) for each null v of S.
        let offset = 3 * n;
        let mut null = DMatrix::zeros(offset + g, null_red.len());
        for (z, &k) in null_red.iter().enumerate() {
            // Ŝ v̂ = 0 ⇔ S D⁻¹ v̂ = 0.
            let v = DVector::from_fn(g, |r, _| eig.eigenvectors[(r, k)] / scale[r]);
            let cv = fit.c_times(&v);
            for p in 0..n {
                let x = -(fit.m_pinv[p] * cv[p]);
                for a in 0..3 {
                    null[(3 * p + a, z)] = x[a];
                }
            }
            null.view_mut((offset, z), (g, 1)).copy_from(&v);
        }
        fit.null_dense = orthonormal_columns(null);
        fit
    }

    /// Identifiable directions: the points' kept directions plus the reduced system's.
    /// Wᵀ (reduced × global): each global column's part contiguous.
    pub fn reduced_transpose(&self) -> DMatrix<f64> {
        self.w_red.transpose()
    }

    /// Rank of the reduced system (the stations', segments' and effects' part).
    pub fn reduced_dim(&self) -> usize {
        self.w_red.ncols()
    }

    pub fn rank(&self) -> usize {
        self.point_rank + self.w_red.ncols()
    }

    pub fn rows(&self) -> &[usize] {
        &self.rows
    }

    pub fn design(&self) -> &Design {
        &self.design
    }

    fn members(&self, p: usize) -> &[usize] {
        &self.point_rows[self.point_start[p]..self.point_start[p + 1]]
    }

    /// C_p v for every point (v over the global columns).
    fn c_times(&self, v: &DVector<f64>) -> Vec<Vector3<f64>> {
        let d = &self.design;
        let mut entries = Vec::new();
        let mut out = vec![Vector3::zeros(); d.n_points];
        for &i in &self.rows {
            d.global_entries(i, &mut entries);
            let bv: f64 = entries.iter().map(|&(c, x)| x * v[c]).sum();
            out[d.rows[i].point] += d.a(i) * bv;
        }
        out
    }

    /// The minimum-norm x with N x = v, N = XᵀX over the fit's rows (v in its range).
    pub fn normal_solve(&self, v: &DVector<f64>) -> DVector<f64> {
        self.normal_solve_columns(&DMatrix::from_column_slice(v.len(), 1, v.as_slice()))
            .column(0)
            .into_owned()
    }

    /// x minus its part in the null space (the minimum-norm representative).
    fn remove_null(&self, x: &mut DVector<f64>) {
        if self.null_dense.ncols() > 0 {
            let coeff = self.null_dense.transpose() * &*x;
            *x -= &self.null_dense * coeff;
        }
        for (p, v) in &self.point_null {
            let mut xp = x.fixed_rows_mut::<3>(3 * p);
            let c = v.dot(&xp.clone_owned());
            xp -= v * c;
        }
    }

    /// [`Schur::normal_solve`] of every column of `v` together: one walk over the rows per
    /// step for all of them (each row's entries made once), each column's sums as alone.
    pub fn normal_solve_columns(&self, v: &DMatrix<f64>) -> DMatrix<f64> {
        let d = &self.design;
        let (n, k, g) = (d.n_points, v.ncols(), d.n_global());
        let offset = 3 * n;
        let mut vp = DMatrix::zeros(offset, k);
        for p in 0..n {
            let block = self.m_pinv[p] * v.fixed_rows::<3>(3 * p);
            vp.fixed_rows_mut::<3>(3 * p).copy_from(&block);
        }
        // Σ_p C_pᵀ (M_p⁺ v_p): Σ over the rows of b_i (a_i · (M_p⁺ v_p)).
        let mut ct = DMatrix::zeros(g, k);
        let mut entries = Vec::new();
        let mut at = vec![0.0; k];
        for &i in &self.rows {
            let a = d.a(i);
            let p = d.rows[i].point;
            for (col, out) in at.iter_mut().enumerate() {
                *out = a.dot(&vp.fixed_view::<3, 1>(3 * p, col));
            }
            d.global_entries(i, &mut entries);
            for &(c, x) in &entries {
                for (col, &t) in at.iter().enumerate() {
                    if t != 0.0 {
                        ct[(c, col)] += x * t;
                    }
                }
            }
        }
        let reduced = v.rows(offset, g) - ct;
        let xg = &self.w_red * self.w_red.tr_mul(&reduced);
        // C_p xg per point, as `c_times` per column.
        let mut cx = DMatrix::zeros(offset, k);
        let mut bv = vec![0.0; k];
        for &i in &self.rows {
            d.global_entries(i, &mut entries);
            for (col, out) in bv.iter_mut().enumerate() {
                *out = entries.iter().map(|&(c, x)| x * xg[(c, col)]).sum();
            }
            let a = d.a(i);
            let p = d.rows[i].point;
            for (col, &b) in bv.iter().enumerate() {
                let mut target = cx.fixed_view_mut::<3, 1>(3 * p, col);
                target += a * b;
            }
        }
        let mut x = DMatrix::zeros(d.n_params(), k);
        for p in 0..n {
            let block = self.m_pinv[p] * (v.fixed_rows::<3>(3 * p) - cx.fixed_rows::<3>(3 * p));
            x.fixed_rows_mut::<3>(3 * p).copy_from(&block);
        }
        x.rows_mut(offset, g).copy_from(&xg);
        for mut column in x.column_iter_mut() {
            let mut owned = column.clone_owned();
            self.remove_null(&mut owned);
            column.copy_from(&owned);
        }
        x
    }

    /// Least-squares minimum-norm x of X x ≈ y over the fit's rows (y whitened, by position).
    pub fn solve(&self, y: &DVector<f64>) -> DVector<f64> {
        self.solve_columns(&DMatrix::from_column_slice(y.len(), 1, y.as_slice()))
            .column(0)
            .into_owned()
    }

    /// [`Schur::solve`] of every column of `y` together (one walk over the rows per step for
    /// all of them).
    pub fn solve_columns(&self, y: &DMatrix<f64>) -> DMatrix<f64> {
        self.solve_columns_owned(y.clone())
    }

    /// [`Schur::solve_columns`], the refinement's residuals made in `y`'s place.
    pub fn solve_columns_owned(&self, mut y: DMatrix<f64>) -> DMatrix<f64> {
        let mut x = self.normal_solve_columns(&self.xt_columns(&y));
        // One step of iterative refinement: the normal equations square the condition number.
        self.subtract_times_columns(&x, &mut y);
        x += self.normal_solve_columns(&self.xt_columns(&y));
        x
    }

    /// Xᵀ y over the fit's rows for every column of `y` (by position): the normal equations'
    /// right-hand sides.
    fn xt_columns(&self, y: &DMatrix<f64>) -> DMatrix<f64> {
        let d = &self.design;
        let offset = 3 * d.n_points;
        let mut out = DMatrix::zeros(d.n_params(), y.ncols());
        let mut entries = Vec::new();
        for (pos, &i) in self.rows.iter().enumerate() {
            let a = d.a(i);
            let p = d.rows[i].point;
            d.global_entries(i, &mut entries);
            for col in 0..y.ncols() {
                let yv = y[(pos, col)];
                for k in 0..3 {
                    out[(3 * p + k, col)] += a[k] * yv;
                }
                for &(c, x) in &entries {
                    out[(offset + c, col)] += x * yv;
                }
            }
        }
        out
    }

    /// X x over the fit's rows for every column of `x` (whitened, by position).
    #[cfg(test)]
    fn times_columns(&self, x: &DMatrix<f64>) -> DMatrix<f64> {
        let mut out = DMatrix::zeros(self.rows.len(), x.ncols());
        self.subtract_times_columns(x, &mut out);
        -out
    }

    /// y − X x over the fit's rows for every column of `x` (whitened, by position), in place.
    fn subtract_times_columns(&self, x: &DMatrix<f64>, y: &mut DMatrix<f64>) {
        let d = &self.design;
        let offset = 3 * d.n_points;
        let mut entries = Vec::new();
        for (pos, &i) in self.rows.iter().enumerate() {
            let p = d.rows[i].point;
            let a = d.a(i);
            d.global_entries(i, &mut entries);
            for col in 0..x.ncols() {
                let xp = x.fixed_view::<3, 1>(3 * p, col);
                y[(pos, col)] -= a.dot(&xp)
                    + entries
                        .iter()
                        .map(|&(c, v)| v * x[(offset + c, col)])
                        .sum::<f64>();
            }
        }
    }

    /// y minus its projection on the design's column space (over the fit's rows).
    pub fn project_off_vec(&self, y: &DVector<f64>) -> DVector<f64> {
        // Twice: the second pass removes what rounding in the first left in the column space.
        let once = self.project_off_once(y);
        self.project_off_once(&once)
    }

    fn project_off_once(&self, y: &DVector<f64>) -> DVector<f64> {
        let d = &self.design;
        // Off the points' columns, point by point.
        let mut tilde = y.clone();
        self.project_off_points(&mut tilde);
        // Off B̃ = (I − P_A) B: B̃ᵀ y = Bᵀ ỹ.
        let mut entries = Vec::new();
        let mut t = DVector::zeros(d.n_global());
        for (pos, &i) in self.rows.iter().enumerate() {
            d.global_entries(i, &mut entries);
            for &(c, x) in &entries {
                t[c] += x * tilde[pos];
            }
        }
        let z = &self.w_red * self.w_red.tr_mul(&t);
        let mut v = DVector::from_fn(self.rows.len(), |pos, _| {
            d.global_entries(self.rows[pos], &mut entries);
            entries.iter().map(|&(c, x)| x * z[c]).sum()
        });
        self.project_off_points(&mut v);
        tilde - v
    }

    /// y ← (I − P_A) y, A the points' columns over the fit's rows.
    fn project_off_points(&self, y: &mut DVector<f64>) {
        let d = &self.design;
        for p in 0..d.n_points {
            let members = self.members(p);
            let q: Vector3<f64> = members
                .iter()
                .map(|&pos| d.a(self.rows[pos]) * y[pos])
                .sum();
            let t = self.m_pinv[p] * q;
            for &pos in members {
                y[pos] -= d.a(self.rows[pos]).dot(&t);
            }
        }
    }

    /// Each column of m (rows by position) minus its projection on the column space: the
    /// columns together, the rows' entries gathered once, each column walked contiguously (the
    /// same sums in the same order as `project_off_vec` makes for one).
    pub fn project_off(&self, m: &DMatrix<f64>) -> DMatrix<f64> {
        self.project_off_owned(m.clone())
    }

    /// [`Schur::project_off`] in place of `m`: besides it, one column's scratch.
    pub fn project_off_owned(&self, m: DMatrix<f64>) -> DMatrix<f64> {
        let d = &self.design;
        let rows = RowEntries::of(d, &self.rows);
        let once = self.project_off_columns_once(m, &rows);
        self.project_off_columns_once(once, &rows)
    }

    /// One pass of the projection over every column. The columns are independent: groups of
    /// them run on their own threads, each column's sums in the same order as alone.
    fn project_off_columns_once(&self, mut tilde: DMatrix<f64>, rows: &RowEntries) -> DMatrix<f64> {
        let n = self.rows.len();
        let (k, g, width) = (tilde.ncols(), self.design.n_global(), rows.width);
        if n == 0 || k == 0 {
            return tilde;
        }
        let threads = if n * k >= THREADED_PROJECTION_ENTRIES {
            parallel::threads(MAX_PROJECTION_THREADS)
        } else {
            1
        };
        let groups = parallel::balanced_groups(k, threads);
        // Off the points' columns, then each column's global sums Bᵀ ỹ.
        let mut t = DMatrix::<f64>::zeros(g, k);
        let parts: Vec<_> = split_lengths(tilde.as_mut_slice(), groups.iter().map(|c| c * n))
            .into_iter()
            .zip(split_lengths(
                t.as_mut_slice(),
                groups.iter().map(|c| c * g),
            ))
            .collect();
        in_parallel(parts, |(columns, ts)| {
            for (column, tc) in columns.chunks_mut(n).zip(ts.chunks_mut(g)) {
                self.project_off_points_slice(column, &rows.a);
                for (pos, &v) in column.iter().enumerate() {
                    let at = pos * width;
                    let row = at..at + width;
                    for (&c, &x) in rows.cols[row.clone()].iter().zip(&rows.vals[row]) {
                        tc[c] += x * v;
                    }
                }
            }
        });
        let z = &self.w_red * self.w_red.tr_mul(&t);
        // Off B̃ = (I − P_A) B.
        let z_groups = groups.iter().scan(z.as_slice(), |rest, &c| {
            let (group, tail) = rest.split_at(c * g);
            *rest = tail;
            Some(group)
        });
        let parts: Vec<_> = split_lengths(tilde.as_mut_slice(), groups.iter().map(|c| c * n))
            .into_iter()
            .zip(z_groups)
            .collect();
        in_parallel(parts, |(columns, zs)| {
            let mut vc = vec![0.0; n];
            for (column, zc) in columns.chunks_mut(n).zip(zs.chunks(g)) {
                for (pos, out) in vc.iter_mut().enumerate() {
                    let at = pos * width;
                    *out = (at..at + width)
                        .map(|e| rows.vals[e] * zc[rows.cols[e]])
                        .sum();
                }
                self.project_off_points_slice(&mut vc, &rows.a);
                for (y, v) in column.iter_mut().zip(&vc) {
                    *y -= v;
                }
            }
        });
        tilde
    }

    /// y ← (I − P_A) y for one column over the fit's rows (`a`: each row's point coefficients).
    fn project_off_points_slice(&self, y: &mut [f64], a: &[Vector3<f64>]) {
        for p in 0..self.design.n_points {
            let members = self.members(p);
            let q: Vector3<f64> = members.iter().map(|&pos| a[pos] * y[pos]).sum();
            let t = self.m_pinv[p] * q;
            for &pos in members {
                y[pos] -= a[pos].dot(&t);
            }
        }
    }

    /// Whether design row i (any row, unwhitened) lies in the row space of the fit: its part in
    /// the null space is at most 1e-12 of its squared norm (rounding leaves ~1e-12), as the
    /// dense test `|row|² − |Vᵀrow|²` did.
    pub fn in_row_space(&self, i: usize) -> bool {
        let d = &self.design;
        let r = &d.rows[i];
        let offset = 3 * d.n_points;
        let w = r.w;
        let mut entries = Vec::new();
        d.global_entries(i, &mut entries);
        let point = -r.u;
        let mut norm2 = point.norm_squared();
        for &(_, x) in &entries {
            norm2 += (x / w).powi(2);
        }
        let mut outside = 0.0;
        for z in 0..self.null_dense.ncols() {
            let col = self.null_dense.column(z);
            let mut dot = (0..3).map(|a| col[3 * r.point + a] * point[a]).sum::<f64>();
            for &(c, x) in &entries {
                dot += col[offset + c] * x / w;
            }
            outside += dot * dot;
        }
        for (p, v) in &self.point_null {
            if *p == r.point {
                outside += v.dot(&point).powi(2);
            }
        }
        outside <= 1e-12 * norm2
    }

    /// Σ_j b_j (a_j · t) over point p's rows of the fit: C_pᵀ t, dense over the global columns.
    fn ct_point(&self, p: usize, t: &Vector3<f64>, out: &mut DVector<f64>) {
        let d = &self.design;
        out.fill(0.0);
        let mut entries = Vec::new();
        for &pos in self.members(p) {
            let i = self.rows[pos];
            let at = d.a(i).dot(t);
            d.global_entries(i, &mut entries);
            for &(c, x) in &entries {
                out[c] += x * at;
            }
        }
    }

    /// Variance of the prediction row_i · x̂ (unwhitened rows, estimable ones: in the row
    /// space) under unit whitened noise: row N⁺ rowᵀ, by the blocks.
    pub fn prediction_variances(&self, held: &[usize]) -> Vec<f64> {
        let d = &self.design;
        let mut ct = DVector::zeros(d.n_global());
        held.iter()
            .map(|&i| {
                let r = &d.rows[i];
                let xp = -r.u;
                let t = self.m_pinv[r.point] * xp;
                self.ct_point(r.point, &t, &mut ct);
                let mut xg = d.global_dense(i) / r.w;
                xg -= &ct;
                xp.dot(&t) + self.w_red.tr_mul(&xg).norm_squared()
            })
            .collect()
    }

    /// The rows of U (the column space's orthonormal basis) in split form, for leverages and
    /// the change-point search: per point F_p = Wᵀ C_pᵀ M_p⁺ (reduced × 3).
    pub fn reduced(&self) -> Reduced {
        let d = &self.design;
        let (n, g, r) = (d.n_points, d.n_global(), self.w_red.ncols());
        let wt = self.w_red.transpose();
        let mut f = DMatrix::zeros(r, 3 * n);
        let mut entries = Vec::new();
        // C_pᵀ M_p⁺ (g × 3) of a chunk of points side by side, then one product by Wᵀ.
        for first in (0..n).step_by(REDUCED_CHUNK_POINTS) {
            let points = REDUCED_CHUNK_POINTS.min(n - first);
            let mut ct = DMatrix::zeros(g, 3 * points);
            for p in first..first + points {
                for &pos in self.members(p) {
                    let i = self.rows[pos];
                    let at = self.m_pinv[p] * d.a(i);
                    d.global_entries(i, &mut entries);
                    for &(c, x) in &entries {
                        for k in 0..3 {
                            ct[(c, 3 * (p - first) + k)] += x * at[k];
                        }
                    }
                }
            }
            f.columns_mut(3 * first, 3 * points).copy_from(&(&wt * ct));
        }
        Reduced { f, wt, dim: r }
    }

    /// Row i's coordinates in the column space: its point p and a_i, with ρ_i written into
    /// `rho` (the reduced system's dimension), such that
    /// |P_X v|² = Σ_p q_pᵀ M_p⁺ q_p + |Σ v_i ρ_i|², q_p = Σ_{i of p} v_i a_i. `entries` is
    /// scratch, so that a walk over the rows allocates nothing per row.
    pub fn row_parts(
        &self,
        red: &Reduced,
        i: usize,
        rho: &mut DVector<f64>,
        entries: &mut Vec<(usize, f64)>,
    ) -> (usize, Vector3<f64>) {
        let d = &self.design;
        let p = d.rows[i].point;
        let a = d.a(i);
        d.global_entries(i, entries);
        red.f_point(p).mul_to(&a, rho);
        rho.neg_mut();
        for &(c, x) in entries.iter() {
            rho.axpy(x, &red.wt.column(c), 1.0);
        }
        (p, a)
    }

    pub fn m_pinv(&self, p: usize) -> &Matrix3<f64> {
        &self.m_pinv[p]
    }

    /// The hat matrix on each set of design rows (each among the fit's rows): H_ij =
    /// a_iᵀ M_p⁺ a_j for two rows of point p, plus ρ_iᵀ ρ_j (`row_parts`).
    pub fn hat_rows(&self, sets: &[&[usize]]) -> Vec<HatRows> {
        let red = Arc::new(self.reduced());
        sets.iter()
            .map(|set| {
                let mut by_point: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
                for (k, &i) in set.iter().enumerate() {
                    by_point
                        .entry(self.design.rows[i].point)
                        .or_default()
                        .push(k);
                }
                let groups = by_point
                    .into_iter()
                    .map(|(p, positions)| {
                        let n = positions.len();
                        let a: Vec<Vector3<f64>> =
                            positions.iter().map(|&k| self.design.a(set[k])).collect();
                        let block =
                            DMatrix::from_fn(n, n, |x, y| a[x].dot(&(self.m_pinv[p] * a[y])));
                        (positions, block)
                    })
                    .collect();
                let low = ReducedRows {
                    design: self.design.clone(),
                    red: red.clone(),
                    set: set.to_vec(),
                };
                HatRows {
                    groups,
                    low: Box::new(low),
                }
            })
            .collect()
    }

    /// Diagonal of the hat matrix over the fit's rows (by position).
    pub fn leverages(&self) -> Vec<f64> {
        let red = self.reduced();
        let blocks: Vec<&[usize]> = self.rows.chunks(LEVERAGE_ROWS_AT_ONCE).collect();
        parallel::in_groups(&blocks, parallel::threads(MAX_PROJECTION_THREADS), |rows| {
            let (mut rho, mut entries) = (DVector::zeros(red.dim), Vec::new());
            rows.iter()
                .map(|&i| {
                    let (p, a) = self.row_parts(&red, i, &mut rho, &mut entries);
                    a.dot(&(self.m_pinv[p] * a)) + rho.norm_squared()
                })
                .collect::<Vec<f64>>()
        })
        .concat()
    }

    /// Entries (cols × cols, full parameter order) of the pseudo-inverse of the normal matrix:
    /// the covariance of those parameters under unit whitened noise.
    pub fn pinv_block(&self, cols: &[usize]) -> DMatrix<f64> {
        let np = self.design.n_params();
        // The unit vectors solved a group at a time (one walk over the rows per group), the
        // groups on the cores.
        let groups: Vec<&[usize]> = cols.chunks(PINV_SOLVED_TOGETHER).collect();
        let solved = parallel::in_groups(
            &groups,
            parallel::threads(MAX_PROJECTION_THREADS),
            |group| {
                let mut units = DMatrix::zeros(np, group.len());
                for (k, &c) in group.iter().enumerate() {
                    let mut e = DVector::zeros(np);
                    e[c] = 1.0;
                    self.remove_null(&mut e);
                    units.column_mut(k).copy_from(&e);
                }
                let x = self.normal_solve_columns(&units);
                DMatrix::from_fn(cols.len(), group.len(), |l, k| x[(cols[l], k)])
            },
        );
        let mut out = DMatrix::zeros(cols.len(), cols.len());
        let mut at = 0;
        for block in solved {
            out.columns_mut(at, block.ncols()).copy_from(&block);
            at += block.ncols();
        }
        out
    }

    /// For leave-one-station-out: the point parts of the held rows' prediction covariance,
    /// X_H N⁺ X_Hᵀ = blockdiag(A_H M⁺ A_Hᵀ) + F Fᵀ with F_i = Wᵀ C_pᵀ M_p⁺ a_i (whitened held
    /// rows restricted to their points' columns). F_i from point p's rows of this fit (C_pᵀ y
    /// = Σ b_j (a_j · y)), not from the reduced parts of every point; `wt`: Wᵀ
    /// ([`Schur::reduced_transpose`]).
    pub fn held_point_covariance(
        &self,
        wt: &DMatrix<f64>,
        i: usize,
    ) -> (Vector3<f64>, DVector<f64>) {
        let d = &self.design;
        let p = d.rows[i].point;
        let m_a = self.m_pinv[p] * d.a(i);
        let mut f = DVector::zeros(self.w_red.ncols());
        let mut entries = Vec::new();
        for &pos in self.members(p) {
            let j = self.rows[pos];
            let along = d.a(j).dot(&m_a);
            d.global_entries(j, &mut entries);
            for &(c, x) in &entries {
                f.axpy(x * along, &wt.column(c), 1.0);
            }
        }
        (m_a, f)
    }
}

/// A fit's rows' whitened coefficients gathered once: each row's point part, and its global
/// entries (stations, segment, effects: the same number for every row) flat.
struct RowEntries {
    a: Vec<Vector3<f64>>,
    width: usize,
    cols: Vec<usize>,
    vals: Vec<f64>,
}

impl RowEntries {
    fn of(design: &Design, rows: &[usize]) -> RowEntries {
        let width = 4 + design.effect_columns();
        let mut out = RowEntries {
            a: rows.iter().map(|&i| design.a(i)).collect(),
            width,
            cols: Vec::with_capacity(width * rows.len()),
            vals: Vec::with_capacity(width * rows.len()),
        };
        let mut entries = Vec::new();
        for &i in rows {
            design.global_entries(i, &mut entries);
            out.cols.extend(entries.iter().map(|e| e.0));
            out.vals.extend(entries.iter().map(|e| e.1));
        }
        out
    }
}

/// Per point F_p = Wᵀ C_pᵀ M_p⁺ of a fit (side by side: point p's are columns 3p..3p + 3),
/// and Wᵀ.
pub struct Reduced {
    f: DMatrix<f64>,
    wt: DMatrix<f64>,
    dim: usize,
}

impl Reduced {
    fn f_point(&self, p: usize) -> nalgebra::DMatrixView<'_, f64> {
        self.f.columns(3 * p, 3)
    }

    /// Rank of the reduced system (rows of each F_p).
    pub fn dim(&self) -> usize {
        self.dim
    }
}

/// The hat matrix's low-rank rows ρ_i (`Schur::row_parts`) of a set of design rows, made when
/// asked from the fit's reduced parts, which every fold shares.
struct ReducedRows {
    design: Arc<Design>,
    red: Arc<Reduced>,
    set: Vec<usize>,
}

impl LowRank for ReducedRows {
    fn row_count(&self) -> usize {
        self.set.len()
    }

    fn dim(&self) -> usize {
        self.red.dim
    }

    fn transposed_rows(&self, positions: &[usize]) -> DMatrix<f64> {
        let d = &self.design;
        let mut out = DMatrix::zeros(self.red.dim, positions.len());
        let mut entries = Vec::new();
        let k = self.red.dim;
        let (f, wt) = (self.red.f.as_slice(), self.red.wt.as_slice());
        // On contiguous slices: these loops vectorise, a view's iterators do not.
        for (rho, &pos) in out.as_mut_slice().chunks_exact_mut(k).zip(positions) {
            let i = self.set[pos];
            let (p, a) = (d.rows[i].point, d.a(i));
            let fp = &f[3 * p * k..(3 * p + 3) * k];
            let (f0, rest) = fp.split_at(k);
            let (f1, f2) = rest.split_at(k);
            for (((r, x0), x1), x2) in rho.iter_mut().zip(f0).zip(f1).zip(f2) {
                *r = -(x0 * a[0] + x1 * a[1] + x2 * a[2]);
            }
            d.global_entries(i, &mut entries);
            for &(c, x) in &entries {
                for (r, w) in rho.iter_mut().zip(&wt[c * k..(c + 1) * k]) {
                    *r += x * w;
                }
            }
        }
        out
    }
}

/// Gram–Schmidt (twice) of the columns; columns that vanish are dropped.
fn orthonormal_columns(m: DMatrix<f64>) -> DMatrix<f64> {
    let mut kept: Vec<DVector<f64>> = Vec::new();
    for c in 0..m.ncols() {
        let mut v = m.column(c).into_owned();
        let norm0 = v.norm();
        for _ in 0..2 {
            for q in &kept {
                let d = q.dot(&v);
                v -= q * d;
            }
        }
        let norm = v.norm();
        if norm > 1e-8 * norm0 && norm > 0.0 {
            kept.push(v / norm);
        }
    }
    DMatrix::from_fn(m.nrows(), kept.len(), |r, c| kept[c][r])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::diagnose::stats::{Basis, RANK_TOL};

    /// A small multilateration design: 6 stations around 30 points, one segment per station,
    /// one effect column, and a point seen from one station only (a rank-deficient block); with
    /// `tiny_effect` a second effect column ~1e-7 of the first.
    pub(super) fn small(tiny_effect: bool) -> Design {
        let stations = [
            Vector3::new(-1.0, -1.0, 0.2),
            Vector3::new(2.5, -0.8, 0.6),
            Vector3::new(2.2, 3.1, -0.3),
            Vector3::new(-0.9, 2.8, 1.1),
            Vector3::new(0.6, -1.5, 1.6),
            Vector3::new(0.7, 3.6, 0.9),
        ];
        let points: Vec<Vector3<f64>> = (0..30)
            .map(|k| {
                Vector3::new(
                    0.05 * k as f64,
                    0.3 + 0.17 * (k % 5) as f64,
                    0.2 * (k % 3) as f64 + 0.03 * (k % 7) as f64,
                )
            })
            .collect();
        let mut rows = Vec::new();
        for (p, x) in points.iter().enumerate() {
            for (s, st) in stations.iter().enumerate() {
                if p == 29 && s > 0 {
                    continue;
                }
                let v = st - x;
                rows.push(Row {
                    point: p,
                    station: s,
                    segment: s,
                    u: v / v.norm(),
                    w: 1.0 / (5e-8 * (1.0 + 0.1 * ((p + s) % 3) as f64)),
                });
            }
        }
        let effects = DMatrix::from_fn(rows.len(), 1 + usize::from(tiny_effect), |i, c| match c {
            0 => 0.5 * rows[i].u.x * ((i % 7) as f64 - 3.0) / 3.0,
            _ => 1e-7 * ((i * 13 % 17) as f64 - 8.0) / 8.0,
        });
        Design {
            n_points: points.len(),
            n_stations: stations.len(),
            n_segments: stations.len(),
            rows,
            effects: Vec::new(),
        }
        .with_effects(effects)
    }

    #[test]
    fn blocks_match_the_dense_svd() {
        let design = Arc::new(small(false));
        // The pseudo-inverse block of the effect column and a station coordinate.
        let cols = [design.n_params() - 1, 3 * 30 + 4];
        check_against_the_dense_svd(design, true, &cols);
    }

    /// An effect column ~1e-7 of the stations' in the whitened design, like air refraction's
    /// (dn·L): a rank cut that depends on the columns' units drops it. With parameters whose
    /// units differ by 1e7 the minimum-norm solution's gauge part is fixed only to ~1e-8 of its
    /// largest entry by either algebra, so the solve is compared on its fitted values and the
    /// pseudo-inverse on the effects' (estimable) block.
    #[test]
    fn blocks_match_the_dense_svd_with_a_tiny_effect_column() {
        let design = Arc::new(small(true));
        let cols = [design.n_params() - 2, design.n_params() - 1];
        check_against_the_dense_svd(design, false, &cols);
    }

    /// The columns solved together are each solved alone (points', stations' and the
    /// effect's coordinates, and a mixed right-hand side).
    #[test]
    fn normal_equations_solved_together_equal_each_alone() {
        let design = Arc::new(small(false));
        let all: Vec<usize> = (0..design.lengths()).collect();
        let fit = Schur::new(design.clone(), all);
        let np = design.n_params();
        let v = DMatrix::from_fn(np, 4, |r, c| match c {
            0 => f64::from(u8::from(r == 5)),
            1 => f64::from(u8::from(r == 3 * 30 + 4)),
            2 => f64::from(u8::from(r == np - 1)),
            _ => ((r * 7 % 13) as f64 - 6.0) * 0.1,
        });
        let together = fit.normal_solve_columns(&v);
        for c in 0..v.ncols() {
            let alone = fit.normal_solve(&v.column(c).into_owned());
            let gap = (together.column(c) - &alone).amax();
            assert!(gap <= 1e-12 * alone.amax(), "column {c}: {gap:e}");
        }
        // Least squares likewise: lengths-long right-hand sides.
        let y = DMatrix::from_fn(design.lengths(), 3, |r, c| {
            ((r * (c + 3) % 11) as f64 - 5.0) * 0.2
        });
        let together = fit.solve_columns(&y);
        for c in 0..y.ncols() {
            let alone = fit.solve(&y.column(c).into_owned());
            let gap = (together.column(c) - &alone).amax();
            assert!(
                gap <= 1e-12 * alone.amax(),
                "least squares column {c}: {gap:e}"
            );
        }
    }

    /// Effect columns held by rows (a per-station effect's few entries, and a block times a
    /// right factor) beside a dense block give the design the same columns held dense: the
    /// same dense design, predictions and least-squares solution.
    #[test]
    fn effect_blocks_by_rows_equal_the_dense_columns() {
        use crate::diagnose::columns::RowSparse;
        let dense = small(false);
        let n = dense.lengths();
        let mut per_station = RowSparse::new(3 * dense.n_stations, n, 1);
        let mut turned = RowSparse::new(2, n, 2);
        for i in 0..n {
            let s = dense.station_of(i);
            let t = 1e-3 * (i % 5) as f64;
            per_station.push_row([(3 * s + i % 3, t)]);
            turned.push_row([(0, t), (1, -0.5 * t)]);
        }
        let right = DMatrix::from_row_slice(2, 3, &[1.0, 0.5, 0.0, -0.25, 2.0, 1.0]);
        let turned = turned.with_right(right);
        let blocks = vec![
            Columns::Dense(
                dense
                    .to_dense()
                    .columns(dense.n_params() - 1, 1)
                    .into_owned(),
            ),
            Columns::Sparse(per_station.clone()),
            Columns::Sparse(turned.clone()),
        ];
        let held = Design {
            effects: Vec::new(),
            ..dense.clone()
        };
        let by_rows = held.with_effect_blocks(blocks.clone());
        let all_dense = held.with_effects(
            blocks
                .into_iter()
                .map(Columns::into_dense)
                .reduce(|a, b| crate::kinds::tracer_plan::diagnosis::hcat(&a, &b))
                .expect("blocks"),
        );
        assert_eq!(by_rows.effect_columns(), 1 + 3 * 6 + 3);
        assert_eq!(by_rows.to_dense(), all_dense.to_dense());
        let x = DVector::from_fn(by_rows.n_params(), |r, _| ((r * 7 % 13) as f64 - 6.0) * 0.1);
        let y = DVector::from_fn(n, |r, _| ((r * 5 % 11) as f64 - 5.0) * 0.2);
        for i in 0..n {
            assert_eq!(by_rows.predict(i, &x), all_dense.predict(i, &x), "row {i}");
        }
        let all: Vec<usize> = (0..n).collect();
        let a = Schur::new(Arc::new(by_rows), all.clone()).solve(&y);
        let b = Schur::new(Arc::new(all_dense), all).solve(&y);
        assert_eq!(a, b);
    }

    /// The hat rows of a fold (one station's lengths of every sixth point, like a
    /// cross-validation fold) are the dense hat matrix's block, and the fold's downdated
    /// held-out residuals and prediction variances are the structured refit's.
    #[test]
    fn a_folds_hat_rows_and_downdate_match_the_refit() {
        use crate::diagnose::downdate::FoldDowndate;
        let design = Arc::new(small(false));
        let n = design.lengths();
        let all: Vec<usize> = (0..n).collect();
        let held: Vec<usize> = all
            .iter()
            .copied()
            .filter(|&i| (design.point_of(i) + design.station_of(i)) % 6 == 1)
            .collect();
        let full = Schur::new(design.clone(), all.clone());
        let Some(hat) = full.hat_rows(&[&held]).pop() else {
            panic!("one set, one hat");
        };
        let dense = design.to_dense();
        let xw = DMatrix::from_fn(n, dense.ncols(), |r, c| dense[(r, c)] * design.weight(r));
        let u = Basis::new(&xw, RANK_TOL, 0.0).u;
        let all_held: Vec<usize> = (0..held.len()).collect();
        let lt = hat.low.transposed_rows(&all_held);
        let mut assembled = lt.tr_mul(&lt);
        for (positions, block) in &hat.groups {
            for (x, &px) in positions.iter().enumerate() {
                for (y, &py) in positions.iter().enumerate() {
                    assembled[(px, py)] += block[(x, y)];
                }
            }
        }
        let want = u.select_rows(&held) * u.select_rows(&held).transpose();
        assert!(
            (&assembled - &want).amax() <= 1e-10,
            "{assembled} vs {want}"
        );

        let y = DVector::from_fn(n, |k, _| ((k * 37 % 11) as f64 - 5.0) * 0.3);
        let e = full.project_off_vec(&y);
        let Some(fold) = FoldDowndate::new(hat) else {
            panic!("the fold keeps every direction");
        };
        let got = fold.residuals(&e.select_rows(&held));
        let train: Vec<usize> = all.iter().copied().filter(|i| !held.contains(i)).collect();
        let refit = Schur::new(design.clone(), train.clone());
        let beta = refit.solve(&y.select_rows(&train));
        let variances = refit.prediction_variances(&held);
        for (k, &h) in held.iter().enumerate() {
            let w = design.weight(h);
            let predicted = y[h] - w * design.predict(h, &beta);
            assert!(
                (got[k] - predicted).abs() <= 1e-9,
                "row {h}: {} vs {predicted}",
                got[k]
            );
            let variance = (fold.inflation()[k] - 1.0) / (w * w);
            assert!(
                (variance - variances[k]).abs() <= 1e-9 * variances[k],
                "row {h}: {variance} vs {}",
                variances[k]
            );
        }
    }

    fn check_against_the_dense_svd(design: Arc<Design>, min_norm: bool, pinv_cols: &[usize]) {
        let n = design.lengths();
        let w = DVector::from_fn(n, |i, _| design.weight(i));
        let dense = design.to_dense();
        // Train on all rows but every fifth; check projections, solves, leverages, variances.
        let train: Vec<usize> = (0..n).filter(|i| i % 5 != 2).collect();
        let held: Vec<usize> = (0..n).filter(|i| i % 5 == 2).collect();
        let xw = DMatrix::from_fn(train.len(), dense.ncols(), |r, c| {
            dense[(train[r], c)] * w[train[r]]
        });
        let basis = Basis::new(&xw, RANK_TOL, 0.0);
        let fit = Schur::new(design.clone(), train.clone());
        assert_eq!(fit.rank(), basis.rank());
        let y = DVector::from_fn(train.len(), |k, _| ((k * 37 % 11) as f64 - 5.0) * 0.3);
        let close = |a: &DVector<f64>, b: &DVector<f64>, what: &str| {
            let scale = a.amax().max(b.amax());
            assert!((a - b).amax() <= 1e-9 * scale, "{what}: {a} vs {b}");
        };
        close(
            &fit.project_off_vec(&y),
            &basis.project_off_vec(&y),
            "projection",
        );
        let (x, dense_x) = (fit.solve(&y), basis.solve(&y));
        if min_norm {
            close(&x, &dense_x, "minimum-norm solve");
        }
        close(
            &fit.times_columns(&DMatrix::from_column_slice(x.len(), 1, x.as_slice()))
                .column(0)
                .into_owned(),
            &(&xw * &dense_x),
            "fitted values",
        );
        let lev = DVector::from_vec(fit.leverages());
        close(&lev, &DVector::from_vec(basis.leverages()), "leverages");
        for &h in &held {
            let row: Vec<f64> = dense.row(h).iter().copied().collect();
            let r = DVector::from_vec(row.clone());
            let inside = &basis.vt * &r;
            let dense_in = r.norm_squared() - inside.norm_squared() <= 1e-12 * r.norm_squared();
            assert_eq!(fit.in_row_space(h), dense_in, "row {h}");
            if dense_in {
                let v = fit.prediction_variances(&[h])[0];
                let dv = basis.prediction_variance(&row);
                assert!(
                    (v - dv).abs() <= 1e-9 * dv,
                    "variance of row {h}: {v} vs {dv}"
                );
            }
        }
        let cols = pinv_cols;
        let block = fit.pinv_block(cols);
        for (a, &ca) in cols.iter().enumerate() {
            for (b, &cb) in cols.iter().enumerate() {
                let d: f64 = (0..basis.rank())
                    .map(|k| basis.vt[(k, ca)] * basis.vt[(k, cb)] / basis.s[k].powi(2))
                    .sum();
                assert!(
                    (block[(a, b)] - d).abs() <= 1e-9 * d.abs().max(block[(a, a)]),
                    "pinv {ca},{cb}: {} vs {d}",
                    block[(a, b)]
                );
            }
        }
    }
}
