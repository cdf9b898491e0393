//! The simulated world of plan kind `rotary_sphere`: a seeded true axis (location and harmonic
//! motion errors), the sphere truly placed at each height, the table's motion in virtual time,
//! the arm that brings the probe to a point, and the probe reading the true surface with noise.

use std::sync::{Arc, Mutex, MutexGuard};

use async_trait::async_trait;
use geocal_drivers::{DeviceError, Probe, ProbeReading, RotaryState, RotaryTable};
use nalgebra::Vector3;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use serde::Serialize;

use crate::clock::VirtualClock;
use crate::kinds::rotary_sphere::config::{RotarySphereConfig, SphereSimConfig};
use crate::kinds::rotary_sphere::plan::SpherePlan;
use crate::kinds::rotary_sphere::sequence::ProbeArm;
use crate::model::rotary_sphere::{LOCATION_NAMES, MOTION_NAMES};
use crate::solve::rotary_sphere::simulation::TrueAxis;

/// How much virtual time one table state query takes (the sequencer polls until in position).
const STATE_POLL_S: f64 = 0.1;
/// How much virtual time one probe reading takes (readings are logged after their point's
/// `probe_point_begin`, never at the same instant).
const READ_S: f64 = 0.05;

pub type SharedSphereWorld = Arc<Mutex<SphereWorld>>;

pub struct SphereWorld {
    clock: Arc<VirtualClock>,
    now_s: f64,
    sim: SphereSimConfig,
    pub truth: TrueAxis,
    /// True sphere centre at θ = 0 under an ideal axis, per height, metres.
    pub positions_m: Vec<Vector3<f64>>,
    radius_m: f64,
    standoff_m: f64,
    noise: Option<Normal<f64>>,
    rng: ChaCha8Rng,
    commanded_rad: f64,
    in_position_at_s: f64,
    height: Option<usize>,
    /// The probe's approach: start point and outward normal (it travels along −normal).
    approach: Option<(Vector3<f64>, Vector3<f64>)>,
}

impl SphereWorld {
    pub fn new(
        config: &RotarySphereConfig,
        plan: &SpherePlan,
        clock: Arc<VirtualClock>,
    ) -> Result<SphereWorld, String> {
        let sim = config
            .sim
            .clone()
            .ok_or("the simulated world needs the [sim] section")?;
        let mut rng = ChaCha8Rng::seed_from_u64(sim.seed ^ 0x5350_4845_5245);
        let truth = TrueAxis::realistic(&mut rng, sim.harmonics);
        let placement = Normal::new(0.0, sim.sphere_placement_m)
            .map_err(|e| format!("sim.sphere_placement_m: {e}"))?;
        let positions_m = plan
            .heights
            .iter()
            .map(|h| h.sphere_m + Vector3::from_fn(|_, _| placement.sample(&mut rng)))
            .collect();
        let noise_m = config.devices.probe.noise_m;
        Ok(SphereWorld {
            clock,
            now_s: 0.0,
            sim,
            truth,
            positions_m,
            radius_m: plan.radius_m,
            standoff_m: plan.standoff_m,
            noise: Normal::new(0.0, noise_m).ok(),
            rng,
            commanded_rad: 0.0,
            in_position_at_s: 0.0,
            height: None,
            approach: None,
        })
    }

    pub fn now_s(&self) -> f64 {
        self.now_s
    }

    /// Continue after an interrupted run: the same true axis and spheres, time `t_s`, the
    /// probe noise drawn from `noise_seed`.
    pub fn resume_at(&mut self, t_s: f64, noise_seed: u64) {
        self.now_s = t_s;
        self.clock.advance_to(t_s);
        self.rng = ChaCha8Rng::seed_from_u64(noise_seed);
    }

    fn advance(&mut self, dt_s: f64) {
        self.now_s += dt_s.max(0.0);
        self.clock.advance_to(self.now_s);
    }

    /// The operator puts the sphere on its stand at height `h`.
    pub fn mount_sphere(&mut self, h: usize) -> bool {
        if h >= self.positions_m.len() {
            return false;
        }
        if self.height.is_some() {
            self.advance(self.sim.remount_s);
        }
        self.height = Some(h);
        self.approach = None;
        true
    }

    /// The arm brings the probe to `start_m`, pointing along −`normal`.
    pub fn approach(&mut self, start_m: Vector3<f64>, normal: Vector3<f64>) {
        self.advance(self.sim.point_time_s);
        self.approach = Some((start_m, normal.normalize()));
    }

    pub fn start_rotation(&mut self, commanded_rad: f64) {
        let move_s = (commanded_rad - self.commanded_rad).abs() / self.sim.speed_rad_s;
        let settle = if move_s > 0.0 { self.sim.settle_s } else { 0.0 };
        self.commanded_rad = commanded_rad;
        self.in_position_at_s = self.now_s + move_s + settle;
        self.approach = None;
    }

