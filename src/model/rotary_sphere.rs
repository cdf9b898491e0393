//! Rotary (C) axis seen through a reference sphere: what a probed surface point and a sphere
//! centre at a commanded table angle predict, with Jacobians, in the small-angle error model.

use nalgebra::{Matrix3, SMatrix, Vector3, Vector6};

/// Index of the position-independent (location) errors of a C axis in parameter vectors,
/// ISO 230-1 names: EXOC, EYOC (where the axis pierces z = 0) and EAOC, EBOC (its tilt about
/// x and about y).
pub const LOCATION_NAMES: [&str; 4] = ["EXOC", "EYOC", "EAOC", "EBOC"];

/// Index of the motion errors in `Vector6` parameter vectors: EXC, EYC, EZC (m) and EAC, EBC,
/// ECC (rad) — the small displacement and rotation of the table at one angle, taken about the
/// origin of the reference frame (on the nominal axis at z = 0).
pub const MOTION_NAMES: [&str; 6] = ["EXC", "EYC", "EZC", "EAC", "EBC", "ECC"];

/// Nominal table rotation about z.
pub fn rz(theta_rad: f64) -> Matrix3<f64> {
    let (s, c) = theta_rad.sin_cos();
    Matrix3::new(c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0)
}

/// Cross-product matrix: skew(v) w = v × w.
pub fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// Surface point residual |p − c| − r and its gradient with respect to the centre (the
/// gradient with respect to the radius is −1).
pub fn sphere_point_residual(
    point_m: &Vector3<f64>,
    centre_m: &Vector3<f64>,
    radius_m: f64,
) -> (f64, Vector3<f64>) {
    let d = point_m - centre_m;
    let n = d.norm();
    // A point at the centre has no direction; any unit gradient keeps the fit defined.
    let grad = if n > 0.0 { -d / n } else { -Vector3::z() };
    (n - radius_m, grad)
}

/// Sphere centre at table angle θ when the axis carries only its location errors
/// `loc` = [EXOC m, EYOC m, EAOC rad, EBOC rad]; `q_m` is the centre at θ = 0.
///
/// The table turns about the line through a = (EXOC, EYOC, 0) with direction
/// ẑ + w × ẑ, w = (EAOC, EBOC, 0); to first order R_u(θ) = Rz + [w]× Rz − Rz [w]×, so
/// c = Rz q + (I − Rz) a + w × (Rz q) − Rz (w × q), which equals q at θ = 0.
pub fn located_centre(theta_rad: f64, q_m: &Vector3<f64>, loc: &[f64; 4]) -> Vector3<f64> {
    let r = rz(theta_rad);
    let a = Vector3::new(loc[0], loc[1], 0.0);
    let w = Vector3::new(loc[2], loc[3], 0.0);
    let rq = r * q_m;
    rq + (Matrix3::identity() - r) * a + w.cross(&rq) - r * w.cross(q_m)
}

/// Jacobians of `located_centre` with respect to q (3x3) and to `loc` (3x4).
pub fn located_centre_jacobian(
    theta_rad: f64,
    q_m: &Vector3<f64>,
    loc: &[f64; 4],
) -> (Matrix3<f64>, SMatrix<f64, 3, 4>) {
    let r = rz(theta_rad);
    let w = Vector3::new(loc[2], loc[3], 0.0);
    let dq = r + skew(&w) * r - r * skew(&w);
    let ia = Matrix3::identity() - r;
    // ∂(w × v)/∂w = −[v]×.
    let dw = -skew(&(r * q_m)) + r * skew(q_m);
    let mut dl = SMatrix::<f64, 3, 4>::zeros();
    dl.fixed_view_mut::<3, 2>(0, 0)
        .copy_from(&ia.fixed_view::<3, 2>(0, 0));
    dl.fixed_view_mut::<3, 2>(0, 2)
        .copy_from(&dw.fixed_view::<3, 2>(0, 0));
    (dq, dl)
}

