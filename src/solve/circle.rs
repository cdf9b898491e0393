//! A circle in space fitted by least squares to points (plane, centre, radius and the angle of
//! every point about the axis), with the first-order covariance propagated from the points'.

use nalgebra::{DMatrix, DVector, Matrix3, Rotation3, SymmetricEigen, Unit, Vector3};

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum CircleError {
    #[error("a circle needs at least 3 points, found {0}")]
    TooFewPoints(usize),
    #[error("point {0} is not finite")]
    NotFinite(usize),
    #[error("the points are (nearly) collinear or coincident: no circle through them")]
    Degenerate,
    #[error("the point covariance is {found}x{found}: expected {expected}x{expected}")]
    CovarianceShape { found: usize, expected: usize },
    #[error("the circle fit did not converge in {0} iterations")]
    NoConvergence(usize),
}

/// Model: point j = centre + radius (cos φ_j e1 + sin φ_j e2), with (e1, e2, normal) a
/// right-handed frame. Parameters, in the order of `covariance`: centre (3), a tilt of the
/// frame about e1 and about e2 (2, radians), radius (1), φ_0 … φ_{m−1} (m, radians). A turn
/// of the frame about the normal only shifts every φ: angle differences are what is measured.
#[derive(Debug, Clone)]
pub struct CircleFit {
    pub centre_m: Vector3<f64>,
    /// The plane normal: the axis the angles turn about, right-handed.
    pub normal: Unit<Vector3<f64>>,
    pub e1: Vector3<f64>,
    pub e2: Vector3<f64>,
    pub radius_m: f64,
    /// Angle of each point about the normal, from e1 towards e2, radians in (−π, π].
    pub angles_rad: Vec<f64>,
    /// RMS of the residual vectors' lengths (point minus its model point), metres.
    pub residual_rms_m: f64,
    /// Covariance of the parameters (see the type's doc), propagated from the points'.
    pub covariance: DMatrix<f64>,
    pub iterations: usize,
}

const MAX_ITERATIONS: usize = 100;

impl CircleFit {
    /// Angle of point `j` about the normal measured from point `reference`, in [0, 2π), and
    /// its standard deviation.
    pub fn angle_from(&self, reference: usize, j: usize) -> (f64, f64) {
        let angle =
            (self.angles_rad[j] - self.angles_rad[reference]).rem_euclid(std::f64::consts::TAU);
        let (a, b) = (6 + j, 6 + reference);
        let var = self.covariance[(a, a)] + self.covariance[(b, b)] - 2.0 * self.covariance[(a, b)];
        (angle, var.max(0.0).sqrt())
    }

    /// Covariance of points `j`'s and `k`'s angles, both measured from point `reference`.
    pub fn angle_covariance(&self, reference: usize, j: usize, k: usize) -> f64 {
        let c = |a: usize, b: usize| self.covariance[(6 + a, 6 + b)];
        c(j, k) - c(j, reference) - c(reference, k) + c(reference, reference)
    }

    pub fn centre_covariance(&self) -> Matrix3<f64> {
        self.covariance.fixed_view::<3, 3>(0, 0).into_owned()
    }

    /// Covariance of the unit normal (rank 2: it only moves perpendicular to itself).
    pub fn normal_covariance(&self) -> Matrix3<f64> {
        // δn = a (e1 × n) + b (e2 × n) = −a e2 + b e1.
        let mut t = nalgebra::Matrix3x2::zeros();
        t.set_column(0, &(-self.e2));
        t.set_column(1, &self.e1);
        let tilt = self.covariance.fixed_view::<2, 2>(3, 3).into_owned();
        t * tilt * t.transpose()
    }

    pub fn radius_sigma_m(&self) -> f64 {
        self.covariance[(5, 5)].max(0.0).sqrt()
    }
}

