//! The `rotary_sphere` plan expanded: heights × commanded angles × probed points, with each
//! point's nominal surface point and probing direction (frame: nominal table axis = z).

use nalgebra::Vector3;

use crate::kinds::rotary_sphere::config::{HeightRole, SpherePlanConfig};
use crate::model::rotary_sphere::rz;
use crate::solve::rotary_sphere::simulation::probe_directions;

#[derive(Debug, Clone, PartialEq)]
pub struct SphereHeight {
    /// Nominal sphere centre at commanded angle 0, metres.
    pub sphere_m: Vector3<f64>,
    pub role: HeightRole,
}

#[derive(Debug, Clone, PartialEq)]
pub struct SpherePlan {
    pub table: String,
    pub radius_m: f64,
    pub standoff_m: f64,
    pub readings_per_point: usize,
    pub heights: Vec<SphereHeight>,
    pub angles_rad: Vec<f64>,
    /// Outward unit normals of the probed points, fixed in the reference frame (the arm
    /// probes the top pole and the four equator poles as published, more on rings).
    pub directions: Vec<Vector3<f64>>,
    pub in_position_timeout_s: f64,
    pub poll_interval_s: f64,
}

impl SpherePlan {
    pub fn from_config(plan: &SpherePlanConfig) -> SpherePlan {
        SpherePlan {
            table: plan.table.clone(),
            radius_m: plan.sphere_radius_m,
            standoff_m: plan.standoff_m,
            readings_per_point: plan.readings_per_point,
            heights: plan
                .heights
                .iter()
                .map(|h| SphereHeight {
                    sphere_m: Vector3::from(h.sphere_m),
                    role: h.role,
                })
                .collect(),
            angles_rad: plan.angles_rad(),
            directions: probe_directions(plan.points),
            in_position_timeout_s: plan.in_position_timeout_s,
            poll_interval_s: plan.poll_interval_s,
        }
    }

    /// Nominal centre of the sphere at height `h` with the table at commanded `angle_rad`.
    pub fn nominal_centre(&self, h: usize, angle_rad: f64) -> Vector3<f64> {
        rz(angle_rad) * self.heights[h].sphere_m
    }

    /// Nominal surface point of point `k` at height `h`, angle `a`, and its outward normal.
    pub fn nominal_point(&self, h: usize, a: usize, k: usize) -> (Vector3<f64>, Vector3<f64>) {
        let d = self.directions[k];
        (
            self.nominal_centre(h, self.angles_rad[a]) + d * self.radius_m,
            d,
        )
    }

    /// Where the probe starts its approach to a nominal surface point along −`direction`.
    pub fn approach_start(
        &self,
        nominal_m: &Vector3<f64>,
        direction: &Vector3<f64>,
    ) -> Vector3<f64> {
        nominal_m + direction * self.standoff_m
    }

    /// The probed point a reading stands for: the nominal point moved by the reading along
    /// the approach (a positive reading: the surface lay further in).
    pub fn measured_point(
        nominal_m: &Vector3<f64>,
        direction: &Vector3<f64>,
        value_m: f64,
    ) -> Vector3<f64> {
        nominal_m - direction * value_m
    }

    /// Probed points of the whole plan (for progress).
    pub fn total_points(&self) -> u64 {
        (self.heights.len() * self.angles_rad.len() * self.directions.len()) as u64
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinds::rotary_sphere::config::RotarySphereConfig;

    #[test]
    fn published_plan_expands() {
        let path =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rotary-sphere.toml");
        let c = RotarySphereConfig::load(&path).expect("config");
        let plan = SpherePlan::from_config(&c.plan);
        assert_eq!(plan.total_points(), 3 * 36 * 5);
        // At 90° the sphere of the first height stands on +y, its top pole above it.
        let (p, d) = plan.nominal_point(0, 9, 0);
        assert!((p - Vector3::new(0.0, 0.071, 0.179 + 0.0127)).amax() < 1e-12);
        assert_eq!(d, Vector3::z());
        let m = SpherePlan::measured_point(&p, &d, 1e-5);
        assert!((m.z - (0.179 + 0.0127 - 1e-5)).abs() < 1e-15);
    }
}
