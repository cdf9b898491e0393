//! Statistics and dense linear algebra for the diagnosis: chi-square tail probabilities,
//! orthonormal bases with a rank cut, projections and pseudo-inverse solves.

use nalgebra::{DMatrix, DVector};

use crate::parallel;

/// Relative singular value below which a direction counts as not identifiable (gauge,
/// collinear columns). Rounding in the SVD of the whitened designs is about 1e-15 of the
/// largest singular value times the condition of the real directions (< 1e4 here).
pub const RANK_TOL: f64 = 1e-9;
/// A candidate effect's direction whose part off the current model is smaller than this
/// fraction of the effect's own (whitened) column norm is one the model absorbs (e.g. the
/// vertical eccentricity = station height; a common shift of a target = the gauge's).
pub const EFFECT_RANK_TOL: f64 = 1e-6;

pub use crate::solve::chi2::{chi2_sf, gamma_q, ln_gamma};

/// The x with P(χ²(dof) > x) = p (bisection on the survival function).
pub fn chi2_isf(p: f64, dof: f64) -> f64 {
    let (mut lo, mut hi) = (0.0, dof.max(1.0));
    while chi2_sf(hi, dof) > p && hi < 1e12 {
        hi *= 2.0;
    }
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if chi2_sf(mid, dof) > p {
            lo = mid;
        } else {
            hi = mid;
        }
        if hi - lo <= 1e-12 * hi {
            break;
        }
    }
    0.5 * (lo + hi)
}

/// Regularised incomplete beta I_x(a, b) (continued fraction, Lentz).
pub fn beta_i(a: f64, b: f64, x: f64) -> f64 {
    if x <= 0.0 {
        return 0.0;
    }
    if x >= 1.0 {
        return 1.0;
    }
    let ln_front = ln_gamma(a + b) - ln_gamma(a) - ln_gamma(b) + a * x.ln() + b * (1.0 - x).ln();
    // The fraction converges fast for x < (a + 1)/(a + b + 2); use the symmetry otherwise.
    if x > (a + 1.0) / (a + b + 2.0) {
        return 1.0 - beta_i(b, a, 1.0 - x);
    }
    let tiny = 1e-300;
    let (qab, qap, qam) = (a + b, a + 1.0, a - 1.0);
    let mut c = 1.0;
    let mut d = 1.0 - qab * x / qap;
    if d.abs() < tiny {
        d = tiny;
    }
    d = 1.0 / d;
    let mut h = d;
    for m in 1..1000 {
        let m = m as f64;
        let m2 = 2.0 * m;
        for aa in [
            m * (b - m) * x / ((qam + m2) * (a + m2)),
            -(a + m) * (qab + m) * x / ((a + m2) * (qap + m2)),
        ] {
            d = 1.0 + aa * d;
            if d.abs() < tiny {
                d = tiny;
            }
            c = 1.0 + aa / c;
            if c.abs() < tiny {
                c = tiny;
            }
            d = 1.0 / d;
            h *= d * c;
        }
        if (d * c - 1.0).abs() < 1e-15 {
            break;
        }
    }
    (ln_front.exp() * h / a).clamp(0.0, 1.0)
}

/// P(F(d1, d2) > f).
pub fn f_sf(f: f64, d1: f64, d2: f64) -> f64 {
    if f <= 0.0 {
        return 1.0;
    }
    beta_i(0.5 * d2, 0.5 * d1, d2 / (d2 + d1 * f))
}

/// A thin SVD with the directions above the rank cut: U (n×r), singular values, Vᵀ (r×p).
pub struct Basis {
    pub u: DMatrix<f64>,
    pub s: DVector<f64>,
    pub vt: DMatrix<f64>,
}

impl Basis {
    pub fn rank(&self) -> usize {
        self.s.len()
    }

    /// Directions with singular value > tol · max(reference, largest singular value).
    pub fn new(a: &DMatrix<f64>, tol: f64, reference: f64) -> Basis {
        let (n, p) = a.shape();
        if n == 0 || p == 0 {
            return Basis {
                u: DMatrix::zeros(n, 0),
                s: DVector::zeros(0),
                vt: DMatrix::zeros(0, p),
            };
        }
        Basis::from_svd(accurate_svd(a), n, p, tol, reference)
    }

