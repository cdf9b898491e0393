//! A cross-validation fold's held-out residuals from the fit on all rows, without refitting on
//! the fold's training rows. For least squares with hat matrix H, the residuals of held rows k
//! predicted from the other rows are (I − H_kk)⁻¹ e_k (e: the residuals of the fit on all
//! rows), and the variance of those predictions under unit noise is diag((I − H_kk)⁻¹) − 1.
//! Where the hat matrix is block diagonal plus low rank on the held rows (H_kk = B + L Lᵀ: a
//! point's own block and the reduced system's part), I − H_kk = D − L Lᵀ with D = I − B is
//! inverted by Woodbury: (D − L Lᵀ)⁻¹ = D⁻¹ + D⁻¹L K⁻¹ LᵀD⁻¹, K = I − LᵀD⁻¹L. A candidate
//! effect adds its projected columns' orthonormal basis U to L. The two are invertible exactly
//! when the training rows determine what all rows do (the same rank); where they are not
//! (or nearly not) the caller refits.

use nalgebra::{DMatrix, DVector};

use crate::parallel::position_blocks;

/// Smallest eigenvalue of D and of K (their eigenvalues lie in (0, 1]: the share of a
/// direction's information the training rows keep) for which the fold is downdated; below it
/// the fold is refitted, so that a direction the training rows nearly lose is decided by the
/// refit's own rank cut. The Woodbury inverse's rounding grows as 1 / that eigenvalue: 1e-8
/// keeps it ~1e-8 relative at worst, ~1e-13 for this problem's folds (eigenvalues ≳ 0.5).
const MIN_KEPT_INFORMATION: f64 = 1e-8;

/// The hat matrix of a fit on a set of its rows: H = blockdiag(groups' blocks) + L Lᵀ.
pub struct HatRows {
    /// Positions (in the set) of each group, with its block of H minus L Lᵀ.
    pub groups: Vec<(Vec<usize>, DMatrix<f64>)>,
    /// L: one row per position.
    pub low: Box<dyn LowRank>,
}

/// The low-rank part L of a hat matrix over a set of rows (one row per position): held as a
/// matrix, or made a few rows at a time from a form the fit shares between its folds, so that
/// a fold does not hold a row of the reduced system's width for each of its rows.
pub trait LowRank: Send + Sync {
    /// Rows (positions).
    fn row_count(&self) -> usize;
    /// Columns (the rank of the low-rank part).
    fn dim(&self) -> usize;
    /// Lᵀ's columns at `positions`, in that order (dim × positions: each row of L contiguous).
    fn transposed_rows(&self, positions: &[usize]) -> DMatrix<f64>;
}

impl LowRank for DMatrix<f64> {
    fn row_count(&self) -> usize {
        self.nrows()
    }

    fn dim(&self) -> usize {
        self.ncols()
    }

    fn transposed_rows(&self, positions: &[usize]) -> DMatrix<f64> {
        self.select_rows(positions).transpose()
    }
}

/// Rows of L made at once by [`low_tr_mul`] and [`low_mul`]: large enough for the products to
/// run as matrix products, small enough to stay in cache.
const LOW_ROWS_AT_ONCE: usize = 256;

/// The position ranges L is walked in.
fn low_chunks(low: &dyn LowRank) -> impl Iterator<Item = Vec<usize>> {
    position_blocks(low.row_count(), LOW_ROWS_AT_ONCE)
}

/// Lᵀ v (v one row per position).
fn low_tr_mul(low: &dyn LowRank, v: &DMatrix<f64>) -> DMatrix<f64> {
    let mut out = DMatrix::zeros(low.dim(), v.ncols());
    for positions in low_chunks(low) {
        let lt = low.transposed_rows(&positions);
        out.gemm(1.0, &lt, &v.rows(positions[0], positions.len()), 1.0);
    }
    out
}

/// L y (one row per position).
fn low_mul(low: &dyn LowRank, y: &DMatrix<f64>) -> DMatrix<f64> {
    let mut out = DMatrix::zeros(low.row_count(), y.ncols());
    for positions in low_chunks(low) {
        let lt = low.transposed_rows(&positions);
        out.rows_mut(positions[0], positions.len())
            .copy_from(&lt.tr_mul(y));
    }
    out
}

