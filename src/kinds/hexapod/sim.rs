//! Simulated world of plan kind `hexapod`: a 6-leg machine with seeded true hinge coordinates,
//! incremental leg encoders with noise and a pose sensor, in virtual time.
//!
//! The controller turns a commanded pose into leg lengths with the design hinges; the legs
//! reach them and the true pose is the forward kinematics of those lengths with the true hinges
//! (unless `[sim] exact_poses`). The encoders count the legs' change since power-on (at home).

use std::sync::{Arc, Mutex, MutexGuard};

use async_trait::async_trait;
use geocal_drivers::{
    DeviceError, Hexapod, HexapodState, LegReading, PlatformPose, PoseReading, PoseSensor,
};
use nalgebra::{Rotation3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::Serialize;

use crate::clock::VirtualClock;
use crate::kinds::hexapod::config::HexapodConfig;
use crate::model::hexapod::{forward_kinematics, leg_length, HexapodGeometry, Pose, LEGS};

const POLL_S: f64 = 0.02;

/// What `geocal run --truth` writes for a `hexapod` run.
#[derive(Debug, Clone, Serialize)]
pub struct HexapodTruth {
    pub kind: &'static str,
    pub seed: u64,
    pub base_m: Vec<[f64; 3]>,
    pub platform_m: Vec<[f64; 3]>,
    pub encoder_noise_m: f64,
    /// The power-on home, then every commanded pose in order, with the pose truly reached.
    pub poses: Vec<CommandedAndTrue>,
}

#[derive(Debug, Clone, Copy, Serialize)]
pub struct CommandedAndTrue {
    pub commanded: PoseValues,
    pub reached: PoseValues,
}

/// A platform pose as the truth file writes it.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct PoseValues {
    pub translation_m: [f64; 3],
    pub rotation_vector_rad: [f64; 3],
}

impl From<PlatformPose> for PoseValues {
    fn from(p: PlatformPose) -> Self {
        PoseValues {
            translation_m: p.translation_m,
            rotation_vector_rad: p.rotation_vector_rad,
        }
    }
}

pub struct HexapodWorld {
    clock: Arc<VirtualClock>,
    seed: u64,
    truth: HexapodGeometry,
    /// The design hinges the controller's inverse kinematics uses.
    nominal: HexapodGeometry,
    exact_poses: bool,
    /// Commanded and reached poses, power-on home first.
    poses: Vec<(PlatformPose, PlatformPose)>,
    rng: ChaCha8Rng,
    encoder_noise_m: f64,
    pose_noise: (f64, f64),
    speed_m_s: f64,
    angular_speed_rad_s: f64,
    reading_period_s: f64,
    /// The encoders' counts at power-on (home): arbitrary, unknown to the method.
    start_count_m: [f64; LEGS],
    home_lengths_m: [f64; LEGS],
    pose: PlatformPose,
    move_end_s: f64,
    /// The withheld effects of `[sim]` (all zero: none).
    effects: SimEffects,
    /// Each leg's last motion (+1 extending, −1 retracting, 0 none since power-on) and the
    /// last commanded pose: what the backlash depends on.
    motion_sign: [f64; LEGS],
    last_commanded: PlatformPose,
}

/// The unmodelled effects a simulated hexapod may carry (docs/diagnosis.md, "hexapod").
#[derive(Debug, Clone, Copy, Default)]
struct SimEffects {
    leg_scale: [f64; LEGS],
    leg_backlash_m: [f64; LEGS],
    sensor_drift: [f64; 6],
    platform_sag_m: f64,
}

pub type SharedHexapodWorld = Arc<Mutex<HexapodWorld>>;

pub fn to_pose(p: &PlatformPose) -> Pose {
    Pose {
        rotation: Rotation3::new(Vector3::from(p.rotation_vector_rad)),
        translation_m: Vector3::from(p.translation_m),
    }
}

/// The pose the platform reaches when commanded to `commanded`: the controller sets the legs to
/// the design geometry's lengths there; the true hinges turn those into a slightly different
/// pose (forward kinematics from the commanded one). `exact`: the commanded pose itself.
fn reached_pose(
    nominal: &HexapodGeometry,
    truth: &HexapodGeometry,
    exact: bool,
    commanded: &PlatformPose,
) -> Option<PlatformPose> {
    if exact {
        return Some(*commanded);
    }
    let c = to_pose(commanded);
    let lengths: [f64; LEGS] = std::array::from_fn(|i| leg_length(&nominal.leg(i), &c).0);
    let p = forward_kinematics(truth, &lengths, &c)?;
    Some(PlatformPose {
        translation_m: p.translation_m.into(),
        rotation_vector_rad: p.rotation.scaled_axis().into(),
    })
}

