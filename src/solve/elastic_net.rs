//! Elastic net by cyclic coordinate descent (glmnet / scikit-learn objective), with warm-started
//! λ paths, optional standardisation, row weights and grouped K-fold cross-validation.
//!
//! Objective, for N rows with weights wᵢ normalised to Σwᵢ = N (all 1 when unweighted):
//!
//!   (1/2N) Σ wᵢ (yᵢ − b₀ − xᵢ·b)² + λ (α ‖b‖₁ + (1−α)/2 ‖b‖²)
//!
//! which is scikit-learn's `ElasticNet(alpha=λ, l1_ratio=α)` when `standardize` is off. With
//! `standardize` on, the penalty acts on the coefficients of unit-variance columns (glmnet's
//! convention) and the coefficients are returned on the original scale.

use std::time::Instant;

use nalgebra::{DMatrix, DVector};
use rand::seq::SliceRandom;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// Why an elastic-net problem was rejected.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum ElasticNetError {
    #[error("elastic net: {0}")]
    InvalidInput(String),
}

/// How the design is prepared and when coordinate descent stops.
#[derive(Clone, Debug, PartialEq)]
pub struct ElasticNetOptions {
    /// Scale every column to unit (weighted) variance before fitting; the penalty then acts on
    /// the standardised coefficients. Off = scikit-learn's convention.
    pub standardize: bool,
    /// Fit an unpenalised intercept (centre columns and response by their weighted means).
    pub fit_intercept: bool,
    /// Converged when no standardised coefficient moves by more than `tolerance` times the
    /// largest standardised coefficient in a full sweep.
    pub tolerance: f64,
    /// Maximum number of coordinate sweeps per λ.
    pub max_sweeps: usize,
}

impl Default for ElasticNetOptions {
    fn default() -> Self {
        ElasticNetOptions {
            standardize: true,
            fit_intercept: true,
            tolerance: 1e-9,
            max_sweeps: 100_000,
        }
    }
}

/// One fitted model.
#[derive(Clone, Debug, PartialEq)]
pub struct ElasticNetFit {
    pub lambda: f64,
    pub alpha: f64,
    /// Coefficients on the original column scale.
    pub coefficients: DVector<f64>,
    pub intercept: f64,
    /// Coordinate sweeps used (full and active-set sweeps).
    pub sweeps: usize,
    pub converged: bool,
}

impl ElasticNetFit {
    /// Number of non-zero coefficients.
    pub fn n_active(&self) -> usize {
        self.coefficients.iter().filter(|b| **b != 0.0).count()
    }

    /// Prediction for the rows of `x` (original scale).
    pub fn predict(&self, x: &DMatrix<f64>) -> DVector<f64> {
        x * &self.coefficients + DVector::from_element(x.nrows(), self.intercept)
    }
}

/// A prepared problem: columns centred, scaled and multiplied by √w, so that coordinate
/// descent runs on an unweighted least-squares problem.
#[derive(Clone, Debug)]
pub struct ElasticNet {
    z: DMatrix<f64>,
    ty: DVector<f64>,
    /// Per column: mean (0 without intercept) and scale (1 without standardisation).
    x_mean: DVector<f64>,
    x_scale: DVector<f64>,
    y_mean: f64,
    /// ‖z_j‖² / N.
    col_sq: DVector<f64>,
    /// (ZᵀZ/N, Zᵀy/N) when N > p: coordinate updates then cost O(p) instead of O(N).
    gram: Option<(DMatrix<f64>, DVector<f64>)>,
    options: ElasticNetOptions,
}

fn check_finite(what: &str, v: impl Iterator<Item = f64>) -> Result<(), ElasticNetError> {
    for (i, x) in v.enumerate() {
        if !x.is_finite() {
            return Err(ElasticNetError::InvalidInput(format!(
                "{what} element {i} is not finite ({x})"
            )));
        }
    }
    Ok(())
}