/// A symmetric matrix's inverse, if every eigenvalue is at least `MIN_KEPT_INFORMATION`:
/// m − MIN_KEPT_INFORMATION·I has a Cholesky factor exactly when it is positive definite, and
/// m's own factor gives the inverse (a third of an eigen-decomposition's work, twice).
fn inverse_if_kept(m: DMatrix<f64>) -> Option<DMatrix<f64>> {
    let n = m.nrows();
    if n == 0 {
        return Some(m);
    }
    if n == 1 {
        let d = m[(0, 0)];
        return (d >= MIN_KEPT_INFORMATION).then(|| DMatrix::from_element(1, 1, 1.0 / d));
    }
    if m.iter().any(|v| !v.is_finite()) {
        return None;
    }
    let shifted = &m - DMatrix::identity(n, n) * MIN_KEPT_INFORMATION;
    shifted.cholesky()?;
    Some(m.cholesky()?.inverse())
}

/// One fold's held rows downdated from the full fit.
pub struct FoldDowndate {
    /// D⁻¹ per group (positions among the held rows).
    d_inv: Vec<(Vec<usize>, DMatrix<f64>)>,
    /// L; G = D⁻¹ L is applied, not held.
    low: Box<dyn LowRank>,
    /// K⁻¹.
    k_inv: DMatrix<f64>,
    /// diag((D − L Lᵀ)⁻¹): 1 plus each held row's prediction variance, whitened.
    inflation: Vec<f64>,
}

impl FoldDowndate {
    /// None where the training rows lose (nearly) a direction that all rows determine. A row
    /// in no group has no block of D⁻¹ (as `apply_blocks` takes it): its row of G is zero.
    pub fn new(hat: HatRows) -> Option<FoldDowndate> {
        let HatRows { groups, low } = hat;
        let r = low.dim();
        let mut inflation = vec![0.0; low.row_count()];
        let mut d_inv = Vec::with_capacity(groups.len());
        for (positions, block) in groups {
            let n = positions.len();
            let inv = inverse_if_kept(DMatrix::identity(n, n) - block)?;
            for (x, &pos) in positions.iter().enumerate() {
                inflation[pos] = inv[(x, x)];
            }
            d_inv.push((positions, inv));
        }
        // K = I − Lᵀ D⁻¹ L, groups of rows at a time.
        let mut k = DMatrix::identity(r, r);
        for batch in group_batches(&d_inv) {
            let (_, lt, gt) = l_and_g_transposed(&*low, batch);
            k.gemm(-1.0, &lt, &gt.transpose(), 1.0);
        }
        let k_inv = inverse_if_kept(symmetrised(k))?;
        // Plus diag(G K⁻¹ Gᵀ).
        for batch in group_batches(&d_inv) {
            let (positions, _, gt) = l_and_g_transposed(&*low, batch);
            let kg = &k_inv * &gt;
            for (x, &pos) in positions.iter().enumerate() {
                inflation[pos] += gt.column(x).dot(&kg.column(x));
            }
        }
        Some(FoldDowndate {
            d_inv,
            low,
            k_inv,
            inflation,
        })
    }

    /// diag((I − H_kk)⁻¹) of the base: each held row's σ² plus prediction variance, in units of
    /// its σ².
    pub fn inflation(&self) -> &[f64] {
        &self.inflation
    }

    /// The held rows' residuals predicted from the training rows: (I − H_kk)⁻¹ e =
    /// D⁻¹e + G K⁻¹ Gᵀe.
    pub fn residuals(&self, e: &DVector<f64>) -> DVector<f64> {
        let de = self.d_inv_times(&as_column(e));
        let y = &self.k_inv * low_tr_mul(&*self.low, &de);
        (de + self.g_times(&y)).column(0).into_owned()
    }

    /// D⁻¹ v.
    fn d_inv_times(&self, v: &DMatrix<f64>) -> DMatrix<f64> {
        apply_d_inv(&self.d_inv, v)
    }

    /// G y = D⁻¹ (L y).
    fn g_times(&self, y: &DMatrix<f64>) -> DMatrix<f64> {
        self.d_inv_times(&low_mul(&*self.low, y))
    }

