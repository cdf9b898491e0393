//! Decomposition of measured volumetric errors into the 21 geometric errors of a 3-axis machine
//! (quasi-rigid-body model): elastic net + QR for one target offset, weighted least squares for several.
//!
//! Unknowns: per axis the 6 error values at each of its grid positions, the 3 squareness values
//! and 6 rigid-motion nuisance parameters (the point errors come in the multilateration's
//! inner-constraint gauge, so any rigid motion of the whole field is meaningless). The datum
//! (docs/kinematics.md, "Decomposition") fixes the values the data cannot see: a candidate
//! constraint "parameter = 0" is applied only when that parameter is not estimable, so the
//! datum never changes the fitted field. Whatever is still not estimable after the datum is
//! reported as `identifiable: false` with null values, never as a number.

use std::time::Instant;

use nalgebra::{DMatrix, DVector, Matrix3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use serde::ser::SerializeMap;
use serde::{Serialize, Serializer};

use crate::model::kinematics::{
    actual_position, error_jacobian, nominal_position, Axis, AxisErrors, GeometricErrors,
    Squareness, Structure, SQUARENESS_COLUMN,
};
use crate::solve::elastic_net::{cross_validate, CvOptions, ElasticNet, ElasticNetOptions};
use crate::solve::multilateration::best_fit_rigid;

/// One measured point: commanded axis positions, reflector offset (tool frame), measured
/// volumetric error (actual − nominal, inner-constraint gauge) and its covariance.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PointObservation {
    pub axes_m: [f64; 3],
    pub target_offset_m: [f64; 3],
    pub error_m: [f64; 3],
    /// 3x3 covariance of `error_m`, m².
    pub covariance: Matrix3<f64>,
}

/// Which solver the decomposition uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Route {
    /// Elastic net (CV-chosen λ, α) for what one offset determines, QR least squares for the
    /// deferred rotations (ref1).
    ElasticNetQr,
    /// Weighted least squares on the full model, exact covariance.
    WeightedLeastSquares,
}

/// Controls of the decomposition.
#[derive(Clone, Debug, PartialEq)]
pub struct DecompositionOptions {
    /// `None`: elastic net + QR for one distinct target offset, WLS for two or more.
    pub route: Option<Route>,
    /// Cross-validation grid of the elastic-net route.
    pub cv: CvOptions,
    /// After CV selection, refit the selected (non-zero) columns by ridge-regularised least
    /// squares with the chosen L2 part, so that values and reported sigmas belong together.
    pub ridge_refit: bool,
    /// Singular values below this fraction of the largest (column-normalised whitened
    /// design) count as zero: exact collinearity, not weak determination.
    pub rank_tolerance: f64,
    /// Points whose axis position is within this of a grid position sit on it.
    pub grid_tolerance_m: f64,
    /// Offsets closer than this are the same offset.
    pub offset_tolerance_m: f64,
}

impl Default for DecompositionOptions {
    fn default() -> Self {
        DecompositionOptions {
            route: None,
            cv: CvOptions {
                fit: ElasticNetOptions {
                    standardize: true,
                    // The rigid-motion projection already centres the columns (exactly for
                    // isotropic weights); an intercept in the whitened space would be a
                    // spurious point-dependent shift.
                    fit_intercept: false,
                    tolerance: 1e-9,
                    max_sweeps: 200_000,
                },
                ..CvOptions::default()
            },
            ridge_refit: true,
            rank_tolerance: 1e-9,
            grid_tolerance_m: 1e-7,
            offset_tolerance_m: 1e-6,
        }
    }
}

/// Why a decomposition could not be computed.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum DecompositionError {
    #[error("geometric error decomposition: invalid input: {0}")]
    InvalidInput(String),
    #[error("geometric error decomposition: {0}")]
    Numerical(String),
}

fn invalid(msg: impl Into<String>) -> DecompositionError {
    DecompositionError::InvalidInput(msg.into())
}

/// A map serialised in insertion order (ISO order of the errors, x-y-z order of the axes).
#[derive(Clone, Debug, PartialEq)]
pub struct OrderedMap<T>(pub Vec<(String, T)>);

impl<T> OrderedMap<T> {
    pub fn get(&self, key: &str) -> Option<&T> {
        self.0.iter().find(|(k, _)| k == key).map(|(_, v)| v)
    }
}

impl<T: Serialize> Serialize for OrderedMap<T> {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        let mut map = s.serialize_map(Some(self.0.len()))?;
        for (k, v) in &self.0 {
            map.serialize_entry(k, v)?;
        }
        map.end()
    }
}

/// One error function sampled at the axis grid positions.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ErrorFunction {
    /// "m" or "rad".
    pub unit: &'static str,
    /// Per grid position; null where the data cannot determine it.
    pub values: Vec<Option<f64>>,
    pub sigma: Vec<Option<f64>>,
    pub identifiable: bool,
    /// Errors that this data cannot separate from this one and whose effect it therefore
    /// carries (e.g. EXZ carries z1·EBZ with one offset): an effective value at the offset.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub absorbs: Vec<String>,
}

#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct AxisResult {
    pub positions_m: Vec<f64>,
    pub errors: OrderedMap<ErrorFunction>,
}

#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct SquarenessEstimate {
    pub value_rad: Option<f64>,
    pub sigma_rad: Option<f64>,
    pub identifiable: bool,
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub absorbs: Vec<String>,
}

/// The rigid motion of the error field that the gauge leaves (first order): displacement
/// t + ω × (p − centre).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct RigidMotion {
    pub translation_m: [f64; 3],
    pub rotation_rad: [f64; 3],
    pub centre_m: [f64; 3],
}

#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct CvCurveSummary {
    pub alpha: f64,
    pub lambdas: Vec<f64>,
    pub mse: Vec<f64>,
}

/// The elastic-net choice (whitened units: mse ≈ 1 at the noise level).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ElasticNetSummary {
    pub lambda: f64,
    pub alpha: f64,
    pub cv_mse: f64,
    pub folds: usize,
    pub n_parameters: usize,
    pub n_active: usize,
    /// Wall time of the cross-validation; kept out of results, which must replay identically.
    #[serde(skip)]
    pub cv_seconds: f64,
    pub curves: Vec<CvCurveSummary>,
}

