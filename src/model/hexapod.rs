//! Six-leg parallel machine with universal joints: leg lengths and relative leg-length changes
//! predicted from the hinge coordinates at measured platform poses, with Jacobians.

use nalgebra::{Rotation3, SMatrix, Vector3};

pub const LEGS: usize = 6;

/// Hinge coordinates: fixed-platform hinges B_i in the fixed frame and moving-platform hinges
/// P_i in the platform frame (m). As a parameter vector (36): B_0 … B_5 (x, y, z each), then
/// P_0 … P_5; per leg, the 6 parameters [B_i, P_i].
#[derive(Debug, Clone, PartialEq)]
pub struct HexapodGeometry {
    pub base_m: [Vector3<f64>; LEGS],
    pub platform_m: [Vector3<f64>; LEGS],
}

/// A measured platform pose: x_fixed = rotation · x_platform + translation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    pub rotation: Rotation3<f64>,
    pub translation_m: Vector3<f64>,
}

impl HexapodGeometry {
    /// Parameters of leg i: [B_i, P_i].
    pub fn leg(&self, i: usize) -> SMatrix<f64, 6, 1> {
        let mut x = SMatrix::<f64, 6, 1>::zeros();
        x.fixed_rows_mut::<3>(0).copy_from(&self.base_m[i]);
        x.fixed_rows_mut::<3>(3).copy_from(&self.platform_m[i]);
        x
    }

    pub fn set_leg(&mut self, i: usize, x: &SMatrix<f64, 6, 1>) {
        self.base_m[i] = x.fixed_rows::<3>(0).into_owned();
        self.platform_m[i] = x.fixed_rows::<3>(3).into_owned();
    }

    /// The 36-vector: B_0..B_5 then P_0..P_5.
    pub fn to_vec(&self) -> Vec<f64> {
        self.base_m
            .iter()
            .chain(self.platform_m.iter())
            .flat_map(|v| v.iter().copied())
            .collect()
    }

    pub fn from_slice(v: &[f64]) -> HexapodGeometry {
        let p = |k: usize| Vector3::new(v[3 * k], v[3 * k + 1], v[3 * k + 2]);
        HexapodGeometry {
            base_m: std::array::from_fn(p),
            platform_m: std::array::from_fn(|i| p(LEGS + i)),
        }
    }
}

/// Leg length |R P + t − B| for the leg parameters x = [B, P], and its gradient with respect to
/// x: ∂L/∂B = −u, ∂L/∂P = Rᵀ u, u the unit leg direction.
pub fn leg_length(x: &SMatrix<f64, 6, 1>, pose: &Pose) -> (f64, SMatrix<f64, 1, 6>) {
    let b = x.fixed_rows::<3>(0);
    let p = x.fixed_rows::<3>(3).into_owned();
    let d = pose.rotation * p + pose.translation_m - b;
    let l = d.norm();
    let u = d / l;
    let mut g = SMatrix::<f64, 1, 6>::zeros();
    g.fixed_columns_mut::<3>(0).copy_from(&(-u).transpose());
    g.fixed_columns_mut::<3>(3)
        .copy_from(&(pose.rotation.inverse() * u).transpose());
    (l, g)
}

/// Length change of a leg from the reference pose to `pose` — what a relative (incremental)
/// encoder reads — and its gradient with respect to [B, P].
pub fn relative_length(
    x: &SMatrix<f64, 6, 1>,
    reference: &Pose,
    pose: &Pose,
) -> (f64, SMatrix<f64, 1, 6>) {
    let (l0, g0) = leg_length(x, reference);
    let (l, g) = leg_length(x, pose);
    (l - l0, g - g0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gradient_matches_finite_differences() {
        let x = SMatrix::<f64, 6, 1>::from_column_slice(&[0.4, 0.05, 0.0, 0.19, -0.06, 0.01]);
        let reference = Pose {
            rotation: Rotation3::identity(),
            translation_m: Vector3::new(0.0, 0.0, -0.6),
        };
        let pose = Pose {
            rotation: Rotation3::new(Vector3::new(0.1, -0.05, 0.2)),
            translation_m: Vector3::new(0.03, -0.02, -0.55),
        };
        let (_, g) = relative_length(&x, &reference, &pose);
        let h = 1e-7;
        for k in 0..6 {
            let mut xp = x;
            xp[k] += h;
            let num = (relative_length(&xp, &reference, &pose).0
                - relative_length(&x, &reference, &pose).0)
                / h;
            assert!((num - g[k]).abs() < 1e-6, "{k}: {num} vs {}", g[k]);
        }
        let geo = HexapodGeometry {
            base_m: std::array::from_fn(|i| Vector3::new(i as f64, 1.0, 2.0)),
            platform_m: std::array::from_fn(|i| Vector3::new(3.0, i as f64, 4.0)),
        };
        assert_eq!(HexapodGeometry::from_slice(&geo.to_vec()), geo);
    }
}
