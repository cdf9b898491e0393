//! Laser probe installation calibration on a 5-axis CMM: the paper's exterior-penalty objective,
//! Levenberg–Marquardt on the constrained problem (beam as two angles), the improved GA, sphere fit.
//!
//! LM parametrises the unit beam by two tilt angles about the start direction, so the constraint
//! l² + m² + n² = 1 holds exactly and the covariance of (l, m, n) is rank 2 (it lives on the sphere).

use std::time::Instant;

use nalgebra::{DMatrix, DVector, SMatrix, SVector, Vector3};
use rand::Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::Serialize;

use crate::model::probe_install::{
    beam_in_base, probe_offset, sphere_residual, sphere_residual_jacobian, InstallParams,
    ProbeObservation, N_PARAMS, PARAM_NAMES,
};
use crate::solve::genetic::{self, GeneticOptions};

/// Penalty factor M of the paper's eq. (11).
pub const PUBLISHED_PENALTY: f64 = 1e4;

/// The paper evaluates its objective in millimetres; we divide residuals by this length so that
/// M = 1e4 keeps its published weight against the sum of squares.
pub const PAPER_LENGTH_UNIT_M: f64 = 1e-3;

/// Probe readings of one reference sphere at several postures.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ProbeInstallProblem {
    /// Nominal (design) installation: the LM start and the centre of the GA search box.
    pub nominal: InstallParams,
    /// Calibrated radius of the reference sphere.
    pub sphere_radius_m: f64,
    pub observations: Vec<ProbeObservation>,
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ProbeInstallError {
    #[error("invalid probe installation problem: {0}")]
    InvalidInput(String),
    #[error("probe installation is singular: {0}")]
    Singular(String),
}

fn validate(problem: &ProbeInstallProblem) -> Result<(), ProbeInstallError> {
    let n = problem.observations.len();
    if n < 10 {
        return Err(ProbeInstallError::InvalidInput(format!(
            "{n} observations given; 11 parameters with one constraint need at least 10"
        )));
    }
    if problem.sphere_radius_m.is_nan() || problem.sphere_radius_m <= 0.0 {
        return Err(ProbeInstallError::InvalidInput(format!(
            "sphere_radius_m = {} must be positive",
            problem.sphere_radius_m
        )));
    }
    if problem.nominal.beam().norm() < 1e-6 {
        return Err(ProbeInstallError::InvalidInput(
            "nominal beam direction is zero".into(),
        ));
    }
    for (i, o) in problem.observations.iter().enumerate() {
        let finite = o.a_rad.is_finite()
            && o.b_rad.is_finite()
            && o.reading_m.is_finite()
            && o.machine_m.iter().all(|v| v.is_finite());
        if !finite || o.sigma_m.is_nan() || o.sigma_m <= 0.0 {
            return Err(ProbeInstallError::InvalidInput(format!(
                "observation {i}: non-finite value or sigma_m <= 0"
            )));
        }
    }
    Ok(())
}

/// Sum of squared sphere residuals (m²).
pub fn sum_of_squares_m2(problem: &ProbeInstallProblem, p: &InstallParams) -> f64 {
    problem
        .observations
        .iter()
        .map(|o| sphere_residual(p, o, problem.sphere_radius_m).powi(2))
        .sum()
}

/// The exterior-penalty objective of eq. (11): Σ (r / 1 mm)² + M h², h = l² + m² + n² − 1.
/// Dimensionless; our residuals are point-on-sphere distances rather than the paper's centre
/// differences (see docs/probe-install.md).
pub fn penalty_objective(problem: &ProbeInstallProblem, p: &InstallParams, penalty: f64) -> f64 {
    sum_of_squares_m2(problem, p) / PAPER_LENGTH_UNIT_M.powi(2)
        + penalty * p.unit_norm_violation().powi(2)
}

/// Levenberg–Marquardt controls.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LmOptions {
    pub max_iterations: usize,
    /// Converged when an accepted step lowers the cost by less than this fraction.
    pub tolerance: f64,
    pub initial_lambda: f64,
}

impl Default for LmOptions {
    fn default() -> Self {
        Self {
            max_iterations: 200,
            tolerance: 1e-14,
            initial_lambda: 1e-3,
        }
    }
}

