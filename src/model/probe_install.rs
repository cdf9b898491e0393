//! Installation model of a 1-D laser displacement probe on a 5-axis CMM (X, Y, Z + rotary A, B):
//! the 11 installation parameters, the probed surface point and its sphere residual with Jacobians.
//!
//! Frames (Fei et al. 2011, eqs 1–7, our reading of the garbled text):
//! `q0 = Q10 + R21(B+δB) · (Q32 + R32(A) · (Q43 + t·R43))`, with `Q10` the scale readings
//! (x, y, z), `R21` a rotation about Z by the B angle plus the offset δB of the A-axis motor
//! centreline, `Q32 = (0, y32, 0)` the offset of the A frame along Y2, `R32` a rotation about
//! X by A, `Q43` the probe zero point and `R43 = (l, m, n)` the beam direction in the A frame,
//! and `t` the probe reading. Rotations are right-handed (positive angle counter-clockwise
//! seen from the positive axis).

use nalgebra::{Matrix3, RowSVector, SVector, Vector3};
use serde::Serialize;

/// Number of installation parameters in the paper's individual string
/// `X = (δB, y32, l, m, n, x43, y43, z43, x0, y0, z0)`.
pub const N_PARAMS: usize = 11;

/// Parameter names in vector order, with units.
pub const PARAM_NAMES: [&str; N_PARAMS] = [
    "b_offset_rad",
    "y_offset_m",
    "beam_l",
    "beam_m",
    "beam_n",
    "zero_point_x_m",
    "zero_point_y_m",
    "zero_point_z_m",
    "sphere_centre_x_m",
    "sphere_centre_y_m",
    "sphere_centre_z_m",
];

/// The 11 installation unknowns.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct InstallParams {
    /// δB: angle of the A-axis motor centreline off the design zero, about Z.
    pub b_offset_rad: f64,
    /// y32: offset of the A-axis frame origin from the B-axis frame origin along Y2.
    pub y_offset_m: f64,
    /// (l, m, n): beam direction in the A-axis frame; unit norm is a constraint, not built in.
    pub beam_dir: [f64; 3],
    /// (x43, y43, z43): probe zero point (reading t = 0) in the A-axis frame.
    pub zero_point_m: [f64; 3],
    /// (x0, y0, z0): reference sphere centre in the machine base frame.
    pub sphere_centre_m: [f64; 3],
}

impl InstallParams {
    pub fn to_vector(&self) -> SVector<f64, N_PARAMS> {
        let mut x = SVector::<f64, N_PARAMS>::zeros();
        x[0] = self.b_offset_rad;
        x[1] = self.y_offset_m;
        for k in 0..3 {
            x[2 + k] = self.beam_dir[k];
            x[5 + k] = self.zero_point_m[k];
            x[8 + k] = self.sphere_centre_m[k];
        }
        x
    }

    pub fn from_vector(x: &SVector<f64, N_PARAMS>) -> Self {
        Self {
            b_offset_rad: x[0],
            y_offset_m: x[1],
            beam_dir: [x[2], x[3], x[4]],
            zero_point_m: [x[5], x[6], x[7]],
            sphere_centre_m: [x[8], x[9], x[10]],
        }
    }

    pub fn beam(&self) -> Vector3<f64> {
        Vector3::from(self.beam_dir)
    }

    pub fn zero_point(&self) -> Vector3<f64> {
        Vector3::from(self.zero_point_m)
    }

    pub fn sphere_centre(&self) -> Vector3<f64> {
        Vector3::from(self.sphere_centre_m)
    }

    /// h = l² + m² + n² − 1, the equality constraint of the paper's eq. (10).
    pub fn unit_norm_violation(&self) -> f64 {
        self.beam().norm_squared() - 1.0
    }
}

/// One probe reading: posture, scale readings and the distance along the beam.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ProbeObservation {
    pub a_rad: f64,
    pub b_rad: f64,
    /// Q10: X, Y, Z scale readings.
    pub machine_m: [f64; 3],
    /// t: probe reading, distance from the zero point along the beam.
    pub reading_m: f64,
    /// Standard uncertainty of the reading (the probe noise).
    pub sigma_m: f64,
}

/// Rotation about Z by `angle_rad` (R21 of the paper).
pub fn rot_z(angle_rad: f64) -> Matrix3<f64> {
    let (s, c) = angle_rad.sin_cos();
    Matrix3::new(c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0)
}

/// d/dθ of `rot_z(θ)`.
fn rot_z_derivative(angle_rad: f64) -> Matrix3<f64> {
    let (s, c) = angle_rad.sin_cos();
    Matrix3::new(-s, -c, 0.0, c, -s, 0.0, 0.0, 0.0, 0.0)
}

/// Rotation about X by `angle_rad` (R32 of the paper).
pub fn rot_x(angle_rad: f64) -> Matrix3<f64> {
    let (s, c) = angle_rad.sin_cos();
    Matrix3::new(1.0, 0.0, 0.0, 0.0, c, -s, 0.0, s, c)
}

/// Offset from the scale readings to the probed point: R21 (Q32 + R32 (Q43 + t·R43)).
/// At a fixed posture and reading it is the constant (Δx, Δy, Δz) of the paper's eq. (8).
pub fn probe_offset(p: &InstallParams, a_rad: f64, b_rad: f64, reading_m: f64) -> Vector3<f64> {
    let w = p.zero_point() + reading_m * p.beam();
    let v = Vector3::new(0.0, p.y_offset_m, 0.0) + rot_x(a_rad) * w;
    rot_z(b_rad + p.b_offset_rad) * v
}

