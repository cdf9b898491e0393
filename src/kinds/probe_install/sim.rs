//! Simulated world of plan kind `probe_install`: a 5-axis CMM with a mis-installed laser probe
//! (seeded true installation) and a reference sphere, in virtual time; the CMM and the probe.

use std::sync::{Arc, Mutex, MutexGuard};

use async_trait::async_trait;
use geocal_drivers::{AxisPositions, DeviceError, Machine, MachineState, Probe, ProbeReading};
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::Serialize;

use crate::clock::VirtualClock;
use crate::kinds::probe_install::config::ProbeInstallConfig;
use crate::kinds::probe_install::plan::CMM_AXES;
use crate::model::probe_install::{beam_in_base, probe_offset, InstallParams};

/// How often (virtual time) the sequencer's state queries advance the clock, seconds.
const POLL_S: f64 = 0.02;

/// What `geocal run --truth` writes for a `probe_install` run.
#[derive(Debug, Clone, Serialize)]
pub struct ProbeInstallTruth {
    pub kind: &'static str,
    pub seed: u64,
    /// The true installation, in the order of `model::probe_install::PARAM_NAMES`.
    pub parameters: Vec<TruthParameter>,
    pub sphere_radius_m: f64,
    pub probe_noise_m: f64,
    /// `[sim.effects] probe_direction`: the readings' relative scale error (0 when off).
    pub probe_scale_error: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct TruthParameter {
    pub name: &'static str,
    pub value: f64,
}

pub struct ProbeInstallWorld {
    clock: Arc<VirtualClock>,
    truth: InstallParams,
    seed: u64,
    radius_m: f64,
    noise_m: f64,
    /// Relative scale error of the readings (`probe_direction` effect), 0 when off.
    scale_error: f64,
    range_m: [f64; 2],
    reading_period_s: f64,
    feed_m_s: f64,
    rotary_speed_rad_s: f64,
    travel_m: [[f64; 2]; 3],
    rng: ChaCha8Rng,
    /// Axis positions x, y, z, a, b now (at rest) or after the current move.
    position: [f64; 5],
    /// Where the current move started, and when (for the emulated controller's reports).
    move_from: [f64; 5],
    move_start_s: f64,
    move_end_s: f64,
    /// `[sim.effects]` beyond the reading scale (docs/diagnosis.md, "probe_install").
    effects: crate::kinds::probe_install::config::ProbeInstallEffects,
}

pub type SharedProbeWorld = Arc<Mutex<ProbeInstallWorld>>;

/// The true installation: the nominal plus errors drawn uniformly within the configured sizes.
pub fn true_installation(config: &ProbeInstallConfig, rng: &mut ChaCha8Rng) -> InstallParams {
    let n = config.plan.nominal.params();
    let Some(sim) = &config.sim else {
        return n;
    };
    let mut u = |s: f64| s * (2.0 * rng.random::<f64>() - 1.0);
    let beam = n.beam().normalize();
    let (e1, e2) = crate::solve::probe_install::tangent_basis(&beam);
    let tilted = (beam + u(sim.beam_tilt_rad) * e1 + u(sim.beam_tilt_rad) * e2).normalize();
    let zero = n.zero_point() + Vector3::from_fn(|_, _| u(sim.zero_point_m));
    let sphere = n.sphere_centre() + Vector3::from_fn(|_, _| u(sim.sphere_centre_m));
    InstallParams {
        b_offset_rad: n.b_offset_rad + u(sim.b_offset_rad),
        y_offset_m: n.y_offset_m + u(sim.y_offset_m),
        beam_dir: tilted.into(),
        zero_point_m: zero.into(),
        sphere_centre_m: sphere.into(),
    }
}

impl ProbeInstallWorld {
    pub fn new(config: &ProbeInstallConfig, clock: Arc<VirtualClock>) -> Self {
        let seed = config.sim.as_ref().map_or(0, |s| s.seed);
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let truth = true_installation(config, &mut rng);
        let travel = |a: &str| {
            config
                .machine
                .travel_m
                .get(a)
                .copied()
                .unwrap_or([-1.0, 1.0])
        };
        let probe = &config.devices.probe;
        let machine = &config.devices.machine;
        Self {
            clock,
            truth,
            seed,
            radius_m: config.plan.sphere_radius_m,
            noise_m: probe.noise_m,
            scale_error: config
                .sim
                .as_ref()
                .map_or(0.0, |s| s.effects.reading_scale_error()),
            range_m: probe.range_m,
            reading_period_s: probe.reading_period_s,
            feed_m_s: machine.feed_m_s,
            rotary_speed_rad_s: machine.rotary_speed_rad_s,
            travel_m: [travel("x"), travel("y"), travel("z")],
            rng,
            position: [travel("x")[0], travel("y")[0], travel("z")[1], 0.0, 0.0],
            move_from: [travel("x")[0], travel("y")[0], travel("z")[1], 0.0, 0.0],
            move_start_s: 0.0,
            move_end_s: 0.0,
            effects: config
                .sim
                .as_ref()
                .map(|s| s.effects.clone())
                .unwrap_or_default(),
        }
    }