    /// The encoder angle once in position (the servo holds the encoder at the command; the
    /// positioning error ECC lies between encoder and table), else None. Each query takes time.
    pub fn table_state(&mut self) -> Option<f64> {
        self.advance(STATE_POLL_S);
        (self.now_s >= self.in_position_at_s).then_some(self.commanded_rad)
    }

    /// True centre of the mounted sphere at the table's commanded angle (drifting with
    /// `[sim] thermal_drift_m_per_s`).
    pub fn true_centre(&self) -> Option<Vector3<f64>> {
        let h = self.height?;
        Some(
            self.truth.centre(self.commanded_rad, &self.positions_m[h])
                + Vector3::from(self.sim.thermal_drift_m_per_s) * self.now_s,
        )
    }

    /// Travel beyond the standoff until the probe meets the true surface (no noise); None
    /// when the probe is not placed or its line misses the sphere.
    pub fn exact_probe_value(&self) -> Option<f64> {
        let (start, normal) = self.approach?;
        let c = self.true_centre()?;
        let u = -normal;
        let w = start - c;
        let b = u.dot(&w);
        let disc = b * b - w.norm_squared() + self.radius_m * self.radius_m;
        if disc < 0.0 {
            return None;
        }
        let mut t = -b - disc.sqrt();
        if !self.sim.sphere_form_m.is_empty() {
            // The form at the perfect sphere's hit point, in the sphere's own frame (its
            // second-order change ignored).
            let n = crate::model::rotary_sphere::rz(-self.commanded_rad) * (w + u * t).normalize();
            let y = crate::kinds::rotary_sphere::diagnosis::turning_form_harmonics(&n);
            let radius = self.radius_m
                + self
                    .sim
                    .sphere_form_m
                    .iter()
                    .zip(y)
                    .map(|(c, y)| c * y)
                    .sum::<f64>();
            let disc = b * b - w.norm_squared() + radius * radius;
            if disc < 0.0 {
                return None;
            }
            t = -b - disc.sqrt();
        }
        let (az, el) = (normal.y.atan2(normal.x), normal.z.clamp(-1.0, 1.0).asin());
        let lobing = self.sim.probe_lobing_m
            * ((3.0 * az).cos() * el.cos() + 0.6 * (el.cos().powi(2) - 0.5));
        let vibration =
            self.sim.probe_vibration_m * (std::f64::consts::TAU * self.now_s / 7.3).sin();
        Some(t - self.standoff_m + lobing + vibration)
    }

    /// One probe reading with the probe's noise.
    pub fn read_probe(&mut self) -> Option<f64> {
        self.advance(READ_S);
        let exact = self.exact_probe_value()?;
        let noise = self.noise.map_or(0.0, |n| n.sample(&mut self.rng));
        Some(exact + noise)
    }

    /// The truth `--truth` exports.
    pub fn export_truth(&self, plan: &SpherePlan) -> SphereTruth {
        let angles = plan.angles_rad.clone();
        SphereTruth {
            kind: crate::kinds::rotary_sphere::config::KIND,
            location_names: LOCATION_NAMES,
            location: self.truth.location,
            motion_names: MOTION_NAMES,
            motion_coefficients: self.truth.motion_coefficients.clone(),
            motion: angles
                .iter()
                .map(|&a| self.truth.motion(a).into())
                .collect(),
            sphere_positions_m: self.positions_m.iter().map(|p| (*p).into()).collect(),
            centres_m: self
                .positions_m
                .iter()
                .map(|q| {
                    angles
                        .iter()
                        .map(|&a| self.truth.centre(a, q).into())
                        .collect()
                })
                .collect(),
            angles_rad: angles,
            radius_m: self.radius_m,
        }
    }
}

/// The simulated truth of a `rotary_sphere` run (SI units).
#[derive(Debug, Clone, Serialize)]
pub struct SphereTruth {
    pub kind: &'static str,
    pub location_names: [&'static str; 4],
    /// EXOC, EYOC (m), EAOC, EBOC (rad).
    pub location: [f64; 4],
    pub motion_names: [&'static str; 6],
    /// Per error, harmonic coefficients [c0, a1, b1, …] (m or rad).
    pub motion_coefficients: [Vec<f64>; 6],
    pub angles_rad: Vec<f64>,
    /// Per commanded angle, the six motion errors.
    pub motion: Vec<[f64; 6]>,
    /// Per height, the true sphere centre at θ = 0 under an ideal axis.
    pub sphere_positions_m: Vec<[f64; 3]>,
    /// Per height and angle, the true sphere centre.
    pub centres_m: Vec<Vec<[f64; 3]>>,
    pub radius_m: f64,
}

fn lock<'a>(
    world: &'a SharedSphereWorld,
    device: &str,
) -> Result<MutexGuard<'a, SphereWorld>, DeviceError> {
    world.lock().map_err(|_| DeviceError::Disconnected {
        device: device.to_string(),
        message: "simulated world poisoned by an earlier panic".into(),
    })
}