/// The probed point q0 in the machine base frame (eq. 7).
pub fn surface_point(p: &InstallParams, obs: &ProbeObservation) -> Vector3<f64> {
    Vector3::from(obs.machine_m) + probe_offset(p, obs.a_rad, obs.b_rad, obs.reading_m)
}

/// q0 and ∂q0/∂X (3 x 11, parameter order of [`PARAM_NAMES`]; the sphere centre columns are 0).
pub fn surface_point_jacobian(
    p: &InstallParams,
    obs: &ProbeObservation,
) -> (Vector3<f64>, nalgebra::SMatrix<f64, 3, N_PARAMS>) {
    let rz = rot_z(obs.b_rad + p.b_offset_rad);
    let rx = rot_x(obs.a_rad);
    let w = p.zero_point() + obs.reading_m * p.beam();
    let v = Vector3::new(0.0, p.y_offset_m, 0.0) + rx * w;
    let q = Vector3::from(obs.machine_m) + rz * v;
    let rzx = rz * rx;
    let mut j = nalgebra::SMatrix::<f64, 3, N_PARAMS>::zeros();
    j.set_column(0, &(rot_z_derivative(obs.b_rad + p.b_offset_rad) * v));
    j.set_column(1, &rz.column(1).into_owned());
    for k in 0..3 {
        j.set_column(2 + k, &(obs.reading_m * rzx.column(k)));
        j.set_column(5 + k, &rzx.column(k).into_owned());
    }
    (q, j)
}

/// Sphere residual |q0 − S0| − r: zero when the probed point lies on the reference sphere.
pub fn sphere_residual(p: &InstallParams, obs: &ProbeObservation, radius_m: f64) -> f64 {
    (surface_point(p, obs) - p.sphere_centre()).norm() - radius_m
}

/// Residual and its gradient with respect to the 11 parameters.
pub fn sphere_residual_jacobian(
    p: &InstallParams,
    obs: &ProbeObservation,
    radius_m: f64,
) -> (f64, RowSVector<f64, N_PARAMS>) {
    let (q, jq) = surface_point_jacobian(p, obs);
    let diff = q - p.sphere_centre();
    let dist = diff.norm();
    // Direction from the centre to the point; a point at the centre has no defined gradient,
    // so fall back to zero rather than NaN (such a point is a gross outlier anyway).
    let e = if dist > 0.0 {
        diff / dist
    } else {
        Vector3::zeros()
    };
    let mut g = e.transpose() * jq;
    for k in 0..3 {
        g[8 + k] = -e[k];
    }
    (dist - radius_m, g)
}

/// Beam direction in the machine base frame at a posture: R21 R32 R43.
pub fn beam_in_base(p: &InstallParams, a_rad: f64, b_rad: f64) -> Vector3<f64> {
    rot_z(b_rad + p.b_offset_rad) * rot_x(a_rad) * p.beam()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn params() -> InstallParams {
        InstallParams {
            b_offset_rad: 0.012,
            y_offset_m: 0.8e-3,
            beam_dir: [0.004, -0.003, -0.99998750],
            zero_point_m: [1.1e-3, -0.7e-3, -80.2e-3],
            sphere_centre_m: [0.1, 0.05, -0.15],
        }
    }

    fn observations() -> Vec<ProbeObservation> {
        let mut out = Vec::new();
        for (i, &(a, b)) in [(0.0, 0.0), (1.5, 0.2), (-1.2, 0.7), (1.57, 1.57)]
            .iter()
            .enumerate()
        {
            out.push(ProbeObservation {
                a_rad: a,
                b_rad: b,
                machine_m: [0.1 + 0.01 * i as f64, 0.05, -0.06 - 0.003 * i as f64],
                reading_m: 1.3e-3 - 0.9e-3 * i as f64,
                sigma_m: 1e-6,
            });
        }
        out
    }

    #[test]
    fn jacobian_matches_finite_differences() {
        let p = params();
        let x = p.to_vector();
        let radius = 6e-3;
        for obs in observations() {
            let (r, g) = sphere_residual_jacobian(&p, &obs, radius);
            assert!((r - sphere_residual(&p, &obs, radius)).abs() < 1e-15);
            let (_, jq) = surface_point_jacobian(&p, &obs);
            for k in 0..N_PARAMS {
                // Central differences; step scaled to each parameter's size.
                let h = 1e-7 * x[k].abs().max(1e-3);
                let mut xp = x;
                let mut xm = x;
                xp[k] += h;
                xm[k] -= h;
                let (pp, pm) = (
                    InstallParams::from_vector(&xp),
                    InstallParams::from_vector(&xm),
                );
                let fd = (sphere_residual(&pp, &obs, radius) - sphere_residual(&pm, &obs, radius))
                    / (2.0 * h);
                assert!(
                    (fd - g[k]).abs() < 1e-7 * (1.0 + g[k].abs()),
                    "residual param {}: fd {fd} analytic {}",
                    PARAM_NAMES[k],
                    g[k]
                );
                let fdq = (surface_point(&pp, &obs) - surface_point(&pm, &obs)) / (2.0 * h);
                assert!((fdq - jq.column(k)).norm() < 1e-7 * (1.0 + fdq.norm()));
            }
        }
    }

    #[test]
    fn vector_round_trip_and_constraint() {
        let p = params();
        assert_eq!(InstallParams::from_vector(&p.to_vector()), p);
        assert!(p.unit_norm_violation().abs() < 1e-7);
    }

    #[test]
    fn offset_at_zero_posture_is_zero_point_plus_y_offset() {
        let mut p = params();
        p.b_offset_rad = 0.0;
        let o = probe_offset(&p, 0.0, 0.0, 0.0);
        let expect = p.zero_point() + Vector3::new(0.0, p.y_offset_m, 0.0);
        assert!((o - expect).norm() < 1e-15);
    }
}