    /// The directions of `svd` (of an n × p matrix) kept by the rule of [`Basis::new`].
    pub fn from_svd(
        svd: nalgebra::SVD<f64, nalgebra::Dyn, nalgebra::Dyn>,
        n: usize,
        p: usize,
        tol: f64,
        reference: f64,
    ) -> Basis {
        let (Some(u), Some(vt)) = (svd.u, svd.v_t) else {
            return Basis {
                u: DMatrix::zeros(n, 0),
                s: DVector::zeros(0),
                vt: DMatrix::zeros(0, p),
            };
        };
        let smax = svd.singular_values.max().max(reference);
        let keep: Vec<usize> = (0..svd.singular_values.len())
            .filter(|&k| svd.singular_values[k] > tol * smax && smax > 0.0)
            .collect();
        Basis {
            u: DMatrix::from_fn(n, keep.len(), |i, k| u[(i, keep[k])]),
            s: DVector::from_fn(keep.len(), |k, _| svd.singular_values[keep[k]]),
            vt: DMatrix::from_fn(keep.len(), p, |k, j| vt[(keep[k], j)]),
        }
    }

    /// Least-squares minimum-norm solution x of a x ≈ b.
    pub fn solve(&self, b: &DVector<f64>) -> DVector<f64> {
        let utb = self.u.transpose() * b;
        let scaled = DVector::from_fn(self.rank(), |k, _| utb[k] / self.s[k]);
        self.vt.transpose() * scaled
    }

    /// Remove the component of each column of `m` in span(U).
    pub fn project_off(&self, m: &DMatrix<f64>) -> DMatrix<f64> {
        m - &self.u * (self.u.transpose() * m)
    }

    pub fn project_off_vec(&self, v: &DVector<f64>) -> DVector<f64> {
        v - &self.u * (self.u.transpose() * v)
    }

    /// Variance of the prediction row·x under unit whitened noise: |S⁻¹ V row|².
    pub fn prediction_variance(&self, row: &[f64]) -> f64 {
        let mut sum = 0.0;
        for k in 0..self.rank() {
            let mut dot = 0.0;
            for (j, r) in row.iter().enumerate() {
                dot += self.vt[(k, j)] * r;
            }
            sum += (dot / self.s[k]).powi(2);
        }
        sum
    }

    /// Diagonal of the hat matrix U Uᵀ (leverages).
    pub fn leverages(&self) -> Vec<f64> {
        (0..self.u.nrows())
            .map(|i| self.u.row(i).norm_squared())
            .collect()
    }
}

/// Eigenvalues of a Gram matrix AᵀA below this fraction of its largest are rounding (its sums
/// over the rows leave ~k ε of the largest): directions there have no singular value of A.
const GRAM_ROUNDING: f64 = 1e-14;
/// Smallest kept eigenvalue of a Gram matrix, relative to its largest, for which the Gram
/// route is as accurate as the SVD: the normal equations square the condition number, so a
/// kept direction at 1e-5 of the largest (singular values 3e-3) is resolved to ~2e-11.
const GRAM_CONDITION: f64 = 1e-5;

/// Threads the Gram matrix's blocks of rows run on.
const MAX_GRAM_THREADS: usize = 2;

/// The right factor (singular values and Vᵀ, the directions above the rank cut as
/// `Basis::new` keeps them) of a tall n × k matrix `a`, given a block of its rows at a time
/// (`block(start, len)`), from the eigen-decomposition of its k × k Gram matrix, in time n k²
/// without the n × k orthonormal factor. None when some direction is
/// between the Gram's rounding and its accurate range (an effect the model nearly absorbs): the
/// caller then takes the SVD.
pub fn gram_factor(
    shape: (usize, usize),
    block: &(dyn Fn(usize, usize) -> DMatrix<f64> + Sync),
    tol: f64,
    reference: f64,
) -> Option<(DVector<f64>, DMatrix<f64>)> {
    factor_gram(
        block_products(shape, block, None).0,
        shape.0,
        tol,
        reference,
    )
}

/// AᵀA and Aᵀb of a tall n × k matrix A given a block of its rows at a time, in one walk over
/// the rows.
pub fn gram_and_cross(
    shape: (usize, usize),
    block: &(dyn Fn(usize, usize) -> DMatrix<f64> + Sync),
    b: &DVector<f64>,
) -> (DMatrix<f64>, DVector<f64>) {
    block_products(shape, block, Some(b))
}

