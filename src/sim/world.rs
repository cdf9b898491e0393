//! The simulated world's state: truth machine, true stations, the rotary table the tracer
//! may stand on, the machine's motion in virtual time, the tracer's counter and noise, the
//! environment. Simulated drivers share it.

use std::sync::Arc;

use nalgebra::Vector3;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use serde::Serialize;

use crate::clock::VirtualClock;
use crate::config::{Config, SimEnvironmentConfig};
use crate::extract::NoiseModel;
use crate::model::kinematics::{actual_position, Structure};
use crate::plan::Plan;
use crate::sim::compensation::SimControllerCompensation;
use crate::sim::effects::SimEffects;
use crate::sim::rotary::{AngleError, SimTable};
use crate::sim::truth::TruthErrors;

#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error("the configuration has no [sim] table")]
    NoSimTable,
    #[error("machine.structure: {0}")]
    Structure(String),
    #[error("sim.compensation: {0}")]
    Compensation(#[from] crate::compensate::CompensateError),
}

/// A move in virtual time with a smooth (zero end velocity) profile.
#[derive(Debug, Clone, Copy)]
struct Motion {
    from: [f64; 3],
    to: [f64; 3],
    start_s: f64,
    duration_s: f64,
}

impl Motion {
    fn at(&self, t_s: f64) -> [f64; 3] {
        let tau = ((t_s - self.start_s) / self.duration_s).clamp(0.0, 1.0);
        // Cycloidal profile: velocity and acceleration vanish at both ends.
        let s = tau - (2.0 * std::f64::consts::PI * tau).sin() / (2.0 * std::f64::consts::PI);
        std::array::from_fn(|k| self.from[k] + (self.to[k] - self.from[k]) * s)
    }

    fn end_s(&self) -> f64 {
        self.start_s + self.duration_s
    }
}

pub struct SimWorld {
    pub(crate) clock: Arc<VirtualClock>,
    structure: Structure,
    truth: TruthErrors,
    target_offset_m: [f64; 3],
    /// True positions of the stations the operator places (unused for table stations).
    stations_m: Vec<Vector3<f64>>,
    current_station: usize,
    /// Per plan station: does the tracer stand on the rotary table there?
    table_station: Vec<bool>,
    table: Option<SimTable>,
    /// The table as the run found it: the truth follows the plan's commands from here.
    table_at_start: Option<SimTable>,
    /// The tracer stands on the table (and turns with it).
    on_table: bool,
    motion: Motion,
    feed_m_s: f64,
    relocation_s: f64,
    // Tracer.
    sample_period_s: f64,
    next_seq: u64,
    last_sample_s: f64,
    home_distance_m: f64,
    beam_segment: u32,
    /// Set when the tracer or the reflector was moved; the next homing starts a new segment.
    beam_interrupted: bool,
    noise: NoiseModel,
    /// Actual noise over the declared model.
    noise_factor: f64,
    rng: ChaCha8Rng,
    // Environment.
    env: SimEnvironmentConfig,
    env_period_s: f64,
    next_env_s: f64,
    /// Unmodelled effects (`[sim.effects]`), all off by default.
    effects: SimEffects,
    /// The controller's compensation tables (`[sim] compensation`), none by default.
    compensation: SimControllerCompensation,
    /// A real controller's joint positions (real-controller HIL): the carriage stands where
    /// the controller commands it, its compensation trim included, instead of following the
    /// world's own motion and tables.
    external_joints: Option<Box<dyn JointSource>>,
}

/// The commanded joint positions of a controller outside the world (metres), e.g. LinuxCNC's
/// `joint.N.motor-pos-cmd`.
pub trait JointSource: Send {
    fn joints_m(&self) -> [f64; 3];
}

/// Everything the simulation knows that a solver must find: exported with `--truth`.
#[derive(Debug, Clone, Serialize)]
pub struct Truth {
    pub structure: String,
    pub seed: u64,
    pub stations: Vec<TruthStation>,
    pub points: Vec<TruthPoint>,
    /// The error functions sampled along each axis, under their ISO names.
    pub errors: serde_json::Value,
    /// The error functions themselves (coefficients), to evaluate anywhere.
    pub error_model: TruthErrors,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rotary: Option<TruthRotary>,
}