    pub fn truth(&self) -> ProbeInstallTruth {
        let v = self.truth.to_vector();
        ProbeInstallTruth {
            kind: crate::kinds::probe_install::config::KIND,
            seed: self.seed,
            parameters: crate::model::probe_install::PARAM_NAMES
                .iter()
                .enumerate()
                .map(|(k, name)| TruthParameter { name, value: v[k] })
                .collect(),
            sphere_radius_m: self.radius_m,
            probe_noise_m: self.noise_m,
            probe_scale_error: self.scale_error,
        }
    }

    pub fn true_installation(&self) -> InstallParams {
        self.truth
    }

    fn now_s(&self) -> f64 {
        self.clock.elapsed_s()
    }

    /// Continue after an interrupted run: the same true installation and sphere, the machine
    /// at rest where the interrupted run last commanded it (`at`), the probe noise drawn from
    /// `noise_seed` (independent of the first attempt's); a simulated run's clock goes on at
    /// `t_s`, an emulated world follows wall time instead (None).
    pub fn resume_at(&mut self, t_s: Option<f64>, noise_seed: u64, at: Option<[f64; 5]>) {
        if let Some(t_s) = t_s {
            self.clock.advance_to(t_s);
        }
        self.rng = ChaCha8Rng::seed_from_u64(noise_seed);
        if let Some(at) = at {
            self.position = at;
            self.move_from = at;
        }
        self.move_start_s = self.now_s();
        self.move_end_s = self.now_s();
    }

    /// Bring the world's clock up to `t_s` (an emulated run: the world follows wall time).
    pub(crate) fn advance_to(&self, t_s: f64) {
        self.clock.advance_to(t_s);
    }

    /// Axis positions now, moving linearly from the start of the move to its end, and whether
    /// the axes still move (what the emulated controller reports; no clock advance).
    pub(crate) fn axes_now(&self) -> ([f64; 5], bool) {
        let now = self.now_s();
        if now >= self.move_end_s - 1e-9 {
            return (self.position, false);
        }
        let f = ((now - self.move_start_s) / (self.move_end_s - self.move_start_s)).clamp(0.0, 1.0);
        (
            std::array::from_fn(|k| self.move_from[k] + f * (self.position[k] - self.move_from[k])),
            true,
        )
    }