/// LM estimate with the Cramér–Rao covariance (JᵀWJ)⁻¹ from the reading sigmas.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ProbeInstallSolution {
    pub params: InstallParams,
    /// Standard uncertainties in [`PARAM_NAMES`] order.
    pub sigma: [f64; N_PARAMS],
    /// 11 x 11 covariance (row-major), rank 10: the beam direction varies only on the unit sphere.
    pub covariance: Vec<[f64; N_PARAMS]>,
    pub parameter_names: [&'static str; N_PARAMS],
    /// Per observation, measured point distance from the sphere minus the radius.
    pub residuals_m: Vec<f64>,
    pub residual_rms_m: f64,
    /// Σ (r/σ)²; about `dof` when the noise model holds.
    pub chi2: f64,
    /// Observations − 10 free parameters.
    pub dof: usize,
    /// [`penalty_objective`] with M = 1e4 at the estimate (h = 0 to rounding).
    pub objective: f64,
    pub unit_norm_violation: f64,
    pub iterations: usize,
    pub converged: bool,
    pub wall_time_s: f64,
    /// Per parameter ([`PARAM_NAMES`] order), whether the postures identify it: false when it
    /// takes part in a direction the weighted Jacobian cannot see (then its `sigma` means
    /// nothing and is reported as none).
    pub identifiable: [bool; N_PARAMS],
    /// The directions the postures cannot see, as combinations of the solver's free parameters.
    pub unseen_directions: Vec<String>,
    /// One free parameter per unseen direction, held at its start value (the nominal) so the
    /// unseen directions do not steer LM.
    pub held_at_start: Vec<&'static str>,
}

/// The solver's 10 free parameters: the beam as two tilts about its start direction.
pub const FREE_NAMES: [&str; 10] = [
    "b_offset_rad",
    "y_offset_m",
    "beam_tilt_e1_rad",
    "beam_tilt_e2_rad",
    "zero_point_x_m",
    "zero_point_y_m",
    "zero_point_z_m",
    "sphere_centre_x_m",
    "sphere_centre_y_m",
    "sphere_centre_z_m",
];

/// An angle brought into (−π, π].
pub fn wrap_angle(a: f64) -> f64 {
    let w = a.rem_euclid(std::f64::consts::TAU);
    if w > std::f64::consts::PI {
        w - std::f64::consts::TAU
    } else {
        w
    }
}

/// Orthonormal (e1, e2) completing `e3` to a right-handed basis.
pub fn tangent_basis(e3: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>) {
    let helper = if e3.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let e1 = (helper - e3 * e3.dot(&helper)).normalize();
    let e2 = e3.cross(&e1);
    (e1, e2)
}

/// Internal LM parameters: (δB, y32, α, β, Q43, S0); the beam is
/// u = cos β (cos α e3 + sin α e1) + sin β e2, never singular near the start direction e3.
struct BeamChart {
    e1: Vector3<f64>,
    e2: Vector3<f64>,
    e3: Vector3<f64>,
}

impl BeamChart {
    fn beam(&self, alpha: f64, beta: f64) -> Vector3<f64> {
        beta.cos() * (alpha.cos() * self.e3 + alpha.sin() * self.e1) + beta.sin() * self.e2
    }
    /// ∂u/∂α, ∂u/∂β.
    fn beam_derivatives(&self, alpha: f64, beta: f64) -> (Vector3<f64>, Vector3<f64>) {
        let da = beta.cos() * (-alpha.sin() * self.e3 + alpha.cos() * self.e1);
        let db =
            -beta.sin() * (alpha.cos() * self.e3 + alpha.sin() * self.e1) + beta.cos() * self.e2;
        (da, db)
    }
    fn params(&self, z: &SVector<f64, 10>) -> InstallParams {
        let u = self.beam(z[2], z[3]);
        InstallParams {
            b_offset_rad: z[0],
            y_offset_m: z[1],
            beam_dir: [u.x, u.y, u.z],
            zero_point_m: [z[4], z[5], z[6]],
            sphere_centre_m: [z[7], z[8], z[9]],
        }
    }
    /// ∂X/∂z (11 x 10).
    fn chain(&self, z: &SVector<f64, 10>) -> SMatrix<f64, N_PARAMS, 10> {
        let mut g = SMatrix::<f64, N_PARAMS, 10>::zeros();
        g[(0, 0)] = 1.0;
        g[(1, 1)] = 1.0;
        let (da, db) = self.beam_derivatives(z[2], z[3]);
        for k in 0..3 {
            g[(2 + k, 2)] = da[k];
            g[(2 + k, 3)] = db[k];
        }
        for k in 0..6 {
            g[(5 + k, 4 + k)] = 1.0;
        }
        g
    }
}

/// Standard deviation of each sphere residual: the reading sigma times |∂r/∂t| = |e · w|, the
/// cosine between the beam and the surface normal (a reading on the cap's flank moves the point
/// mostly along the surface). Floored so grazing points cannot dominate.
pub(crate) fn residual_sigmas(problem: &ProbeInstallProblem, p: &InstallParams) -> Vec<f64> {
    problem
        .observations
        .iter()
        .map(|o| {
            let q = crate::model::probe_install::surface_point(p, o);
            let e = (q - p.sphere_centre()).normalize();
            let w = beam_in_base(p, o.a_rad, o.b_rad);
            o.sigma_m * e.dot(&w).abs().max(0.05)
        })
        .collect()
}