    /// The same with a candidate's projected columns' orthonormal basis `u` (held rows) added
    /// to the model, `e` the residuals of the full fit with the candidate; None where the
    /// training rows nearly lose one of the candidate's directions.
    pub fn residuals_with(&self, u: &DMatrix<f64>, e: &DVector<f64>) -> Option<DVector<f64>> {
        let c = u.ncols();
        // [D⁻¹U  D⁻¹e], and Gᵀ of both in one walk over L: [X  Gᵀe], X = LᵀD⁻¹U.
        let mut ue = DMatrix::zeros(u.nrows(), c + 1);
        ue.columns_mut(0, c).copy_from(u);
        ue.column_mut(c).copy_from(e);
        let d_ue = self.d_inv_times(&ue);
        let (gu, de) = (d_ue.columns(0, c), d_ue.column(c));
        let gt = low_tr_mul(&*self.low, &d_ue);
        let (cross, top) = (gt.columns(0, c), gt.column(c));
        // K_aug = I − [L U]ᵀ D⁻¹ [L U] = [[K, −X], [−Xᵀ, C]].
        let corner = DMatrix::identity(c, c) - u.tr_mul(&gu);
        // Through the Schur complement of K in K_aug, C − XᵀK⁻¹X.
        let k_cross = &self.k_inv * cross;
        let schur = symmetrised(corner - cross.tr_mul(&k_cross));
        let schur_inv = inverse_if_kept(schur)?;
        // y = K_aug⁻¹ [Gᵀe; (D⁻¹U)ᵀe] by blocks.
        let bottom = gu.tr_mul(e);
        let k_top = &self.k_inv * top;
        let y_bottom = &schur_inv * (&bottom + cross.tr_mul(&k_top));
        let y_top = &k_top + &k_cross * &y_bottom;
        let g_y = self.g_times(&as_column(&y_top));
        Some(g_y.column(0) + gu * &y_bottom + de)
    }
}

/// A vector as a one-column matrix.
fn as_column(v: &DVector<f64>) -> DMatrix<f64> {
    DMatrix::from_column_slice(v.len(), 1, v.as_slice())
}

/// Consecutive groups of D⁻¹ holding about `LOW_ROWS_AT_ONCE` rows together (a group at least).
fn group_batches(
    d_inv: &[(Vec<usize>, DMatrix<f64>)],
) -> impl Iterator<Item = &[(Vec<usize>, DMatrix<f64>)]> {
    let mut rest = d_inv;
    std::iter::from_fn(move || {
        if rest.is_empty() {
            return None;
        }
        let mut rows = 0;
        let take = rest
            .iter()
            .take_while(|(positions, _)| {
                let first = rows == 0;
                rows += positions.len();
                first || rows <= LOW_ROWS_AT_ONCE
            })
            .count();
        let (batch, tail) = rest.split_at(take);
        rest = tail;
        Some(batch)
    })
}

/// A batch of groups' positions, with Lᵀ and Gᵀ = (D⁻¹L)ᵀ on those positions (D⁻¹ symmetric: a
/// group's columns of Gᵀ are its columns of Lᵀ times its block).
fn l_and_g_transposed(
    low: &dyn LowRank,
    batch: &[(Vec<usize>, DMatrix<f64>)],
) -> (Vec<usize>, DMatrix<f64>, DMatrix<f64>) {
    let positions: Vec<usize> = batch.iter().flat_map(|(p, _)| p.iter().copied()).collect();
    let lt = low.transposed_rows(&positions);
    let mut gt = DMatrix::zeros(lt.nrows(), lt.ncols());
    let mut at = 0;
    for (group, inv) in batch {
        let n = group.len();
        gt.columns_mut(at, n).copy_from(&(lt.columns(at, n) * inv));
        at += n;
    }
    (positions, lt, gt)
}

fn symmetrised(m: DMatrix<f64>) -> DMatrix<f64> {
    let t = m.transpose();
    (m + t) * 0.5
}