/// Weights normalised to sum N; `None` = all ones.
fn normalised_weights(
    n: usize,
    weights: Option<&DVector<f64>>,
) -> Result<DVector<f64>, ElasticNetError> {
    let Some(w) = weights else {
        return Ok(DVector::from_element(n, 1.0));
    };
    if w.len() != n {
        return Err(ElasticNetError::InvalidInput(format!(
            "{} weights for {n} rows",
            w.len()
        )));
    }
    check_finite("weight", w.iter().copied())?;
    if w.iter().any(|x| *x < 0.0) {
        return Err(ElasticNetError::InvalidInput("negative weight".into()));
    }
    let sum: f64 = w.sum();
    if sum <= 0.0 {
        return Err(ElasticNetError::InvalidInput("all weights are zero".into()));
    }
    Ok(w * (n as f64 / sum))
}

fn soft_threshold(x: f64, t: f64) -> f64 {
    if x > t {
        x - t
    } else if x < -t {
        x + t
    } else {
        0.0
    }
}

impl ElasticNet {
    /// Prepare `x` (N × p), `y` (N) and optional row weights.
    pub fn new(
        x: &DMatrix<f64>,
        y: &DVector<f64>,
        weights: Option<&DVector<f64>>,
        options: ElasticNetOptions,
    ) -> Result<ElasticNet, ElasticNetError> {
        let (n, p) = x.shape();
        if n == 0 || p == 0 {
            return Err(ElasticNetError::InvalidInput(format!(
                "empty design ({n} rows, {p} columns)"
            )));
        }
        if y.len() != n {
            return Err(ElasticNetError::InvalidInput(format!(
                "{} responses for {n} rows",
                y.len()
            )));
        }
        if options.tolerance.is_nan() || options.tolerance <= 0.0 || options.max_sweeps == 0 {
            return Err(ElasticNetError::InvalidInput(
                "tolerance must be > 0 and max_sweeps >= 1".into(),
            ));
        }
        check_finite("x", x.iter().copied())?;
        check_finite("y", y.iter().copied())?;
        let w = normalised_weights(n, weights)?;
        let nf = n as f64;
        let sw = w.map(f64::sqrt);
        let y_mean = if options.fit_intercept {
            w.dot(y) / nf
        } else {
            0.0
        };
        let ty = y.map(|v| v - y_mean).component_mul(&sw);
        let mut z = x.clone();
        let mut x_mean = DVector::zeros(p);
        let mut x_scale = DVector::from_element(p, 1.0);
        let mut col_sq = DVector::zeros(p);
        for j in 0..p {
            let mut col = z.column_mut(j);
            if options.fit_intercept {
                x_mean[j] = w.dot(&col) / nf;
                col.add_scalar_mut(-x_mean[j]);
            }
            col.component_mul_assign(&sw);
            let sq = col.norm_squared() / nf;
            if options.standardize {
                // A constant (after centring) column carries nothing; keep it at zero.
                let s = sq.sqrt();
                if s > 0.0 {
                    col /= s;
                    x_scale[j] = s;
                    col_sq[j] = 1.0;
                } else {
                    col_sq[j] = 0.0;
                }
            } else {
                col_sq[j] = sq;
            }
        }
        let gram = (n > p && p <= 4000).then(|| {
            let g = z.tr_mul(&z) / nf;
            let zty = z.tr_mul(&ty) / nf;
            (g, zty)
        });
        Ok(ElasticNet {
            gram,
            z,
            ty,
            x_mean,
            x_scale,
            y_mean,
            col_sq,
            options,
        })
    }

    pub fn n_rows(&self) -> usize {
        self.z.nrows()
    }

    pub fn n_cols(&self) -> usize {
        self.z.ncols()
    }

    /// Smallest λ at which every coefficient is zero, for this α (α < 1e-3 treated as 1e-3,
    /// as glmnet does, since pure ridge never zeroes a coefficient).
    pub fn lambda_max(&self, alpha: f64) -> f64 {
        let n = self.n_rows() as f64;
        let a = alpha.max(1e-3);
        (0..self.n_cols())
            .map(|j| self.z.column(j).dot(&self.ty).abs())
            .fold(0.0, f64::max)
            / (n * a)
    }