/// `geometric_errors` in the results JSON.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct GeometricErrorsResult {
    pub method: &'static str,
    pub structure: String,
    pub axes: OrderedMap<AxisResult>,
    pub squareness: OrderedMap<SquarenessEstimate>,
    pub rigid_motion: RigidMotion,
    /// RMS of the (unwhitened) residual components.
    pub residual_rms_m: f64,
    pub chi2_per_dof: f64,
    pub elastic_net: Option<ElasticNetSummary>,
    pub unidentifiable: Vec<String>,
    pub notes: Vec<String>,
}

const LINEAR_UNIT: &str = "m";
const ANGULAR_UNIT: &str = "rad";

/// Parameter indexing: axis functions (axis, k, grid position), squareness, rigid motion.
#[derive(Clone, Debug)]
struct Layout {
    n_pos: [usize; 3],
    start: [usize; 3],
    n_axis_params: usize,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Param {
    Axis { axis: usize, k: usize, pos: usize },
    Square(usize),
    Rigid(usize),
}

impl Layout {
    fn new(grid: &[Vec<f64>; 3]) -> Layout {
        let n_pos = [grid[0].len(), grid[1].len(), grid[2].len()];
        let start = [0, 6 * n_pos[0], 6 * (n_pos[0] + n_pos[1])];
        Layout {
            n_pos,
            start,
            n_axis_params: 6 * (n_pos[0] + n_pos[1] + n_pos[2]),
        }
    }
    fn len(&self) -> usize {
        self.n_axis_params + 9
    }
    fn axis(&self, axis: usize, k: usize, pos: usize) -> usize {
        self.start[axis] + k * self.n_pos[axis] + pos
    }
    fn square(&self, s: usize) -> usize {
        self.n_axis_params + s
    }
    fn rigid(&self, r: usize) -> usize {
        self.n_axis_params + 3 + r
    }
    fn param(&self, i: usize) -> Param {
        if i >= self.n_axis_params + 3 {
            return Param::Rigid(i - self.n_axis_params - 3);
        }
        if i >= self.n_axis_params {
            return Param::Square(i - self.n_axis_params);
        }
        let axis = (0..3).rev().find(|&a| i >= self.start[a]).unwrap_or(0);
        let local = i - self.start[axis];
        let n = self.n_pos[axis].max(1);
        Param::Axis {
            axis,
            k: local / n,
            pos: local % n,
        }
    }
    /// ISO name of the function or squareness the parameter belongs to.
    fn name(&self, i: usize) -> String {
        match self.param(i) {
            Param::Axis { axis, k, .. } => Axis::ALL[axis].iso_names()[k].to_string(),
            Param::Square(s) => Squareness::ISO_NAMES[s].to_string(),
            Param::Rigid(r) => ["TX", "TY", "TZ", "RX", "RY", "RZ"][r].to_string(),
        }
    }
}

/// The decomposition problem in whitened form.
struct System {
    layout: Layout,
    /// Whitened full design (3n × P) and response.
    x: DMatrix<f64>,
    y: DVector<f64>,
    /// Per row: point index (CV groups).
    row_point: Vec<usize>,
    centre: Vector3<f64>,
    grid: [Vec<f64>; 3],
    n_offsets: usize,
    /// How the rows were whitened, to unwhiten residuals.
    whitening: Whitening,
}

/// Rows are whitened by L⁻¹ with L the Cholesky factor of the errors' covariance: per point
/// (3x3 blocks) or, when the correlations between points are known, of the whole 3n x 3n.
enum Whitening {
    Blocks(Vec<Matrix3<f64>>),
    Full(DMatrix<f64>),
}

impl Whitening {
    fn unwhiten(&self, whitened: &DVector<f64>) -> DVector<f64> {
        match self {
            Whitening::Blocks(chol) => {
                let mut out = DVector::zeros(whitened.len());
                for (i, l) in chol.iter().enumerate() {
                    let r =
                        l * Vector3::new(whitened[3 * i], whitened[3 * i + 1], whitened[3 * i + 2]);
                    out.rows_mut(3 * i, 3).copy_from(&r);
                }
                out
            }
            Whitening::Full(l) => l * whitened,
        }
    }
}

/// Sorted distinct grid positions (values closer than `tol` merged).
fn clean_grid(grid: &[f64], tol: f64) -> Result<Vec<f64>, DecompositionError> {
    let mut g: Vec<f64> = grid.to_vec();
    if g.iter().any(|v| !v.is_finite()) {
        return Err(invalid("a grid position is not finite"));
    }
    g.sort_by(f64::total_cmp);
    g.dedup_by(|a, b| (*a - *b).abs() <= tol);
    Ok(g)
}

/// The distinct axis positions of the points, per axis: the grid when the plan's grid is not
/// at hand.
pub fn grid_from_points(points: &[PointObservation], tolerance_m: f64) -> [Vec<f64>; 3] {
    std::array::from_fn(|a| {
        let v: Vec<f64> = points
            .iter()
            .map(|p| p.axes_m[a])
            .filter(|v| v.is_finite())
            .collect();
        clean_grid(&v, tolerance_m).unwrap_or_default()
    })
}

fn grid_index(grid: &[f64], v: f64, tol: f64) -> Option<usize> {
    let i = grid.partition_point(|g| *g < v - tol);
    (i < grid.len() && (grid[i] - v).abs() <= tol).then_some(i)
}

fn build_system(
    structure: &Structure,
    grid_m: &[Vec<f64>; 3],
    points: &[PointObservation],
    full_covariance: Option<&DMatrix<f64>>,
    options: &DecompositionOptions,
) -> Result<System, DecompositionError> {
    if let Some(cov) = full_covariance {
        if cov.nrows() != 3 * points.len() || cov.ncols() != 3 * points.len() {
            return Err(invalid(format!(
                "the full covariance is {}x{}, expected {}x{} for {} points",
                cov.nrows(),
                cov.ncols(),
                3 * points.len(),
                3 * points.len(),
                points.len()
            )));
        }
    }
    if points.is_empty() {
        return Err(invalid("no points"));
    }
    let grid: [Vec<f64>; 3] = [
        clean_grid(&grid_m[0], options.grid_tolerance_m)?,
        clean_grid(&grid_m[1], options.grid_tolerance_m)?,
        clean_grid(&grid_m[2], options.grid_tolerance_m)?,
    ];
    for (a, g) in grid.iter().enumerate() {
        if g.is_empty() {
            return Err(invalid(format!(
                "axis {} has no grid positions",
                Axis::ALL[a]
            )));
        }
    }
    let layout = Layout::new(&grid);
    let n = points.len();
    let p = layout.len();
    let mut x = DMatrix::zeros(3 * n, p);
    let mut y = DVector::zeros(3 * n);
    let mut chol = Vec::with_capacity(n);
    let mut offsets: Vec<[f64; 3]> = Vec::new();
    let centre = points
        .iter()
        .map(|o| Vector3::from(nominal_position(o.axes_m, o.target_offset_m)))
        .sum::<Vector3<f64>>()
        / n as f64;
    for (i, o) in points.iter().enumerate() {
        let finite = o
            .axes_m
            .iter()
            .chain(&o.target_offset_m)
            .chain(&o.error_m)
            .all(|v| v.is_finite())
            && o.covariance.iter().all(|v| v.is_finite());
        if !finite {
            return Err(invalid(format!("point {i} has a non-finite value")));
        }
        let mut idx = [0usize; 3];
        for a in 0..3 {
            idx[a] =
                grid_index(&grid[a], o.axes_m[a], options.grid_tolerance_m).ok_or_else(|| {
                    invalid(format!(
                        "point {i}: {} = {} m is not on the axis grid (tolerance {} m)",
                        Axis::ALL[a],
                        o.axes_m[a],
                        options.grid_tolerance_m
                    ))
                })?;
        }
        if !offsets.iter().any(|t| {
            (0..3).all(|k| (t[k] - o.target_offset_m[k]).abs() <= options.offset_tolerance_m)
        }) {
            offsets.push(o.target_offset_m);
        }
        // With a full covariance the rows are whitened all together below.
        let l = match full_covariance {
            Some(_) => Matrix3::identity(),
            None => (0.5 * (o.covariance + o.covariance.transpose()))
                .cholesky()
                .ok_or_else(|| invalid(format!("point {i}: covariance is not positive definite")))?
                .l(),
        };
        let linv = l
            .try_inverse()
            .ok_or_else(|| invalid(format!("point {i}: covariance is singular")))?;
        // Unwhitened 3-row block, then whitened by L⁻¹.
        let j = error_jacobian(structure, o.axes_m, o.target_offset_m);
        let mut block = DMatrix::<f64>::zeros(3, p);
        for (a, &pos) in idx.iter().enumerate() {
            for k in 0..6 {
                let col = layout.axis(a, k, pos);
                block.column_mut(col).copy_from(&j.column(6 * a + k));
            }
        }
        for s in 0..3 {
            block
                .column_mut(layout.square(s))
                .copy_from(&j.column(SQUARENESS_COLUMN + s));
        }
        let arm = Vector3::from(nominal_position(o.axes_m, o.target_offset_m)) - centre;
        for r in 0..3 {
            let mut e = Vector3::zeros();
            e[r] = 1.0;
            block.column_mut(layout.rigid(r)).copy_from(&e);
            block
                .column_mut(layout.rigid(3 + r))
                .copy_from(&e.cross(&arm));
        }
        let wblock = DMatrix::from_fn(3, 3, |r, c| linv[(r, c)]) * block;
        x.rows_mut(3 * i, 3).copy_from(&wblock);
        y.rows_mut(3 * i, 3)
            .copy_from(&(linv * Vector3::from(o.error_m)));
        chol.push(l);
    }
    let whitening = match full_covariance {
        None => Whitening::Blocks(chol),
        Some(cov) => {
            // The inner-constraint datum leaves the covariance singular along the rigid motions,
            // which the model estimates as nuisance: T = Σ + c·R·Rᵀ (R = rigid columns) is
            // regular and gives the same estimates and covariances of the geometric errors
            // (Rao's unified least squares); only the nuisance sigmas grow.
            let rigid = DMatrix::from_fn(3 * n, 6, |r, c| x[(r, layout.rigid(c))]);
            let rrt = &rigid * rigid.transpose();
            let c = cov.trace() / rrt.trace().max(f64::MIN_POSITIVE);
            let t = 0.5 * (cov + cov.transpose()) + rrt * c;
            let l = t
                .cholesky()
                .ok_or_else(|| {
                    invalid("the full covariance is not positive definite off the rigid motions")
                })?
                .l();
            x = l
                .solve_lower_triangular(&x)
                .ok_or_else(|| invalid("the full covariance is singular"))?;
            y = l
                .solve_lower_triangular(&y)
                .ok_or_else(|| invalid("the full covariance is singular"))?;
            Whitening::Full(l)
        }
    };
    Ok(System {
        layout,
        x,
        y,
        row_point: (0..3 * n).map(|r| r / 3).collect(),
        centre,
        grid,
        n_offsets: offsets.len(),
        whitening,
    })
}

/// The decomposition's least-squares problem, whitened: design `x` (3n x P: the 21 error
/// functions at the grid positions, squareness, rigid motion), response `y` and the lower
/// triangular factor `l` of the covariance used (rows whitened by L⁻¹; block-diagonal when no
/// full covariance is given). The diagnosis fits it as is: its residuals do not depend on
/// the datum or on the elastic net, only on the column space of the quasi-rigid model.
pub struct WhitenedDesign {
    pub x: DMatrix<f64>,
    pub y: DVector<f64>,
    pub l: DMatrix<f64>,
}

pub fn whitened_design(
    structure: &Structure,
    grid_m: &[Vec<f64>; 3],
    points: &[PointObservation],
    full_covariance: Option<&DMatrix<f64>>,
    options: &DecompositionOptions,
) -> Result<WhitenedDesign, DecompositionError> {
    let sys = build_system(structure, grid_m, points, full_covariance, options)?;
    let l = match sys.whitening {
        Whitening::Full(l) => l,
        Whitening::Blocks(blocks) => {
            let mut l = DMatrix::zeros(3 * blocks.len(), 3 * blocks.len());
            for (i, b) in blocks.iter().enumerate() {
                l.view_mut((3 * i, 3 * i), (3, 3)).copy_from(b);
            }
            l
        }
    };
    Ok(WhitenedDesign {
        x: sys.x,
        y: sys.y,
        l,
    })
}

/// Column norms (zero columns get 1 so they stay zero).
fn column_norms(a: &DMatrix<f64>) -> DVector<f64> {
    DVector::from_fn(a.ncols(), |j, _| {
        let n = a.column(j).norm();
        if n > 0.0 {
            n
        } else {
            1.0
        }
    })
}

/// Least squares by QR then SVD of R: min-norm solution on the column-normalised design,
/// its covariance (unit-variance rows) and an orthonormal basis of the null space.
struct LsqSolution {
    theta: DVector<f64>,
    cov: DMatrix<f64>,
    null: DMatrix<f64>,
    rank: usize,
}

fn lsq(
    a: &DMatrix<f64>,
    y: &DVector<f64>,
    rank_tol: f64,
) -> Result<LsqSolution, DecompositionError> {
    lsq_scaled(a, y, rank_tol, &column_norms(a))
}

/// As [`lsq`], with the column scale for the rank decision given: a column that is a tiny
/// remainder of a projection must be judged against the size it had before, not inflated.
fn lsq_scaled(
    a: &DMatrix<f64>,
    y: &DVector<f64>,
    rank_tol: f64,
    d: &DVector<f64>,
) -> Result<LsqSolution, DecompositionError> {
    let (m, p) = a.shape();
    let mut an = a.clone();
    for j in 0..p {
        an.column_mut(j).unscale_mut(d[j]);
    }
    // Reduce to a p×p problem by QR when tall (cost m·p², done once).
    let (r, qty) = if m > p {
        let qr = an.qr();
        let mut qty = y.clone();
        qr.q_tr_mul(&mut qty);
        (qr.r(), qty.rows(0, p).into_owned())
    } else {
        (an, y.clone())
    };
    let svd = r.svd(true, true);
    let (Some(u), Some(vt)) = (svd.u, svd.v_t) else {
        return Err(DecompositionError::Numerical("SVD failed".into()));
    };
    let s = svd.singular_values;
    // Columns are unit-normalised (by their own or their unprojected size), so σ_max ≥ 1
    // unless they are projection remainders; those are judged against 1.
    let smax = s.amax().max(1.0);
    let k = s.len();
    let keep: Vec<bool> = s.iter().map(|v| *v > rank_tol * smax && *v > 0.0).collect();
    let rank = keep.iter().filter(|b| **b).count();
    let uty = u.transpose() * qty;
    let mut theta = DVector::zeros(p);
    let mut cov = DMatrix::zeros(p, p);
    for i in 0..k {
        if keep[i] {
            let v = vt.row(i).transpose();
            theta.axpy(uty[i] / s[i], &v, 1.0);
            cov.ger(1.0 / (s[i] * s[i]), &v, &v, 1.0);
        }
    }
    // Null space: right singular vectors of the dropped values, plus the directions missing
    // when R has fewer rows than columns.
    let mut null_vecs: Vec<DVector<f64>> = (0..k)
        .filter(|&i| !keep[i])
        .map(|i| vt.row(i).transpose())
        .collect();
    if k < p {
        // Complete the basis: project unit vectors off the row space, Gram–Schmidt.
        let mut basis: Vec<DVector<f64>> = (0..k)
            .filter(|&i| keep[i])
            .map(|i| vt.row(i).transpose())
            .collect();
        basis.extend(null_vecs.iter().cloned());
        for j in 0..p {
            let mut e = DVector::zeros(p);
            e[j] = 1.0;
            for b in &basis {
                let c = b.dot(&e);
                e.axpy(-c, b, 1.0);
            }
            let nrm = e.norm();
            if nrm > 1e-8 {
                e /= nrm;
                basis.push(e.clone());
                null_vecs.push(e);
            }
            if basis.len() == p {
                break;
            }
        }
    }
    let mut null = DMatrix::zeros(p, null_vecs.len());
    for (c, v) in null_vecs.iter().enumerate() {
        null.set_column(c, v);
    }
    // Back to the original column scale.
    let theta = theta.component_div(d);
    for i in 0..p {
        for j in 0..p {
            cov[(i, j)] /= d[i] * d[j];
        }
    }
    Ok(LsqSolution {
        theta,
        cov,
        null,
        rank,
    })
}

/// Null-space components above this mark a parameter as not estimable (null vectors are unit
/// length over the normalised columns; genuine participation is ≳ 1e-3).
const ESTIMABLE_TOL: f64 = 1e-6;

fn row_norm(null: &DMatrix<f64>, j: usize) -> f64 {
    if null.ncols() == 0 {
        0.0
    } else {
        null.row(j).norm()
    }
}

/// Remove parameter row `j` from a null-space basis (orthonormal columns): rotate the basis
/// so that only its first column touches row j, drop that column and the row.
fn constrain_null(null: &DMatrix<f64>, j: usize) -> DMatrix<f64> {
    let k = null.ncols();
    let v = null.row(j).transpose();
    let nv = v.norm();
    if k == 0 || nv == 0.0 {
        return null.clone();
    }
    let mut u = v / nv;
    u[0] -= 1.0;
    let h = if u.norm_squared() > 1e-30 {
        DMatrix::identity(k, k) - 2.0 * &u * u.transpose() / u.norm_squared()
    } else {
        DMatrix::identity(k, k)
    };
    let rotated = null * h;
    let mut out = rotated.columns(1, k - 1).into_owned();
    out.row_mut(j).fill(0.0);
    out
}

/// The datum: candidate constraints (parameter = 0) in priority order, each applied only
/// when that parameter is not estimable in the model constrained so far, so the fitted field
/// never changes. Returns the constrained parameters and the remaining null space.
fn apply_datum(layout: &Layout, null: &DMatrix<f64>) -> (Vec<usize>, DMatrix<f64>) {
    let mut candidates = Vec::new();
    // Values at the first grid position: linear (origin shifts ≡ translation), then angular
    // (constant rotations ≡ rigid rotation + straightness slopes).
    for k in 0..6 {
        for a in 0..3 {
            candidates.push(layout.axis(a, k, 0));
        }
    }
    // Straightness reference lines through the last grid position: first the three slopes
    // that trade with squareness (EXY ↔ EC0Y, EXZ ↔ EB0Z, EYZ ↔ EA0Z), then those that trade
    // with the rigid rotation when the offsets cannot show it (EYX, EZX, EZY).
    for (a, k) in [(1, 0), (2, 0), (2, 1), (0, 1), (0, 2), (1, 2)] {
        let last = layout.n_pos[a] - 1;
        if last > 0 {
            candidates.push(layout.axis(a, k, last));
        }
    }
    let mut fixed = Vec::new();
    let mut null = null.clone();
    for j in candidates {
        if row_norm(&null, j) > ESTIMABLE_TOL {
            null = constrain_null(&null, j);
            fixed.push(j);
        }
    }
    (fixed, null)
}

fn select_columns(a: &DMatrix<f64>, cols: &[usize]) -> DMatrix<f64> {
    DMatrix::from_fn(a.nrows(), cols.len(), |i, j| a[(i, cols[j])])
}

/// Per parameter of the full layout: value and sigma, `None` when not estimable.
struct Estimates {
    value: Vec<Option<f64>>,
    sigma: Vec<Option<f64>>,
    absorbs: Vec<Vec<String>>,
}

/// Decompose the measured volumetric errors into the 21 geometric errors.
///
/// `grid_m` holds each axis's grid positions (the plan's); every point must lie on it.
pub fn decompose(
    structure: &Structure,
    grid_m: &[Vec<f64>; 3],
    points: &[PointObservation],
    options: &DecompositionOptions,
) -> Result<GeometricErrorsResult, DecompositionError> {
    decompose_correlated(structure, grid_m, points, None, options)
}

/// As `decompose`, with the full 3n x 3n covariance of the stacked `error_m` (point-major)
/// when known: the correlations between points then enter the estimates and their sigmas.
pub fn decompose_correlated(
    structure: &Structure,
    grid_m: &[Vec<f64>; 3],
    points: &[PointObservation],
    full_covariance: Option<&DMatrix<f64>>,
    options: &DecompositionOptions,
) -> Result<GeometricErrorsResult, DecompositionError> {
    let sys = build_system(structure, grid_m, points, full_covariance, options)?;
    let route = options.route.unwrap_or(if sys.n_offsets >= 2 {
        Route::WeightedLeastSquares
    } else {
        Route::ElasticNetQr
    });
    let layout = &sys.layout;
    let p = layout.len();
    let full = lsq(&sys.x, &sys.y, options.rank_tolerance)?;
    let (fixed, null) = apply_datum(layout, &full.null);
    let mut is_fixed = vec![false; p];
    fixed.iter().for_each(|&j| is_fixed[j] = true);
    let kept: Vec<usize> = (0..p).filter(|&j| !is_fixed[j]).collect();
    let mut notes = vec![datum_note(layout, &fixed)];
    notes.push(format!(
        "{} points, {} distinct target offset(s); per-point covariance blocks whiten the rows \
         (correlations between points from the multilateration gauge are not used)",
        points.len(),
        sys.n_offsets
    ));

    let mut est = Estimates {
        value: vec![None; p],
        sigma: vec![None; p],
        absorbs: vec![Vec::new(); p],
    };
    for &j in &fixed {
        est.value[j] = Some(0.0);
        est.sigma[j] = Some(0.0);
    }
    let (method, elastic_net, fitted_w, dof) = match route {
        Route::WeightedLeastSquares => {
            let xk = select_columns(&sys.x, &kept);
            let sol = lsq(&xk, &sys.y, options.rank_tolerance)?;
            for (c, &j) in kept.iter().enumerate() {
                if row_norm(&null, j) <= ESTIMABLE_TOL {
                    est.value[j] = Some(sol.theta[c]);
                    est.sigma[j] = Some(sol.cov[(c, c)].max(0.0).sqrt());
                }
            }
            notes.push(
                "weighted least squares (QR, SVD of R): sigmas are the exact covariance from the \
                 point covariances, not scaled by chi2"
                    .into(),
            );
            let fitted = &xk * &sol.theta;
            (
                "weighted_least_squares",
                None,
                fitted,
                3 * points.len() - sol.rank,
            )
        }
        Route::ElasticNetQr => {
            let (summary, fitted, dof) =
                elastic_net_route(&sys, &kept, &null, options, &mut est, &mut notes)?;
            ("elastic_net+qr", Some(summary), fitted, dof)
        }
    };

    // Residuals, unwhitened per point for an RMS in metres.
    let resid_w = &sys.y - &fitted_w;
    let chi2 = resid_w.norm_squared();
    let sum_sq = sys.whitening.unwhiten(&resid_w).norm_squared();
    let residual_rms_m = (sum_sq / (3 * points.len()) as f64).sqrt();
    let chi2_per_dof = if dof > 0 { chi2 / dof as f64 } else { f64::NAN };

    Ok(assemble(
        structure,
        &sys,
        est,
        method,
        elastic_net,
        residual_rms_m,
        chi2_per_dof,
        notes,
    ))
}

fn datum_note(layout: &Layout, fixed: &[usize]) -> String {
    let mut slopes = Vec::new();
    for &j in fixed {
        if let Param::Axis { axis, k, pos } = layout.param(j) {
            if pos > 0 {
                slopes.push(Axis::ALL[axis].iso_names()[k]);
            }
        }
    }
    format!(
        "datum: every error is 0 at the first (lowest) grid position of its axis; the \
         straightness of {} is 0 at the last grid position too (reference line through the \
         end points), squareness and the rigid motion take the rest",
        slopes.join(", ")
    )
}

/// Route 1 (ref1): angular functions that one offset cannot separate are deferred; elastic
/// net with CV on the rest (rigid motion projected off), then QR least squares of the
/// residual on the deferred columns for what they add.
fn elastic_net_route(
    sys: &System,
    kept: &[usize],
    null: &DMatrix<f64>,
    options: &DecompositionOptions,
    est: &mut Estimates,
    notes: &mut Vec<String>,
) -> Result<(ElasticNetSummary, DVector<f64>, usize), DecompositionError> {
    let layout = &sys.layout;
    let m = sys.x.nrows();
    let FirstStep {
        deferred,
        first,
        en_cols,
    } = first_step_columns(sys, kept, null, options.rank_tolerance)?;
    let rigid: Vec<usize> = (0..6).map(|r| layout.rigid(r)).collect();

    // Project everything off the whitened rigid-motion columns.
    let rw = select_columns(&sys.x, &rigid);
    let qr = rw.clone().qr();
    let q = qr.q();
    let project = |a: &DMatrix<f64>| a - &q * (q.transpose() * a);
    let a_en = project(&select_columns(&sys.x, &en_cols));
    let y_p = project(&DMatrix::from_column_slice(m, 1, sys.y.as_slice()))
        .column(0)
        .into_owned();

    let start = Instant::now();
    let cv = cross_validate(&a_en, &y_p, None, Some(&sys.row_point), &options.cv)
        .map_err(|e| DecompositionError::Numerical(e.to_string()))?;
    let cv_seconds = start.elapsed().as_secs_f64();
    let net = ElasticNet::new(&a_en, &y_p, None, options.cv.fit.clone())
        .map_err(|e| DecompositionError::Numerical(e.to_string()))?;
    let (_, scale) = net.column_transform();
    let ridge = m as f64 * cv.lambda * (1.0 - cv.alpha);
    let ata = a_en.transpose() * &a_en;
    let nq = en_cols.len();
    let h = DMatrix::from_fn(nq, nq, |i, j| {
        ata[(i, j)]
            + if i == j {
                ridge * scale[i] * scale[i]
            } else {
                0.0
            }
    });
    let hinv = h
        .clone()
        .cholesky()
        .ok_or_else(|| {
            DecompositionError::Numerical("ridge normal matrix not positive definite".into())
        })?
        .inverse();
    let cov = &hinv * &ata * &hinv;
    let active: Vec<usize> = (0..nq).filter(|&c| cv.fit.coefficients[c] != 0.0).collect();
    let mut theta = cv.fit.coefficients.clone();
    if options.ridge_refit && !active.is_empty() {
        let ha = DMatrix::from_fn(active.len(), active.len(), |i, j| h[(active[i], active[j])]);
        let aty = a_en.transpose() * &y_p;
        let rhs = DVector::from_fn(active.len(), |i, _| aty[active[i]]);
        let sol = ha
            .cholesky()
            .ok_or_else(|| {
                DecompositionError::Numerical("ridge refit not positive definite".into())
            })?
            .solve(&rhs);
        theta.fill(0.0);
        for (i, &c) in active.iter().enumerate() {
            theta[c] = sol[i];
        }
    }
    for (c, &j) in en_cols.iter().enumerate() {
        est.value[j] = Some(theta[c]);
        est.sigma[j] = Some(cov[(c, c)].max(0.0).sqrt());
    }
    let resid1 = &y_p - &a_en * &theta;

    // Second step: the deferred columns, made orthogonal to the first-step model, against the
    // first-step residual (QR least squares); what stays collinear is not identifiable.
    let mut second_dof = 0;
    if !deferred.is_empty() {
        let d = project(&select_columns(&sys.x, &deferred));
        let qa = a_en.clone().qr().q();
        let d_perp = &d - &qa * (qa.transpose() * &d);
        let sol = lsq_scaled(&d_perp, &resid1, options.rank_tolerance, &column_norms(&d))?;
        second_dof = sol.rank;
        for (c, &j) in deferred.iter().enumerate() {
            if row_norm(&sol.null, c) <= ESTIMABLE_TOL {
                est.value[j] = Some(sol.theta[c]);
                est.sigma[j] = Some(sol.cov[(c, c)].max(0.0).sqrt());
            }
        }
        // Which first-step functions carry the effect of the unidentifiable deferred ones.
        for (c, &j) in deferred.iter().enumerate() {
            if row_norm(&sol.null, c) <= ESTIMABLE_TOL {
                continue;
            }
            let coef = lsq(&a_en, &d.column(c).into_owned(), options.rank_tolerance)?.theta;
            let dn = d.column(c).norm();
            if dn == 0.0 {
                continue;
            }
            for (ci, &i) in en_cols.iter().enumerate() {
                if (coef[ci] * a_en.column(ci).norm()).abs() > 1e-6 * dn {
                    let name = layout.name(j);
                    if !est.absorbs[i].contains(&name) {
                        est.absorbs[i].push(name);
                    }
                }
            }
        }
        notes.push(format!(
            "second step (QR least squares on the elastic-net residual, conditional on the first \
             step): {}",
            group_names(layout, &deferred)
        ));
    }
    let dropped: Vec<usize> = first
        .iter()
        .copied()
        .filter(|j| !en_cols.contains(j))
        .collect();
    if !dropped.is_empty() {
        notes.push(format!(
            "not estimable even without the deferred rotations: {}",
            group_names(layout, &dropped)
        ));
    }
    notes.push(format!(
        "elastic net on whitened, standardised columns with the rigid motion projected off; \
         λ = {:.3e}, α = {} chosen by {}-fold CV (points kept together); values {}; sigmas \
         from the ridge-regularised least-squares covariance (H⁻¹AᵀAH⁻¹, H = AᵀA + Nλ(1−α)S²) \
         of the selected model",
        cv.lambda,
        cv.alpha,
        options.cv.folds,
        if options.ridge_refit {
            "refitted on the selected (non-zero) columns with the chosen L2 penalty"
        } else {
            "are the elastic-net coefficients"
        }
    ));

    // Fitted (whitened) field: first step + second step + rigid motion.
    let mut fitted_wo_rigid = DVector::zeros(m);
    for &j in en_cols.iter().chain(&deferred) {
        if let Some(v) = est.value[j] {
            fitted_wo_rigid.axpy(v, &sys.x.column(j), 1.0);
        }
    }
    let rigid_fit = lsq(&rw, &(&sys.y - &fitted_wo_rigid), options.rank_tolerance)?;
    for (c, &j) in rigid.iter().enumerate() {
        est.value[j] = Some(rigid_fit.theta[c]);
        est.sigma[j] = Some(rigid_fit.cov[(c, c)].max(0.0).sqrt());
    }
    let fitted = fitted_wo_rigid + &rw * &rigid_fit.theta;
    let dof = m.saturating_sub(en_cols.len() + second_dof + 6);
    let summary = ElasticNetSummary {
        lambda: cv.lambda,
        alpha: cv.alpha,
        cv_mse: cv.cv_mse,
        folds: options.cv.folds,
        n_parameters: nq,
        n_active: active.len(),
        cv_seconds,
        curves: cv
            .curves
            .iter()
            .map(|c| CvCurveSummary {
                alpha: c.alpha,
                lambdas: c.lambdas.clone(),
                mse: c.mse.clone(),
            })
            .collect(),
    };
    Ok((summary, fitted, dof))
}

/// Route 1 column split: (deferred angular parameters, first-step candidates, first-step
/// columns that are estimable without the deferred ones).
fn first_step_columns(
    sys: &System,
    kept: &[usize],
    null: &DMatrix<f64>,
    rank_tol: f64,
) -> Result<FirstStep, DecompositionError> {
    let layout = &sys.layout;
    // Angular functions with any non-estimable value are deferred to the second step.
    let same_fn = |i: usize, axis: usize, k: usize| matches!(layout.param(i), Param::Axis { axis: a2, k: k2, .. } if a2 == axis && k2 == k);
    let deferred_fn = |j: usize| match layout.param(j) {
        Param::Axis { axis, k, .. } if k >= 3 => kept
            .iter()
            .any(|&i| same_fn(i, axis, k) && row_norm(null, i) > ESTIMABLE_TOL),
        _ => false,
    };
    let deferred: Vec<usize> = kept.iter().copied().filter(|&j| deferred_fn(j)).collect();
    let first: Vec<usize> = kept
        .iter()
        .copied()
        .filter(|&j| !deferred.contains(&j) && !matches!(layout.param(j), Param::Rigid(_)))
        .collect();
    // Anything still not estimable without the deferred functions is left out as well.
    let mut cols = first.clone();
    cols.extend((0..6).map(|r| layout.rigid(r)));
    let check = lsq(&select_columns(&sys.x, &cols), &sys.y, rank_tol)?;
    let en_cols = first
        .iter()
        .enumerate()
        .filter(|(c, _)| row_norm(&check.null, *c) <= ESTIMABLE_TOL)
        .map(|(_, &j)| j)
        .collect();
    Ok(FirstStep {
        deferred,
        first,
        en_cols,
    })
}

/// Route 1 column split, as layout indices.
struct FirstStep {
    /// Angular parameters deferred to the second step.
    deferred: Vec<usize>,
    /// First-step candidates (everything else but the rigid motion).
    first: Vec<usize>,
    /// The candidates that are estimable without the deferred ones: the elastic-net columns.
    en_cols: Vec<usize>,
}

fn group_names(layout: &Layout, params: &[usize]) -> String {
    let mut names: Vec<String> = params.iter().map(|&j| layout.name(j)).collect();
    names.dedup();
    names.join(", ")
}

#[allow(clippy::too_many_arguments)]
fn assemble(
    structure: &Structure,
    sys: &System,
    est: Estimates,
    method: &'static str,
    elastic_net: Option<ElasticNetSummary>,
    residual_rms_m: f64,
    chi2_per_dof: f64,
    mut notes: Vec<String>,
) -> GeometricErrorsResult {
    let layout = &sys.layout;
    let mut unidentifiable = Vec::new();
    let mut axes = Vec::new();
    for (a, axis) in Axis::ALL.iter().enumerate() {
        let mut errors = Vec::new();
        for (k, name) in axis.iso_names().iter().enumerate() {
            let idx: Vec<usize> = (0..layout.n_pos[a])
                .map(|pos| layout.axis(a, k, pos))
                .collect();
            let values: Vec<Option<f64>> = idx.iter().map(|&j| est.value[j]).collect();
            let sigma: Vec<Option<f64>> = idx.iter().map(|&j| est.sigma[j]).collect();
            let identifiable = values.iter().all(Option::is_some);
            if !identifiable {
                unidentifiable.push(name.to_string());
            }
            let mut absorbs: Vec<String> =
                idx.iter().flat_map(|&j| est.absorbs[j].clone()).collect();
            absorbs.sort();
            absorbs.dedup();
            errors.push((
                name.to_string(),
                ErrorFunction {
                    unit: if k < 3 { LINEAR_UNIT } else { ANGULAR_UNIT },
                    values,
                    sigma,
                    identifiable,
                    absorbs,
                },
            ));
        }
        axes.push((
            axis.letter().to_ascii_lowercase().to_string(),
            AxisResult {
                positions_m: sys.grid[a].clone(),
                errors: OrderedMap(errors),
            },
        ));
    }
    let squareness = OrderedMap(
        (0..3)
            .map(|s| {
                let j = layout.square(s);
                let identifiable = est.value[j].is_some();
                if !identifiable {
                    unidentifiable.push(Squareness::ISO_NAMES[s].to_string());
                }
                (
                    Squareness::ISO_NAMES[s].to_string(),
                    SquarenessEstimate {
                        value_rad: est.value[j],
                        sigma_rad: est.sigma[j],
                        identifiable,
                        absorbs: est.absorbs[j].clone(),
                    },
                )
            })
            .collect(),
    );
    let rv = |r: usize| est.value[layout.rigid(r)].unwrap_or(0.0);
    if (0..6).any(|r| est.value[layout.rigid(r)].is_none()) {
        notes.push("part of the rigid motion is not estimable (reported as 0)".into());
    }
    if !unidentifiable.is_empty() {
        notes.push(format!(
            "not identifiable from these points and target offsets (values null): {}. One target \
             offset cannot separate a rotation whose lever arm is only the offset from the linear \
             errors of the same axis; offsets on one line cannot show the rotation of the last \
             tool-branch axis about that line: add a target offset off that line",
            unidentifiable.join(", ")
        ));
    }
    GeometricErrorsResult {
        method,
        structure: structure.as_str().to_string(),
        axes: OrderedMap(axes),
        squareness,
        rigid_motion: RigidMotion {
            translation_m: [rv(0), rv(1), rv(2)],
            rotation_rad: [rv(3), rv(4), rv(5)],
            centre_m: [sys.centre.x, sys.centre.y, sys.centre.z],
        },
        residual_rms_m,
        chi2_per_dof,
        elastic_net,
        unidentifiable,
        notes,
    }
}

/// Recovered errors as a `GeometricErrors`: linear interpolation between grid positions,
/// constant beyond the ends, unidentified values taken as 0 (their effect at the measured
/// offsets is carried by the functions that absorb them).
#[derive(Clone, Debug)]
pub struct GridErrors {
    positions_m: [Vec<f64>; 3],
    /// [axis][k][pos]
    values: [[Vec<f64>; 6]; 3],
    squareness: Squareness,
}

impl GridErrors {
    pub fn from_result(result: &GeometricErrorsResult) -> GridErrors {
        let mut positions_m: [Vec<f64>; 3] = Default::default();
        let mut values: [[Vec<f64>; 6]; 3] = Default::default();
        for (a, axis) in Axis::ALL.iter().enumerate() {
            if let Some(ar) = result.axes.0.get(a).map(|(_, r)| r) {
                positions_m[a] = ar.positions_m.clone();
                for (k, name) in axis.iso_names().iter().enumerate() {
                    values[a][k] = ar.errors.get(name).map_or_else(
                        || vec![0.0; ar.positions_m.len()],
                        |f| f.values.iter().map(|v| v.unwrap_or(0.0)).collect(),
                    );
                }
            }
        }
        let sq = |name: &str| {
            result
                .squareness
                .get(name)
                .and_then(|s| s.value_rad)
                .unwrap_or(0.0)
        };
        GridErrors {
            positions_m,
            values,
            squareness: Squareness {
                xy_rad: sq("EC0Y"),
                yz_rad: sq("EA0Z"),
                zx_rad: sq("EB0Z"),
            },
        }
    }