/// blockdiag(blocks) · v (v one row per position; each block with its positions).
pub fn apply_blocks<'a>(
    blocks: impl IntoIterator<Item = (&'a [usize], &'a DMatrix<f64>)>,
    v: &DMatrix<f64>,
) -> DMatrix<f64> {
    let mut out = DMatrix::zeros(v.nrows(), v.ncols());
    for (positions, block) in blocks {
        for c in 0..v.ncols() {
            for (x, &px) in positions.iter().enumerate() {
                out[(px, c)] = positions
                    .iter()
                    .enumerate()
                    .map(|(y, &py)| block[(x, y)] * v[(py, c)])
                    .sum();
            }
        }
    }
    out
}

/// [`apply_blocks`] of a fold's D⁻¹.
fn apply_d_inv(d_inv: &[(Vec<usize>, DMatrix<f64>)], v: &DMatrix<f64>) -> DMatrix<f64> {
    apply_blocks(d_inv.iter().map(|(p, b)| (p.as_slice(), b)), v)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Entries of a fixed pseudo-random sequence in [−1, 1).
    fn noise(n: usize, seed: u64) -> Vec<f64> {
        let mut state = seed;
        (0..n)
            .map(|_| {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                (state >> 11) as f64 / (1u64 << 52) as f64 - 1.0
            })
            .collect()
    }

    /// A tall design of full column rank.
    fn design() -> DMatrix<f64> {
        DMatrix::from_vec(40, 5, noise(200, 1))
    }

    /// The held-out residuals refitted on the training rows.
    fn refit(x: &DMatrix<f64>, y: &DVector<f64>, held: &[usize]) -> DVector<f64> {
        let train: Vec<usize> = (0..x.nrows()).filter(|r| !held.contains(r)).collect();
        let xt = x.select_rows(&train);
        let yt = y.select_rows(&train);
        let beta = xt.svd(true, true).solve(&yt, 1e-12).expect("solve");
        DVector::from_fn(held.len(), |k, _| {
            y[held[k]] - x.row(held[k]).dot(&beta.transpose())
        })
    }

    /// H_kk of a dense fit: no blocks, L the held rows of U.
    fn hat_rows(u: &DMatrix<f64>, held: &[usize]) -> HatRows {
        HatRows {
            groups: (0..held.len())
                .map(|k| (vec![k], DMatrix::zeros(1, 1)))
                .collect(),
            low: Box::new(u.select_rows(held)),
        }
    }

    #[test]
    fn inverse_only_when_every_eigenvalue_is_kept() {
        // Q diag(λ) Qᵀ with a rotation Q mixing all three axes.
        let q = nalgebra::Rotation3::from_euler_angles(0.3, -0.7, 1.1).into_inner();
        let with = |smallest: f64| {
            let d = nalgebra::Matrix3::from_diagonal(&nalgebra::Vector3::new(1.0, 0.5, smallest));
            let m = q * d * q.transpose();
            DMatrix::from_fn(3, 3, |r, c| m[(r, c)])
        };
        let kept = with(4.0 * MIN_KEPT_INFORMATION);
        let inverse = inverse_if_kept(kept.clone()).expect("every eigenvalue kept");
        assert!((&inverse * &kept - DMatrix::identity(3, 3)).amax() < 1e-7);
        assert!(inverse_if_kept(with(0.25 * MIN_KEPT_INFORMATION)).is_none());
        assert!(inverse_if_kept(with(-0.1)).is_none());
        let mut not_finite = kept;
        not_finite[(1, 1)] = f64::NAN;
        assert!(inverse_if_kept(not_finite).is_none());
    }

    #[test]
    fn downdated_residuals_equal_the_refit() {
        let x = design();
        let y = DVector::from_vec(noise(40, 3));
        let svd = x.clone().svd(true, true);
        let beta = svd.solve(&y, 1e-12).expect("solve");
        let u = svd.u.expect("u");
        let e = &y - &x * beta;
        let held = [1, 6, 11, 17, 30, 33];
        let fold = FoldDowndate::new(hat_rows(&u, &held)).expect("kept");
        let got = fold.residuals(&e.select_rows(&held));
        let want = refit(&x, &y, &held);
        assert!((&got - &want).norm() <= 1e-12 * want.norm(), "{got} {want}");
        // The prediction variances: x_h (X_trᵀX_tr)⁻¹ x_hᵀ.
        let train: Vec<usize> = (0..40).filter(|r| !held.contains(r)).collect();
        let xt = x.select_rows(&train);
        let n_inv = (xt.transpose() * &xt).try_inverse().expect("inverse");
        for (k, &h) in held.iter().enumerate() {
            let row = x.row(h);
            let var = (row * &n_inv * row.transpose())[(0, 0)];
            assert!((fold.inflation()[k] - 1.0 - var).abs() <= 1e-12 * (1.0 + var));
        }
    }

    #[test]
    fn a_candidates_columns_downdate_like_the_refit_of_the_wider_design() {
        let x = design();
        let extra = DMatrix::from_vec(40, 2, noise(80, 2));
        let wide = DMatrix::from_fn(
            40,
            7,
            |r, c| if c < 5 { x[(r, c)] } else { extra[(r, c - 5)] },
        );
        let y = DVector::from_vec(noise(40, 4));
        let held = [0, 4, 9, 21, 22, 39];
        let u = x.clone().svd(true, false).u.expect("u");
        let wide_svd = wide.clone().svd(true, true);
        let e = &y - &wide * wide_svd.solve(&y, 1e-12).expect("solve");
        // The candidate's columns projected off X, orthonormalised.
        let p = &extra - &u * u.tr_mul(&extra);
        let q = p.svd(true, false).u.expect("q");
        let fold = FoldDowndate::new(hat_rows(&u, &held)).expect("kept");
        let got = fold
            .residuals_with(&q.select_rows(&held), &e.select_rows(&held))
            .expect("kept");
        let want = refit(&wide, &y, &held);
        assert!((&got - &want).norm() <= 1e-12 * want.norm(), "{got} {want}");
    }

    #[test]
    fn a_point_block_and_the_low_rank_part_together() {
        // H = P_A + P_B̃ split between blocks (A: two columns nonzero on three rows each, like
        // a point's) and L (B̃ = (I − P_A) B), as the points' elimination gives it.
        let mut x = design();
        for r in 0..40 {
            for c in 0..2 {
                x[(r, c)] = 0.0;
            }
        }
        for (c, rows) in [(0usize, [3usize, 8, 12]), (1, [5, 14, 20])] {
            for (k, &r) in rows.iter().enumerate() {
                x[(r, c)] = 1.0 + k as f64 * 0.3;
            }
        }
        let y = DVector::from_vec(noise(40, 5));
        let beta = x.clone().svd(true, true).solve(&y, 1e-12).expect("solve");
        let e = &y - &x * beta;
        // Held: one row of each "point", and two rows of neither.
        let held = [3usize, 5, 10, 25];
        let a = x.columns(0, 2).into_owned();
        let b = x.columns(2, 3).into_owned();
        let pa = &a * (a.transpose() * &a).try_inverse().expect("inverse") * a.transpose();
        let bt = &b - &pa * &b;
        let ub = bt.svd(true, false).u.expect("u");
        let groups = held
            .iter()
            .enumerate()
            .map(|(k, &h)| (vec![k], DMatrix::from_element(1, 1, pa[(h, h)])))
            .collect();
        let hat = HatRows {
            groups,
            low: Box::new(ub.select_rows(&held)),
        };
        let fold = FoldDowndate::new(hat).expect("kept");
        let got = fold.residuals(&e.select_rows(&held));
        let want = refit(&x, &y, &held);
        assert!((&got - &want).norm() <= 1e-12 * want.norm(), "{got} {want}");
    }

    #[test]
    fn a_fold_that_holds_a_direction_alone_is_not_downdated() {
        let mut x = design();
        // Column 0 nonzero on row 2 only: holding row 2 out loses that direction.
        for r in 0..40 {
            x[(r, 0)] = if r == 2 { 1.0 } else { 0.0 };
        }
        let u = x.svd(true, false).u.expect("u");
        assert!(FoldDowndate::new(hat_rows(&u, &[2, 7])).is_none());
        assert!(FoldDowndate::new(hat_rows(&u, &[3, 7])).is_some());
    }
}
