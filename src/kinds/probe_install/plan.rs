//! Plan of kind `probe_install`: for every posture (A, B), the machine positions that put the
//! nominal beam on points of the sphere's cap facing the probe, with spread nominal readings.

use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

use crate::kinds::probe_install::config::ProbeInstallConfig;
use crate::model::probe_install::{beam_in_base, probe_offset};
use crate::solve::probe_install::tangent_basis;

/// Axis names of the 5-axis CMM, in the order of [`ProbePoint::axes`]; `a`, `b` in radians.
pub const CMM_AXES: [&str; 5] = ["x", "y", "z", "a", "b"];

#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct ProbePoint {
    pub posture: usize,
    /// Index of the point within its posture.
    pub point: usize,
    /// Commanded x, y, z (metres), a, b (radians).
    pub axes: [f64; 5],
    /// The reading the nominal installation predicts, metres.
    pub nominal_reading_m: f64,
}

#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct ProbeInstallPlan {
    /// (A, B), radians.
    pub postures_rad: Vec<[f64; 2]>,
    /// Every point, posture by posture.
    pub points: Vec<ProbePoint>,
    pub readings_per_point: usize,
    /// Pause between two machine state polls, seconds: 0 for the simulated CMM (its queries
    /// advance virtual time), `devices.machine.poll_interval_s` for real and emulated ones.
    pub poll_interval_s: f64,
}

impl ProbeInstallPlan {
    pub fn from_config(config: &ProbeInstallConfig) -> Self {
        let plan = &config.plan;
        let nominal = plan.nominal.params();
        let centre = nominal.sphere_centre();
        let mut rng = ChaCha8Rng::seed_from_u64(plan.seed);
        let mut points = Vec::new();
        for (posture, &[a, b]) in plan.postures_rad.iter().enumerate() {
            let w = beam_in_base(&nominal, a, b).normalize();
            let (e1, e2) = tangent_basis(&w);
            let cos_min = plan.cap_half_angle_rad.cos();
            for point in 0..plan.points_per_posture {
                // Uniform on the cap facing the probe (normal within the half-angle of −w).
                let ct = 1.0 - rng.random::<f64>() * (1.0 - cos_min);
                let st = (1.0 - ct * ct).max(0.0).sqrt();
                let phi = rng.random::<f64>() * std::f64::consts::TAU;
                let normal: Vector3<f64> = -ct * w + st * (phi.cos() * e1 + phi.sin() * e2);
                let surface = centre + plan.sphere_radius_m * normal;
                let reading = (2.0 * rng.random::<f64>() - 1.0) * plan.reading_half_range_m;
                let xyz = surface - probe_offset(&nominal, a, b, reading);
                points.push(ProbePoint {
                    posture,
                    point,
                    axes: [xyz.x, xyz.y, xyz.z, a, b],
                    nominal_reading_m: reading,
                });
            }
        }
        Self {
            postures_rad: plan.postures_rad.clone(),
            points,
            readings_per_point: plan.readings_per_point,
            poll_interval_s: if config.all_sim() {
                0.0
            } else {
                config.devices.machine.poll_interval_s
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::probe_install::{surface_point, ProbeObservation};

    #[test]
    fn nominal_beam_hits_the_nominal_sphere_at_every_point() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/config/probe-install.toml");
        let config = ProbeInstallConfig::load(std::path::Path::new(path)).expect("example");
        let plan = ProbeInstallPlan::from_config(&config);
        assert_eq!(plan.points.len(), 4 * config.plan.points_per_posture);
        let nominal = config.plan.nominal.params();
        for p in &plan.points {
            let q = surface_point(
                &nominal,
                &ProbeObservation {
                    a_rad: p.axes[3],
                    b_rad: p.axes[4],
                    machine_m: [p.axes[0], p.axes[1], p.axes[2]],
                    reading_m: p.nominal_reading_m,
                    sigma_m: 1e-6,
                },
            );
            let r = (q - nominal.sphere_centre()).norm();
            assert!((r - config.plan.sphere_radius_m).abs() < 1e-12, "{r}");
        }
    }
}
