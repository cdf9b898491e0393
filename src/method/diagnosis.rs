//! What a kind with a small, dense calibration problem hands the diagnosis (`geocal diagnose`)
//! and the solve with effects (`geocal solve --effects`): its residual model (measured minus
//! modelled quantities against the nominal parameters, their σ, Jacobian and labels) and its
//! effect library (what each unmodelled effect adds to each modelled quantity). The
//! selection (`diagnose::residual_model`) and the joint fit below name no kind.

use nalgebra::{DMatrix, DVector};

/// Where one residual lies in the kind's natural coordinates.
#[derive(Debug, Clone, PartialEq)]
pub struct ResidualLabel {
    /// The groups it belongs to, each (coordinate, key): ("leg", "leg 2"), ("time", "block 3
    /// of 8"), ("direction", "d5"), ... The diagnosis tests each group against the noise model.
    pub groups: Vec<(&'static str, String)>,
    /// The residual plot's row (e.g. "leg 2", "pose sensor") and position along its x axis.
    pub row: String,
    pub x: f64,
    /// Held-out group of the cross-validation (e.g. the pose or the posture it was measured
    /// in); None: always in the training set (e.g. a reading that alone determines nuisance
    /// parameters of its group).
    pub holdout: Option<usize>,
    /// Unit of the residual and of its σ: "m" or "rad".
    pub unit: &'static str,
}

/// A kind's measured quantities against its nominal model.
pub trait ResidualModel: Send + Sync {
    fn kind(&self) -> &'static str;
    fn session_id(&self) -> &str;
    /// The residual plot's x axis, e.g. "time since the first pose [s]".
    fn x_axis(&self) -> &'static str;
    /// Names of the model's parameters (the calibration's and any nuisance parameters).
    fn parameter_names(&self) -> Vec<String>;
    /// Indices of the parameters a report states (the calibration's, not the nuisance ones).
    fn reported_parameters(&self) -> Vec<usize> {
        (0..self.parameter_names().len()).collect()
    }
    /// Where the fit starts (the kind's nominal solve, or its design values).
    fn start(&self) -> DVector<f64>;
    /// Standard deviation of each residual (the declared noise model), in its unit.
    fn sigma(&self) -> &[f64];
    fn labels(&self) -> &[ResidualLabel];
    /// Measured minus modelled quantities at parameters `p`.
    fn residuals(&self, p: &DVector<f64>) -> DVector<f64>;
    /// Step of the finite differences for parameter `j`.
    fn step(&self, _j: usize) -> f64 {
        1e-7
    }
    /// ∂(modelled)/∂p: by default central differences of the residuals.
    fn jacobian(&self, p: &DVector<f64>) -> DMatrix<f64> {
        let n = self.sigma().len();
        let mut jac = DMatrix::zeros(n, p.len());
        for j in 0..p.len() {
            let h = self.step(j);
            let mut plus = p.clone();
            plus[j] += h;
            let mut minus = p.clone();
            minus[j] -= h;
            let d = (self.residuals(&minus) - self.residuals(&plus)) / (2.0 * h);
            jac.set_column(j, &d);
        }
        jac
    }
    /// The kind's effect library (the effects this session can show).
    fn effects(&self) -> Vec<Box<dyn Effect + '_>>;
    /// Parameters that touch only the residuals of one group (e.g. a measured pose's six:
    /// its own rows only), which the diagnosis eliminates group by group. None by default.
    fn local_blocks(&self) -> Vec<LocalBlock> {
        Vec::new()
    }
}

/// Columns of the Jacobian that are zero outside the rows `rows`.
#[derive(Debug, Clone, PartialEq)]
pub struct LocalBlock {
    pub columns: std::ops::Range<usize>,
    pub rows: Vec<usize>,
}

/// How local blocks lay over a design: each row's block, if any, and the columns in no block
/// (in order).
pub struct BlockLayout {
    pub row_block: Vec<Option<usize>>,
    pub global: Vec<usize>,
}

impl BlockLayout {
    /// The layout of `blocks` over `x`; None when a block is empty or reaches past `x`, the
    /// blocks overlap, or a block's columns are non-zero outside its rows (they are not local).
    pub fn of(x: &DMatrix<f64>, blocks: &[LocalBlock]) -> Option<BlockLayout> {
        let (n, p) = x.shape();
        if blocks.is_empty() {
            return None;
        }
        let mut column_block = vec![None; p];
        let mut row_block = vec![None; n];
        for (k, block) in blocks.iter().enumerate() {
            if block.columns.end > p || block.columns.is_empty() {
                return None;
            }
            for c in block.columns.clone() {
                if column_block[c].replace(k).is_some() {
                    return None;
                }
            }
            for &r in &block.rows {
                if r >= n || row_block[r].replace(k).is_some() {
                    return None;
                }
            }
        }
        for (c, owner) in column_block.iter().enumerate() {
            if let Some(k) = *owner {
                if (0..n).any(|r| row_block[r] != Some(k) && x[(r, c)] != 0.0) {
                    return None;
                }
            }
        }
        let global = (0..p).filter(|&c| column_block[c].is_none()).collect();
        Some(BlockLayout { row_block, global })
    }
}

/// One unmodelled effect: linear in its parameters θ, it adds A(p) θ to the modelled
/// quantities.
pub trait Effect {
    /// Its name in the diagnosis's vocabulary (e.g. `leg_scale`).
    fn name(&self) -> &'static str;
    fn parameter_names(&self) -> Vec<String>;
    /// A(p): residuals × parameters, what a unit of each parameter adds to each modelled
    /// quantity (in the quantity's unit).
    fn columns(&self, p: &DVector<f64>) -> DMatrix<f64>;
}

/// The model's parameters and the effects' fitted together.
#[derive(Debug, Clone)]
pub struct JointFit {
    pub params: DVector<f64>,
    /// The effects' parameters, in the order of the effects and of their parameter names.
    pub theta: DVector<f64>,
    /// Covariance of [params, theta] from the whitened design (pseudo-inverse).
    pub covariance: DMatrix<f64>,
    /// Measured minus modelled minus the effects' contribution.
    pub residuals: DVector<f64>,
    /// The effects' fitted contribution to each quantity.
    pub effect_contribution: DVector<f64>,
    pub chi2: f64,
    /// Rank of the whitened design and degrees of freedom (residuals − rank).
    pub rank: usize,
    pub dof: usize,
    pub iterations: usize,
}

impl JointFit {
    pub fn sigma(&self, k: usize) -> f64 {
        self.covariance[(k, k)].max(0.0).sqrt()
    }
}

/// Relative singular value below which a direction of the design is not determined.
const RANK_CUT: f64 = 1e-9;

/// A minimum-norm least-squares solution with its rank, and what its covariance is made from.
struct Pinv {
    sol: DVector<f64>,
    rank: usize,
    covariance: CovarianceOf,
}

enum CovarianceOf {
    Whole(DMatrix<f64>),
    /// V S⁻¹ over the kept directions of the design with unit columns, and the columns'
    /// norms: the covariance V S⁻² Vᵀ back in the columns' units, made only when asked for.
    Factor(DMatrix<f64>, Vec<f64>),
}

impl Pinv {
    /// No solution: a factorisation that did not converge.
    fn zero(p: usize) -> Pinv {
        Pinv {
            sol: DVector::zeros(p),
            rank: 0,
            covariance: CovarianceOf::Whole(DMatrix::zeros(p, p)),
        }
    }