fn weighted_cost(problem: &ProbeInstallProblem, p: &InstallParams, sigmas: &[f64]) -> f64 {
    problem
        .observations
        .iter()
        .zip(sigmas)
        .map(|(o, s)| (sphere_residual(p, o, problem.sphere_radius_m) / s).powi(2))
        .sum()
}

/// The whitened Jacobian (rows: readings / their σ; columns: [`FREE_NAMES`]) of `problem`'s
/// readings at `p` in `chart`.
fn whitened_jacobian(
    problem: &ProbeInstallProblem,
    chart: &BeamChart,
    z: &SVector<f64, 10>,
) -> DMatrix<f64> {
    let p = chart.params(z);
    let g = chart.chain(z);
    let sigmas = residual_sigmas(problem, &p);
    let mut j = DMatrix::zeros(problem.observations.len(), 10);
    for (r, (o, s)) in problem.observations.iter().zip(&sigmas).enumerate() {
        let (_, jx) = sphere_residual_jacobian(&p, o, problem.sphere_radius_m);
        let jz = (jx * g) / *s;
        for c in 0..10 {
            j[(r, c)] = jz[c];
        }
    }
    j
}

/// A singular value of the column-scaled whitened Jacobian below this fraction of the largest
/// is zero (the plan check's tolerance).
const RANK_TOLERANCE: f64 = 1e-8;
/// A parameter whose gradient has more than this share (scaled) in the null space is not
/// identifiable (the plan check's).
const NULL_SHARE: f64 = 1e-6;

/// Column scales (norms) of `jw` and an orthonormal basis of the null space of the scaled
/// Jacobian.
fn null_space(jw: &DMatrix<f64>) -> (Vec<f64>, Vec<DVector<f64>>) {
    let n = jw.ncols();
    let scale: Vec<f64> = (0..n)
        .map(|k| {
            let s = jw.column(k).norm();
            if s > 0.0 && s.is_finite() {
                s
            } else {
                1.0
            }
        })
        .collect();
    let rows = jw.nrows().max(n);
    let js = DMatrix::from_fn(rows, n, |r, c| {
        if r < jw.nrows() {
            jw[(r, c)] / scale[c]
        } else {
            0.0
        }
    });
    let svd = js.svd(false, true);
    let Some(v_t) = svd.v_t else {
        return (scale, Vec::new());
    };
    let s = &svd.singular_values;
    let largest = s.iter().copied().fold(0.0, f64::max);
    let null = (0..s.len())
        .filter(|&i| !(s[i] > largest * RANK_TOLERANCE && s[i] > 0.0))
        .map(|i| v_t.row(i).transpose())
        .collect();
    (scale, null)
}

/// Components of an unseen direction smaller than this (scaled, pivot 1) are left out of its
/// name.
const COMPONENT_SHOWN: f64 = 1e-3;

/// The unseen directions of `jw` in reduced row echelon form: each one's pivot (a free
/// parameter no other direction involves, the largest available) and its name as a
/// combination of free parameters in their units per unit of the pivot.
fn unseen_directions(jw: &DMatrix<f64>) -> (Vec<usize>, Vec<String>) {
    let (scale, null) = null_space(jw);
    let mut basis: Vec<Vec<f64>> = null.iter().map(|v| v.iter().copied().collect()).collect();
    let mut pivots: Vec<usize> = Vec::new();
    for r in 0..basis.len() {
        let Some(p) = (0..FREE_NAMES.len())
            .filter(|c| !pivots.contains(c))
            .max_by(|&a, &b| basis[r][a].abs().total_cmp(&basis[r][b].abs()))
        else {
            break;
        };
        let lead = basis[r][p];
        basis[r].iter_mut().for_each(|v| *v /= lead);
        let row = basis[r].clone();
        for (o, other) in basis.iter_mut().enumerate() {
            if o != r {
                let f = other[p];
                other.iter_mut().zip(&row).for_each(|(v, w)| *v -= f * w);
            }
        }
        pivots.push(p);
    }
    let names = basis
        .iter()
        .zip(&pivots)
        .map(|(z, &p)| {
            let mut text = FREE_NAMES[p].to_string();
            for (c, v) in z.iter().enumerate() {
                if c != p && v.abs() > COMPONENT_SHOWN {
                    let k = (v / scale[c]) / (z[p] / scale[p]);
                    let sign = if k < 0.0 { '-' } else { '+' };
                    text.push_str(&format!(" {sign} {:.4e} {}", k.abs(), FREE_NAMES[c]));
                }
            }
            text
        })
        .collect();
    (pivots, names)
}