    /// Fit at one (λ, α), starting from `warm` (standardised coefficients from an earlier fit
    /// on this problem) or zero. Returns the fit and its standardised coefficients.
    fn fit_std(
        &self,
        lambda: f64,
        alpha: f64,
        warm: Option<&DVector<f64>>,
    ) -> (DVector<f64>, usize, bool) {
        let (n, p) = self.z.shape();
        let nf = n as f64;
        let mut beta = warm.cloned().unwrap_or_else(|| DVector::zeros(p));
        // Naive updates keep the residual (O(N) per coordinate); covariance updates keep Gβ
        // (O(p) per coordinate), the faster choice when N > p (glmnet's "covariance" mode).
        let mut state = match &self.gram {
            Some((g, _)) => g * &beta,
            None => &self.ty - &self.z * &beta,
        };
        let l1 = lambda * alpha;
        let l2 = lambda * (1.0 - alpha);
        let tol = self.options.tolerance;
        let mut sweeps = 0;
        // One sweep over `cols`; returns (max |Δβ|, max |β|).
        let sweep = |cols: &mut dyn Iterator<Item = usize>,
                     beta: &mut DVector<f64>,
                     r: &mut DVector<f64>| {
            let mut max_delta = 0.0f64;
            for j in cols {
                let c = self.col_sq[j];
                if c == 0.0 {
                    continue;
                }
                let old = beta[j];
                let rho = match &self.gram {
                    Some((_, zty)) => zty[j] - r[j] + c * old,
                    None => self.z.column(j).dot(r) / nf + c * old,
                };
                let new = soft_threshold(rho, l1) / (c + l2);
                if new != old {
                    match &self.gram {
                        Some((g, _)) => r.axpy(new - old, &g.column(j), 1.0),
                        None => r.axpy(old - new, &self.z.column(j), 1.0),
                    }
                    beta[j] = new;
                    max_delta = max_delta.max((new - old).abs());
                }
            }
            max_delta
        };
        let converged_at = |delta: f64, beta: &DVector<f64>| delta <= tol * beta.amax();
        loop {
            // Full sweep: may change the active set.
            let delta = sweep(&mut (0..p), &mut beta, &mut state);
            sweeps += 1;
            if converged_at(delta, &beta) {
                return (beta, sweeps, true);
            }
            if sweeps >= self.options.max_sweeps {
                return (beta, sweeps, false);
            }
            // Then iterate on the active set only until it settles (glmnet's strategy).
            let active: Vec<usize> = (0..p).filter(|&j| beta[j] != 0.0).collect();
            loop {
                let delta = sweep(&mut active.iter().copied(), &mut beta, &mut state);
                sweeps += 1;
                if converged_at(delta, &beta) {
                    break;
                }
                if sweeps >= self.options.max_sweeps {
                    return (beta, sweeps, false);
                }
            }
        }
    }

    fn to_fit(
        &self,
        beta: &DVector<f64>,
        lambda: f64,
        alpha: f64,
        sweeps: usize,
        conv: bool,
    ) -> ElasticNetFit {
        let coefficients = beta.component_div(&self.x_scale);
        let intercept = self.y_mean - self.x_mean.dot(&coefficients);
        ElasticNetFit {
            lambda,
            alpha,
            coefficients,
            intercept,
            sweeps,
            converged: conv,
        }
    }

    /// Fit at one (λ, α) from zero.
    pub fn fit(&self, lambda: f64, alpha: f64) -> Result<ElasticNetFit, ElasticNetError> {
        check_penalty(lambda, alpha)?;
        let (beta, sweeps, conv) = self.fit_std(lambda, alpha, None);
        Ok(self.to_fit(&beta, lambda, alpha, sweeps, conv))
    }

    /// Fit along a λ path (any order, usually decreasing), each fit warm-started from the
    /// previous one.
    pub fn path(&self, lambdas: &[f64], alpha: f64) -> Result<Vec<ElasticNetFit>, ElasticNetError> {
        let mut warm: Option<DVector<f64>> = None;
        let mut fits = Vec::with_capacity(lambdas.len());
        for &lambda in lambdas {
            check_penalty(lambda, alpha)?;
            let (beta, sweeps, conv) = self.fit_std(lambda, alpha, warm.as_ref());
            fits.push(self.to_fit(&beta, lambda, alpha, sweeps, conv));
            warm = Some(beta);
        }
        Ok(fits)
    }

    /// Per column (mean, scale) used for centring and standardisation.
    pub fn column_transform(&self) -> (&DVector<f64>, &DVector<f64>) {
        (&self.x_mean, &self.x_scale)
    }
}

