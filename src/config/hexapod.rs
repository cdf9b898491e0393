//! Configuration of plan kind `hexapod` (DESIGN.md method 6): a 6-leg parallel machine with
//! universal joints, its design hinges, leg encoders, a pose sensor and the poses to visit.

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::kind_config::{finite, invalid, non_negative, parse_strict, positive, sim_drivers_only};
use super::{ConfigError, DriverKind};
use crate::model::hexapod::{HexapodGeometry, LEGS};

pub const KIND: &str = "hexapod";

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct HexapodConfig {
    /// Must be `hexapod`.
    pub kind: String,
    pub machine: HexapodMachine,
    pub devices: HexapodDevices,
    pub plan: HexapodPlanConfig,
    #[serde(default)]
    pub sim: Option<HexapodSim>,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct HexapodMachine {
    #[serde(default)]
    pub name: String,
    /// Design fixed-platform hinges B_i, fixed frame, metres.
    pub base_hinges_m: Vec<[f64; 3]>,
    /// Design moving-platform hinges P_i, platform frame, metres.
    pub platform_hinges_m: Vec<[f64; 3]>,
}

impl HexapodMachine {
    /// The design geometry (validated: 6 hinges each).
    pub fn nominal(&self) -> HexapodGeometry {
        let v = |h: &[[f64; 3]], i: usize| {
            nalgebra::Vector3::from(h.get(i).copied().unwrap_or_default())
        };
        HexapodGeometry {
            base_m: std::array::from_fn(|i| v(&self.base_hinges_m, i)),
            platform_m: std::array::from_fn(|i| v(&self.platform_hinges_m, i)),
        }
    }
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct HexapodDevices {
    pub hexapod: HexapodDeviceConfig,
    /// The platform pose instrument; without it the commanded poses are used.
    #[serde(default)]
    pub pose_sensor: Option<PoseSensorConfig>,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct HexapodDeviceConfig {
    pub id: String,
    pub driver: DriverKind,
    /// Standard deviation of one leg encoder reading, metres.
    pub encoder_noise_m: f64,
    pub speed_m_s: f64,
    pub angular_speed_rad_s: f64,
    pub reading_period_s: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct PoseSensorConfig {
    pub id: String,
    pub driver: DriverKind,
    /// Standard deviation per translation coordinate, metres (in the solver's weights).
    pub noise_m: f64,
    /// Standard deviation per rotation-vector component, radians (in the solver's weights).
    pub noise_rad: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct HexapodPlanConfig {
    /// The home (reference) pose: identity rotation at this translation, metres.
    pub home_translation_m: [f64; 3],
    /// Leg readings at each pose (all recorded; the method averages them).
    pub readings_per_pose: usize,
    /// Leg readings at the home pose, the reference of every length change.
    pub reference_readings: usize,
    /// Random poses about home (after it), or ...
    #[serde(default)]
    pub poses: Option<RandomPoses>,
    /// ... listed poses (after home).
    #[serde(default)]
    pub pose_list: Vec<ListedPose>,
    #[serde(default)]
    pub solver: HexapodSolver,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct RandomPoses {
    pub count: usize,
    pub seed: u64,
    pub translation_half_range_m: [f64; 3],
    pub tilt_half_range_rad: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ListedPose {
    pub translation_m: [f64; 3],
    pub rotation_vector_rad: [f64; 3],
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct HexapodSolver {
    pub initial_step_m: f64,
    pub min_step_m: f64,
    pub shrink: f64,
}

impl Default for HexapodSolver {
    fn default() -> Self {
        let d = crate::solve::hexapod::TwoStageOptions::default();
        Self {
            initial_step_m: d.initial_step_m,
            min_step_m: d.min_step_m,
            shrink: d.shrink,
        }
    }
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct HexapodSim {
    pub seed: u64,
    /// Each true hinge coordinate is off its design value by up to ± this, metres.
    pub hinge_error_m: f64,
    /// The platform reaches every commanded pose exactly (idealised "given" poses); default:
    /// the controller's legs follow the design hinges and the true pose is the forward
    /// kinematics of their lengths with the true hinges.
    #[serde(default)]
    pub exact_poses: bool,
}

impl HexapodConfig {
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        Self::parse(&super::kind_config::read(path)?, path)
    }

    pub fn parse(text: &str, file: &Path) -> Result<Self, ConfigError> {
        let c: Self = parse_strict(text, file)?;
        c.validate(file)?;
        Ok(c)
    }

    fn validate(&self, f: &Path) -> Result<(), ConfigError> {
        if self.kind != KIND {
            return Err(invalid(
                f,
                "kind",
                format!("expected \"{KIND}\", got \"{}\"", self.kind),
            ));
        }
        for (key, hinges) in [
            ("machine.base_hinges_m", &self.machine.base_hinges_m),
            ("machine.platform_hinges_m", &self.machine.platform_hinges_m),
        ] {
            if hinges.len() != LEGS {
                return Err(invalid(
                    f,
                    key,
                    format!(
                        "expected {LEGS} hinges [x, y, z] in metres, got {}",
                        hinges.len()
                    ),
                ));
            }
            for (i, h) in hinges.iter().enumerate() {
                finite(f, &format!("{key}[{i}]"), h)?;
            }
        }
        let h = &self.devices.hexapod;
        let mut drivers = vec![("devices.hexapod.driver", h.driver)];
        if let Some(s) = &self.devices.pose_sensor {
            drivers.push(("devices.pose_sensor.driver", s.driver));
            non_negative(f, "devices.pose_sensor.noise_m", s.noise_m)?;
            non_negative(f, "devices.pose_sensor.noise_rad", s.noise_rad)?;
        }
        sim_drivers_only(f, KIND, &drivers, self.sim.is_some())?;
        positive(f, "devices.hexapod.encoder_noise_m", h.encoder_noise_m)?;
        positive(f, "devices.hexapod.speed_m_s", h.speed_m_s)?;
        positive(
            f,
            "devices.hexapod.angular_speed_rad_s",
            h.angular_speed_rad_s,
        )?;
        positive(f, "devices.hexapod.reading_period_s", h.reading_period_s)?;
        let p = &self.plan;
        finite(f, "plan.home_translation_m", &p.home_translation_m)?;
        if p.readings_per_pose == 0 || p.reference_readings == 0 {
            return Err(invalid(
                f,
                "plan.readings_per_pose",
                "expected readings_per_pose and reference_readings of at least 1",
            ));
        }
        let random = p.poses.as_ref().map_or(0, |r| r.count);
        if let Some(r) = &p.poses {
            finite(
                f,
                "plan.poses.translation_half_range_m",
                &r.translation_half_range_m,
            )?;
            non_negative(f, "plan.poses.tilt_half_range_rad", r.tilt_half_range_rad)?;
            if r.translation_half_range_m.iter().any(|v| *v < 0.0) {
                return Err(invalid(
                    f,
                    "plan.poses.translation_half_range_m",
                    "expected half ranges >= 0",
                ));
            }
        }
        for (i, q) in p.pose_list.iter().enumerate() {
            finite(
                f,
                &format!("plan.pose_list[{i}].translation_m"),
                &q.translation_m,
            )?;
            finite(
                f,
                &format!("plan.pose_list[{i}].rotation_vector_rad"),
                &q.rotation_vector_rad,
            )?;
        }
        if random + p.pose_list.len() < 6 {
            return Err(invalid(
                f,
                "plan.poses",
                format!(
                    "expected at least 6 poses besides home (6 unknowns per leg), got {}",
                    random + p.pose_list.len()
                ),
            ));
        }
        let s = &p.solver;
        positive(f, "plan.solver.initial_step_m", s.initial_step_m)?;
        positive(f, "plan.solver.min_step_m", s.min_step_m)?;
        if !(s.shrink > 0.0 && s.shrink < 1.0) {
            return Err(invalid(
                f,
                "plan.solver.shrink",
                format!("expected a factor in (0, 1), got {}", s.shrink),
            ));
        }
        if let Some(sim) = &self.sim {
            non_negative(f, "sim.hinge_error_m", sim.hinge_error_m)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn example() -> String {
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/config/hexapod.toml"))
            .expect("config/hexapod.toml")
    }

    #[test]
    fn the_example_parses() {
        let c = HexapodConfig::parse(&example(), Path::new("hexapod.toml")).expect("example");
        assert_eq!(c.machine.base_hinges_m.len(), 6);
    }

    #[test]
    fn errors_name_file_key_and_expectation() {
        let cases = [
            (
                "    [0.133826, 0.148629, 0.000000],\n]",
                "]",
                "machine.platform_hinges_m",
            ),
            ("shrink = 0.5", "shrink = 1.5", "plan.solver.shrink"),
            ("count = 29", "count = 3", "plan.poses"),
            (
                "encoder_noise_m = 1.0e-6",
                "encoder_noise_m = 0.0",
                "devices.hexapod.encoder_noise_m",
            ),
        ];
        for (from, to, key) in cases {
            let text = example();
            assert!(text.contains(from), "{from}");
            let err = HexapodConfig::parse(&text.replacen(from, to, 1), Path::new("h.toml"))
                .expect_err(to)
                .to_string();
            assert!(
                err.starts_with(&format!("h.toml: key `{key}")),
                "{to}: {err}"
            );
        }
    }
}