/// Levenberg–Marquardt from `start` (usually the nominal installation); what the postures
/// cannot see is judged on `problem` itself (see [`solve_lm_with_design`]).
pub fn solve_lm(
    problem: &ProbeInstallProblem,
    start: &InstallParams,
    options: &LmOptions,
) -> Result<ProbeInstallSolution, ProbeInstallError> {
    solve_lm_with_design(problem, start, options, problem)
}

/// Levenberg–Marquardt from `start`, with an identifiability check first: the rank of the
/// whitened Jacobian of `design` (the same points at their commanded postures: the plan's
/// geometry, free of servo scatter that would make a blind direction look barely seen) at the
/// start, as the plan check computes it. One free parameter per unseen direction is held at
/// its start value; every parameter taking part in an unseen direction is reported as not
/// identifiable.
pub fn solve_lm_with_design(
    problem: &ProbeInstallProblem,
    start: &InstallParams,
    options: &LmOptions,
    design: &ProbeInstallProblem,
) -> Result<ProbeInstallSolution, ProbeInstallError> {
    validate(problem)?;
    let t0 = Instant::now();
    let e3 = start.beam().normalize();
    let (e1, e2) = tangent_basis(&e3);
    let chart = BeamChart { e1, e2, e3 };
    let mut z = SVector::<f64, 10>::zeros();
    z[0] = start.b_offset_rad;
    z[1] = start.y_offset_m;
    for k in 0..3 {
        z[4 + k] = start.zero_point_m[k];
        z[7 + k] = start.sphere_centre_m[k];
    }
    // Per unseen direction, its pivot (reduced echelon form) is held at the start.
    let (pivots, _) = unseen_directions(&whitened_jacobian(design, &chart, &z));
    let mut held = [false; 10];
    for &k in &pivots {
        held[k] = true;
    }
    let held_at_start: Vec<&'static str> = pivots.iter().map(|&k| FREE_NAMES[k]).collect();
    let free_count = held.iter().filter(|h| !**h).count();
    let n = problem.observations.len();
    let radius = problem.sphere_radius_m;
    let normal = |z: &SVector<f64, 10>, sigmas: &[f64]| {
        let p = chart.params(z);
        let g = chart.chain(z);
        let mut a = SMatrix::<f64, 10, 10>::zeros();
        let mut b = SVector::<f64, 10>::zeros();
        for (o, s) in problem.observations.iter().zip(sigmas) {
            let (r, jx) = sphere_residual_jacobian(&p, o, radius);
            let jz = (jx * g) / *s;
            let rw = r / *s;
            a += jz.transpose() * jz;
            b += jz.transpose() * rw;
        }
        // Held parameters take no step: identity rows and columns, no gradient.
        for k in (0..10).filter(|&k| held[k]) {
            for c in 0..10 {
                a[(k, c)] = 0.0;
                a[(c, k)] = 0.0;
            }
            a[(k, k)] = 1.0;
            b[k] = 0.0;
        }
        (a, b)
    };
    let mut lambda = options.initial_lambda;
    let mut iterations = 0;
    let mut converged = false;
    while iterations < options.max_iterations {
        // Weights are held within an outer iteration so every trial is judged on one cost.
        let sigmas = residual_sigmas(problem, &chart.params(&z));
        let mut cost = weighted_cost(problem, &chart.params(&z), &sigmas);
        let (a, b) = normal(&z, &sigmas);
        let mut accepted = false;
        while iterations < options.max_iterations {
            iterations += 1;
            let mut damped = a;
            for k in 0..10 {
                damped[(k, k)] += lambda * a[(k, k)].max(1e-300);
            }
            let Some(chol) = damped.cholesky() else {
                lambda *= 10.0;
                continue;
            };
            let step = -chol.solve(&b);
            let trial = z + step;
            let trial_cost = weighted_cost(problem, &chart.params(&trial), &sigmas);
            if trial_cost.is_finite() && trial_cost <= cost {
                let drop = cost - trial_cost;
                z = trial;
                let small = drop <= options.tolerance * cost.max(f64::MIN_POSITIVE);
                cost = trial_cost;
                lambda = (lambda / 10.0).max(1e-15);
                accepted = true;
                if small {
                    converged = true;
                }
                break;
            }
            lambda *= 10.0;
            if lambda > 1e16 {
                // No descent direction left at machine precision: the minimum is reached.
                converged = true;
                break;
            }
        }
        if converged || !accepted {
            break;
        }
    }
    let sigmas = residual_sigmas(problem, &chart.params(&z));
    let cost = weighted_cost(problem, &chart.params(&z), &sigmas);
    let (a, _) = normal(&z, &sigmas);
    let mut cov_z = a.try_inverse().ok_or_else(|| {
        ProbeInstallError::Singular(
            "normal matrix not invertible: the postures do not identify the parameters left \
             free"
                .into(),
        )
    })?;
    for k in (0..10).filter(|&k| held[k]) {
        for c in 0..10 {
            cov_z[(k, c)] = 0.0;
            cov_z[(c, k)] = 0.0;
        }
    }
    z[0] = wrap_angle(z[0]);
    let g = chart.chain(&z);
    let cov = g * cov_z * g.transpose();
    let params = chart.params(&z);
    // What is unseen is judged again at the solution: a direction can mix in parameters whose
    // lever arm vanishes at the start (δB turns the beam and zero point about z, which does
    // nothing to the design beam on the z axis but moves the installed one).
    let (_, unseen) = unseen_directions(&whitened_jacobian(design, &chart, &z));
    // A parameter is identifiable when its gradient in the free parameters has no part in the
    // unseen directions (beam_n, say, is unchanged by turning the beam about z).
    let (scale, null) = null_space(&whitened_jacobian(design, &chart, &z));
    let identifiable: [bool; N_PARAMS] = std::array::from_fn(|k| {
        let row: Vec<f64> = (0..10).map(|c| g[(k, c)] / scale[c]).collect();
        let norm2: f64 = row.iter().map(|v| v * v).sum();
        let unseen2: f64 = null
            .iter()
            .map(|v| {
                row.iter()
                    .zip(v.iter())
                    .map(|(a, b)| a * b)
                    .sum::<f64>()
                    .powi(2)
            })
            .sum();
        norm2 > 0.0 && unseen2 <= NULL_SHARE * norm2
    });
    let residuals_m: Vec<f64> = problem
        .observations
        .iter()
        .map(|o| sphere_residual(&params, o, radius))
        .collect();
    let residual_rms_m = (residuals_m.iter().map(|r| r * r).sum::<f64>() / n as f64).sqrt();
    let mut sigma = [0.0; N_PARAMS];
    let mut covariance = vec![[0.0; N_PARAMS]; N_PARAMS];
    for i in 0..N_PARAMS {
        sigma[i] = cov[(i, i)].max(0.0).sqrt();
        for j in 0..N_PARAMS {
            covariance[i][j] = cov[(i, j)];
        }
    }
    Ok(ProbeInstallSolution {
        objective: penalty_objective(problem, &params, PUBLISHED_PENALTY),
        unit_norm_violation: params.unit_norm_violation(),
        params,
        sigma,
        covariance,
        parameter_names: PARAM_NAMES,
        residuals_m,
        residual_rms_m,
        chi2: cost,
        dof: n.saturating_sub(free_count),
        iterations,
        converged,
        wall_time_s: t0.elapsed().as_secs_f64(),
        identifiable,
        unseen_directions: unseen,
        held_at_start,
    })
}