/// The rotary table's truth: axis, angular positioning error, the true angle of every step.
#[derive(Debug, Clone, Serialize)]
pub struct TruthRotary {
    pub table: String,
    pub axis_point_m: [f64; 3],
    pub axis_direction: [f64; 3],
    /// The tracer's position at true table angle 0.
    pub tracer_base_m: [f64; 3],
    pub angle_error: AngleError,
    /// The table's reversal (backlash), radians: in position it stands half of it beyond the
    /// command in the direction of its last move.
    #[serde(skip_serializing_if = "crate::config::is_zero")]
    pub reversal_rad: f64,
    /// The scatter of each positioning (standard deviation), radians; drawn into the steps'
    /// true angles.
    #[serde(skip_serializing_if = "crate::config::is_zero")]
    pub repeatability_rad: f64,
    /// The table's error motions (`[sim.effects] table_error_motion`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error_motion: Option<crate::sim::rotary::ErrorMotion>,
    /// The tracer's eccentricity on the table (`[sim.effects] tracer_eccentricity`), turning
    /// with it: e cos(az_t − φ0) + ez sin(el), az_t the azimuth about the axis (from e1 = x
    /// projected on the table's plane) less the table angle.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tracer_eccentricity: Option<TruthTableEccentricity>,
    pub steps: Vec<TruthStep>,
}