/// Fit a circle to `points` (at least 3, not collinear).
///
/// `covariance` is the joint covariance of the points, 3m x 3m (x, y, z of point 0, then
/// point 1, ...); without it the points are taken as independent with the variance per
/// coordinate that the residuals show (zero with fewer than 4 points: nothing to judge by).
/// `orientation` picks the sign of the normal (normal · orientation >= 0); the angles then turn
/// right-handed about it.
pub fn fit_circle(
    points: &[Vector3<f64>],
    covariance: Option<&DMatrix<f64>>,
    orientation: Option<Vector3<f64>>,
) -> Result<CircleFit, CircleError> {
    let m = points.len();
    if m < 3 {
        return Err(CircleError::TooFewPoints(m));
    }
    if let Some(j) = points.iter().position(|p| !p.iter().all(|v| v.is_finite())) {
        return Err(CircleError::NotFinite(j));
    }
    if let Some(c) = covariance {
        if c.nrows() != 3 * m || c.ncols() != 3 * m {
            return Err(CircleError::CovarianceShape {
                found: c.nrows().max(c.ncols()),
                expected: 3 * m,
            });
        }
    }
    let mut state = initial(points, orientation)?;
    let np = m + 6;
    let mut cost = state.cost(points);
    let mut iterations = 0;
    let scale = state.radius_m.max(1e-9);
    loop {
        if iterations >= MAX_ITERATIONS {
            return Err(CircleError::NoConvergence(MAX_ITERATIONS));
        }
        iterations += 1;
        let (jac, res) = state.jacobian_and_residuals(points);
        let normal = jac.transpose() * &jac;
        let Some(chol) = normal.clone().cholesky() else {
            return Err(CircleError::Degenerate);
        };
        let step = chol.solve(&(jac.transpose() * &res));
        // Step halving keeps the iteration downhill even from a poor start.
        let mut t = 1.0;
        let mut accepted = None;
        for _ in 0..30 {
            let trial = state.updated(&(&step * t));
            let c = trial.cost(points);
            if c <= cost {
                accepted = Some((trial, c));
                break;
            }
            t *= 0.5;
        }
        let small = step.amax() * t <= 1e-13 * scale.max(1.0);
        match accepted {
            Some((trial, c)) => {
                state = trial;
                cost = c;
                if small {
                    break;
                }
            }
            // No downhill step left: we sit at the rounding floor of the minimum.
            None => break,
        }
    }
    let (jac, res) = state.jacobian_and_residuals(points);
    let Some(ainv) = (jac.transpose() * &jac).try_inverse() else {
        return Err(CircleError::Degenerate);
    };
    // δθ = (JᵀJ)⁻¹ Jᵀ δP: Σθ = A⁻¹ Jᵀ Σ_P J A⁻¹.
    let g = &ainv * jac.transpose();
    let cov = match covariance {
        Some(c) => &g * c * g.transpose(),
        None => {
            let dof = 3 * m - np;
            let var = if dof > 0 {
                res.norm_squared() / dof as f64
            } else {
                0.0
            };
            &ainv * var
        }
    };
    let residual_rms_m = (res.norm_squared() / m as f64).sqrt();
    Ok(CircleFit {
        centre_m: state.centre_m,
        normal: Unit::new_normalize(state.normal),
        e1: state.e1,
        e2: state.e2,
        radius_m: state.radius_m,
        angles_rad: state.angles_rad.iter().map(|&a| wrap_pi(a)).collect(),
        residual_rms_m,
        covariance: cov,
        iterations,
    })
}

fn wrap_pi(a: f64) -> f64 {
    let w = a.rem_euclid(std::f64::consts::TAU);
    if w > std::f64::consts::PI {
        w - std::f64::consts::TAU
    } else {
        w
    }
}

#[derive(Debug, Clone)]
struct State {
    centre_m: Vector3<f64>,
    e1: Vector3<f64>,
    e2: Vector3<f64>,
    normal: Vector3<f64>,
    radius_m: f64,
    angles_rad: Vec<f64>,
}