/// Half-widths of the GA search box around the nominal installation, in [`PARAM_NAMES`] order.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SearchBox {
    pub half_width: [f64; N_PARAMS],
}

impl Default for SearchBox {
    /// ±0.02 rad on δB, ±2 mm on lengths, ±0.02 on each beam component: a mis-installed probe
    /// on its fixture, and a sphere placed within a few millimetres of its nominal position.
    fn default() -> Self {
        Self {
            half_width: [
                0.02, 2e-3, 0.02, 0.02, 0.02, 2e-3, 2e-3, 2e-3, 2e-3, 2e-3, 2e-3,
            ],
        }
    }
}

/// Improved-GA estimate: the best individual and how it got there.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ProbeInstallGaSolution {
    pub params: InstallParams,
    /// [`penalty_objective`] with the penalty used.
    pub objective: f64,
    pub unit_norm_violation: f64,
    pub evaluations: usize,
    /// Individuals replaced by random ones for being too close to the best.
    pub replaced: usize,
    /// Best objective after each generation.
    pub history: Vec<f64>,
    pub wall_time_s: f64,
}

/// Minimises the exterior-penalty objective (M = `penalty`) with the improved GA over `search`.
pub fn solve_ga(
    problem: &ProbeInstallProblem,
    search: &SearchBox,
    penalty: f64,
    options: &GeneticOptions,
) -> Result<ProbeInstallGaSolution, ProbeInstallError> {
    validate(problem)?;
    let t0 = Instant::now();
    let centre = problem.nominal.to_vector();
    let lower: Vec<f64> = (0..N_PARAMS)
        .map(|k| centre[k] - search.half_width[k])
        .collect();
    let upper: Vec<f64> = (0..N_PARAMS)
        .map(|k| centre[k] + search.half_width[k])
        .collect();
    let objective = |x: &[f64]| {
        let p = InstallParams::from_vector(&SVector::<f64, N_PARAMS>::from_column_slice(x));
        penalty_objective(problem, &p, penalty)
    };
    let result = genetic::minimise(objective, &lower, &upper, options)
        .map_err(|e| ProbeInstallError::InvalidInput(e.to_string()))?;
    let params =
        InstallParams::from_vector(&SVector::<f64, N_PARAMS>::from_column_slice(&result.best));
    Ok(ProbeInstallGaSolution {
        unit_norm_violation: params.unit_norm_violation(),
        params,
        objective: result.best_objective,
        evaluations: result.evaluations,
        replaced: result.replaced,
        history: result.history,
        wall_time_s: t0.elapsed().as_secs_f64(),
    })
}