/// The simulated rotary table carrying the sphere.
pub struct SimSphereTable {
    pub id: String,
    pub world: SharedSphereWorld,
}

#[async_trait]
impl RotaryTable for SimSphereTable {
    fn id(&self) -> &str {
        &self.id
    }
    async fn start_rotation(&mut self, commanded_rad: f64) -> Result<(), DeviceError> {
        if !commanded_rad.is_finite() {
            return Err(DeviceError::Rejected {
                device: self.id.clone(),
                message: format!("commanded angle {commanded_rad} rad is not finite"),
            });
        }
        lock(&self.world, &self.id)?.start_rotation(commanded_rad);
        Ok(())
    }
    async fn state(&mut self) -> Result<RotaryState, DeviceError> {
        Ok(match lock(&self.world, &self.id)?.table_state() {
            Some(encoder_rad) => RotaryState::InPosition { encoder_rad },
            None => RotaryState::Moving,
        })
    }
}

/// The simulated probe: the true surface along the arm's approach, plus its noise.
pub struct SimSphereProbe {
    pub id: String,
    pub world: SharedSphereWorld,
}

#[async_trait]
impl Probe for SimSphereProbe {
    fn id(&self) -> &str {
        &self.id
    }
    async fn read(&mut self) -> Result<ProbeReading, DeviceError> {
        let mut world = lock(&self.world, &self.id)?;
        let t_s = world.now_s();
        match world.read_probe() {
            Some(value_m) => Ok(ProbeReading { t_s, value_m }),
            None => Err(DeviceError::Rejected {
                device: self.id.clone(),
                message: "out of range: the probe's line misses the sphere".into(),
            }),
        }
    }
}

/// The simulated arm and operator: approaching takes `point_time_s`, remounting `remount_s`.
pub struct SimArm {
    pub world: SharedSphereWorld,
}

#[async_trait]
impl ProbeArm for SimArm {
    async fn mount_sphere(
        &mut self,
        height_index: usize,
        _nominal_m: [f64; 3],
    ) -> Result<(), DeviceError> {
        if lock(&self.world, "arm")?.mount_sphere(height_index) {
            Ok(())
        } else {
            Err(DeviceError::Rejected {
                device: "arm".into(),
                message: format!("no sphere height {height_index} in the simulated world"),
            })
        }
    }
    async fn approach(
        &mut self,
        start_m: [f64; 3],
        direction: [f64; 3],
    ) -> Result<(), DeviceError> {
        lock(&self.world, "arm")?.approach(start_m.into(), direction.into());
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinds::rotary_sphere::config::RotarySphereConfig;

    fn world(noise_m: f64) -> (SphereWorld, SpherePlan) {
        let path =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rotary-sphere.toml");
        let mut c = RotarySphereConfig::load(&path).expect("config");
        c.devices.probe.noise_m = noise_m;
        let plan = SpherePlan::from_config(&c.plan);
        let w = SphereWorld::new(&c, &plan, Arc::new(VirtualClock::new(0))).expect("world");
        (w, plan)
    }

    #[test]
    fn probed_points_lie_on_the_true_sphere() {
        let (mut w, plan) = world(0.0);
        assert!(w.mount_sphere(1));
        w.start_rotation(plan.angles_rad[7]);
        while w.table_state().is_none() {}
        let c = w.true_centre().expect("centre");
        for k in 0..plan.directions.len() {
            let (n, d) = plan.nominal_point(1, 7, k);
            w.approach(plan.approach_start(&n, &d), d);
            let v = w.read_probe().expect("reading");
            let p = SpherePlan::measured_point(&n, &d, v);
            assert!(((p - c).norm() - plan.radius_m).abs() < 1e-12);
            // Misplacement of ~0.5 mm: readings stay well inside the standoff.
            assert!(v.abs() < plan.standoff_m);
        }
    }

    #[test]
    fn noise_has_the_configured_sigma() {
        let (mut w, plan) = world(2.7e-5);
        w.mount_sphere(0);
        let (n, d) = plan.nominal_point(0, 0, 0);
        w.approach(plan.approach_start(&n, &d), d);
        let exact = w.exact_probe_value().expect("exact");
        let m = 4000;
        let var = (0..m)
            .map(|_| (w.read_probe().expect("reading") - exact).powi(2))
            .sum::<f64>()
            / m as f64;
        // The sample σ of 4000 normal draws has a relative spread of 1/√8000 ≈ 1.1 %: ±5 %
        // is 4.5 of those.
        assert!((var.sqrt() / 2.7e-5 - 1.0).abs() < 0.05, "{}", var.sqrt());
    }

    #[test]
    fn table_takes_time_to_reach_position() {
        let (mut w, _) = world(0.0);
        w.start_rotation(1.0);
        assert_eq!(w.table_state(), None);
        let mut polls = 1;
        while w.table_state().is_none() {
            polls += 1;
        }
        // 1 rad at 0.2 rad/s plus 2 s settling, polled every 0.1 s.
        assert!((69..=72).contains(&polls), "{polls}");
    }
}