/// AᵀA, and Aᵀb when `b` is given (else an empty vector). The blocks' products run in the
/// blocked matrix multiplication, the blocks on the cores, their products summed in the
/// blocks' order (the same sums on any number of cores).
fn block_products(
    (n, k): (usize, usize),
    block: &(dyn Fn(usize, usize) -> DMatrix<f64> + Sync),
    b: Option<&DVector<f64>>,
) -> (DMatrix<f64>, DVector<f64>) {
    const BLOCK: usize = 2048;
    let starts: Vec<usize> = (0..n).step_by(BLOCK).collect();
    let parts = parallel::in_groups(&starts, parallel::threads(MAX_GRAM_THREADS), |&start| {
        let len = BLOCK.min(n - start);
        let block = block(start, len);
        let cross = b.map_or_else(|| DVector::zeros(0), |b| block.tr_mul(&b.rows(start, len)));
        (block.tr_mul(&block), cross)
    });
    let mut gram = DMatrix::<f64>::zeros(k, k);
    let mut cross = DVector::<f64>::zeros(if b.is_some() { k } else { 0 });
    for (g, c) in parts {
        gram += g;
        cross += c;
    }
    (gram, cross)
}

/// The right factor of a matrix of `rows` rows from its Gram matrix (`gram_factor`); None
/// when the Gram route is not accurate enough for it.
pub fn factor_gram(
    g: DMatrix<f64>,
    rows: usize,
    tol: f64,
    reference: f64,
) -> Option<(DVector<f64>, DMatrix<f64>)> {
    let k = g.ncols();
    if rows == 0 || k == 0 {
        return Some((DVector::zeros(0), DMatrix::zeros(0, k)));
    }
    let g = DMatrix::from_fn(k, k, |r, c| 0.5 * (g[(r, c)] + g[(c, r)]));
    let eig = g.symmetric_eigen();
    let top = eig.eigenvalues.iter().copied().fold(0.0, f64::max);
    let smax = top.sqrt().max(reference);
    let cut = tol * smax;
    let mut keep = Vec::new();
    for (j, &l) in eig.eigenvalues.iter().enumerate() {
        if l <= GRAM_ROUNDING * top {
            // Rounding: the true singular value is below √(2 · rounding), which must be
            // well under the cut to call it null.
            if cut * cut <= 2.0 * GRAM_ROUNDING * top {
                return None;
            }
        } else if l >= GRAM_CONDITION * top {
            if l.sqrt() > cut && smax > 0.0 {
                keep.push(j);
            }
        } else {
            return None;
        }
    }
    // Largest first, as the SVD orders them.
    keep.sort_by(|&x, &y| eig.eigenvalues[y].total_cmp(&eig.eigenvalues[x]));
    let s = DVector::from_fn(keep.len(), |r, _| eig.eigenvalues[keep[r]].sqrt());
    let vt = DMatrix::from_fn(keep.len(), k, |r, c| eig.eigenvectors[(c, keep[r])]);
    Some((s, vt))
}

/// Singular values and right vectors (Vᵀ) of a tall `a` (n × k, n ≫ k, given a block of its
/// rows at a time), the directions above the rank cut as [`Basis::new`] keeps them, from the
/// SVD of the triangular factor R of its Householder QR. R is taken block of rows by block of
/// rows (the R of [R so far; the next rows]): as backward stable as the SVD of the whole
/// matrix, with one block in memory.
pub fn qr_right_factor(
    (n, k): (usize, usize),
    block: &(dyn Fn(usize, usize) -> DMatrix<f64> + Sync),
    tol: f64,
    reference: f64,
) -> (DVector<f64>, DMatrix<f64>) {
    const BLOCK: usize = 4096;
    if n == 0 || k == 0 {
        return (DVector::zeros(0), DMatrix::zeros(0, k));
    }
    let mut r = DMatrix::<f64>::zeros(0, k);
    let mut start = 0;
    while start < n {
        let len = BLOCK.min(n - start);
        let mut stacked = DMatrix::zeros(r.nrows() + len, k);
        stacked.rows_mut(0, r.nrows()).copy_from(&r);
        stacked
            .rows_mut(r.nrows(), len)
            .copy_from(&block(start, len));
        r = stacked.qr().r();
        start += len;
    }
    let basis = Basis::new(&r, tol, reference);
    (basis.s, basis.vt)
}