fn check_penalty(lambda: f64, alpha: f64) -> Result<(), ElasticNetError> {
    if !(lambda >= 0.0 && lambda.is_finite() && (0.0..=1.0).contains(&alpha)) {
        return Err(ElasticNetError::InvalidInput(format!(
            "need λ >= 0 and 0 <= α <= 1, got λ = {lambda}, α = {alpha}"
        )));
    }
    Ok(())
}

/// `n` values log-spaced from `lambda_max` down to `lambda_max * min_ratio`.
pub fn lambda_path(lambda_max: f64, n: usize, min_ratio: f64) -> Vec<f64> {
    match n {
        0 => Vec::new(),
        1 => vec![lambda_max],
        _ => (0..n)
            .map(|k| lambda_max * min_ratio.powf(k as f64 / (n - 1) as f64))
            .collect(),
    }
}

/// Cross-validation grid and folds.
#[derive(Clone, Debug, PartialEq)]
pub struct CvOptions {
    pub alphas: Vec<f64>,
    pub n_lambdas: usize,
    /// Smallest λ of the path as a fraction of λ_max (of each α, on the full data).
    pub lambda_min_ratio: f64,
    pub folds: usize,
    /// Seed of the fold assignment (groups are shuffled, then dealt round-robin).
    pub seed: u64,
    pub fit: ElasticNetOptions,
}

impl Default for CvOptions {
    fn default() -> Self {
        CvOptions {
            alphas: vec![0.1, 0.5, 0.9, 1.0],
            n_lambdas: 50,
            lambda_min_ratio: 1e-4,
            folds: 5,
            seed: 1,
            fit: ElasticNetOptions::default(),
        }
    }
}

/// Cross-validated mean squared error along one α's path.
#[derive(Clone, Debug, PartialEq)]
pub struct CvCurve {
    pub alpha: f64,
    pub lambdas: Vec<f64>,
    /// Weighted mean squared prediction error over all held-out rows.
    pub mse: Vec<f64>,
    /// Standard error of `mse` from the spread between folds.
    pub mse_se: Vec<f64>,
}

/// The CV choice and the final fit on all rows at the chosen (λ, α).
#[derive(Clone, Debug, PartialEq)]
pub struct CvResult {
    pub curves: Vec<CvCurve>,
    pub lambda: f64,
    pub alpha: f64,
    pub cv_mse: f64,
    pub fit: ElasticNetFit,
    pub seconds: f64,
}

/// Rows of each fold: groups (e.g. the 3 coordinate rows of one point) stay together.
fn fold_rows(n: usize, groups: Option<&[usize]>, folds: usize, seed: u64) -> Vec<Vec<usize>> {
    let group_of = |i: usize| groups.map_or(i, |g| g[i]);
    let mut ids: Vec<usize> = (0..n).map(group_of).collect();
    ids.sort_unstable();
    ids.dedup();
    ids.shuffle(&mut ChaCha8Rng::seed_from_u64(seed));
    let fold_of: std::collections::HashMap<usize, usize> = ids
        .iter()
        .enumerate()
        .map(|(k, &g)| (g, k % folds))
        .collect();
    let mut out = vec![Vec::new(); folds];
    for i in 0..n {
        out[fold_of[&group_of(i)]].push(i);
    }
    out
}

fn select_rows(x: &DMatrix<f64>, rows: &[usize]) -> DMatrix<f64> {
    DMatrix::from_fn(rows.len(), x.ncols(), |i, j| x[(rows[i], j)])
}

fn select(v: &DVector<f64>, rows: &[usize]) -> DVector<f64> {
    DVector::from_fn(rows.len(), |i, _| v[rows[i]])
}

