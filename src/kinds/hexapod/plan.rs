//! Plan of kind `hexapod`: the platform poses to visit, home (the reference of every leg-length
//! change) first, then the random (seeded) and listed poses.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

use crate::kinds::hexapod::config::HexapodConfig;

/// Names of a pose's coordinates in `pose_begin` events: translation (m), rotation vector (rad).
pub const POSE_AXES: [&str; 6] = ["x", "y", "z", "rx", "ry", "rz"];

#[derive(Debug, Clone, Copy, Serialize, PartialEq)]
pub struct PlanPose {
    pub translation_m: [f64; 3],
    pub rotation_vector_rad: [f64; 3],
}

impl PlanPose {
    pub fn axes(&self) -> [f64; 6] {
        let [x, y, z] = self.translation_m;
        let [rx, ry, rz] = self.rotation_vector_rad;
        [x, y, z, rx, ry, rz]
    }
}

#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct HexapodPlan {
    /// Pose 0 is home.
    pub poses: Vec<PlanPose>,
    pub readings_per_pose: usize,
    pub reference_readings: usize,
}

impl HexapodPlan {
    pub fn from_config(config: &HexapodConfig) -> Self {
        let p = &config.plan;
        let home = p.home_translation_m;
        let mut poses = vec![PlanPose {
            translation_m: home,
            rotation_vector_rad: [0.0; 3],
        }];
        if let Some(r) = &p.poses {
            let mut rng = ChaCha8Rng::seed_from_u64(r.seed);
            let mut u = |s: f64| s * (2.0 * rng.random::<f64>() - 1.0);
            for _ in 0..r.count {
                let h = r.translation_half_range_m;
                let translation_m = [home[0] + u(h[0]), home[1] + u(h[1]), home[2] + u(h[2])];
                let t = r.tilt_half_range_rad;
                poses.push(PlanPose {
                    translation_m,
                    rotation_vector_rad: [u(t), u(t), u(t)],
                });
            }
        }
        poses.extend(p.pose_list.iter().map(|q| PlanPose {
            translation_m: q.translation_m,
            rotation_vector_rad: q.rotation_vector_rad,
        }));
        Self {
            poses,
            readings_per_pose: p.readings_per_pose,
            reference_readings: p.reference_readings,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn home_first_then_poses_within_their_ranges() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/config/hexapod.toml");
        let c = HexapodConfig::load(std::path::Path::new(path)).expect("example");
        let plan = HexapodPlan::from_config(&c);
        assert_eq!(plan.poses.len(), 30);
        assert_eq!(plan.poses[0].rotation_vector_rad, [0.0; 3]);
        for q in &plan.poses[1..] {
            assert!((q.translation_m[2] + 0.7).abs() <= 0.04);
            assert!(q.rotation_vector_rad.iter().all(|r| r.abs() <= 0.1746));
        }
        assert_eq!(plan, HexapodPlan::from_config(&c), "deterministic");
    }
}