/// Convergence tolerances of the SVD's bidiagonal iteration, tried in turn. nalgebra's
/// default (5 ε, with an absolute test on the bidiagonal scaled to its largest entry) stops
/// early on rank-deficient designs (the gauge's null directions): U S Vᵀ then misses the matrix
/// by ~1e-8 of its largest entry and least-squares solutions by up to 1e-4 (nalgebra issue
/// #1172). A tolerance below ε runs to rounding, but no single one is safe: on one 270-length
/// design 1e-17 returned U S Vᵀ off by 6e5 of 2e8 while 1e-16 and 1e-18 were exact.
const SVD_TOLERANCES: [f64; 5] = [1e-18, 1e-16, 1e-20, 1e-15, 1e-17];
/// Largest entry of U S Vᵀ − A, relative to A's largest, of an SVD taken as converged
/// (rounding leaves ~1e-14; nalgebra's early stop ~1e-8).
const SVD_RECONSTRUCTION: f64 = 1e-12;

/// The thin SVD, checked: the first of `SVD_TOLERANCES` whose U S Vᵀ reproduces `a` to
/// `SVD_RECONSTRUCTION`; the best of them should none (never seen).
pub fn accurate_svd(a: &DMatrix<f64>) -> nalgebra::SVD<f64, nalgebra::Dyn, nalgebra::Dyn> {
    let max_iterations = 1000 + 100 * a.nrows().min(a.ncols());
    let scale = a.amax();
    let mut best: Option<(f64, nalgebra::SVD<f64, nalgebra::Dyn, nalgebra::Dyn>)> = None;
    for eps in SVD_TOLERANCES {
        let Some(svd) = a.clone().try_svd(true, true, eps, max_iterations) else {
            continue;
        };
        let error = match (&svd.u, &svd.v_t) {
            (Some(u), Some(vt)) => {
                let mut us = u.clone();
                for (k, mut column) in us.column_iter_mut().enumerate() {
                    column *= svd.singular_values[k];
                }
                (us * vt - a).amax()
            }
            _ => f64::INFINITY,
        };
        if error <= SVD_RECONSTRUCTION * scale {
            return svd;
        }
        if best.as_ref().is_none_or(|(e, _)| error < *e) {
            best = Some((error, svd));
        }
    }
    best.map_or_else(|| a.clone().svd(true, true), |(_, svd)| svd)
}