/// Least-squares sphere through points: (centre, radius, rms of the radial residuals).
/// Algebraic fit for the start, then Gauss–Newton on the geometric distances.
pub fn fit_sphere(points: &[Vector3<f64>]) -> Result<(Vector3<f64>, f64, f64), ProbeInstallError> {
    let n = points.len();
    if n < 4 {
        return Err(ProbeInstallError::InvalidInput(format!(
            "{n} points given; a sphere needs at least 4"
        )));
    }
    // Centred coordinates keep the algebraic system well conditioned far from the origin.
    let mean = points.iter().sum::<Vector3<f64>>() / n as f64;
    let mut a = DMatrix::<f64>::zeros(n, 4);
    let mut b = DVector::<f64>::zeros(n);
    for (i, p) in points.iter().enumerate() {
        let q = p - mean;
        a[(i, 0)] = 2.0 * q.x;
        a[(i, 1)] = 2.0 * q.y;
        a[(i, 2)] = 2.0 * q.z;
        a[(i, 3)] = 1.0;
        b[i] = q.norm_squared();
    }
    let sol = a
        .svd(true, true)
        .solve(&b, 1e-14)
        .map_err(|e| ProbeInstallError::Singular(e.to_string()))?;
    let mut c = Vector3::new(sol[0], sol[1], sol[2]);
    let mut r = (sol[3] + c.norm_squared()).max(0.0).sqrt();
    for _ in 0..20 {
        let mut jtj = nalgebra::Matrix4::<f64>::zeros();
        let mut jtr = nalgebra::Vector4::<f64>::zeros();
        for p in points {
            let d = p - mean - c;
            let dist = d.norm();
            let e = d / dist;
            let row = nalgebra::Vector4::new(-e.x, -e.y, -e.z, -1.0);
            let res = dist - r;
            jtj += row * row.transpose();
            jtr += row * res;
        }
        let Some(step) = jtj.cholesky().map(|ch| -ch.solve(&jtr)) else {
            return Err(ProbeInstallError::Singular(
                "sphere fit: points are coplanar or collinear".into(),
            ));
        };
        c += step.fixed_rows::<3>(0);
        r += step[3];
        if step.norm() < 1e-15 {
            break;
        }
    }
    let rms = (points
        .iter()
        .map(|p| ((p - mean - c).norm() - r).powi(2))
        .sum::<f64>()
        / n as f64)
        .sqrt();
    Ok((c + mean, r, rms))
}

/// Sphere radius measured with the given installation parameters: every reading is turned into
/// a point (eq. 7) and one sphere is fitted through all postures' points together.
pub fn measured_radius_m(
    params: &InstallParams,
    observations: &[ProbeObservation],
) -> Result<f64, ProbeInstallError> {
    let pts: Vec<Vector3<f64>> = observations
        .iter()
        .map(|o| crate::model::probe_install::surface_point(params, o))
        .collect();
    fit_sphere(&pts).map(|(_, r, _)| r)
}

/// How to synthesise readings of the reference sphere (tests, the example, the later sim).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SimulationSpec {
    /// (A, B) postures in radians.
    pub postures_rad: Vec<(f64, f64)>,
    pub points_per_posture: usize,
    /// Largest angle between a probed point's surface normal and the beam (visible cap).
    pub cap_half_angle_rad: f64,
    /// Readings are drawn uniformly in ±this, so the beam direction is observable.
    pub reading_half_range_m: f64,
    pub noise_sigma_m: f64,
}