/// K-fold cross-validation over α ∈ `alphas` and a λ path per α; picks the (λ, α) of least
/// CV error and refits on all rows along the path down to it (warm starts). `groups[i]` keeps
/// rows of one group in the same fold. Folds run on parallel threads.
pub fn cross_validate(
    x: &DMatrix<f64>,
    y: &DVector<f64>,
    weights: Option<&DVector<f64>>,
    groups: Option<&[usize]>,
    options: &CvOptions,
) -> Result<CvResult, ElasticNetError> {
    let start = Instant::now();
    let n = x.nrows();
    if options.folds < 2 || options.alphas.is_empty() || options.n_lambdas == 0 {
        return Err(ElasticNetError::InvalidInput(
            "cross-validation needs >= 2 folds, >= 1 alpha and >= 1 lambda".into(),
        ));
    }
    if let Some(g) = groups {
        if g.len() != n {
            return Err(ElasticNetError::InvalidInput(format!(
                "{} group labels for {n} rows",
                g.len()
            )));
        }
    }
    for &a in &options.alphas {
        check_penalty(0.0, a)?;
    }
    let full = ElasticNet::new(x, y, weights, options.fit.clone())?;
    let w = normalised_weights(n, weights)?;
    let folds = fold_rows(n, groups, options.folds, options.seed);
    if folds.iter().filter(|f| !f.is_empty()).count() < 2 {
        return Err(ElasticNetError::InvalidInput(
            "too few rows/groups for cross-validation".into(),
        ));
    }
    let paths: Vec<Vec<f64>> = options
        .alphas
        .iter()
        .map(|&a| {
            lambda_path(
                full.lambda_max(a).max(f64::MIN_POSITIVE),
                options.n_lambdas,
                options.lambda_min_ratio,
            )
        })
        .collect();

    // Per fold, per α, per λ: (Σ w e², Σ w) on the held-out rows.
    type FoldErr = Result<Vec<Vec<(f64, f64)>>, ElasticNetError>;
    let fold_errors: Vec<FoldErr> = std::thread::scope(|s| {
        let handles: Vec<_> = folds
            .iter()
            .filter(|f| !f.is_empty())
            .map(|test| {
                let paths = &paths;
                let w = &w;
                s.spawn(move || -> FoldErr {
                    let mut in_test = vec![false; n];
                    test.iter().for_each(|&i| in_test[i] = true);
                    let train: Vec<usize> = (0..n).filter(|&i| !in_test[i]).collect();
                    let xt = select_rows(x, &train);
                    let wt = select(w, &train);
                    let net =
                        ElasticNet::new(&xt, &select(y, &train), Some(&wt), options.fit.clone())?;
                    let xv = select_rows(x, test);
                    let yv = select(y, test);
                    let wv = select(w, test);
                    let sw = wv.sum();
                    let mut out = Vec::new();
                    for (ai, &alpha) in options.alphas.iter().enumerate() {
                        let fits = net.path(&paths[ai], alpha)?;
                        out.push(
                            fits.iter()
                                .map(|f| {
                                    let e = &yv - f.predict(&xv);
                                    (e.component_mul(&e).dot(&wv), sw)
                                })
                                .collect(),
                        );
                    }
                    Ok(out)
                })
            })
            .collect();
        handles
            .into_iter()
            .map(|h| {
                h.join().unwrap_or_else(|_| {
                    Err(ElasticNetError::InvalidInput("a CV thread panicked".into()))
                })
            })
            .collect()
    });
    let fold_errors = fold_errors.into_iter().collect::<Result<Vec<_>, _>>()?;

    let mut curves = Vec::new();
    let mut best = (f64::INFINITY, 0usize, 0usize);
    for (ai, &alpha) in options.alphas.iter().enumerate() {
        let k = fold_errors.len() as f64;
        let mut mse = Vec::new();
        let mut mse_se = Vec::new();
        for li in 0..paths[ai].len() {
            let (sse, sw) = fold_errors
                .iter()
                .fold((0.0, 0.0), |(a, b), f| (a + f[ai][li].0, b + f[ai][li].1));
            let m = sse / sw;
            let var = fold_errors
                .iter()
                .map(|f| (f[ai][li].0 / f[ai][li].1 - m).powi(2))
                .sum::<f64>()
                / (k - 1.0).max(1.0);
            mse.push(m);
            mse_se.push((var / k).sqrt());
            // Ties go to the larger λ (earlier on the path) and the earlier α.
            if m < best.0 {
                best = (m, ai, li);
            }
        }
        curves.push(CvCurve {
            alpha,
            lambdas: paths[ai].clone(),
            mse,
            mse_se,
        });
    }
    let (cv_mse, ai, li) = best;
    let alpha = options.alphas[ai];
    let lambda = paths[ai][li];
    let fit = full
        .path(&paths[ai][..=li], alpha)?
        .pop()
        .ok_or_else(|| ElasticNetError::InvalidInput("empty path".into()))?;
    Ok(CvResult {
        curves,
        lambda,
        alpha,
        cv_mse,
        fit,
        seconds: start.elapsed().as_secs_f64(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::Rng;

    fn opts(standardize: bool, fit_intercept: bool) -> ElasticNetOptions {
        ElasticNetOptions {
            standardize,
            fit_intercept,
            tolerance: 1e-13,
            max_sweeps: 1_000_000,
        }
    }

    #[test]
    fn orthogonal_design_is_soft_threshold() {
        // Columns orthogonal with ‖x_j‖²/N = c_j: b_j = S(x_jᵀy/N, λα) / (c_j + λ(1−α)).
        let n = 8;
        let mut x = DMatrix::zeros(n, 3);
        for i in 0..n {
            x[(i, 0)] = if i % 2 == 0 { 1.0 } else { -1.0 };
            x[(i, 1)] = if (i / 2) % 2 == 0 { 2.0 } else { -2.0 };
            x[(i, 2)] = if (i / 4) % 2 == 0 { 0.5 } else { -0.5 };
        }
        let y = DVector::from_fn(n, |i, _| (i as f64 * 0.7).sin() * 3.0 + 0.2 * i as f64);
        let net = ElasticNet::new(&x, &y, None, opts(false, false)).unwrap();
        for (lambda, alpha) in [(0.1, 1.0), (0.3, 0.5), (0.05, 0.1), (2.0, 0.9), (0.2, 0.0)] {
            let fit = net.fit(lambda, alpha).unwrap();
            assert!(fit.converged);
            for j in 0..3 {
                let xj = x.column(j);
                let c = xj.norm_squared() / n as f64;
                let expect = soft_threshold(xj.dot(&y) / n as f64, lambda * alpha)
                    / (c + lambda * (1.0 - alpha));
                assert!(
                    (fit.coefficients[j] - expect).abs() < 1e-12,
                    "λ {lambda} α {alpha} col {j}: {} vs {expect}",
                    fit.coefficients[j]
                );
            }
        }
    }

    #[test]
    fn tiny_case_by_hand() {
        // x = [[1, 1], [1, −1]] / no intercept, y = [3, 1], N = 2. xᵀy/N = (2, 1), c = (1, 1):
        // orthogonal, so lasso λ = 0.5: b = (1.5, 0.5); ridge λ = 1 (α = 0): b = (1, 0.5).
        // Non-orthogonal: x = [[1, 0], [1, 1]], y = [1, 3], lasso λ = 0.25. Stationarity with
        // both active and positive: (1/2)[2b1 + b2 − 4] = −0.25, (1/2)[b1 + b2 − 3] = −0.25
        // → b1 + b2 = 2.5, 2b1 + b2 = 3.5 → b1 = 1, b2 = 1.5.
        let x = DMatrix::from_row_slice(2, 2, &[1.0, 1.0, 1.0, -1.0]);
        let y = DVector::from_vec(vec![3.0, 1.0]);
        let net = ElasticNet::new(&x, &y, None, opts(false, false)).unwrap();
        let b = net.fit(0.5, 1.0).unwrap().coefficients;
        assert!(
            (b[0] - 1.5).abs() < 1e-12 && (b[1] - 0.5).abs() < 1e-12,
            "{b}"
        );
        let b = net.fit(1.0, 0.0).unwrap().coefficients;
        assert!(
            (b[0] - 1.0).abs() < 1e-12 && (b[1] - 0.5).abs() < 1e-12,
            "{b}"
        );

        let x = DMatrix::from_row_slice(2, 2, &[1.0, 0.0, 1.0, 1.0]);
        let y = DVector::from_vec(vec![1.0, 3.0]);
        let net = ElasticNet::new(&x, &y, None, opts(false, false)).unwrap();
        let b = net.fit(0.25, 1.0).unwrap().coefficients;
        assert!(
            (b[0] - 1.0).abs() < 1e-10 && (b[1] - 1.5).abs() < 1e-10,
            "{b}"
        );
    }

    #[test]
    fn intercept_and_weights_match_replicated_rows() {
        // A weight of 2 must equal duplicating the row.
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let n = 30;
        let x = DMatrix::from_fn(n, 4, |_, _| rng.random_range(-1.0..1.0));
        let y = DVector::from_fn(n, |i, _| {
            2.0 + x[(i, 0)] - 0.5 * x[(i, 2)] + rng.random_range(-0.1..0.1)
        });
        let w = DVector::from_fn(n, |i, _| if i < 10 { 2.0 } else { 1.0 });
        let mut xr = DMatrix::zeros(n + 10, 4);
        let mut yr = DVector::zeros(n + 10);
        for i in 0..n + 10 {
            let src = if i < n { i } else { i - n };
            xr.set_row(i, &x.row(src));
            yr[i] = y[src];
        }
        for standardize in [false, true] {
            let a = ElasticNet::new(&x, &y, Some(&w), opts(standardize, true)).unwrap();
            let b = ElasticNet::new(&xr, &yr, None, opts(standardize, true)).unwrap();
            let fa = a.fit(0.02, 0.7).unwrap();
            let fb = b.fit(0.02, 0.7).unwrap();
            assert!((&fa.coefficients - &fb.coefficients).amax() < 1e-10);
            assert!((fa.intercept - fb.intercept).abs() < 1e-10);
            assert!((fa.intercept - 2.0).abs() < 0.1);
        }
    }

    #[test]
    fn lasso_path_sparsity_is_monotone() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let (n, p) = (60, 12);
        let x = DMatrix::from_fn(n, p, |_, _| rng.random_range(-1.0..1.0));
        // Well separated true coefficients so the entry order along the path is clean.
        let truth = DVector::from_fn(p, |j, _| if j < 4 { 4.0 - j as f64 } else { 0.0 });
        let y = &x * &truth + DVector::from_fn(n, |_, _| rng.random_range(-0.01..0.01));
        let net = ElasticNet::new(&x, &y, None, opts(true, true)).unwrap();
        let lmax = net.lambda_max(1.0);
        let fits = net.path(&lambda_path(lmax, 40, 1e-3), 1.0).unwrap();
        assert_eq!(fits[0].n_active(), 0, "at λ_max all coefficients are zero");
        let just_below = net.fit(lmax * 0.999, 1.0).unwrap();
        assert_eq!(just_below.n_active(), 1);
        let counts: Vec<usize> = fits.iter().map(|f| f.n_active()).collect();
        for w in counts.windows(2) {
            assert!(w[1] >= w[0], "active counts {counts:?}");
        }
        // The strong coefficients are active at the end and close to the truth.
        let last = fits.last().unwrap();
        for j in 0..4 {
            assert!(
                (last.coefficients[j] - truth[j]).abs() < 0.05,
                "{}",
                last.coefficients
            );
        }
        assert!(fits.iter().all(|f| f.converged));
    }

    #[test]
    fn cv_picks_small_lambda_on_noiseless_data() {
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let (n, p) = (90, 10);
        let x = DMatrix::from_fn(n, p, |_, _| rng.random_range(-1.0..1.0));
        let truth = DVector::from_fn(p, |j, _| (j as f64 - 4.5) * 0.3);
        let y = &x * &truth;
        let groups: Vec<usize> = (0..n).map(|i| i / 3).collect();
        let cv = cross_validate(&x, &y, None, Some(&groups), &CvOptions::default()).unwrap();
        let path = &cv
            .curves
            .iter()
            .find(|c| c.alpha == cv.alpha)
            .unwrap()
            .lambdas;
        assert_eq!(cv.lambda, *path.last().unwrap(), "smallest λ of the path");
        assert!(
            (&cv.fit.coefficients - &truth).amax() < 1e-3,
            "{}",
            cv.fit.coefficients
        );
        assert!(cv.cv_mse < 1e-6);
    }

    #[test]
    fn rejects_bad_input() {
        let x = DMatrix::from_element(3, 2, 1.0);
        let y = DVector::from_vec(vec![1.0, f64::NAN, 2.0]);
        assert!(ElasticNet::new(&x, &y, None, ElasticNetOptions::default()).is_err());
        let y = DVector::from_vec(vec![1.0, 2.0]);
        assert!(ElasticNet::new(&x, &y, None, ElasticNetOptions::default()).is_err());
        let y = DVector::from_vec(vec![1.0, 2.0, 3.0]);
        let net = ElasticNet::new(&x, &y, None, ElasticNetOptions::default()).unwrap();
        assert!(net.fit(-1.0, 0.5).is_err());
        assert!(net.fit(1.0, 1.5).is_err());
    }
}