/// Largest cosine of the principal angles between span(a) and span(b) (orthonormal columns).
pub fn max_principal_cosine(a: &DMatrix<f64>, b: &DMatrix<f64>) -> f64 {
    if a.ncols() == 0 || b.ncols() == 0 {
        return 0.0;
    }
    let m = a.transpose() * b;
    m.svd(false, false).singular_values.max().min(1.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A dense matrix's blocks of rows.
    fn blocks_of(a: &DMatrix<f64>) -> impl Fn(usize, usize) -> DMatrix<f64> + Sync + '_ {
        |start, len| a.rows(start, len).into_owned()
    }

    #[test]
    fn chi2_tail_matches_known_values() {
        // Quantiles from tables: χ²(1) 3.841 -> 0.05, χ²(10) 23.209 -> 0.01, χ²(2) exp(-x/2).
        assert!((chi2_sf(3.841_459, 1.0) - 0.05).abs() < 1e-6);
        assert!((chi2_sf(23.209_251, 10.0) - 0.01).abs() < 1e-6);
        assert!((chi2_sf(40.0, 2.0) - (-20.0f64).exp()).abs() < 1e-18);
        assert!((chi2_sf(100.0, 100.0) - 0.481_191).abs() < 1e-5);
        assert!((ln_gamma(5.0) - 24f64.ln()).abs() < 1e-13);
        // F quantiles: F(1, 100) 6.895 -> 0.01, F(3, 50) 2.790 -> 0.05.
        assert!((f_sf(6.895_2, 1.0, 100.0) - 0.01).abs() < 1e-4);
        assert!((f_sf(2.790_0, 3.0, 50.0) - 0.05).abs() < 1e-4);
    }

    /// A tall matrix with columns of different scales and one column a combination of
    /// two others: the Gram route keeps the SVD's directions (same rank, singular values and
    /// projector V Vᵀ); with a direction at 1e-4 of the largest singular value (Gram
    /// eigenvalue 1e-8, outside its accurate range) it declines, for the SVD to decide.
    #[test]
    fn gram_factor_matches_the_svd_or_declines() {
        let n = 5000;
        let column = |i: usize, c: usize| -> f64 {
            let x = i as f64 / n as f64;
            match c {
                0 => (7.0 * x).sin(),
                1 => 0.03 * (3.0 * x).cos() + 0.03 * x * x,
                2 => 2.0 * (7.0 * x).sin() - 3.0 * (0.03 * (3.0 * x).cos() + 0.03 * x * x),
                _ => ((i * 7919 % 101) as f64 - 50.0) / 50.0,
            }
        };
        let a = DMatrix::from_fn(n, 4, column);
        let reference = (0..4).map(|c| a.column(c).norm()).fold(0.0, f64::max);
        let (s, vt) = gram_factor(a.shape(), &blocks_of(&a), EFFECT_RANK_TOL, reference)
            .expect("well conditioned");
        let basis = Basis::new(&a, EFFECT_RANK_TOL, reference);
        assert_eq!(s.len(), 3);
        assert_eq!(basis.rank(), 3);
        for (gram, svd) in s.iter().zip(basis.s.iter()) {
            assert!(
                (gram - svd).abs() <= 1e-11 * basis.s[0],
                "{s} vs {}",
                basis.s
            );
        }
        let projector = vt.transpose() * &vt;
        let svd_projector = basis.vt.transpose() * &basis.vt;
        assert!((projector - svd_projector).amax() <= 1e-10);
        // Column 1 nearly a multiple of column 0: its part off column 0 is 1e-4 of it.
        let b = DMatrix::from_fn(n, 2, |i, c| match c {
            0 => (7.0 * i as f64 / n as f64).sin(),
            _ => (7.0 * i as f64 / n as f64).sin() + 1e-4 * column(i, 3),
        });
        assert!(gram_factor(
            b.shape(),
            &blocks_of(&b),
            EFFECT_RANK_TOL,
            b.column(0).norm()
        )
        .is_none());
        // There the QR route keeps the SVD's directions: singular values, V Vᵀ, and with
        // U = B V S⁻¹ the fitted values U Uᵀ y and Uᵀ y.
        let (s, vt) = qr_right_factor(
            b.shape(),
            &blocks_of(&b),
            EFFECT_RANK_TOL,
            b.column(0).norm(),
        );
        let svd = Basis::new(&b, EFFECT_RANK_TOL, b.column(0).norm());
        assert_eq!(s.len(), 2);
        assert_eq!(svd.rank(), 2);
        assert!((&s - &svd.s).amax() <= 1e-12 * svd.s[0], "{s} vs {}", svd.s);
        let projector = vt.transpose() * &vt;
        assert!((projector - svd.vt.transpose() * &svd.vt).amax() <= 1e-10);
        let y = DVector::from_fn(n, |i, _| column(i, 3) + (5.0 * i as f64 / n as f64).cos());
        // Both are backward stable; U from B's columns loses orthogonality by rounding times
        // the condition.
        let condition = svd.s[0] / svd.s[1];
        let tol = 1e-14 * condition * y.norm();
        let u = &b * DMatrix::from_fn(2, 2, |c, k| vt[(k, c)] / s[k]);
        let svd_ut = svd.u.tr_mul(&y);
        let gap = (&u * u.tr_mul(&y) - &svd.u * &svd_ut).amax();
        assert!(
            gap <= tol,
            "fitted values {gap:e} apart (tolerance {tol:e})"
        );
        assert!((u.tr_mul(&y).norm() - svd_ut.norm()).abs() <= tol);
        assert!((u.tr_mul(&u) - DMatrix::identity(2, 2)).amax() <= 1e-14 * condition);
        // Blocks of rows: a matrix over several of them, with a zero column, keeps the SVD's
        // singular values.
        let tall = DMatrix::from_fn(10_000, 3, |i, c| match c {
            1 => 0.0,
            _ => column(i, c) + (c as f64 * i as f64 / 10_000.0).sin(),
        });
        let (s, _) = qr_right_factor(
            tall.shape(),
            &blocks_of(&tall),
            EFFECT_RANK_TOL,
            tall.column(0).norm(),
        );
        let svd = Basis::new(&tall, EFFECT_RANK_TOL, tall.column(0).norm());
        assert_eq!(s.len(), svd.rank());
        assert!((&s - &svd.s).amax() <= 1e-12 * svd.s[0], "{s} vs {}", svd.s);
    }
}