/// Readings of the sphere `truth.sphere_centre_m` (radius `radius_m`) under the true installation:
/// pick a visible surface point and a reading, then the machine position that puts them together.
pub fn simulate<R: Rng>(
    truth: &InstallParams,
    radius_m: f64,
    spec: &SimulationSpec,
    rng: &mut R,
) -> Vec<ProbeObservation> {
    let mut out = Vec::with_capacity(spec.postures_rad.len() * spec.points_per_posture);
    let c = truth.sphere_centre();
    for &(a, b) in &spec.postures_rad {
        let w = beam_in_base(truth, a, b).normalize();
        let (e1, e2) = tangent_basis(&w);
        for _ in 0..spec.points_per_posture {
            // Uniform on the spherical cap facing the probe (normal within the half-angle of −w).
            let cos_min = spec.cap_half_angle_rad.cos();
            let ct = 1.0 - rng.random::<f64>() * (1.0 - cos_min);
            let st = (1.0 - ct * ct).max(0.0).sqrt();
            let phi = rng.random::<f64>() * std::f64::consts::TAU;
            let normal = -ct * w + st * (phi.cos() * e1 + phi.sin() * e2);
            let surface = c + radius_m * normal;
            let reading = (2.0 * rng.random::<f64>() - 1.0) * spec.reading_half_range_m;
            let machine = surface - probe_offset(truth, a, b, reading);
            let noise: f64 = StandardNormal.sample(rng);
            out.push(ProbeObservation {
                a_rad: a,
                b_rad: b,
                machine_m: [machine.x, machine.y, machine.z],
                reading_m: reading + spec.noise_sigma_m * noise,
                sigma_m: spec.noise_sigma_m.max(1e-9),
            });
        }
    }
    out
}

/// The paper's calibration postures (A, B) = (0, 0), (90°, 0), (−90°, 0), (90°, 90°).
pub fn published_postures_rad() -> Vec<(f64, f64)> {
    let q = std::f64::consts::FRAC_PI_2;
    vec![(0.0, 0.0), (q, 0.0), (-q, 0.0), (q, q)]
}

/// Design installation used by the tests and the example: beam along −Z, zero point 60 mm below
/// the A axis, sphere at a fixed place on the table.
pub fn example_nominal() -> InstallParams {
    InstallParams {
        b_offset_rad: 0.0,
        y_offset_m: 0.0,
        beam_dir: [0.0, 0.0, -1.0],
        zero_point_m: [0.0, 0.0, -0.060],
        sphere_centre_m: [0.100, 0.080, -0.120],
    }
}

