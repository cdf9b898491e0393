//! Six-leg parallel machine with universal joints: leg lengths and relative leg-length changes
//! predicted from the hinge coordinates at measured platform poses, with Jacobians, and the
//! forward kinematics (the pose that given leg lengths reach).

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

/// ∂L_i/∂[t, w] (6 legs × 6): t the translation, w the rotation vector (the quantities the
/// pose sensor reports and its noise perturbs). Rotation part by central differences.
pub fn pose_jacobian(geometry: &HexapodGeometry, pose: &Pose) -> SMatrix<f64, LEGS, 6> {
    let w = pose.rotation.scaled_axis();
    let h = 1e-6;
    let mut a = SMatrix::<f64, LEGS, 6>::zeros();
    for i in 0..LEGS {
        let x = geometry.leg(i);
        let d = pose.rotation * geometry.platform_m[i] + pose.translation_m - geometry.base_m[i];
        let u = d / d.norm();
        for c in 0..3 {
            a[(i, c)] = u[c];
            let mut e = Vector3::zeros();
            e[c] = h;
            let at = |w: Vector3<f64>| {
                leg_length(
                    &x,
                    &Pose {
                        rotation: Rotation3::new(w),
                        translation_m: pose.translation_m,
                    },
                )
                .0
            };
            a[(i, 3 + c)] = (at(w + e) - at(w - e)) / (2.0 * h);
        }
    }
    a
}

/// Forward kinematics: the pose at which the legs of `geometry` have `lengths_m`, by Newton on
/// the 6 leg-length equations in [t, w] from `start` (a nearby pose, e.g. the commanded one).
/// None if it does not converge to 1 pm within 50 iterations.
pub fn forward_kinematics(
    geometry: &HexapodGeometry,
    lengths_m: &[f64; LEGS],
    start: &Pose,
) -> Option<Pose> {
    let mut t = start.translation_m;
    let mut w = start.rotation.scaled_axis();
    for _ in 0..50 {
        let pose = Pose {
            rotation: Rotation3::new(w),
            translation_m: t,
        };
        let f = SMatrix::<f64, LEGS, 1>::from_fn(|i, _| {
            leg_length(&geometry.leg(i), &pose).0 - lengths_m[i]
        });
        if f.amax() < 1e-12 {
            return Some(pose);
        }
        let step = pose_jacobian(geometry, &pose).lu().solve(&f)?;
        t -= step.fixed_rows::<3>(0);
        w -= step.fixed_rows::<3>(3);
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Legs set to the design lengths at a commanded pose, a geometry off the design by
    /// millimetres: the pose found reproduces the lengths and differs from the commanded one.
    #[test]
    fn forward_kinematics_closes_the_leg_lengths() {
        let design = HexapodGeometry {
            base_m: std::array::from_fn(|i| {
                let a = (i as f64 * 60.0 + 10.0).to_radians();
                Vector3::new(0.45 * a.cos(), 0.45 * a.sin(), 0.0)
            }),
            platform_m: std::array::from_fn(|i| {
                let a = (i as f64 * 60.0 + 40.0).to_radians();
                Vector3::new(0.2 * a.cos(), 0.2 * a.sin(), 0.0)
            }),
        };
        let mut v = design.to_vec();
        for (k, x) in v.iter_mut().enumerate() {
            *x += 2e-3 * ((k as f64 * 1.7).sin());
        }
        let truth = HexapodGeometry::from_slice(&v);
        let commanded = Pose {
            rotation: Rotation3::new(Vector3::new(0.1, -0.05, 0.15)),
            translation_m: Vector3::new(0.03, -0.02, -0.68),
        };
        let lengths: [f64; LEGS] =
            std::array::from_fn(|i| leg_length(&design.leg(i), &commanded).0);
        let reached = forward_kinematics(&truth, &lengths, &commanded).expect("converges");
        for (i, l) in lengths.iter().enumerate() {
            assert!((leg_length(&truth.leg(i), &reached).0 - l).abs() < 1e-11);
        }
        let moved = (reached.translation_m - commanded.translation_m).norm();
        assert!(moved > 1e-4 && moved < 0.1, "{moved}");
    }

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
