//! Rotary axis from a reference sphere probed at many table angles on two or more heights:
//! sphere centres, 4 location errors, per-angle motion errors, harmonic fits and validation.

use nalgebra::{DMatrix, DVector, Matrix3, SMatrix, Vector3, Vector6};
use serde::Serialize;

use crate::model::rotary_sphere::{
    harmonic_basis, located_centre, located_centre_jacobian, motion_jacobian, rz, skew,
    sphere_point_residual, MOTION_NAMES,
};

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RotarySphereError {
    #[error("a sphere fit needs at least {needed} points, found {found}")]
    TooFewPoints { needed: usize, found: usize },
    #[error("the points do not determine a sphere (coplanar or coincident)")]
    DegenerateSphere,
    #[error("need at least 2 heights to separate tilt from translation, found {0}")]
    TooFewHeights(usize),
    #[error("height {0} has {1} angles but {2} centres/covariances")]
    SeriesShape(usize, usize, usize),
    #[error("height {0} is not probed at the same angles as height 0")]
    AnglesDiffer(usize),
    #[error("need at least 3 distinct angles, found {0}")]
    TooFewAngles(usize),
    #[error("the normal equations are singular: the data do not determine the {0}")]
    Singular(&'static str),
    #[error("the iteration did not converge in {0} steps")]
    NoConvergence(usize),
}

/// A sphere centre fitted to probed surface points.
#[derive(Debug, Clone, Serialize)]
pub struct SphereFit {
    pub centre_m: [f64; 3],
    /// The fitted radius, or the given one when it was known.
    pub radius_m: f64,
    pub radius_sigma_m: f64,
    /// Covariance of the centre (m²).
    pub centre_covariance_m2: [[f64; 3]; 3],
    pub residual_rms_m: f64,
    pub iterations: usize,
}

impl SphereFit {
    pub fn centre(&self) -> Vector3<f64> {
        Vector3::from(self.centre_m)
    }
    pub fn covariance(&self) -> Matrix3<f64> {
        Matrix3::from_fn(|r, c| self.centre_covariance_m2[r][c])
    }
}

/// Least-squares sphere through surface points, minimising Σ (|p − c| − r)².
///
/// `radius_m`: Some for a calibrated sphere (then 3 unknowns, ≥ 3 points), None to fit it too
/// (≥ 4 points). `sigma_m`: the probe's standard deviation along the surface normal; without it
/// the residuals' variance is used (zero when there is no redundancy).
pub fn fit_sphere(
    points_m: &[Vector3<f64>],
    radius_m: Option<f64>,
    sigma_m: Option<f64>,
) -> Result<SphereFit, RotarySphereError> {
    let np = if radius_m.is_some() { 3 } else { 4 };
    if points_m.len() < np.max(4) {
        return Err(RotarySphereError::TooFewPoints {
            needed: np.max(4),
            found: points_m.len(),
        });
    }
    let (mut centre, r0) = algebraic_sphere(points_m)?;
    let mut radius = radius_m.unwrap_or(r0);
    let cost_of = |c: &Vector3<f64>, r: f64| -> f64 {
        points_m
            .iter()
            .map(|p| sphere_point_residual(p, c, r).0.powi(2))
            .sum()
    };
    let jac_res = |c: &Vector3<f64>, r: f64| -> (DMatrix<f64>, DVector<f64>) {
        let mut j = DMatrix::zeros(points_m.len(), np);
        let mut e = DVector::zeros(points_m.len());
        for (k, p) in points_m.iter().enumerate() {
            let (res, g) = sphere_point_residual(p, c, r);
            e[k] = res;
            for a in 0..3 {
                j[(k, a)] = g[a];
            }
            if np == 4 {
                j[(k, 3)] = -1.0;
            }
        }
        (j, e)
    };
    let mut cost = cost_of(&centre, radius);
    let mut iterations = 0;
    loop {
        if iterations >= 100 {
            return Err(RotarySphereError::NoConvergence(100));
        }
        iterations += 1;
        let (j, e) = jac_res(&centre, radius);
        let Some(chol) = (j.transpose() * &j).cholesky() else {
            return Err(RotarySphereError::DegenerateSphere);
        };
        let step = -chol.solve(&(j.transpose() * &e));
        let mut t = 1.0;
        let mut accepted = false;
        for _ in 0..30 {
            let c = centre + Vector3::new(step[0], step[1], step[2]) * t;
            let r = if np == 4 {
                radius + step[3] * t
            } else {
                radius
            };
            let k = cost_of(&c, r);
            if k <= cost {
                centre = c;
                radius = r;
                cost = k;
                accepted = true;
                break;
            }
            t *= 0.5;
        }
        if !accepted || step.amax() * t <= 1e-15 {
            break;
        }
    }
    let (j, e) = jac_res(&centre, radius);
    let Some(ainv) = (j.transpose() * &j).try_inverse() else {
        return Err(RotarySphereError::DegenerateSphere);
    };
    let dof = points_m.len() - np;
    let var = match sigma_m {
        Some(s) => s * s,
        None if dof > 0 => e.norm_squared() / dof as f64,
        None => 0.0,
    };
    let cov = ainv * var;
    Ok(SphereFit {
        centre_m: centre.into(),
        radius_m: radius,
        radius_sigma_m: if np == 4 { cov[(3, 3)].sqrt() } else { 0.0 },
        centre_covariance_m2: std::array::from_fn(|r| std::array::from_fn(|c| cov[(r, c)])),
        residual_rms_m: (e.norm_squared() / points_m.len() as f64).sqrt(),
        iterations,
    })
}

/// |p|² + D x + E y + F z + G = 0 by linear least squares: a start for the geometric fit.
fn algebraic_sphere(points: &[Vector3<f64>]) -> Result<(Vector3<f64>, f64), RotarySphereError> {
    let centroid = points.iter().sum::<Vector3<f64>>() / points.len() as f64;
    let a = DMatrix::from_fn(points.len(), 4, |k, c| {
        if c < 3 {
            points[k][c] - centroid[c]
        } else {
            1.0
        }
    });
    let b = DVector::from_fn(points.len(), |k, _| -(points[k] - centroid).norm_squared());
    let svd = a.svd(true, true);
    let smax = svd.singular_values.max();
    if !(smax.is_finite() && svd.singular_values.min() > 1e-9 * smax) {
        return Err(RotarySphereError::DegenerateSphere);
    }
    let s = svd
        .solve(&b, 0.0)
        .map_err(|_| RotarySphereError::DegenerateSphere)?;
    let c = Vector3::new(-s[0] / 2.0, -s[1] / 2.0, -s[2] / 2.0);
    let r2 = c.norm_squared() - s[3];
    if !(r2 > 0.0 && r2.is_finite()) {
        return Err(RotarySphereError::DegenerateSphere);
    }
    Ok((centroid + c, r2.sqrt()))
}

/// Sphere centres at one height, one per commanded table angle.
#[derive(Debug, Clone)]
pub struct CentreSeries {
    pub angles_rad: Vec<f64>,
    pub centres_m: Vec<Vector3<f64>>,
    /// Per centre, its covariance (m²), e.g. from `fit_sphere`.
    pub covariances_m2: Vec<Matrix3<f64>>,
}

impl CentreSeries {
    pub fn from_fits(angles_rad: Vec<f64>, fits: &[SphereFit]) -> CentreSeries {
        CentreSeries {
            angles_rad,
            centres_m: fits.iter().map(SphereFit::centre).collect(),
            covariances_m2: fits.iter().map(SphereFit::covariance).collect(),
        }
    }
}

/// How the one combination that a sphere at a single radius cannot split is attributed.
///
/// At each angle a sphere at radius r sees a tangential translation t and an angular
/// positioning error ECC only as t + r·ECC; heights along the axis do not help (ECC × ẑ-offset
/// vanishes). A second sphere at another radius would.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Default)]
pub enum TangentialConvention {
    /// The tangential deviation is angular positioning (ECC); the translation EXC, EYC is
    /// purely radial. Natural for a rotary table, whose encoder error dominates.
    #[default]
    AngularPositioning,
    /// ECC = 0 and the tangential deviation is a translation.
    Translation,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum HarmonicOrder {
    Fixed(usize),
    /// Orders 0..=max chosen per error by the Bayesian information criterion
    /// χ² + (2k + 1) ln n with the per-angle variances as weights.
    Bic {
        max_order: usize,
    },
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct IdentifyOptions {
    pub convention: TangentialConvention,
    pub harmonics: HarmonicOrder,
    /// Under `AngularPositioning`, the azimuth φ (at θ = 0) along which the radial translation
    /// is written at angle θ: EXC, EYC = e_r (cos(θ + φ), sin(θ + φ)), and ECC takes up what
    /// that direction leaves of the tangential deviation. Give the sphere's nominal azimuth
    /// (a fixed direction, as an independent evaluation can reproduce it); None: the fitted
    /// sphere's azimuth. Either way the centres are explained alike.
    pub radial_azimuth_rad: Option<f64>,
}

impl Default for IdentifyOptions {
    fn default() -> Self {
        IdentifyOptions {
            convention: TangentialConvention::AngularPositioning,
            harmonics: HarmonicOrder::Bic { max_order: 8 },
            radial_azimuth_rad: None,
        }
    }
}

/// A sinusoidal model of one error function: value(θ) = c0 + Σ a_k cos kθ + b_k sin kθ.
#[derive(Debug, Clone, Serialize)]
pub struct HarmonicFit {
    pub name: &'static str,
    pub order: usize,
    /// [c0, a1, b1, a2, b2, …] in the error's unit (m or rad).
    pub coefficients: Vec<f64>,
    pub covariance: Vec<Vec<f64>>,
    /// RMS of per-angle value − model.
    pub residual_rms: f64,
}

impl HarmonicFit {
    pub fn value(&self, theta_rad: f64) -> f64 {
        harmonic_basis(theta_rad, self.order)
            .iter()
            .zip(&self.coefficients)
            .map(|(b, c)| b * c)
            .sum()
    }
    pub fn sigma(&self, theta_rad: f64) -> f64 {
        let b = harmonic_basis(theta_rad, self.order);
        let mut v = 0.0;
        for (i, bi) in b.iter().enumerate() {
            for (j, bj) in b.iter().enumerate() {
                v += bi * self.covariance[i][j] * bj;
            }
        }
        v.max(0.0).sqrt()
    }
}

/// The identified axis. Location errors are the least-squares axis through all centres (the
/// motion errors are what is left, so they carry no part that a fixed axis would explain).
#[derive(Debug, Clone, Serialize)]
pub struct RotaryAxisIdentification {
    /// EXOC, EYOC (m), EAOC, EBOC (rad): see `model::rotary_sphere::LOCATION_NAMES`.
    pub location: [f64; 4],
    pub location_sigma: [f64; 4],
    pub location_covariance: [[f64; 4]; 4],
    /// Per height, the sphere centre at θ = 0 under the fitted axis (m).
    pub sphere_positions_m: Vec<[f64; 3]>,
    pub angles_rad: Vec<f64>,
    /// Per angle, EXC, EYC, EZC (m), EAC, EBC, ECC (rad) under `convention`.
    pub motion: Vec<[f64; 6]>,
    pub motion_sigma: Vec<[f64; 6]>,
    pub convention: TangentialConvention,
    /// Per angle, the tangential combination the data fix: t + r·ECC (m), r = mean radius.
    pub tangential_m: Vec<f64>,
    pub reference_radius_m: f64,
    /// Azimuth of the sphere at θ = 0 (the fitted positions' mean): at angle θ its radial
    /// direction is (cos(θ + φ), sin(θ + φ), 0) and the tangential one (ẑ × radial) that
    /// `tangential_m` is taken along.
    pub sphere_azimuth_rad: f64,
    /// The azimuth along which EXC, EYC are written (`IdentifyOptions::radial_azimuth_rad`).
    pub radial_azimuth_rad: f64,
    pub harmonics: Vec<HarmonicFit>,
    /// χ² of the per-angle motion model (heights beyond 2 give redundancy) and its dof.
    pub chi2: f64,
    pub dof: usize,
    /// Joint covariance of [location (4), all harmonic coefficients in `harmonics` order].
    #[serde(skip)]
    pub model_covariance: DMatrix<f64>,
}

impl RotaryAxisIdentification {
    /// Motion errors at any angle from the harmonic fits.
    pub fn motion_model(&self, theta_rad: f64) -> Vector6<f64> {
        Vector6::from_fn(|k, _| self.harmonics[k].value(theta_rad))
    }

    /// Predicted centre of a sphere at `q_m` (its position at θ = 0) and the Jacobian of the
    /// prediction with respect to [location, coefficients] (for its covariance).
    pub fn predict(&self, theta_rad: f64, q_m: &Vector3<f64>) -> (Vector3<f64>, DMatrix<f64>) {
        let loc = self.location;
        let p = rz(theta_rad) * q_m;
        let m = self.motion_model(theta_rad);
        let centre = located_centre(theta_rad, q_m, &loc) + motion_jacobian(&p) * m;
        let (_, dl) = located_centre_jacobian(theta_rad, q_m, &loc);
        let jm = motion_jacobian(&p);
        let n = self.model_covariance.nrows();
        let mut j = DMatrix::zeros(3, n);
        j.view_mut((0, 0), (3, 4)).copy_from(&dl);
        let mut col = 4;
        for (k, h) in self.harmonics.iter().enumerate() {
            let b = harmonic_basis(theta_rad, h.order);
            for (i, bi) in b.iter().enumerate() {
                for r in 0..3 {
                    j[(r, col + i)] = jm[(r, k)] * bi;
                }
            }
            col += b.len();
        }
        (centre, j)
    }

    /// Covariance (m²) of `predict`'s centre from the model's uncertainty.
    pub fn predict_covariance(&self, theta_rad: f64, q_m: &Vector3<f64>) -> Matrix3<f64> {
        let (_, j) = self.predict(theta_rad, q_m);
        let c = &j * &self.model_covariance * j.transpose();
        Matrix3::from_fn(|r, k| c[(r, k)])
    }
}

const ANGLE_TOL_RAD: f64 = 1e-9;

/// Identify the axis from the centres at ≥ 2 heights, all probed at the same angles.
pub fn identify_rotary_axis(
    series: &[CentreSeries],
    options: &IdentifyOptions,
) -> Result<RotaryAxisIdentification, RotarySphereError> {
    let nh = series.len();
    if nh < 2 {
        return Err(RotarySphereError::TooFewHeights(nh));
    }
    for (h, s) in series.iter().enumerate() {
        let n = s.angles_rad.len();
        if s.centres_m.len() != n || s.covariances_m2.len() != n {
            return Err(RotarySphereError::SeriesShape(
                h,
                n,
                s.centres_m.len().min(s.covariances_m2.len()),
            ));
        }
        if n != series[0].angles_rad.len()
            || s.angles_rad
                .iter()
                .zip(&series[0].angles_rad)
                .any(|(a, b)| (a - b).abs() > ANGLE_TOL_RAD)
        {
            return Err(RotarySphereError::AnglesDiffer(h));
        }
    }
    let angles = series[0].angles_rad.clone();
    let na = angles.len();
    if na < 3 {
        return Err(RotarySphereError::TooFewAngles(na));
    }
    // Observation order: height-major, then angle, then x, y, z.
    let nobs = 3 * nh * na;
    let obs_index = |h: usize, i: usize| 3 * (h * na + i);
    let mut c_obs = DVector::zeros(nobs);
    let mut sigma_c = DMatrix::zeros(nobs, nobs);
    let mut weight = DMatrix::zeros(nobs, nobs);
    for (h, s) in series.iter().enumerate() {
        for i in 0..na {
            let o = obs_index(h, i);
            c_obs.fixed_rows_mut::<3>(o).copy_from(&s.centres_m[i]);
            let cov = s.covariances_m2[i];
            sigma_c.fixed_view_mut::<3, 3>(o, o).copy_from(&cov);
            let w = inverse_weight(&cov)?;
            weight.fixed_view_mut::<3, 3>(o, o).copy_from(&w);
        }
    }
    // Stage 1 weighs every centre alike (the inverse of the mean centre covariance): weights
    // that vary with the angle (a misplaced sphere meets the fixed probing lines at other
    // normals at each angle) would correlate with the motion errors and pull part of them
    // into the location errors. The loss of efficiency is second order; the covariance below
    // is propagated from each centre's own covariance, so it stays exact.
    //
    // Nor does it couple z with x or y: the axial motion errors (z) and the radial ones (x, y)
    // are orthogonal to the location model only each on its own; a weight with x–z or y–z
    // terms mixes them, and its products with the axial motion's harmonics pulled up to
    // 7 nm / 60 nrad of it into EXOC..EBOC. The weight is the inverse of the mean covariance's
    // xy block beside the inverse of its zz term.
    let mut mean_cov = series
        .iter()
        .flat_map(|s| s.covariances_m2.iter())
        .sum::<Matrix3<f64>>()
        / (nh * na) as f64;
    for k in 0..2 {
        mean_cov[(k, 2)] = 0.0;
        mean_cov[(2, k)] = 0.0;
    }
    let common_weight = inverse_weight(&mean_cov)?;
    let mut weight1 = DMatrix::zeros(nobs, nobs);
    for b in 0..nh * na {
        weight1
            .fixed_view_mut::<3, 3>(3 * b, 3 * b)
            .copy_from(&common_weight);
    }

    // Stage 1: sphere positions q_h and the location errors, motion errors treated as zero.
    let np1 = 3 * nh + 4;
    let mut q: Vec<Vector3<f64>> = series
        .iter()
        .map(|s| {
            s.angles_rad
                .iter()
                .zip(&s.centres_m)
                .map(|(a, c)| rz(-a) * c)
                .sum::<Vector3<f64>>()
                / na as f64
        })
        .collect();
    let mut loc = [0.0; 4];
    let stage1 = |q: &[Vector3<f64>], loc: &[f64; 4]| -> (DMatrix<f64>, DVector<f64>) {
        let mut j = DMatrix::zeros(nobs, np1);
        let mut r = DVector::zeros(nobs);
        for (h, qh) in q.iter().enumerate() {
            for (i, &a) in angles.iter().enumerate() {
                let o = obs_index(h, i);
                let pred = located_centre(a, qh, loc);
                let (dq, dl) = located_centre_jacobian(a, qh, loc);
                j.view_mut((o, 3 * h), (3, 3)).copy_from(&dq);
                j.view_mut((o, 3 * nh), (3, 4)).copy_from(&dl);
                r.fixed_rows_mut::<3>(o)
                    .copy_from(&(c_obs.fixed_rows::<3>(o) - pred));
            }
        }
        (j, r)
    };
    let mut converged = false;
    for _ in 0..50 {
        let (j, r) = stage1(&q, &loc);
        let jtw = j.transpose() * &weight1;
        let Some(chol) = (&jtw * &j).cholesky() else {
            return Err(RotarySphereError::Singular("axis location"));
        };
        let step = chol.solve(&(&jtw * r));
        for (h, qh) in q.iter_mut().enumerate() {
            *qh += step.fixed_rows::<3>(3 * h);
        }
        for (k, l) in loc.iter_mut().enumerate() {
            *l += step[3 * nh + k];
        }
        // The model is bilinear in two small quantities: a few steps reach rounding level.
        if step.amax() < 1e-15 {
            converged = true;
            break;
        }
    }
    if !converged {
        return Err(RotarySphereError::NoConvergence(50));
    }
    let (j1, resid1) = stage1(&q, &loc);
    let jtw = j1.transpose() * &weight1;
    let a1inv = (&jtw * &j1)
        .try_inverse()
        .ok_or(RotarySphereError::Singular("axis location"))?;
    let g1 = &a1inv * &jtw; // δx = G1 δc
    let proj = DMatrix::<f64>::identity(nobs, nobs) - &j1 * &g1; // δd = P δc
    let g1_loc = g1.rows(3 * nh, 4).into_owned();
    let loc_cov = &g1_loc * &sigma_c * g1_loc.transpose();

    // Stage 2: per angle, the motion errors from the deviations at all heights. Radial and
    // tangential are those of the sphere at that angle (wherever it stands on the table): its
    // fitted position at θ = 0, averaged over the heights, turned by θ.
    let reference_radius_m = q.iter().map(|v| v.xy().norm()).sum::<f64>() / nh as f64;
    let mean_xy = q.iter().map(|v| v.xy()).sum::<nalgebra::Vector2<f64>>();
    let sphere_azimuth_rad = mean_xy.y.atan2(mean_xy.x);
    let mut motion_map = DMatrix::zeros(6 * na, nobs); // motion = M d
    let mut motion = Vec::with_capacity(na);
    let mut chi2 = 0.0;
    let radial_azimuth_rad = options.radial_azimuth_rad.unwrap_or(sphere_azimuth_rad);
    for (i, &a) in angles.iter().enumerate() {
        let (s, c) = (a + radial_azimuth_rad).sin_cos();
        // Free parameters → the six motion errors.
        let t: SMatrix<f64, 6, 5> = match options.convention {
            TangentialConvention::AngularPositioning => SMatrix::<f64, 6, 5>::from_row_slice(&[
                c, 0., 0., 0., 0., //
                s, 0., 0., 0., 0., //
                0., 1., 0., 0., 0., //
                0., 0., 1., 0., 0., //
                0., 0., 0., 1., 0., //
                0., 0., 0., 0., 1.,
            ]),
            TangentialConvention::Translation => SMatrix::<f64, 6, 5>::from_row_slice(&[
                1., 0., 0., 0., 0., //
                0., 1., 0., 0., 0., //
                0., 0., 1., 0., 0., //
                0., 0., 0., 1., 0., //
                0., 0., 0., 0., 1., //
                0., 0., 0., 0., 0.,
            ]),
        };
        let mut a_mat = DMatrix::zeros(3 * nh, 5);
        let mut w_i = DMatrix::zeros(3 * nh, 3 * nh);
        let mut d_i = DVector::zeros(3 * nh);
        for (h, qh) in q.iter().enumerate() {
            let p = rz(a) * qh;
            a_mat
                .view_mut((3 * h, 0), (3, 5))
                .copy_from(&(motion_jacobian(&p) * t));
            let o = obs_index(h, i);
            w_i.view_mut((3 * h, 3 * h), (3, 3))
                .copy_from(&weight.view((o, o), (3, 3)));
            d_i.fixed_rows_mut::<3>(3 * h)
                .copy_from(&resid1.fixed_rows::<3>(o));
        }
        let atw = a_mat.transpose() * &w_i;
        let ainv = (&atw * &a_mat)
            .try_inverse()
            .ok_or(RotarySphereError::Singular("motion errors"))?;
        let k = t * (&ainv * &atw); // 6 x 3nh
        let m = &k * &d_i;
        let e = &d_i - &a_mat * (&ainv * (&atw * &d_i));
        chi2 += (e.transpose() * &w_i * &e)[(0, 0)];
        motion.push(Vector6::from_fn(|r, _| m[r]));
        for h in 0..nh {
            let o = obs_index(h, i);
            motion_map
                .view_mut((6 * i, o), (6, 3))
                .copy_from(&k.view((0, 3 * h), (6, 3)));
        }
    }
    let motion_of_c = &motion_map * &proj; // motion = Mc δc
    let motion_cov = &motion_of_c * &sigma_c * motion_of_c.transpose();

    // Stage 3: harmonic fit of each error function.
    let mut harmonics = Vec::with_capacity(6);
    let mut coef_maps: Vec<DMatrix<f64>> = Vec::with_capacity(6);
    let max_order = (na - 1) / 2;
    for (k, name) in MOTION_NAMES.iter().enumerate() {
        let y = DVector::from_fn(na, |i, _| motion[i][k]);
        let var: Vec<f64> = (0..na)
            .map(|i| motion_cov[(6 * i + k, 6 * i + k)])
            .collect();
        let vmax = var.iter().cloned().fold(0.0, f64::max);
        // Zero-variance values (noise-free input, or an error fixed by the convention) get
        // equal weights: the fit is then plain least squares.
        let w: Vec<f64> = var
            .iter()
            .map(|&v| {
                if vmax > 0.0 {
                    1.0 / v.max(vmax * 1e-12)
                } else {
                    1.0
                }
            })
            .collect();
        let fit_order = |order: usize| {
            let b = DMatrix::from_fn(na, 2 * order + 1, |i, c| {
                harmonic_basis(angles[i], order)[c]
            });
            let bw = DMatrix::from_fn(2 * order + 1, na, |c, i| b[(i, c)] * w[i]);
            let ainv = (&bw * &b).try_inverse();
            ainv.map(|ai| {
                let g = ai * bw; // coef = G y
                let coef = &g * &y;
                let e = &y - &b * &coef;
                let chi2: f64 = e.iter().zip(&w).map(|(e, w)| e * e * w).sum();
                (g, coef, e, chi2)
            })
        };
        let order = match options.harmonics {
            HarmonicOrder::Fixed(o) => o.min(max_order),
            HarmonicOrder::Bic { max_order: mo } => {
                let mut best = (f64::INFINITY, 0);
                for o in 0..=mo.min(max_order) {
                    if let Some((_, _, _, c2)) = fit_order(o) {
                        let bic = c2 + (2 * o + 1) as f64 * (na as f64).ln();
                        if bic < best.0 {
                            best = (bic, o);
                        }
                    }
                }
                best.1
            }
        };
        let (g, coef, e, _) =
            fit_order(order).ok_or(RotarySphereError::Singular("harmonic coefficients"))?;
        // Coefficients as a linear function of all centres, for the joint covariance.
        let rows = DMatrix::from_fn(na, nobs, |i, c| motion_of_c[(6 * i + k, c)]);
        let cmap = &g * rows;
        let cov = &cmap * &sigma_c * cmap.transpose();
        harmonics.push(HarmonicFit {
            name,
            order,
            coefficients: coef.iter().copied().collect(),
            covariance: (0..cov.nrows())
                .map(|r| (0..cov.ncols()).map(|c| cov[(r, c)]).collect())
                .collect(),
            residual_rms: (e.norm_squared() / na as f64).sqrt(),
        });
        coef_maps.push(cmap);
    }
    let ncoef: usize = coef_maps.iter().map(|m| m.nrows()).sum();
    let mut model_map = DMatrix::zeros(4 + ncoef, nobs);
    model_map
        .view_mut((0, 0), (4, nobs))
        .copy_from(&g1.view((3 * nh, 0), (4, nobs)));
    let mut row = 4;
    for m in &coef_maps {
        model_map.view_mut((row, 0), (m.nrows(), nobs)).copy_from(m);
        row += m.nrows();
    }
    let model_covariance = &model_map * &sigma_c * model_map.transpose();
    let tangential_m = motion
        .iter()
        .zip(&angles)
        .map(|(m, &a)| {
            let (s, c) = (a + sphere_azimuth_rad).sin_cos();
            -s * m[0] + c * m[1] + reference_radius_m * m[5]
        })
        .collect();
    Ok(RotaryAxisIdentification {
        location: loc,
        location_sigma: std::array::from_fn(|k| loc_cov[(k, k)].max(0.0).sqrt()),
        location_covariance: std::array::from_fn(|r| std::array::from_fn(|c| loc_cov[(r, c)])),
        sphere_positions_m: q.iter().map(|v| (*v).into()).collect(),
        angles_rad: angles,
        motion: motion.iter().map(|m| (*m).into()).collect(),
        motion_sigma: (0..na)
            .map(|i| std::array::from_fn(|k| motion_cov[(6 * i + k, 6 * i + k)].max(0.0).sqrt()))
            .collect(),
        convention: options.convention,
        tangential_m,
        reference_radius_m,
        sphere_azimuth_rad,
        radial_azimuth_rad,
        harmonics,
        chi2,
        dof: na * (3 * nh - 5),
        model_covariance,
    })
}

/// The inverse of a centre covariance, refused when it is singular or not finite.
fn inverse_weight(cov: &Matrix3<f64>) -> Result<Matrix3<f64>, RotarySphereError> {
    cov.try_inverse()
        .filter(|w| w.iter().all(|v| v.is_finite()))
        .ok_or(RotarySphereError::Singular("centre weights (covariance)"))
}

/// Prediction check on a height not used for fitting.
#[derive(Debug, Clone, Serialize)]
pub struct Validation {
    /// The sphere's position at θ = 0 at this height, fitted to these centres (3 unknowns
    /// against 3·n observations: the error model itself is not refitted).
    pub sphere_position_m: [f64; 3],
    /// Per angle, measured − predicted centre (m).
    pub residuals_m: Vec<[f64; 3]>,
    /// Per angle and coordinate, the predicted standard deviation of the residual: the
    /// centre's own plus the model's.
    pub residual_sigma_m: Vec<[f64; 3]>,
    /// Σ (r/σ)² over all coordinates and its count.
    pub chi2: f64,
    pub count: usize,
}

impl Validation {
    /// Share of angles whose 3-D residual length is within `tol_m`.
    pub fn share_norm_within(&self, tol_m: f64) -> f64 {
        let n = self
            .residuals_m
            .iter()
            .filter(|r| Vector3::from(**r).norm() <= tol_m)
            .count();
        n as f64 / self.residuals_m.len() as f64
    }
    /// Share of single coordinates within `tol_m`.
    pub fn share_coordinates_within(&self, tol_m: f64) -> f64 {
        let n = self
            .residuals_m
            .iter()
            .flat_map(|r| r.iter())
            .filter(|v| v.abs() <= tol_m)
            .count();
        n as f64 / (3 * self.residuals_m.len()) as f64
    }
    /// Share of single coordinates within k predicted standard deviations.
    pub fn share_within_sigmas(&self, k: f64) -> f64 {
        let n = self
            .residuals_m
            .iter()
            .zip(&self.residual_sigma_m)
            .flat_map(|(r, s)| r.iter().zip(s.iter()))
            .filter(|(r, s)| r.abs() <= k * **s)
            .count();
        n as f64 / (3 * self.residuals_m.len()) as f64
    }
}

/// Predict the centres of `series` (a height not used in `id`) and compare.
pub fn validate(
    id: &RotaryAxisIdentification,
    series: &CentreSeries,
) -> Result<Validation, RotarySphereError> {
    let n = series.angles_rad.len();
    if series.centres_m.len() != n || series.covariances_m2.len() != n {
        return Err(RotarySphereError::SeriesShape(
            0,
            n,
            series.centres_m.len().min(series.covariances_m2.len()),
        ));
    }
    let loc = id.location;
    let weights: Vec<Matrix3<f64>> = series
        .covariances_m2
        .iter()
        .map(|c| {
            c.try_inverse()
                .ok_or(RotarySphereError::Singular("centre weights (covariance)"))
        })
        .collect::<Result<_, _>>()?;
    let mut q = series
        .angles_rad
        .iter()
        .zip(&series.centres_m)
        .map(|(a, c)| rz(-a) * c)
        .sum::<Vector3<f64>>()
        / n as f64;
    for _ in 0..20 {
        let mut ata = Matrix3::zeros();
        let mut atb = Vector3::zeros();
        for (i, &a) in series.angles_rad.iter().enumerate() {
            let (pred, _) = id.predict(a, &q);
            let (dq, _) = located_centre_jacobian(a, &q, &loc);
            let eps = id.motion_model(a).fixed_rows::<3>(3).into_owned();
            let jq = dq + skew(&eps) * rz(a);
            ata += jq.transpose() * weights[i] * jq;
            atb += jq.transpose() * weights[i] * (series.centres_m[i] - pred);
        }
        let step = ata
            .try_inverse()
            .ok_or(RotarySphereError::Singular("validation sphere position"))?
            * atb;
        q += step;
        if step.amax() < 1e-15 {
            break;
        }
    }
    let mut residuals_m = Vec::with_capacity(n);
    let mut residual_sigma_m = Vec::with_capacity(n);
    let mut chi2 = 0.0;
    for (i, &a) in series.angles_rad.iter().enumerate() {
        let (pred, _) = id.predict(a, &q);
        let r = series.centres_m[i] - pred;
        let cov = series.covariances_m2[i] + id.predict_covariance(a, &q);
        let s: [f64; 3] = std::array::from_fn(|k| cov[(k, k)].max(0.0).sqrt());
        for k in 0..3 {
            if s[k] > 0.0 {
                chi2 += (r[k] / s[k]).powi(2);
            }
        }
        residuals_m.push(r.into());
        residual_sigma_m.push(s);
    }
    Ok(Validation {
        sphere_position_m: q.into(),
        residuals_m,
        residual_sigma_m,
        chi2,
        count: 3 * n,
    })
}

/// A simulated rotary table carrying a sphere, and its probing (tests and examples).
pub mod simulation {
    use super::*;
    use nalgebra::Rotation3;
    use rand::Rng;

    /// True axis: location errors and harmonic motion errors (coefficients in the order of
    /// `harmonic_basis`, per error in `MOTION_NAMES` order).
    #[derive(Debug, Clone)]
    pub struct TrueAxis {
        pub location: [f64; 4],
        pub motion_coefficients: [Vec<f64>; 6],
    }

    impl TrueAxis {
        /// Errors of realistic size for a precision rotary table: location tens of µm and
        /// µrad, radial/axial motion a few µm, tilt a few µrad, positioning ~ 4″, harmonics up
        /// to `order`.
        pub fn realistic<R: Rng>(rng: &mut R, order: usize) -> TrueAxis {
            let mut g = |s: f64| -> f64 {
                let z: f64 = rand_distr::Distribution::sample(&rand_distr::StandardNormal, rng);
                z * s
            };
            let location = [g(25e-6), g(25e-6), g(40e-6), g(40e-6)];
            let scale = [2e-6, 2e-6, 1.5e-6, 3e-6, 3e-6, 10e-6];
            let motion_coefficients = std::array::from_fn(|k| {
                (0..2 * order + 1)
                    .map(|c| g(scale[k] / (1.0 + (c / 2) as f64)))
                    .collect()
            });
            TrueAxis {
                location,
                motion_coefficients,
            }
        }

        pub fn motion(&self, theta_rad: f64) -> Vector6<f64> {
            Vector6::from_fn(|k, _| {
                let c = &self.motion_coefficients[k];
                let order = (c.len() - 1) / 2;
                harmonic_basis(theta_rad, order)
                    .iter()
                    .zip(c)
                    .map(|(b, c)| b * c)
                    .sum()
            })
        }

        /// True centre of a sphere whose centre is `q_m` at θ = 0 under an ideal axis: exact
        /// rotation about the tilted, shifted axis, then the exact rigid motion error.
        pub fn centre(&self, theta_rad: f64, q_m: &Vector3<f64>) -> Vector3<f64> {
            let l = &self.location;
            let a = Vector3::new(l[0], l[1], 0.0);
            let tilt = Rotation3::new(Vector3::new(l[2], l[3], 0.0));
            let turn = Rotation3::new(Vector3::z() * theta_rad);
            let p = a + tilt * turn * tilt.inverse() * (q_m - a);
            let m = self.motion(theta_rad);
            let eps = Rotation3::new(Vector3::new(m[3], m[4], m[5]));
            eps * p + Vector3::new(m[0], m[1], m[2])
        }
    }

    impl TrueAxis {
        /// The same centre from the first-order model the solver inverts: data on which the
        /// identification must be exact.
        pub fn centre_first_order(&self, theta_rad: f64, q_m: &Vector3<f64>) -> Vector3<f64> {
            crate::model::rotary_sphere::predicted_centre(
                theta_rad,
                q_m,
                &self.location,
                &self.motion(theta_rad),
            )
        }
    }

    /// Probing: `points` surface points (5 = the top pole and 4 equator poles, as published;
    /// more are spread over the upper hemisphere), each with isotropic Gaussian noise of
    /// `sigma_m` per coordinate, then a sphere fit with the known radius.
    pub fn probe_sphere<R: Rng>(
        rng: &mut R,
        centre_m: &Vector3<f64>,
        radius_m: f64,
        points: usize,
        sigma_m: f64,
    ) -> SphereFit {
        let dirs = probe_directions(points);
        let pts: Vec<Vector3<f64>> = dirs
            .iter()
            .map(|d| {
                let noise = Vector3::from_fn(|_, _| {
                    let z: f64 = rand_distr::Distribution::sample(&rand_distr::StandardNormal, rng);
                    z * sigma_m
                });
                centre_m + d * radius_m + noise
            })
            .collect();
        fit_sphere(&pts, Some(radius_m), Some(sigma_m.max(1e-12)))
            .expect("simulated probing determines the sphere")
    }

    pub fn probe_directions(points: usize) -> Vec<Vector3<f64>> {
        let mut d = vec![
            Vector3::z(),
            Vector3::x(),
            -Vector3::x(),
            Vector3::y(),
            -Vector3::y(),
        ];
        // Further points on rings at 45° elevation, staggered.
        let mut k = 0;
        while d.len() < points {
            let az = 0.4 + k as f64 * 2.399963; // golden angle
            let el: f64 = if k % 2 == 0 { 0.785 } else { 0.35 };
            d.push(Vector3::new(
                el.cos() * az.cos(),
                el.cos() * az.sin(),
                el.sin(),
            ));
            k += 1;
        }
        d.truncate(points.max(4));
        d
    }

    /// The sphere probed at every angle at each of the given positions (θ = 0, m).
    pub fn simulate_series<R: Rng>(
        rng: &mut R,
        truth: &TrueAxis,
        positions_m: &[Vector3<f64>],
        angles_rad: &[f64],
        radius_m: f64,
        points: usize,
        sigma_m: f64,
    ) -> Vec<CentreSeries> {
        positions_m
            .iter()
            .map(|q| {
                let fits: Vec<SphereFit> = angles_rad
                    .iter()
                    .map(|&a| probe_sphere(rng, &truth.centre(a, q), radius_m, points, sigma_m))
                    .collect();
                CentreSeries::from_fits(angles_rad.to_vec(), &fits)
            })
            .collect()
    }

    /// Published geometry: sphere at (71, 0, 179) mm, heights 100 mm apart, validation
    /// between them; every 10°.
    pub fn published_positions_m() -> [Vector3<f64>; 3] {
        [
            Vector3::new(0.071, 0.0, 0.179),
            Vector3::new(0.071, 0.0, 0.279),
            Vector3::new(0.071, 0.0, 0.229),
        ]
    }

    pub fn angles_every(step_deg: f64) -> Vec<f64> {
        let n = (360.0 / step_deg).round() as usize;
        (0..n).map(|k| (k as f64 * step_deg).to_radians()).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::simulation::*;
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    const SPHERE_RADIUS_M: f64 = 0.0127;

    #[test]
    fn sphere_fit_exact_and_covariance() {
        let c = Vector3::new(0.071, -0.002, 0.179);
        let dirs = probe_directions(9);
        let pts: Vec<_> = dirs.iter().map(|d| c + d * SPHERE_RADIUS_M).collect();
        let known = fit_sphere(&pts, Some(SPHERE_RADIUS_M), Some(1e-6)).unwrap();
        assert!((known.centre() - c).amax() < 1e-14);
        let free = fit_sphere(&pts, None, None).unwrap();
        assert!((free.centre() - c).amax() < 1e-14);
        assert!((free.radius_m - SPHERE_RADIUS_M).abs() < 1e-14);
        // Monte Carlo of the 5-point known-radius fit against its covariance.
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let sigma = 27e-6;
        let pred = probe_sphere(&mut rng, &c, SPHERE_RADIUS_M, 5, sigma).covariance();
        let trials = 3000;
        let mut ss = Vector3::zeros();
        for _ in 0..trials {
            let f = probe_sphere(&mut rng, &c, SPHERE_RADIUS_M, 5, sigma);
            ss += (f.centre() - c).map(|v| v * v);
        }
        for k in 0..3 {
            let ratio = ss[k] / trials as f64 / pred[(k, k)];
            assert!((0.85..1.15).contains(&ratio), "axis {k}: {ratio}");
        }
        assert!(matches!(
            fit_sphere(&pts[..3], None, None),
            Err(RotarySphereError::TooFewPoints { .. })
        ));
    }

    fn noise_free(
        truth: &TrueAxis,
        opts: &IdentifyOptions,
        first_order: bool,
    ) -> (Vec<CentreSeries>, RotaryAxisIdentification) {
        let pos = published_positions_m();
        let angles = angles_every(10.0);
        let series: Vec<CentreSeries> = pos
            .iter()
            .map(|q| CentreSeries {
                angles_rad: angles.clone(),
                centres_m: angles
                    .iter()
                    .map(|&a| {
                        if first_order {
                            truth.centre_first_order(a, q)
                        } else {
                            truth.centre(a, q)
                        }
                    })
                    .collect(),
                covariances_m2: vec![Matrix3::identity() * 1e-12; angles.len()],
            })
            .collect();
        let id = identify_rotary_axis(&series[..2], opts).unwrap();
        (series, id)
    }

    #[test]
    fn location_exact_without_motion_errors() {
        let truth = TrueAxis {
            location: [25e-6, -18e-6, 40e-6, -25e-6],
            motion_coefficients: std::array::from_fn(|_| vec![0.0]),
        };
        let (_, id) = noise_free(&truth, &IdentifyOptions::default(), true);
        for k in 0..4 {
            assert!((id.location[k] - truth.location[k]).abs() < 1e-14, "{k}");
        }
        for m in &id.motion {
            assert!(m.iter().all(|v| v.abs() < 1e-13), "{m:?}");
        }
        // Exact rotations: only second-order terms (tilt² · height, nm) are left out.
        let (_, id) = noise_free(&truth, &IdentifyOptions::default(), false);
        for k in 0..4 {
            assert!((id.location[k] - truth.location[k]).abs() < 2e-8, "{k}");
        }
    }

    /// Harmonic truth, no noise: the fixed-order fit reproduces every per-angle value and the
    /// model predicts the third (unused) height to rounding level.
    #[test]
    fn harmonic_fit_exact_on_noise_free_truth() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let truth = TrueAxis::realistic(&mut rng, 3);
        let opts = IdentifyOptions {
            harmonics: HarmonicOrder::Fixed(6),
            ..Default::default()
        };
        let (series, id) = noise_free(&truth, &opts, true);
        // What is left is second order: motion errors (µrad) times the shift of the fitted
        // sphere positions that absorb their once-per-turn part (µm).
        for h in &id.harmonics {
            assert!(h.residual_rms < 2e-10, "{}: {}", h.name, h.residual_rms);
        }
        let v = validate(&id, &series[2]).unwrap();
        for r in &v.residuals_m {
            assert!(Vector3::from(*r).amax() < 1e-9, "{r:?}");
        }
        // The tangential combination is convention-free.
        let (_, id_t) = noise_free(
            &truth,
            &IdentifyOptions {
                convention: TangentialConvention::Translation,
                ..opts
            },
            true,
        );
        for (a, b) in id.tangential_m.iter().zip(&id_t.tangential_m) {
            assert!((a - b).abs() < 1e-9, "{a} {b}");
        }
    }

    /// Noisy probing (27 µm per point, 5 points): location and motion errors against the
    /// noise-free identification (the estimand) within 3 σ for ≥ 97 % of values, and the
    /// validation residuals consistent with their predicted σ.
    #[test]
    fn noisy_recovery_within_reported_uncertainty() {
        let mut rng = ChaCha8Rng::seed_from_u64(17);
        let truth = TrueAxis::realistic(&mut rng, 3);
        let opts = IdentifyOptions {
            harmonics: HarmonicOrder::Fixed(4),
            ..Default::default()
        };
        let (_, exact) = noise_free(&truth, &opts, false);
        let pos = published_positions_m();
        let angles = angles_every(10.0);
        let (mut inside, mut total) = (0usize, 0usize);
        let (mut v_inside, mut v_total) = (0.0, 0.0);
        let mut chi2 = 0.0;
        let mut count = 0;
        for _ in 0..6 {
            let series =
                simulate_series(&mut rng, &truth, &pos, &angles, SPHERE_RADIUS_M, 5, 27e-6);
            let id = identify_rotary_axis(&series[..2], &opts).unwrap();
            for k in 0..4 {
                total += 1;
                if (id.location[k] - exact.location[k]).abs() <= 3.0 * id.location_sigma[k] {
                    inside += 1;
                }
            }
            for i in 0..angles.len() {
                for k in 0..6 {
                    total += 1;
                    if (id.motion[i][k] - exact.motion[i][k]).abs()
                        <= 3.0 * id.motion_sigma[i][k] + 1e-15
                    {
                        inside += 1;
                    }
                }
            }
            let v = validate(&id, &series[2]).unwrap();
            v_inside += v.share_within_sigmas(3.0) * v.count as f64;
            v_total += v.count as f64;
            chi2 += v.chi2;
            count += v.count;
        }
        let share = inside as f64 / total as f64;
        assert!(share >= 0.97, "within 3σ: {share}");
        assert!(
            v_inside / v_total >= 0.97,
            "validation within 3σ: {}",
            v_inside / v_total
        );
        let ratio = chi2 / count as f64;
        assert!((0.75..1.3).contains(&ratio), "validation χ²/n = {ratio}");
    }

    /// A truth whose motion errors hold nothing a fixed axis or the sphere positions would
    /// absorb (no constant or co-rotating once-per-turn part at the sphere), so the physical
    /// axis and motion are exactly what the identification must return.
    fn unabsorbed_truth() -> TrueAxis {
        // Per error, [c0, a1, b1, a2, b2, a3, b3] (harmonic_basis order 3).
        let (ex, ey) = (
            vec![0.0, 0.0, 0.0, 0.6e-6, -0.3e-6, 0.2e-6, 0.4e-6],
            vec![0.0, 0.0, 0.0, 0.3e-6, 0.6e-6, -0.4e-6, 0.2e-6],
        );
        // ε_xy = a e^{3iθ} + b e^{-iθ}: at the sphere its z displacement is of order 2 and 4θ.
        let (a, b) = (1.5e-6, -0.8e-6);
        TrueAxis {
            location: [-44e-6, 80e-6, -18e-6, 9e-6],
            motion_coefficients: [
                ex,
                ey,
                vec![0.0, 0.0, 0.0, -0.2e-6, 0.4e-6, 0.3e-6, -0.1e-6],
                vec![0.0, b, 0.0, 0.0, 0.0, a, 0.0],
                vec![0.0, 0.0, -b, 0.0, 0.0, 0.0, a],
                vec![0.0, 0.0, 0.0, 3e-6, -2e-6, 1e-6, 1.5e-6],
            ],
        }
    }

    /// The truth's motion at θ under the convention: the radial translation e·u_r (u_r the
    /// sphere's true direction) written along the nominal direction u_n, ECC taking up the
    /// tangential rest, so that both move the sphere's centre alike.
    fn motion_in_convention(
        truth: &TrueAxis,
        theta: f64,
        q: &Vector3<f64>,
        nominal: f64,
    ) -> [f64; 6] {
        let m = truth.motion(theta);
        let p = rz(theta) * q;
        let r = p.xy().norm();
        let u_r = Vector3::new(p.x / r, p.y / r, 0.0);
        let u_t = Vector3::z().cross(&u_r);
        let u_n = Vector3::new((theta + nominal).cos(), (theta + nominal).sin(), 0.0);
        let e = Vector3::new(m[0], m[1], m[2]);
        let e_r = e.dot(&u_r) / u_n.dot(&u_r);
        let ecc = m[5] + (e.dot(&u_t) - e_r * u_n.dot(&u_t)) / r;
        [e_r * u_n.x, e_r * u_n.y, m[2], m[3], m[4], ecc]
    }

    /// The sphere at several azimuths, misplaced by 0.3 mm from nominal, its centres'
    /// covariances varying with the angle (as a misplaced sphere's do): noise-free, the
    /// identification returns the physical axis and motion; noisy, their errors are
    /// consistent with the reported σ.
    /// Spheres at two heights, 0.133 m off the axis at azimuth `nominal` (placed 0.3 mm off
    /// their nominal), and the options that identify them with that radial direction.
    fn two_heights_at(nominal: f64) -> (Vec<Vector3<f64>>, IdentifyOptions) {
        let placement = Vector3::new(0.26e-3, -0.29e-3, 0.04e-3);
        let q = [0.178, 0.084]
            .iter()
            .map(|&z| Vector3::new(0.133 * nominal.cos(), 0.133 * nominal.sin(), z) + placement)
            .collect();
        let opts = IdentifyOptions {
            harmonics: HarmonicOrder::Fixed(4),
            radial_azimuth_rad: Some(nominal),
            ..Default::default()
        };
        (q, opts)
    }

    #[test]
    fn sphere_at_any_azimuth_against_the_physical_truth() {
        let truth = unabsorbed_truth();
        let angles: Vec<f64> = (0..24)
            .map(|k| (7.5 + 15.0 * k as f64).to_radians())
            .collect();
        let sigma = 0.4e-6;
        let mut rng = ChaCha8Rng::seed_from_u64(41);
        let (mut z2, mut count) = (0.0, 0usize);
        for nominal in [0.0, 1.0, -1.4311699866353502, 2.5, std::f64::consts::PI] {
            let (q, opts) = two_heights_at(nominal);
            let covariance =
                |a: f64| Matrix3::identity() * (sigma * sigma) * (1.0 + 0.3 * (2.0 * a).cos());
            let series_of = |noisy: bool, rng: &mut ChaCha8Rng| -> Vec<CentreSeries> {
                q.iter()
                    .map(|qh| CentreSeries {
                        angles_rad: angles.clone(),
                        centres_m: angles
                            .iter()
                            .map(|&a| {
                                let n = Vector3::from_fn(|_, _| {
                                    let z: f64 = rand_distr::Distribution::sample(
                                        &rand_distr::StandardNormal,
                                        rng,
                                    );
                                    z
                                });
                                truth.centre(a, qh)
                                    + if noisy {
                                        n * (sigma * (1.0 + 0.3 * (2.0 * a).cos()).sqrt())
                                    } else {
                                        Vector3::zeros()
                                    }
                            })
                            .collect(),
                        covariances_m2: angles.iter().map(|&a| covariance(a)).collect(),
                    })
                    .collect()
            };
            let exact = identify_rotary_axis(&series_of(false, &mut rng), &opts).unwrap();
            for k in 0..4 {
                let tol = if k < 2 { 2e-9 } else { 2e-8 };
                let e = exact.location[k] - truth.location[k];
                assert!(e.abs() < tol, "azimuth {nominal}: location {k} off by {e}");
            }
            for (i, &a) in angles.iter().enumerate() {
                let want = motion_in_convention(&truth, a, &q[0], nominal);
                for k in 0..6 {
                    let tol = if k < 3 { 2e-9 } else { 2e-8 };
                    let e = exact.motion[i][k] - want[k];
                    assert!(
                        e.abs() < tol,
                        "azimuth {nominal}, angle {i}: {} off by {e}",
                        MOTION_NAMES[k]
                    );
                }
            }
            for _ in 0..4 {
                let id = identify_rotary_axis(&series_of(true, &mut rng), &opts).unwrap();
                for k in 0..4 {
                    z2 += ((id.location[k] - truth.location[k]) / id.location_sigma[k]).powi(2);
                    count += 1;
                }
                for (i, &a) in angles.iter().enumerate() {
                    let want = motion_in_convention(&truth, a, &q[0], nominal);
                    // EXC, EYC are one radial value: count it once, by the larger component.
                    let k_radial = if id.motion_sigma[i][0] > id.motion_sigma[i][1] {
                        0
                    } else {
                        1
                    };
                    for k in [k_radial, 2, 3, 4, 5] {
                        z2 += ((id.motion[i][k] - want[k]) / id.motion_sigma[i][k]).powi(2);
                        count += 1;
                    }
                }
            }
        }
        let mean = z2 / count as f64;
        assert!((0.85..1.15).contains(&mean), "mean z² {mean} over {count}");
    }

    /// Centre covariances that couple z with x and y (probing lines meeting the sphere
    /// obliquely), varying with the angle: noise-free, the location errors are still the
    /// physical ones (2 nm / 20 nrad).
    #[test]
    fn coupled_centre_covariances_leave_the_location_physical() {
        let truth = unabsorbed_truth();
        let angles: Vec<f64> = (0..24)
            .map(|k| (7.5 + 15.0 * k as f64).to_radians())
            .collect();
        let sigma = 0.05e-6;
        let base = Matrix3::new(1.0, 0.1, 0.45, 0.1, 1.2, -0.35, 0.45, -0.35, 0.8) * sigma * sigma;
        for nominal in [0.0f64, 1.0, 2.5] {
            let (q, opts) = two_heights_at(nominal);
            let series: Vec<CentreSeries> = q
                .iter()
                .map(|qh| CentreSeries {
                    angles_rad: angles.clone(),
                    centres_m: angles.iter().map(|&a| truth.centre(a, qh)).collect(),
                    covariances_m2: angles
                        .iter()
                        .map(|&a| base * (1.0 + 0.3 * (2.0 * a).cos()))
                        .collect(),
                })
                .collect();
            let exact = identify_rotary_axis(&series, &opts).unwrap();
            for k in 0..4 {
                let tol = if k < 2 { 2e-9 } else { 2e-8 };
                let e = exact.location[k] - truth.location[k];
                println!("azimuth {nominal}: location {k} off by {e:.3e}");
                assert!(e.abs() < tol, "azimuth {nominal}: location {k} off by {e}");
            }
        }
    }

    #[test]
    fn input_errors() {
        let s = CentreSeries {
            angles_rad: vec![0.0, 1.0],
            centres_m: vec![Vector3::zeros(); 2],
            covariances_m2: vec![Matrix3::identity(); 2],
        };
        assert!(matches!(
            identify_rotary_axis(std::slice::from_ref(&s), &IdentifyOptions::default()),
            Err(RotarySphereError::TooFewHeights(1))
        ));
        let mut t = s.clone();
        t.angles_rad[1] = 2.0;
        assert!(matches!(
            identify_rotary_axis(&[s, t], &IdentifyOptions::default()),
            Err(RotarySphereError::AnglesDiffer(1))
        ));
    }
}