/// A realistic mis-installation of [`example_nominal`]: 1.5 mrad on δB, 0.25 mm on y32,
/// a 3.6 mrad beam tilt, zero point off by a few tenths of a millimetre, sphere off by ~1 mm.
pub fn example_truth() -> InstallParams {
    let nominal = example_nominal();
    let (tx, ty) = (3.0e-3_f64, -2.0e-3_f64);
    let u = Vector3::new(tx.sin(), ty.sin(), -1.0).normalize();
    InstallParams {
        b_offset_rad: 1.5e-3,
        y_offset_m: 0.25e-3,
        beam_dir: [u.x, u.y, u.z],
        zero_point_m: [0.15e-3, -0.10e-3, -0.060 + 0.20e-3],
        sphere_centre_m: [
            nominal.sphere_centre_m[0] + 1.0e-3,
            nominal.sphere_centre_m[1] - 0.8e-3,
            nominal.sphere_centre_m[2] + 0.5e-3,
        ],
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    const RADIUS_M: f64 = 6e-3;

    fn problem(points_per_posture: usize, noise_sigma_m: f64, seed: u64) -> ProbeInstallProblem {
        let spec = SimulationSpec {
            postures_rad: published_postures_rad(),
            points_per_posture,
            cap_half_angle_rad: 60f64.to_radians(),
            reading_half_range_m: 2e-3,
            noise_sigma_m,
        };
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        ProbeInstallProblem {
            nominal: example_nominal(),
            sphere_radius_m: RADIUS_M,
            observations: simulate(&example_truth(), RADIUS_M, &spec, &mut rng),
        }
    }

    #[test]
    fn lm_is_exact_on_noise_free_data() {
        let pr = problem(12, 0.0, 3);
        let sol = solve_lm(&pr, &pr.nominal, &LmOptions::default()).unwrap();
        let err = sol.params.to_vector() - example_truth().to_vector();
        assert!(sol.converged);
        for k in 0..N_PARAMS {
            assert!(err[k].abs() < 1e-11, "{}: {:e}", PARAM_NAMES[k], err[k]);
        }
        assert!(sol.residual_rms_m < 1e-12);
    }

    #[test]
    fn lm_recovers_truth_within_three_sigma() {
        // Per seed every parameter within 3σ (seeds 20..25); over 20 seeds (220 normalised
        // errors) their rms must be near 1, i.e. the covariance is neither optimistic nor loose.
        let mut sum_z2 = 0.0;
        let mut count = 0;
        for seed in 10..30 {
            let pr = problem(20, 1e-6, seed);
            let sol = solve_lm(&pr, &pr.nominal, &LmOptions::default()).unwrap();
            assert!(sol.converged);
            assert!(sol.unit_norm_violation.abs() < 1e-12);
            let err = sol.params.to_vector() - example_truth().to_vector();
            for k in 0..N_PARAMS {
                // n is second order in the tilt, so its first-order sigma is tiny: allow 1e-9.
                if (20..25).contains(&seed) {
                    assert!(
                        err[k].abs() <= 3.0 * sol.sigma[k] + 1e-9,
                        "seed {seed} {}: err {:e} sigma {:e}",
                        PARAM_NAMES[k],
                        err[k],
                        sol.sigma[k]
                    );
                }
                sum_z2 += (err[k] / sol.sigma[k]).powi(2);
                count += 1;
            }
            // chi² per degree of freedom near 1 when the noise model holds (70 dof).
            let ratio = sol.chi2 / sol.dof as f64;
            assert!((0.5..1.6).contains(&ratio), "chi2/dof {ratio}");
        }
        let rms = (sum_z2 / count as f64).sqrt();
        assert!((0.8..1.25).contains(&rms), "rms normalised error {rms}");
    }

    #[test]
    fn ga_is_within_stated_factor_of_lm_and_lm_is_not_worse() {
        let pr = problem(8, 1e-6, 21);
        let lm = solve_lm(&pr, &pr.nominal, &LmOptions::default()).unwrap();
        let opts = GeneticOptions {
            population: 100,
            generations: 1000,
            seed: 7,
            ..Default::default()
        };
        let ga = solve_ga(&pr, &SearchBox::default(), PUBLISHED_PENALTY, &opts).unwrap();
        assert!(
            ga.objective <= GA_FACTOR * lm.objective,
            "GA {:e} LM {:e}",
            ga.objective,
            lm.objective
        );
        assert!(lm.objective <= ga.objective * (1.0 + 1e-9));
        // Penalty handling: M = 1e4 holds the unit norm.
        assert!(
            ga.unit_norm_violation.abs() < 1e-4,
            "{:e}",
            ga.unit_norm_violation
        );
    }

    /// The GA objective may exceed LM's by at most this factor on the small case (32 readings,
    /// N = 100, G = 1000, seed 7: observed 132; with 100 readings and G = 2000 the example sees 3.7).
    const GA_FACTOR: f64 = 200.0;

    #[test]
    fn penalty_term_is_what_holds_the_norm() {
        let pr = problem(8, 1e-6, 5);
        let mut p = example_truth();
        let base = penalty_objective(&pr, &p, PUBLISHED_PENALTY);
        p.beam_dir[2] *= 1.0 + 1e-3;
        let h = p.unit_norm_violation();
        let with = penalty_objective(&pr, &p, PUBLISHED_PENALTY);
        // Scaling the beam by 1e-3 costs M h² ≈ 4e-2, far above the data term at 1 µm noise.
        assert!(with - base > 0.9 * PUBLISHED_PENALTY * h * h);
        assert!(PUBLISHED_PENALTY * h * h > 100.0 * base);
    }

    #[test]
    fn radius_is_recovered_after_calibration() {
        let pr = problem(20, 1e-6, 31);
        let sol = solve_lm(&pr, &pr.nominal, &LmOptions::default()).unwrap();
        let r = measured_radius_m(&sol.params, &pr.observations).unwrap();
        assert!((r - RADIUS_M).abs() < 1e-6, "{r}");
    }

    #[test]
    fn sphere_fit_is_exact_on_exact_points() {
        let c = Vector3::new(0.1, -0.2, 0.3);
        let pts: Vec<_> = (0..30)
            .map(|i| {
                let t = i as f64 * 0.7;
                let z = (i as f64 / 15.0) - 1.0;
                let s = (1.0 - z * z).sqrt();
                c + 6e-3 * Vector3::new(s * t.cos(), s * t.sin(), z)
            })
            .collect();
        let (cc, r, rms) = fit_sphere(&pts).unwrap();
        assert!((cc - c).norm() < 1e-12 && (r - 6e-3).abs() < 1e-12 && rms < 1e-12);
    }

    #[test]
    fn bad_input_is_an_error() {
        let mut pr = problem(3, 1e-6, 1);
        pr.observations.truncate(5);
        assert!(solve_lm(&pr, &pr.nominal, &LmOptions::default()).is_err());
        let mut pr = problem(4, 1e-6, 1);
        pr.sphere_radius_m = -1.0;
        assert!(solve_lm(&pr, &pr.nominal, &LmOptions::default()).is_err());
    }
}