impl State {
    fn model(&self, j: usize) -> Vector3<f64> {
        let (s, c) = self.angles_rad[j].sin_cos();
        self.centre_m + (self.e1 * c + self.e2 * s) * self.radius_m
    }

    fn cost(&self, points: &[Vector3<f64>]) -> f64 {
        points
            .iter()
            .enumerate()
            .map(|(j, p)| (p - self.model(j)).norm_squared())
            .sum()
    }

    /// Jacobian of the model points (3m x (m+6)) and the residuals point − model (3m).
    fn jacobian_and_residuals(&self, points: &[Vector3<f64>]) -> (DMatrix<f64>, DVector<f64>) {
        let m = points.len();
        let mut jac = DMatrix::zeros(3 * m, m + 6);
        let mut res = DVector::zeros(3 * m);
        let r = self.radius_m;
        for (j, p) in points.iter().enumerate() {
            let (s, c) = self.angles_rad[j].sin_cos();
            let radial = self.e1 * c + self.e2 * s;
            let tangent = (self.e2 * c - self.e1 * s) * r;
            // Tilt about e1 turns e2 towards n; tilt about e2 turns e1 away from n.
            let d_a = self.normal * (r * s);
            let d_b = self.normal * (-r * c);
            let d = p - self.model(j);
            for k in 0..3 {
                let row = 3 * j + k;
                jac[(row, k)] = 1.0;
                jac[(row, 3)] = d_a[k];
                jac[(row, 4)] = d_b[k];
                jac[(row, 5)] = radial[k];
                jac[(row, 6 + j)] = tangent[k];
                res[row] = d[k];
            }
        }
        (jac, res)
    }

    fn updated(&self, step: &DVector<f64>) -> State {
        let omega = self.e1 * step[3] + self.e2 * step[4];
        let rot = Rotation3::new(omega);
        State {
            centre_m: self.centre_m + Vector3::new(step[0], step[1], step[2]),
            e1: rot * self.e1,
            e2: rot * self.e2,
            normal: rot * self.normal,
            radius_m: self.radius_m + step[5],
            angles_rad: self
                .angles_rad
                .iter()
                .enumerate()
                .map(|(j, a)| a + step[6 + j])
                .collect(),
        }
    }
}