    /// Start a move; it ends after the slower of the linear path and the rotary axes.
    pub(crate) fn start_move(&mut self, target: [f64; 5]) -> Result<(), String> {
        for k in 0..3 {
            let [lo, hi] = self.travel_m[k];
            if !(lo..=hi).contains(&target[k]) {
                return Err(format!(
                    "axis {} target {} m outside its travel [{lo}, {hi}] m",
                    CMM_AXES[k], target[k]
                ));
            }
        }
        let linear = (0..3)
            .map(|k| (target[k] - self.position[k]).powi(2))
            .sum::<f64>()
            .sqrt()
            / self.feed_m_s;
        let rotary = (3..5)
            .map(|k| (target[k] - self.position[k]).abs())
            .fold(0.0, f64::max)
            / self.rotary_speed_rad_s;
        let (here, _) = self.axes_now();
        self.move_from = here;
        self.move_start_s = self.now_s();
        self.move_end_s = self.now_s() + linear.max(rotary);
        self.position = target;
        Ok(())
    }

    /// Idle at the position, or moving (each query lets `POLL_S` of virtual time pass).
    fn state(&mut self) -> Option<[f64; 5]> {
        let now = self.now_s();
        // The clock counts whole nanoseconds: within one of the end is there.
        if now >= self.move_end_s - 1e-9 {
            return Some(self.position);
        }
        self.clock.advance_to((now + POLL_S).min(self.move_end_s));
        None
    }

    /// One reading: where the true beam first meets the true sphere (scaled by the
    /// `probe_direction` effect's error when on), plus noise; None when the
    /// beam misses the sphere or the distance is outside the probe's range.
    fn read(&mut self) -> (f64, Option<f64>) {
        let t_s = self.now_s() + self.reading_period_s;
        self.clock.advance_to(t_s);
        (t_s, self.reading_now())
    }

    /// A reading at the axes' position now (no clock advance): where the true beam first meets
    /// the true sphere, plus noise; None when it misses or is out of range.
    pub(crate) fn reading_now(&mut self) -> Option<f64> {
        let [x, y, z, a, b] = self.axes_now().0;
        let e = &self.effects;
        let (w, origin) = if e.a_axis_tilt_rad == 0.0 {
            // q(t) = origin + t·|beam|·w, origin the point at reading 0.
            (
                beam_in_base(&self.truth, a, b).normalize(),
                Vector3::new(x, y, z) + probe_offset(&self.truth, a, b, 0.0),
            )
        } else {
            // The A axis tilted: the beam and the zero point turn about (1, 0, τ).
            use crate::kinds::probe_install::diagnosis::tilted_a_rotation;
            use crate::model::probe_install::rot_z;
            let ra = tilted_a_rotation(a, e.a_axis_tilt_rad);
            let rz = rot_z(b + self.truth.b_offset_rad);
            (
                (rz * ra * self.truth.beam()).normalize(),
                Vector3::new(x, y, z)
                    + rz * (Vector3::new(0.0, self.truth.y_offset_m, 0.0)
                        + ra * self.truth.zero_point()),
            )
        };
        let origin = origin
            + Vector3::new(
                e.x_periodic_error_m * (std::f64::consts::TAU * x / 1e-3).sin(),
                0.0,
                0.0,
            );
        let centre =
            self.truth.sphere_centre() + Vector3::from(e.thermal_drift_m_per_s) * self.now_s();
        let scale = self.truth.beam().norm();
        let d = origin - centre;
        let half_b = w.dot(&d);
        let mut disc = half_b * half_b - (d.norm_squared() - self.radius_m * self.radius_m);
        if disc < 0.0 {
            return None;
        }
        if !e.sphere_form_m.is_empty() {
            // The form at the perfect sphere's hit point (its second-order change ignored).
            let hit = d + w * (-half_b - disc.sqrt());
            let y = crate::kinds::probe_install::diagnosis::form_harmonics(&hit.normalize());
            let radius = self.radius_m
                + e.sphere_form_m
                    .iter()
                    .zip(y)
                    .map(|(c, y)| c * y)
                    .sum::<f64>();
            disc = half_b * half_b - (d.norm_squared() - radius * radius);
            if disc < 0.0 {
                return None;
            }
        }
        // The entry point: the smaller root along the beam.
        let reading = (1.0 + self.scale_error) * (-half_b - disc.sqrt()) / scale;
        let noise: f64 = StandardNormal.sample(&mut self.rng);
        let value = reading + self.noise_m * noise;
        let inside = value >= self.range_m[0] && value <= self.range_m[1];
        inside.then_some(value)
    }
}

fn lock<'a>(
    world: &'a SharedProbeWorld,
    device: &str,
) -> Result<MutexGuard<'a, ProbeInstallWorld>, DeviceError> {
    world.lock().map_err(|_| DeviceError::Disconnected {
        device: device.to_string(),
        message: "simulated world poisoned by an earlier panic".into(),
    })
}