impl HexapodWorld {
    pub fn new(config: &HexapodConfig, clock: Arc<VirtualClock>) -> Self {
        let seed = config.sim.as_ref().map_or(0, |s| s.seed);
        let amplitude = config.sim.as_ref().map_or(0.0, |s| s.hinge_error_m);
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let nominal = config.machine.nominal();
        let v: Vec<f64> = nominal
            .to_vec()
            .iter()
            .map(|x| x + amplitude * (2.0 * rng.random::<f64>() - 1.0))
            .collect();
        let truth = HexapodGeometry::from_slice(&v);
        let home = PlatformPose {
            translation_m: config.plan.home_translation_m,
            rotation_vector_rad: [0.0; 3],
        };
        let exact_poses = config.sim.as_ref().is_some_and(|s| s.exact_poses);
        // A home the true machine cannot reach from the design lengths stays as commanded.
        let reached = reached_pose(&nominal, &truth, exact_poses, &home).unwrap_or(home);
        let home_pose = to_pose(&reached);
        let home_lengths_m = std::array::from_fn(|i| leg_length(&truth.leg(i), &home_pose).0);
        let start_count_m = std::array::from_fn(|_| rng.random_range(-0.01..0.01));
        let h = &config.devices.hexapod;
        let pose_noise = config
            .devices
            .pose_sensor
            .as_ref()
            .map_or((0.0, 0.0), |s| (s.noise_m, s.noise_rad));
        Self {
            clock,
            seed,
            truth,
            nominal,
            exact_poses,
            poses: vec![(home, reached)],
            rng,
            encoder_noise_m: h.encoder_noise_m,
            pose_noise,
            speed_m_s: h.speed_m_s,
            angular_speed_rad_s: h.angular_speed_rad_s,
            reading_period_s: h.reading_period_s,
            start_count_m,
            home_lengths_m,
            pose: reached,
            move_end_s: 0.0,
            effects: config
                .sim
                .as_ref()
                .map_or_else(SimEffects::default, |s| SimEffects {
                    leg_scale: s.leg_scale,
                    leg_backlash_m: s.leg_backlash_m,
                    sensor_drift: s.sensor_drift,
                    platform_sag_m: s.platform_sag_m,
                }),
            motion_sign: [0.0; LEGS],
            last_commanded: home,
        }
    }

    pub fn truth(&self) -> HexapodTruth {
        HexapodTruth {
            kind: crate::kinds::hexapod::config::KIND,
            seed: self.seed,
            base_m: self.truth.base_m.iter().map(|v| (*v).into()).collect(),
            platform_m: self.truth.platform_m.iter().map(|v| (*v).into()).collect(),
            encoder_noise_m: self.encoder_noise_m,
            poses: self
                .poses
                .iter()
                .map(|(c, r)| CommandedAndTrue {
                    commanded: (*c).into(),
                    reached: (*r).into(),
                })
                .collect(),
        }
    }

    pub fn true_geometry(&self) -> &HexapodGeometry {
        &self.truth
    }

    fn now_s(&self) -> f64 {
        self.clock.elapsed_s()
    }

    /// Continue after an interrupted run: the same true hinges and encoder counts, the
    /// interrupted run's moves (`commanded`, in order) in the truth with the platform at rest
    /// at the last of them, the noise drawn from `noise_seed` (independent of the first
    /// attempt's); a simulated run's clock goes on at `t_s`, an emulated world follows wall
    /// time instead (None). A commanded pose without a true pose near it leaves the platform
    /// where it was, as `start_move` refuses it.
    pub fn resume_at(&mut self, t_s: Option<f64>, noise_seed: u64, commanded: &[PlatformPose]) {
        if let Some(t_s) = t_s {
            self.clock.advance_to(t_s);
        }
        self.rng = ChaCha8Rng::seed_from_u64(noise_seed);
        for c in commanded {
            if let Some(reached) = reached_pose(&self.nominal, &self.truth, self.exact_poses, c) {
                self.poses.push((*c, reached));
                self.pose = reached;
            }
        }
        self.move_end_s = self.now_s();
    }