/// Plane through the centroid (smallest principal direction), then an algebraic (Kåsa) circle
/// in that plane.
fn initial(
    points: &[Vector3<f64>],
    orientation: Option<Vector3<f64>>,
) -> Result<State, CircleError> {
    let m = points.len() as f64;
    let centroid = points.iter().sum::<Vector3<f64>>() / m;
    let mut scatter = Matrix3::zeros();
    for p in points {
        let d = p - centroid;
        scatter += d * d.transpose();
    }
    let eig = SymmetricEigen::new(scatter);
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
    let spread = eig.eigenvalues[order[2]];
    if !spread.is_finite() || spread <= 0.0 || eig.eigenvalues[order[1]] <= 1e-12 * spread {
        return Err(CircleError::Degenerate);
    }
    let mut normal: Vector3<f64> = eig.eigenvectors.column(order[0]).into_owned().normalize();
    if let Some(o) = orientation {
        if normal.dot(&o) < 0.0 {
            normal = -normal;
        }
    }
    let helper = if normal.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let e1 = (helper - normal * helper.dot(&normal)).normalize();
    let e2 = normal.cross(&e1);
    // x² + y² + D x + E y + F = 0 by linear least squares.
    let mut a = DMatrix::zeros(points.len(), 3);
    let mut b = DVector::zeros(points.len());
    let xy: Vec<(f64, f64)> = points
        .iter()
        .map(|p| {
            let d = p - centroid;
            (d.dot(&e1), d.dot(&e2))
        })
        .collect();
    for (j, &(x, y)) in xy.iter().enumerate() {
        a[(j, 0)] = x;
        a[(j, 1)] = y;
        a[(j, 2)] = 1.0;
        b[j] = -(x * x + y * y);
    }
    let svd = a.svd(true, true);
    let smax = svd.singular_values.max();
    if !smax.is_finite() || svd.singular_values.min() <= 1e-12 * smax {
        return Err(CircleError::Degenerate);
    }
    let sol = svd.solve(&b, 0.0).map_err(|_| CircleError::Degenerate)?;
    let (cx, cy) = (-sol[0] / 2.0, -sol[1] / 2.0);
    let r2 = cx * cx + cy * cy - sol[2];
    if !(r2 > 0.0 && r2.is_finite()) {
        return Err(CircleError::Degenerate);
    }
    let angles_rad = xy.iter().map(|&(x, y)| (y - cy).atan2(x - cx)).collect();
    Ok(State {
        centre_m: centroid + e1 * cx + e2 * cy,
        e1,
        e2,
        normal,
        radius_m: r2.sqrt(),
        angles_rad,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;
    use rand_distr::{Distribution, StandardNormal};

    struct Truth {
        centre: Vector3<f64>,
        normal: Vector3<f64>,
        radius: f64,
        angles: Vec<f64>,
        points: Vec<Vector3<f64>>,
    }

    /// A tilted circle; points at 30° steps plus small irregularities.
    fn truth(count: usize) -> Truth {
        let centre = Vector3::new(0.31, 0.28, -0.34);
        let normal = Vector3::new(2e-3, -1e-3, 1.0).normalize();
        let e1 = (Vector3::x() - normal * normal.x).normalize();
        let e2 = normal.cross(&e1);
        let radius = 0.152;
        let angles: Vec<f64> = (0..count)
            .map(|k| 0.4 + k as f64 * std::f64::consts::TAU / 12.0 + 2e-5 * (k as f64).sin())
            .collect();
        let points = angles
            .iter()
            .map(|a| centre + (e1 * a.cos() + e2 * a.sin()) * radius)
            .collect();
        Truth {
            centre,
            normal,
            radius,
            angles,
            points,
        }
    }

    #[test]
    fn exact_on_noise_free_points() {
        for count in [3, 5, 12] {
            let t = truth(count);
            let fit = fit_circle(&t.points, None, Some(Vector3::z())).expect("fit");
            assert!((fit.centre_m - t.centre).amax() < 1e-12, "{count}: centre");
            assert!(
                (fit.normal.into_inner() - t.normal).amax() < 1e-12,
                "normal"
            );
            assert!((fit.radius_m - t.radius).abs() < 1e-12);
            assert!(fit.residual_rms_m < 1e-12);
            for j in 1..count {
                let (angle, _) = fit.angle_from(0, j);
                let want = (t.angles[j] - t.angles[0]).rem_euclid(std::f64::consts::TAU);
                assert!((angle - want).abs() < 1e-12, "{count}: angle {j}");
            }
        }
    }

    #[test]
    fn orientation_flips_normal_and_angles() {
        let t = truth(6);
        let up = fit_circle(&t.points, None, Some(Vector3::z())).expect("fit");
        let down = fit_circle(&t.points, None, Some(-Vector3::z())).expect("fit");
        assert!((up.normal.into_inner() + down.normal.into_inner()).amax() < 1e-12);
        let (a_up, _) = up.angle_from(0, 1);
        let (a_down, _) = down.angle_from(0, 1);
        assert!((a_up + a_down - std::f64::consts::TAU).abs() < 1e-12);
    }

    #[test]
    fn degenerate_input_is_an_error() {
        let line: Vec<Vector3<f64>> = (0..4).map(|k| Vector3::new(k as f64, 0.0, 0.0)).collect();
        assert_eq!(
            fit_circle(&line, None, None).err(),
            Some(CircleError::Degenerate)
        );
        assert_eq!(
            fit_circle(&line[..2], None, None).err(),
            Some(CircleError::TooFewPoints(2))
        );
        let mut bad = truth(4).points;
        bad[2].y = f64::NAN;
        assert_eq!(
            fit_circle(&bad, None, None).err(),
            Some(CircleError::NotFinite(2))
        );
        let t = truth(4);
        assert!(matches!(
            fit_circle(&t.points, Some(&DMatrix::zeros(3, 3)), None),
            Err(CircleError::CovarianceShape { .. })
        ));
    }

    /// Propagated covariance against the scatter of fits to noisy points drawn from a full
    /// (correlated) covariance: the ratio of variances lies within [0.8, 1.25].
    #[test]
    fn covariance_matches_monte_carlo() {
        let t = truth(12);
        let m = t.points.len();
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        // Σ = σ² (I + B Bᵀ): correlated as multilateration stations are.
        let sigma = 1e-6;
        let b = DMatrix::<f64>::from_fn(3 * m, 4, |_, _| {
            let z: f64 = StandardNormal.sample(&mut rng);
            0.7 * z
        });
        let cov = (DMatrix::<f64>::identity(3 * m, 3 * m) + &b * b.transpose()) * (sigma * sigma);
        let chol = cov.clone().cholesky().expect("spd").l();
        let fit0 = fit_circle(&t.points, Some(&cov), Some(Vector3::z())).expect("fit");
        let trials = 2000;
        let quantities = |f: &CircleFit| -> Vec<f64> {
            vec![
                f.angle_from(0, 3).0,
                f.angle_from(0, 7).0,
                f.angle_from(2, 11).0,
                f.centre_m.x,
                f.centre_m.z,
                f.radius_m,
                f.normal.x,
            ]
        };
        let predicted = [
            fit0.angle_from(0, 3).1.powi(2),
            fit0.angle_from(0, 7).1.powi(2),
            fit0.angle_from(2, 11).1.powi(2),
            fit0.centre_covariance()[(0, 0)],
            fit0.centre_covariance()[(2, 2)],
            fit0.radius_sigma_m().powi(2),
            fit0.normal_covariance()[(0, 0)],
        ];
        let truth_values = quantities(&fit0);
        let mut sums = vec![0.0; predicted.len()];
        // The two angles from point 0 share its error: their cross-covariance too.
        let mut cross = 0.0;
        for _ in 0..trials {
            let z = DVector::<f64>::from_fn(3 * m, |_, _| StandardNormal.sample(&mut rng));
            let noise = &chol * z;
            let noisy: Vec<Vector3<f64>> = t
                .points
                .iter()
                .enumerate()
                .map(|(j, p)| p + Vector3::new(noise[3 * j], noise[3 * j + 1], noise[3 * j + 2]))
                .collect();
            let fit = fit_circle(&noisy, None, Some(Vector3::z())).expect("fit");
            let q = quantities(&fit);
            for (k, q) in q.iter().enumerate() {
                sums[k] += (q - truth_values[k]).powi(2);
            }
            cross += (q[0] - truth_values[0]) * (q[1] - truth_values[1]);
        }
        let correlation = |c: f64, v0: f64, v1: f64| c / (v0 * v1).sqrt();
        let predicted_correlation =
            correlation(fit0.angle_covariance(0, 3, 7), predicted[0], predicted[1]);
        let monte_carlo_correlation = correlation(cross, sums[0], sums[1]);
        assert!(
            (monte_carlo_correlation - predicted_correlation).abs() < 3.0 / (trials as f64).sqrt(),
            "angle correlation: Monte Carlo {monte_carlo_correlation}, \
             predicted {predicted_correlation}"
        );
        for (k, (ss, want)) in sums.iter().zip(&predicted).enumerate() {
            let ratio = ss / trials as f64 / want;
            assert!(
                (0.8..=1.25).contains(&ratio),
                "quantity {k}: Monte Carlo / predicted variance = {ratio}"
            );
        }
    }
}