#[derive(Debug, Clone, Serialize)]
pub struct TruthTableEccentricity {
    pub e_m: f64,
    pub phi0_rad: f64,
    pub ez_m: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct TruthStep {
    pub station: String,
    pub commanded_rad: f64,
    /// True table angle in position.
    pub true_rad: f64,
    /// true − commanded.
    pub error_rad: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct TruthStation {
    pub id: String,
    pub position_m: [f64; 3],
    /// |P - A_0| for each target: distance to the homing point.
    pub home_distance_m: std::collections::BTreeMap<String, f64>,
}

#[derive(Debug, Clone, Serialize)]
pub struct TruthPoint {
    pub target: String,
    pub point: usize,
    pub axes_m: [f64; 3],
    pub nominal_m: [f64; 3],
    pub actual_m: [f64; 3],
}

impl SimWorld {
    pub fn new(
        config: &Config,
        plan: &Plan,
        clock: Arc<VirtualClock>,
    ) -> Result<SimWorld, SimError> {
        let sim = config.sim.as_ref().ok_or(SimError::NoSimTable)?;
        let structure = Structure::parse(&config.machine.structure)
            .map_err(|e| SimError::Structure(e.to_string()))?;
        let travel = ["x", "y", "z"].map(|a| {
            config
                .machine
                .travel_m
                .get(a)
                .copied()
                .unwrap_or([0.0, 1.0])
        });
        let truth = TruthErrors::random(sim.seed, travel, &sim.errors);
        // Separate streams so that changing the noise does not move the stations.
        let mut station_rng = ChaCha8Rng::seed_from_u64(sim.seed ^ 0x5157_4154_494f_4e53);
        let offset = Normal::new(0.0, sim.station_hint_error_m.max(0.0))
            .map_err(|e| SimError::Structure(e.to_string()))?;
        let stations_m = plan
            .stations
            .iter()
            .map(|s| {
                let hint = s.hint_m.unwrap_or([0.0; 3]);
                Vector3::from_fn(|k, _| hint[k] + offset.sample(&mut station_rng))
            })
            .collect();
        let table = config.plan.rotary.as_ref().map(|rotary| {
            let table = SimTable::random(sim.seed, rotary, &sim.rotary, sim.station_hint_error_m);
            match sim.effects.table_error_motion {
                m if m.enabled => table.with_error_motion(sim.seed, m.size),
                _ => table,
            }
        });
        let table_station = plan.stations.iter().map(|s| s.rotation.is_some()).collect();
        let tracer = &config.devices.tracer;
        let home = plan.points.first().map_or([0.0; 3], |p| p.axes_m);
        let env_rate = config
            .devices
            .environment
            .as_ref()
            .map_or(1.0, |e| e.sample_rate_hz);
        Ok(SimWorld {
            clock,
            structure,
            truth,
            target_offset_m: plan.targets.first().map_or([0.0; 3], |t| t.offset_m),
            stations_m,
            current_station: 0,
            table_station,
            table_at_start: table.clone(),
            table,
            on_table: false,
            motion: Motion {
                from: home,
                to: home,
                start_s: 0.0,
                duration_s: 1.0,
            },
            feed_m_s: config.devices.machine.feed_m_s,
            relocation_s: sim.relocation_s,
            sample_period_s: 1.0 / tracer.sample_rate_hz,
            next_seq: 0,
            last_sample_s: 0.0,
            home_distance_m: 0.0,
            beam_segment: 0,
            beam_interrupted: false,
            noise: tracer.noise_model(),
            noise_factor: sim.tracer_noise_factor.unwrap_or(1.0),
            rng: ChaCha8Rng::seed_from_u64(sim.noise_seed.unwrap_or(sim.seed.wrapping_add(1))),
            effects: SimEffects::new(
                &sim.effects,
                &sim.environment,
                sim.seed,
                plan.stations.len(),
                plan.targets.len() * plan.passes.len() * plan.points.len(),
            )
            .with_declared_dead_path(tracer.dead_path_m),
            env: sim.environment.clone(),
            env_period_s: 1.0 / env_rate,
            next_env_s: 0.0,
            compensation: SimControllerCompensation::load(&sim.compensation)?,
            external_joints: None,
        })
    }

    pub fn now_s(&self) -> f64 {
        self.clock.elapsed_s()
    }

    fn target_at(&self, axes_m: [f64; 3], t_s: f64) -> Vector3<f64> {
        self.target_at_joints(self.compensation.joint_positions_m(axes_m), t_s)
    }

    /// The target's true position with the carriages at `joints_m`.
    fn target_at_joints(&self, joints_m: [f64; 3], t_s: f64) -> Vector3<f64> {
        Vector3::from(actual_position(
            &self.structure,
            &self.truth,
            self.effects.actual_axes_m(joints_m, t_s),
            self.effects.actual_offset_m(self.target_offset_m),
        ))
    }

    /// Where the tracer stands at `t_s`: on the turning table, or where the operator put it.
    fn station_at(&self, t_s: f64) -> Vector3<f64> {
        match (&self.table, self.on_table) {
            (Some(table), true) => table.tracer_at(table.angle_at(t_s)),
            _ => self.stations_m[self.current_station],
        }
    }

    fn true_distance_m(&self, t_s: f64) -> f64 {
        let target = match &self.external_joints {
            Some(source) => self.target_at_joints(source.joints_m(), t_s),
            None => self.target_at(self.motion.at(t_s), t_s),
        };
        let station = self.station_at(t_s);
        // The tracer on the table turns with it: its eccentricity is fixed in the table.
        let table_frame = match (&self.table, self.on_table) {
            (Some(table), true) => Some((table.axis_direction.into_inner(), table.angle_at(t_s))),
            _ => None,
        };
        self.effects
            .distance_m(self.current_station, &station, &target, t_s, table_frame)
    }

    // --- tracer ---

    /// The next sample of the length stream; advances virtual time by one period.
    pub fn next_tracer_sample(&mut self) -> geocal_drivers::TracerReading {
        let t_s = (self.last_sample_s + self.sample_period_s).max(self.now_s());
        self.last_sample_s = t_s;
        self.clock.advance_to(t_s);
        let distance_m = self.true_distance_m(t_s);
        let length_m = distance_m - self.home_distance_m;
        let sigma = self.noise_factor * self.noise.sample_sigma_m(distance_m);
        let noise = Normal::new(0.0, sigma).map_or(0.0, |n| n.sample(&mut self.rng));
        let seq = self.next_seq;
        self.next_seq += 1;
        geocal_drivers::TracerReading {
            seq,
            t_s,
            length_m: length_m + noise,
            signal: 0.9,
            tracking: true,
            beam_segment: self.beam_segment,
        }
    }

    pub fn home_tracer(&mut self) {
        if self.beam_interrupted {
            self.beam_interrupted = false;
            self.beam_segment += 1;
        }
        self.home_distance_m = self.true_distance_m(self.now_s());
    }

    /// The operator mounts another reflector: the beam is lost until the next homing.
    pub fn mount_target(&mut self, offset_m: [f64; 3]) {
        if offset_m != self.target_offset_m {
            self.target_offset_m = offset_m;
            self.beam_interrupted = self.next_seq > 0;
        }
    }

    // --- machine ---

    pub fn start_move(&mut self, target: [f64; 3]) {
        let now = self.now_s();
        let from = self.motion.at(now);
        let distance: f64 = (0..3)
            .map(|k| (target[k] - from[k]).powi(2))
            .sum::<f64>()
            .sqrt();
        // The cycloidal profile peaks at twice the mean speed: keep the peak at the feed.
        let duration_s = (2.0 * distance / self.feed_m_s).max(0.1);
        self.effects.on_move(from, target, now, now + duration_s);
        self.compensation.on_move(from, target);
        self.motion = Motion {
            from,
            to: target,
            start_s: now,
            duration_s,
        };
    }

    /// The commanded end position once the move has finished, else None.
    pub fn machine_idle_at(&self) -> Option<[f64; 3]> {
        (self.now_s() >= self.motion.end_s()).then_some(self.motion.to)
    }

    // --- station mover ---

    /// The operator puts the tracer on station `index`: on the table for a table station
    /// (nothing to do if it already stands there), else at that station's true position.
    pub fn place_station(&mut self, index: usize) {
        let index = index.min(self.stations_m.len().saturating_sub(1));
        let to_table = self.table_station.get(index).copied().unwrap_or(false);
        if to_table && self.on_table {
            return;
        }
        if index != self.current_station || self.next_seq > 0 {
            self.clock.advance_to(self.now_s() + self.relocation_s);
        }
        self.beam_interrupted = self.next_seq > 0;
        self.current_station = index;
        self.on_table = to_table;
        self.effects.on_station(index, self.now_s());
        // The counter is meaningless until the sequencer homes again.
        self.home_distance_m = self.true_distance_m(self.now_s());
    }

    // --- rotary table ---

    /// Start turning the table; the tracer on it turns too, so the beam is lost until the
    /// next homing. False if the world has no table.
    pub fn start_rotation(&mut self, commanded_rad: f64) -> bool {
        let now = self.now_s();
        let Some(table) = self.table.as_mut() else {
            return false;
        };
        if table.start_rotation(commanded_rad, now) && self.on_table {
            self.beam_interrupted = self.next_seq > 0;
        }
        true
    }

    pub fn has_table(&self) -> bool {
        self.table.is_some()
    }

    /// The table's encoder angle when in position; None while moving (or without a table).
    pub fn table_in_position(&self) -> Option<f64> {
        self.table.as_ref()?.in_position_at(self.now_s())
    }

    // --- environment ---

    pub fn env_samples_until_now(&mut self) -> Vec<geocal_drivers::EnvReading> {
        let now = self.now_s();
        let mut out = Vec::new();
        while self.next_env_s <= now {
            out.push(self.env_at(self.next_env_s));
            self.next_env_s += self.env_period_s;
        }
        out
    }

    /// The environment sensors' values at `t_s`.
    pub(crate) fn env_at(&self, t_s: f64) -> geocal_drivers::EnvReading {
        let air_temp_k = crate::sim::effects::air_temp_k(&self.env, t_s);
        geocal_drivers::EnvReading {
            t_s,
            air_temp_k,
            pressure_pa: self.env.pressure_pa,
            humidity_pct: self.env.humidity_pct,
            material_temp_k: self
                .env
                .material_temp_k
                .iter()
                .map(|&m| crate::sim::effects::material_temp_k(&self.env, m, t_s))
                .collect(),
        }
    }

    /// Continue an interrupted run (`geocal run --resume`): the world, rebuilt from the same
    /// seed, resumes at `t_s` (after the last recorded log time), its environment log follows
    /// from there, and the tracer noise draws from a fresh stream (`noise_seed`) so that the
    /// repeated points' noise is independent of the first attempt's.
    pub fn resume_at(&mut self, t_s: f64, noise_seed: u64) {
        self.clock.advance_to(t_s);
        self.last_sample_s = self.now_s();
        self.next_env_s = self.now_s();
        self.rng = ChaCha8Rng::seed_from_u64(noise_seed);
    }

    // --- hardware-in-the-loop (src/sim/hil.rs): the emulators read the world directly ---

    /// The carriages follow `source` from now on (a real controller in the loop); the
    /// world's own compensation tables are not applied then (the controller applies its own).
    pub fn follow_joints(&mut self, source: Box<dyn JointSource>) {
        self.external_joints = Some(source);
    }

    /// True tracer-to-target distance now (the emulator keeps its own origin).
    pub(crate) fn hil_distance_m(&self) -> f64 {
        self.true_distance_m(self.now_s())
    }

    /// The machine's axis positions now, and whether it is still moving (a move to where
    /// the axes already are is no motion).
    pub(crate) fn hil_machine_axes(&self) -> ([f64; 3], bool) {
        let now = self.now_s();
        let moving = now < self.motion.end_s() && self.motion.from != self.motion.to;
        (self.motion.at(now), moving)
    }

    /// The table's encoder angle now and whether it is in position (None without a table).
    pub(crate) fn hil_table_encoder(&self) -> Option<(f64, bool)> {
        Some(self.table.as_ref()?.encoder_at(self.now_s()))
    }

    // --- truth ---

    /// Per plan station, the true table angle it is measured at (None off the table): the
    /// table as the run found it, commanded through the plan's rotations in order.
    fn table_true_angles(&self, plan: &Plan) -> Vec<Option<f64>> {
        let mut table = self.table_at_start.clone();
        plan.stations
            .iter()
            .map(|s| {
                let (r, table) = (s.rotation.as_ref()?, table.as_mut()?);
                for commanded_rad in r.via_rad.into_iter().chain([r.commanded_rad]) {
                    table.start_rotation(commanded_rad, 0.0);
                }
                Some(table.rest_angle_rad())
            })
            .collect()
    }

    pub fn truth(&self, config: &Config, plan: &Plan) -> Truth {
        let home = plan.points.first().map_or([0.0; 3], |p| p.axes_m);
        let table_true_rad = self.table_true_angles(plan);
        let at = |axes: [f64; 3], offset: [f64; 3]| {
            Vector3::from(actual_position(
                &self.structure,
                &self.truth,
                axes,
                self.effects.actual_offset_m(offset),
            ))
        };
        Truth {
            structure: self.structure.as_str().to_string(),
            seed: config.sim.as_ref().map_or(0, |s| s.seed),
            stations: plan
                .stations
                .iter()
                .zip(&self.stations_m)
                .zip(&table_true_rad)
                .map(|((s, p), true_rad)| match (true_rad, &self.table) {
                    (Some(true_rad), Some(table)) => (s, table.tracer_at(*true_rad)),
                    _ => (s, *p),
                })
                .map(|(s, p)| TruthStation {
                    id: s.id.clone(),
                    position_m: [p.x, p.y, p.z],
                    home_distance_m: plan
                        .targets
                        .iter()
                        .map(|t| (t.id.clone(), (p - at(home, t.offset_m)).norm()))
                        .collect(),
                })
                .collect(),
            points: plan
                .targets
                .iter()
                .flat_map(|t| {
                    plan.points.iter().map(move |p| {
                        let a = at(p.axes_m, t.offset_m);
                        TruthPoint {
                            target: t.id.clone(),
                            point: p.index,
                            axes_m: p.axes_m,
                            nominal_m: plan.nominal_m(p.index, t),
                            actual_m: [a.x, a.y, a.z],
                        }
                    })
                })
                .collect(),
            errors: self.truth.sample_table(21),
            error_model: self.truth.clone(),
            rotary: self.table.as_ref().map(|table| TruthRotary {
                table: table.id.clone(),
                axis_point_m: table.axis_point_m.into(),
                axis_direction: table.axis_direction.into_inner().into(),
                tracer_base_m: table.tracer_base_m.into(),
                angle_error: table.error.clone(),
                reversal_rad: table.reversal_rad,
                repeatability_rad: table.repeatability_rad(),
                error_motion: table.error_motion.clone(),
                tracer_eccentricity: self.effects.table_eccentricity().map(
                    |(e_m, phi0_rad, ez_m)| TruthTableEccentricity {
                        e_m,
                        phi0_rad,
                        ez_m,
                    },
                ),
                steps: plan
                    .stations
                    .iter()
                    .zip(&table_true_rad)
                    .filter_map(|(s, true_rad)| {
                        let r = s.rotation.as_ref()?;
                        let true_rad = (*true_rad)?;
                        Some(TruthStep {
                            station: s.id.clone(),
                            commanded_rad: r.commanded_rad,
                            true_rad,
                            error_rad: true_rad - r.commanded_rad,
                        })
                    })
                    .collect(),
            }),
        }
    }
}