    fn interp(&self, a: usize, k: usize, q: f64) -> f64 {
        let g = &self.positions_m[a];
        let v = &self.values[a][k];
        match g.len() {
            0 => 0.0,
            1 => v[0],
            n => {
                if q <= g[0] {
                    return v[0];
                }
                if q >= g[n - 1] {
                    return v[n - 1];
                }
                let i = g.partition_point(|x| *x <= q).clamp(1, n - 1);
                let t = (q - g[i - 1]) / (g[i] - g[i - 1]);
                v[i - 1] + t * (v[i] - v[i - 1])
            }
        }
    }
}

impl GeometricErrors for GridErrors {
    fn axis(&self, axis: Axis, q_m: f64) -> AxisErrors {
        let a = axis.index();
        AxisErrors {
            linear_m: std::array::from_fn(|k| self.interp(a, k, q_m)),
            angular_rad: std::array::from_fn(|k| self.interp(a, k + 3, q_m)),
        }
    }
    fn squareness(&self) -> Squareness {
        self.squareness
    }
}

impl GeometricErrorsResult {
    /// Predicted measured error at (q, offset): the exact model with the recovered errors plus
    /// the fitted rigid motion of the gauge.
    pub fn predicted_error_m(
        &self,
        structure: &Structure,
        q: [f64; 3],
        offset_m: [f64; 3],
    ) -> [f64; 3] {
        let e = GridErrors::from_result(self);
        let nominal = nominal_position(q, offset_m);
        let actual = actual_position(structure, &e, q, offset_m);
        let rm = &self.rigid_motion;
        let arm = Vector3::from(nominal) - Vector3::from(rm.centre_m);
        let rigid = Vector3::from(rm.translation_m) + Vector3::from(rm.rotation_rad).cross(&arm);
        std::array::from_fn(|k| actual[k] - nominal[k] + rigid[k])
    }
}

/// Simulated observations for tests and benchmarks: the exact model with `truth` at every
/// grid point and offset, a random rigid motion applied and the best-fit rigid motion removed
/// (as the multilateration gauge does), then Gaussian noise `noise_m` per coordinate.
pub fn simulate_observations(
    structure: &Structure,
    truth: &dyn GeometricErrors,
    grid_m: &[Vec<f64>; 3],
    offsets_m: &[[f64; 3]],
    noise_m: f64,
    seed: u64,
) -> Vec<PointObservation> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut q_list = Vec::new();
    for t in offsets_m {
        for &x in &grid_m[0] {
            for &y in &grid_m[1] {
                for &z in &grid_m[2] {
                    q_list.push(([x, y, z], *t));
                }
            }
        }
    }
    let rot = nalgebra::Rotation3::from_scaled_axis(Vector3::from_fn(|_, _| {
        rng.random_range(-2e-5..2e-5)
    }));
    let shift = Vector3::from_fn(|_, _| rng.random_range(-1e-5..1e-5));
    let nominal: Vec<Vector3<f64>> = q_list
        .iter()
        .map(|(q, t)| Vector3::from(nominal_position(*q, *t)))
        .collect();
    let moved: Vec<Vector3<f64>> = q_list
        .iter()
        .map(|(q, t)| rot * Vector3::from(actual_position(structure, truth, *q, *t)) + shift)
        .collect();
    let (r, tr) =
        best_fit_rigid(&moved, &nominal).unwrap_or((Matrix3::identity(), Vector3::zeros()));
    let normal = Normal::new(0.0, noise_m.max(0.0)).ok();
    q_list
        .iter()
        .zip(moved.iter().zip(&nominal))
        .map(|((q, t), (a, n))| {
            let back = r * a + tr;
            let mut noise = || normal.map_or(0.0, |d| d.sample(&mut rng));
            let e = back - n;
            PointObservation {
                axes_m: *q,
                target_offset_m: *t,
                error_m: [e.x + noise(), e.y + noise(), e.z + noise()],
                covariance: Matrix3::identity() * (noise_m * noise_m).max(1e-30),
            }
        })
        .collect()
}