    fn covariance(self) -> DMatrix<f64> {
        match self.covariance {
            CovarianceOf::Whole(cov) => cov,
            CovarianceOf::Factor(v_scaled, norms) => {
                let mut cov = &v_scaled * v_scaled.transpose();
                unscale_covariance(&mut cov, &norms);
                cov
            }
        }
    }
}

/// Minimum-norm least squares of the whitened design `x` against `b`, and the pseudo-inverse
/// covariance (xᵀx)⁺ with the rank; block by block when the model's local `blocks` give a
/// design of full rank.
fn pinv_solve(x: &DMatrix<f64>, b: &DVector<f64>, blocks: &[LocalBlock]) -> Pinv {
    // Columns scaled to unit norm so that the rank cut does not depend on their units.
    let norms: Vec<f64> = (0..x.ncols())
        .map(|c| x.column(c).norm().max(f64::MIN_POSITIVE))
        .collect();
    let mut scaled = x.clone();
    for (c, n) in norms.iter().enumerate() {
        scaled.column_mut(c).scale_mut(1.0 / n);
    }
    if let Some((mut sol, mut cov, rank)) = super::blocked_lsq::solve_blocked(&scaled, b, blocks) {
        unscale_solution(&mut sol, &norms);
        unscale_covariance(&mut cov, &norms);
        return Pinv {
            sol,
            rank,
            covariance: CovarianceOf::Whole(cov),
        };
    }
    let p = x.ncols();
    // The solution needs the singular values, V, and each kept direction's uₖᵀb. For a tall
    // design X = QR, from R and Qᵀb (`tall_svd`: the same singular values and pseudo-inverse
    // to rounding); R's right vectors are the left ones of Rᵀ, whose SVD without its right
    // vectors costs half of R's with both, and uₖᵀ(Qᵀb) = vₖᵀRᵀ(Qᵀb)/sₖ.
    let (singular_values, v, utb) = if super::tall_svd::is_tall(scaled.nrows(), p) {
        let qr = scaled.qr();
        let mut qtb = b.clone();
        qr.q_tr_mul(&mut qtb);
        let r = qr.r();
        let rt_qtb = r.tr_mul(&qtb.rows(0, p));
        let svd = r.transpose().svd(true, false);
        let Some(v) = svd.u else {
            return Pinv::zero(p);
        };
        let utb = DVector::from_fn(p, |k, _| {
            let s = svd.singular_values[k];
            if s > 0.0 {
                v.column(k).dot(&rt_qtb) / s
            } else {
                0.0
            }
        });
        (svd.singular_values, v, utb)
    } else {
        let svd = scaled.svd(true, true);
        let (Some(u), Some(vt)) = (svd.u, svd.v_t) else {
            return Pinv::zero(p);
        };
        let utb = u.tr_mul(b);
        (svd.singular_values, vt.transpose(), utb)
    };
    let smax = singular_values.max();
    let keep: Vec<usize> = (0..singular_values.len())
        .filter(|&k| smax > 0.0 && singular_values[k] > RANK_CUT * smax)
        .collect();
    let mut sol = DVector::zeros(p);
    // V S⁻¹ over the kept directions: the covariance V S⁻² Vᵀ is one product.
    let mut v_scaled = DMatrix::zeros(p, keep.len());
    for (j, &k) in keep.iter().enumerate() {
        let s = singular_values[k];
        sol.axpy(utb[k] / s, &v.column(k), 1.0);
        v_scaled.set_column(j, &(v.column(k) / s));
    }
    unscale_solution(&mut sol, &norms);
    Pinv {
        sol,
        rank: keep.len(),
        covariance: CovarianceOf::Factor(v_scaled, norms),
    }
}

/// The solution of the design with unit columns back in the columns' units.
fn unscale_solution(sol: &mut DVector<f64>, norms: &[f64]) {
    for (value, n) in sol.iter_mut().zip(norms) {
        *value /= n;
    }
}

/// Its covariance back in the columns' units.
fn unscale_covariance(cov: &mut DMatrix<f64>, norms: &[f64]) {
    for i in 0..norms.len() {
        for j in 0..norms.len() {
            cov[(i, j)] /= norms[i] * norms[j];
        }
    }
}

/// Gauss–Newton on the model's parameters and the effects' together, from `start` (the
/// effects' parameters from zero), relinearising at each step.
pub fn joint_fit(
    model: &dyn ResidualModel,
    effects: &[&dyn Effect],
    start: &DVector<f64>,
) -> JointFit {
    let sigma = DVector::from_column_slice(model.sigma());
    let np = start.len();
    let widths: Vec<usize> = effects.iter().map(|e| e.parameter_names().len()).collect();
    let nt: usize = widths.iter().sum();
    let mut params = start.clone();
    let mut theta = DVector::zeros(nt);
    let columns = |p: &DVector<f64>| {
        let mut a = DMatrix::zeros(sigma.len(), nt);
        let mut at = 0;
        for (e, w) in effects.iter().zip(&widths) {
            a.columns_mut(at, *w).copy_from(&e.columns(p));
            at += w;
        }
        a
    };
    let residual =
        |p: &DVector<f64>, a: &DMatrix<f64>, theta: &DVector<f64>| model.residuals(p) - a * theta;
    let whitened = |m: DMatrix<f64>| {
        let mut m = m;
        for (i, s) in sigma.iter().enumerate() {
            m.row_mut(i).scale_mut(1.0 / s);
        }
        m
    };
    let blocks = model.local_blocks();
    let mut iterations = 0;
    let mut cost = f64::INFINITY;
    // The last factorisation, when it was made at the parameters returned.
    let mut at_end = None;
    for _ in 0..30 {
        iterations += 1;
        let a = columns(&params);
        let r = residual(&params, &a, &theta);
        let rw = r.component_div(&sigma);
        cost = cost.min(rw.norm_squared());
        let design = whitened(concat(&model.jacobian(&params), &a));
        let solved = pinv_solve(&design, &rw, &blocks);
        // Converged when the step would move no modelled quantity by more than 1e-6 of its
        // σ: it is not taken, so this factorisation gives the covariance at the end.
        if (&design * &solved.sol).amax() < 1e-6 {
            at_end = Some((a, r, rw, solved));
            break;
        }
        // Halve a step that raises the cost (a poor start far from the optimum).
        let mut scale = 1.0;
        let mut accepted = false;
        for _ in 0..8 {
            let p_try = &params + solved.sol.rows(0, np) * scale;
            let t_try = &theta + solved.sol.rows(np, nt) * scale;
            let c = residual(&p_try, &columns(&p_try), &t_try)
                .component_div(&sigma)
                .norm_squared();
            if c <= cost * (1.0 + 1e-12) {
                params = p_try;
                theta = t_try;
                cost = c;
                accepted = true;
                break;
            }
            scale *= 0.5;
        }
        if !accepted {
            at_end = Some((a, r, rw, solved));
            break;
        }
    }
    let (a, r, rw, solved) = at_end.unwrap_or_else(|| {
        let a = columns(&params);
        let r = residual(&params, &a, &theta);
        let rw = r.component_div(&sigma);
        let design = whitened(concat(&model.jacobian(&params), &a));
        let solved = pinv_solve(&design, &rw, &blocks);
        (a, r, rw, solved)
    });
    let rank = solved.rank;
    let covariance = solved.covariance();
    let chi2 = rw.norm_squared();
    JointFit {
        effect_contribution: &a * &theta,
        params,
        theta,
        covariance,
        residuals: r,
        chi2,
        rank,
        dof: sigma.len().saturating_sub(rank),
        iterations,
    }
}

/// [a b] side by side.
pub fn concat(a: &DMatrix<f64>, b: &DMatrix<f64>) -> DMatrix<f64> {
    let mut out = DMatrix::zeros(a.nrows(), a.ncols() + b.ncols());
    out.columns_mut(0, a.ncols()).copy_from(a);
    out.columns_mut(a.ncols(), b.ncols()).copy_from(b);
    out
}

/// The effects of `model`'s library named in `names` (comma lists allowed), in the order
/// given; an unknown name is an error listing the library.
pub fn effects_named<'a>(
    library: &'a [Box<dyn Effect + 'a>],
    names: &[String],
) -> Result<Vec<&'a dyn Effect>, String> {
    let mut out: Vec<&dyn Effect> = Vec::new();
    for name in names.iter().flat_map(|n| n.split(',')).map(str::trim) {
        if name.is_empty() || out.iter().any(|e| e.name() == name) {
            continue;
        }
        match library.iter().find(|e| e.name() == name) {
            Some(e) => out.push(e.as_ref()),
            None => {
                return Err(format!(
                    "unknown effect `{name}` for this session (its library: {})",
                    library
                        .iter()
                        .map(|e| e.name())
                        .collect::<Vec<_>>()
                        .join(", ")
                ))
            }
        }
    }
    Ok(out)
}

/// The effects' names, comma-separated (as `--effects` takes them).
pub fn effect_names(effects: &[&dyn Effect]) -> String {
    effects
        .iter()
        .map(|e| e.name())
        .collect::<Vec<_>>()
        .join(",")
}

/// One effect's fitted parameters: name → value, with `<name>.sigma` beside each.
pub fn effect_parameters(
    effects: &[&dyn Effect],
    fit: &JointFit,
    offset: usize,
) -> std::collections::BTreeMap<String, std::collections::BTreeMap<String, f64>> {
    let mut out = std::collections::BTreeMap::new();
    let mut at = 0;
    for e in effects {
        let mut params = std::collections::BTreeMap::new();
        for name in e.parameter_names() {
            params.insert(name.clone(), fit.theta[at]);
            params.insert(format!("{name}.sigma"), fit.sigma(offset + at));
            at += 1;
        }
        out.insert(e.name().to_string(), params);
    }
    out
}