/// The simulated 5-axis CMM: it reaches every commanded position exactly.
pub struct SimCmm {
    pub id: String,
    pub world: SharedProbeWorld,
}

#[async_trait]
impl Machine for SimCmm {
    fn id(&self) -> &str {
        &self.id
    }
    async fn start_move(&mut self, target: &AxisPositions) -> Result<(), DeviceError> {
        let mut axes = [0.0; 5];
        for (k, name) in CMM_AXES.iter().enumerate() {
            axes[k] = *target.get(*name).ok_or_else(|| DeviceError::Rejected {
                device: self.id.clone(),
                message: format!("move without axis `{name}`"),
            })?;
        }
        lock(&self.world, &self.id)?
            .start_move(axes)
            .map_err(|message| DeviceError::Rejected {
                device: self.id.clone(),
                message,
            })
    }
    async fn state(&mut self) -> Result<MachineState, DeviceError> {
        Ok(match lock(&self.world, &self.id)?.state() {
            None => MachineState::Moving,
            Some(at) => MachineState::Idle {
                position: CMM_AXES
                    .iter()
                    .zip(at)
                    .map(|(name, v)| (name.to_string(), v))
                    .collect(),
            },
        })
    }
}

/// The simulated laser displacement probe; out of range is a `Rejected` error saying so.
pub struct SimLaserProbe {
    pub id: String,
    pub world: SharedProbeWorld,
}

/// The message of a probe's out-of-range reply (the sequencer records it as a null reading).
pub const OUT_OF_RANGE: &str = "out of range";

#[async_trait]
impl Probe for SimLaserProbe {
    fn id(&self) -> &str {
        &self.id
    }
    async fn read(&mut self) -> Result<ProbeReading, DeviceError> {
        match lock(&self.world, &self.id)?.read() {
            (t_s, Some(value_m)) => Ok(ProbeReading { t_s, value_m }),
            (_, None) => Err(DeviceError::Rejected {
                device: self.id.clone(),
                message: OUT_OF_RANGE.into(),
            }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::probe_install::{sphere_residual, ProbeObservation};

    #[test]
    fn readings_put_the_probed_point_on_the_true_sphere() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/config/probe-install.toml");
        let mut config =
            ProbeInstallConfig::load(std::path::Path::new(path)).expect("example config");
        config.devices.probe.noise_m = 1e-15;
        let clock = Arc::new(VirtualClock::new(0));
        let mut world = ProbeInstallWorld::new(&config, clock);
        let plan = crate::kinds::probe_install::plan::ProbeInstallPlan::from_config(&config);
        let truth = world.true_installation();
        for p in &plan.points {
            world.start_move(p.axes).expect("in travel");
            while world.state().is_none() {}
            let (_, value) = world.read();
            let value = value.expect("the beam stays on the sphere and in range");
            let obs = ProbeObservation {
                a_rad: p.axes[3],
                b_rad: p.axes[4],
                machine_m: [p.axes[0], p.axes[1], p.axes[2]],
                reading_m: value,
                sigma_m: 1e-6,
            };
            assert!(sphere_residual(&truth, &obs, config.plan.sphere_radius_m).abs() < 1e-12);
        }
    }
}