/// The whitened, rigid-motion-projected design that the elastic-net route hands to the solver
/// (columns in layout order without datum and deferred columns), with the CV groups: for
/// benchmarking the solver against other implementations on a realistic matrix.
pub fn elastic_net_design(
    structure: &Structure,
    grid_m: &[Vec<f64>; 3],
    points: &[PointObservation],
    options: &DecompositionOptions,
) -> Result<ElasticNetDesign, DecompositionError> {
    let sys = build_system(structure, grid_m, points, None, options)?;
    let layout = &sys.layout;
    let full = lsq(&sys.x, &sys.y, options.rank_tolerance)?;
    let (fixed, null) = apply_datum(layout, &full.null);
    let kept: Vec<usize> = (0..layout.len()).filter(|j| !fixed.contains(j)).collect();
    let cols = first_step_columns(&sys, &kept, &null, options.rank_tolerance)?.en_cols;
    let rigid: Vec<usize> = (0..6).map(|r| layout.rigid(r)).collect();
    let q = select_columns(&sys.x, &rigid).qr().q();
    let a = select_columns(&sys.x, &cols);
    let a = &a - &q * (q.transpose() * &a);
    let y = &sys.y - &q * (q.transpose() * &sys.y);
    Ok(ElasticNetDesign {
        x: a,
        y,
        groups: sys.row_point,
    })
}

/// See [`elastic_net_design`].
#[derive(Clone, Debug)]
pub struct ElasticNetDesign {
    /// Whitened, projected design (3n × p).
    pub x: DMatrix<f64>,
    pub y: DVector<f64>,
    /// Per row, the point it belongs to (CV groups).
    pub groups: Vec<usize>,
}

#[cfg(test)]
mod tests;
pub mod validation;