    pub fn start_move(&mut self, commanded: PlatformPose) -> Result<(), String> {
        let target = reached_pose(&self.nominal, &self.truth, self.exact_poses, &commanded)
            .ok_or_else(|| {
                format!("the legs' lengths for pose {commanded:?} have no nearby true pose")
            })?;
        self.poses.push((commanded, target));
        // The controller drives each leg to its design length: the sign of that change.
        let (from, to) = (to_pose(&self.last_commanded), to_pose(&commanded));
        for i in 0..LEGS {
            let change =
                leg_length(&self.nominal.leg(i), &to).0 - leg_length(&self.nominal.leg(i), &from).0;
            if change != 0.0 {
                self.motion_sign[i] = change.signum();
            }
        }
        self.last_commanded = commanded;
        let dist =
            (Vector3::from(target.translation_m) - Vector3::from(self.pose.translation_m)).norm();
        let turn = (Rotation3::new(Vector3::from(target.rotation_vector_rad))
            * to_pose(&self.pose).rotation.inverse())
        .angle();
        self.move_end_s =
            self.now_s() + (dist / self.speed_m_s).max(turn / self.angular_speed_rad_s);
        self.pose = target;
        Ok(())
    }

    pub fn idle(&mut self) -> bool {
        let now = self.now_s();
        if now >= self.move_end_s - 1e-9 {
            return true;
        }
        self.clock.advance_to((now + POLL_S).min(self.move_end_s));
        false
    }

    pub fn read_legs(&mut self) -> LegReading {
        let t_s = self.now_s() + self.reading_period_s;
        self.clock.advance_to(t_s);
        let pose = to_pose(&self.pose);
        let e = self.effects;
        let tilt = pose.rotation.angle();
        let lengths_m = std::array::from_fn(|i| {
            let z: f64 = StandardNormal.sample(&mut self.rng);
            let leg = self.truth.leg(i);
            let change = leg_length(&leg, &pose).0 - self.home_lengths_m[i];
            let d = pose.rotation * self.truth.platform_m[i] + pose.translation_m
                - self.truth.base_m[i];
            let sag = e.platform_sag_m * (tilt / 0.1).powi(2) * d.z / d.norm();
            change * (1.0 + e.leg_scale[i])
                + e.leg_backlash_m[i] * self.motion_sign[i]
                + sag
                + self.start_count_m[i]
                + self.encoder_noise_m * z
        });
        LegReading { t_s, lengths_m }
    }

    fn measure_pose(&mut self) -> PoseReading {
        let t_s = self.now_s() + self.reading_period_s;
        self.clock.advance_to(t_s);
        let (sm, sr) = self.pose_noise;
        let mut n = |s: f64| {
            let z: f64 = StandardNormal.sample(&mut self.rng);
            s * z
        };
        let p = self.pose;
        let drift = self.effects.sensor_drift.map(|v| v * t_s);
        PoseReading {
            t_s,
            pose: PlatformPose {
                translation_m: std::array::from_fn(|c| p.translation_m[c] + drift[c] + n(sm)),
                rotation_vector_rad: std::array::from_fn(|c| {
                    p.rotation_vector_rad[c] + drift[3 + c] + n(sr)
                }),
            },
        }
    }
}

fn lock<'a>(
    world: &'a SharedHexapodWorld,
    device: &str,
) -> Result<MutexGuard<'a, HexapodWorld>, DeviceError> {
    world.lock().map_err(|_| DeviceError::Disconnected {
        device: device.to_string(),
        message: "simulated world poisoned by an earlier panic".into(),
    })
}

pub struct SimHexapod {
    pub id: String,
    pub world: SharedHexapodWorld,
}

#[async_trait]
impl Hexapod for SimHexapod {
    fn id(&self) -> &str {
        &self.id
    }
    async fn start_move(&mut self, pose: &PlatformPose) -> Result<(), DeviceError> {
        let finite = pose
            .translation_m
            .iter()
            .chain(&pose.rotation_vector_rad)
            .all(|v| v.is_finite());
        if !finite {
            return Err(DeviceError::Rejected {
                device: self.id.clone(),
                message: format!("pose {pose:?} is not finite"),
            });
        }
        lock(&self.world, &self.id)?
            .start_move(*pose)
            .map_err(|message| DeviceError::Rejected {
                device: self.id.clone(),
                message,
            })
    }
    async fn state(&mut self) -> Result<HexapodState, DeviceError> {
        Ok(if lock(&self.world, &self.id)?.idle() {
            HexapodState::Idle
        } else {
            HexapodState::Moving
        })
    }
    async fn read_legs(&mut self) -> Result<LegReading, DeviceError> {
        Ok(lock(&self.world, &self.id)?.read_legs())
    }
}

pub struct SimPoseSensor {
    pub id: String,
    pub world: SharedHexapodWorld,
}

#[async_trait]
impl PoseSensor for SimPoseSensor {
    fn id(&self) -> &str {
        &self.id
    }
    async fn measure(&mut self) -> Result<PoseReading, DeviceError> {
        Ok(lock(&self.world, &self.id)?.measure_pose())
    }
}