/// Displacement of a table point at `p_m` (reference frame) by the motion errors
/// `m` = [EXC, EYC, EZC, EAC, EBC, ECC]: e + ε × p.
pub fn motion_displacement(p_m: &Vector3<f64>, m: &Vector6<f64>) -> Vector3<f64> {
    motion_jacobian(p_m) * m
}

/// Jacobian of `motion_displacement` with respect to the six motion errors: [I | −[p]×].
pub fn motion_jacobian(p_m: &Vector3<f64>) -> SMatrix<f64, 3, 6> {
    let mut j = SMatrix::<f64, 3, 6>::zeros();
    j.fixed_view_mut::<3, 3>(0, 0)
        .copy_from(&Matrix3::identity());
    j.fixed_view_mut::<3, 3>(0, 3).copy_from(&(-skew(p_m)));
    j
}

/// Sphere centre at θ with location and motion errors: the located centre displaced by the
/// motion errors at the nominal position Rz q (the product of two small errors is dropped).
pub fn predicted_centre(
    theta_rad: f64,
    q_m: &Vector3<f64>,
    loc: &[f64; 4],
    motion: &Vector6<f64>,
) -> Vector3<f64> {
    located_centre(theta_rad, q_m, loc) + motion_displacement(&(rz(theta_rad) * q_m), motion)
}

/// Harmonic basis of order k in θ: [1, cos θ, sin θ, …, cos kθ, sin kθ] (2k + 1 terms).
pub fn harmonic_basis(theta_rad: f64, order: usize) -> Vec<f64> {
    let mut b = Vec::with_capacity(2 * order + 1);
    b.push(1.0);
    for k in 1..=order {
        let (s, c) = (k as f64 * theta_rad).sin_cos();
        b.push(c);
        b.push(s);
    }
    b
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn location_jacobian_matches_finite_differences() {
        let q = Vector3::new(0.071, 0.002, 0.179);
        let loc = [2e-5, -1.5e-5, 3e-5, -2e-5];
        let theta = 0.7;
        let (dq, dl) = located_centre_jacobian(theta, &q, &loc);
        let h = 1e-7;
        for k in 0..3 {
            let mut qp = q;
            qp[k] += h;
            let num = (located_centre(theta, &qp, &loc) - located_centre(theta, &q, &loc)) / h;
            assert!((num - dq.column(k)).amax() < 1e-8, "q {k}");
        }
        for k in 0..4 {
            let mut lp = loc;
            lp[k] += h;
            let num = (located_centre(theta, &q, &lp) - located_centre(theta, &q, &loc)) / h;
            assert!((num - dl.column(k)).amax() < 1e-8, "loc {k}");
        }
        assert!((located_centre(0.0, &q, &loc) - q).amax() < 1e-18);
    }

    /// The first-order model against an exact rotation about the tilted, shifted axis.
    #[test]
    fn location_model_is_first_order_exact() {
        let q = Vector3::new(0.071, 0.0, 0.179);
        let loc = [2e-5, -1.5e-5, 3e-5, -2e-5];
        let a = Vector3::new(loc[0], loc[1], 0.0);
        let tilt = nalgebra::Rotation3::new(Vector3::new(loc[2], loc[3], 0.0));
        for theta in [0.3, 1.9, 4.0] {
            let exact = a + tilt
                * nalgebra::Rotation3::new(Vector3::z() * theta)
                * tilt.inverse()
                * (q - a);
            let exact0 = a + (q - a); // θ = 0 gives q
            let model = located_centre(theta, &q, &loc);
            assert!((exact - model).amax() < 1e-8, "{theta}");
            assert!((exact0 - q).amax() < 1e-15);
        }
    }

    #[test]
    fn sphere_residual_gradient() {
        let c = Vector3::new(0.01, 0.02, 0.03);
        let p = c + Vector3::new(0.003, -0.004, 0.012);
        let (r, g) = sphere_point_residual(&p, &c, 0.0125);
        assert!((r - 0.0005).abs() < 1e-15);
        assert!((g + Vector3::new(0.003, -0.004, 0.012) / 0.013).amax() < 1e-12);
    }
}
