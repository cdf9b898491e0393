//! Configuration of plan kind `probe_install` (DESIGN.md method 5): a 5-axis CMM (X, Y, Z + A, B)
//! with a 1-D laser displacement probe, a reference sphere probed at several postures.

use std::collections::BTreeMap;
use std::path::Path;

use serde::{Deserialize, Serialize};

use super::kind_config::{finite, invalid, non_negative, parse_strict, positive, sim_drivers_only};
use super::{ConfigError, DriverKind};
use crate::model::probe_install::InstallParams;

pub const KIND: &str = "probe_install";

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ProbeInstallConfig {
    /// Must be `probe_install`.
    pub kind: String,
    pub machine: CmmConfig,
    pub devices: ProbeInstallDevices,
    pub plan: ProbeInstallPlan,
    /// The simulated world; required when a device uses the `sim` driver.
    #[serde(default)]
    pub sim: Option<ProbeInstallSim>,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct CmmConfig {
    #[serde(default)]
    pub name: String,
    /// Travel of the linear axes `x`, `y`, `z`: [low, high], metres.
    pub travel_m: BTreeMap<String, [f64; 2]>,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ProbeInstallDevices {
    pub machine: CmmDeviceConfig,
    pub probe: LaserProbeConfig,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct CmmDeviceConfig {
    pub id: String,
    pub driver: DriverKind,
    /// Path feed of the linear axes, m/s.
    pub feed_m_s: f64,
    /// Speed of the rotary axes A and B, rad/s.
    pub rotary_speed_rad_s: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct LaserProbeConfig {
    pub id: String,
    pub driver: DriverKind,
    /// Standard deviation of one reading, metres.
    pub noise_m: f64,
    /// Measuring range of the probe [low, high], metres from its zero point.
    pub range_m: [f64; 2],
    /// Time between readings, seconds.
    pub reading_period_s: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ProbeInstallPlan {
    /// Calibrated radius of the reference sphere, metres.
    pub sphere_radius_m: f64,
    /// Postures (A, B), radians, in measuring order.
    pub postures_rad: Vec<[f64; 2]>,
    /// Sphere points probed at each posture.
    pub points_per_posture: usize,
    /// Points lie on the cap facing the probe, normals within this angle of the beam, radians.
    pub cap_half_angle_rad: f64,
    /// Nominal readings are spread uniformly over ±this (makes the beam direction observable).
    pub reading_half_range_m: f64,
    /// Raw readings taken at each point (all recorded; the method averages them).
    pub readings_per_point: usize,
    /// Seed of the point layout on the cap (the plan is deterministic).
    #[serde(default = "default_plan_seed")]
    pub seed: u64,
    /// The design installation: the plan's machine positions, the LM start, the GA box centre.
    pub nominal: NominalInstall,
    #[serde(default)]
    pub solver: ProbeInstallSolver,
}

fn default_plan_seed() -> u64 {
    1
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct NominalInstall {
    pub b_offset_rad: f64,
    pub y_offset_m: f64,
    pub beam_dir: [f64; 3],
    pub zero_point_m: [f64; 3],
    pub sphere_centre_m: [f64; 3],
}

impl NominalInstall {
    pub fn params(&self) -> InstallParams {
        InstallParams {
            b_offset_rad: self.b_offset_rad,
            y_offset_m: self.y_offset_m,
            beam_dir: self.beam_dir,
            zero_point_m: self.zero_point_m,
            sphere_centre_m: self.sphere_centre_m,
        }
    }
}

/// The improved GA's settings (published: crossover 0.5, mutation 0.05, penalty 1e4).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct ProbeInstallSolver {
    pub ga_population: usize,
    pub ga_generations: usize,
    pub ga_seed: u64,
    pub ga_crossover: f64,
    pub ga_mutation: f64,
    pub penalty: f64,
}

impl Default for ProbeInstallSolver {
    fn default() -> Self {
        Self {
            ga_population: 100,
            ga_generations: 2000,
            ga_seed: 1,
            ga_crossover: 0.5,
            ga_mutation: 0.05,
            penalty: crate::solve::probe_install::PUBLISHED_PENALTY,
        }
    }
}

/// The simulated mis-installation: each error drawn uniformly within ±its size (seeded).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ProbeInstallSim {
    pub seed: u64,
    /// δB, radians.
    pub b_offset_rad: f64,
    /// y32, metres.
    pub y_offset_m: f64,
    /// Tilt of the beam from its design direction (each of two directions), radians.
    pub beam_tilt_rad: f64,
    /// Zero point error per coordinate, metres.
    pub zero_point_m: f64,
    /// Sphere placement error per coordinate, metres.
    pub sphere_centre_m: f64,
    /// Unmodelled effects (outside the 11-parameter model), all off by default.
    #[serde(default)]
    pub effects: ProbeInstallEffects,
}

/// `[sim.effects]` of a `probe_install` world.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct ProbeInstallEffects {
    /// `probe_direction` (DESIGN.md vocabulary), here as a scale error of the probe readings:
    /// the probe reports (1 + size) × the true distance from its zero point along the beam.
    /// The model's beam direction is a unit vector, so it cannot take the scale up.
    pub probe_direction: ProbeDirectionEffect,
}

#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ProbeDirectionEffect {
    #[serde(default)]
    pub enabled: bool,
    /// Relative scale error of the readings (dimensionless, e.g. 3e-3).
    #[serde(default)]
    pub size: f64,
}

impl ProbeInstallEffects {
    /// The reading scale error in force: 0 when the switch is off.
    pub fn reading_scale_error(&self) -> f64 {
        let e = &self.probe_direction;
        if e.enabled {
            e.size
        } else {
            0.0
        }
    }
}

impl ProbeInstallConfig {
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
        for axis in ["x", "y", "z"] {
            let Some(t) = self.machine.travel_m.get(axis) else {
                return Err(invalid(
                    f,
                    &format!("machine.travel_m.{axis}"),
                    "missing: expected [low, high] in metres",
                ));
            };
            if !(t[0].is_finite() && t[1].is_finite() && t[0] < t[1]) {
                return Err(invalid(
                    f,
                    &format!("machine.travel_m.{axis}"),
                    format!("expected finite [low, high] with low < high, got {t:?}"),
                ));
            }
        }
        let m = &self.devices.machine;
        let p = &self.devices.probe;
        sim_drivers_only(
            f,
            KIND,
            &[
                ("devices.machine.driver", m.driver),
                ("devices.probe.driver", p.driver),
            ],
            self.sim.is_some(),
        )?;
        positive(f, "devices.machine.feed_m_s", m.feed_m_s)?;
        positive(
            f,
            "devices.machine.rotary_speed_rad_s",
            m.rotary_speed_rad_s,
        )?;
        positive(f, "devices.probe.noise_m", p.noise_m)?;
        positive(f, "devices.probe.reading_period_s", p.reading_period_s)?;
        if !(p.range_m[0].is_finite() && p.range_m[1].is_finite() && p.range_m[0] < p.range_m[1]) {
            return Err(invalid(
                f,
                "devices.probe.range_m",
                format!(
                    "expected finite [low, high] with low < high, got {:?}",
                    p.range_m
                ),
            ));
        }
        let plan = &self.plan;
        positive(f, "plan.sphere_radius_m", plan.sphere_radius_m)?;
        if plan.postures_rad.is_empty() {
            return Err(invalid(
                f,
                "plan.postures_rad",
                "expected at least one posture [A, B] in radians",
            ));
        }
        for (i, ab) in plan.postures_rad.iter().enumerate() {
            finite(f, &format!("plan.postures_rad[{i}]"), ab)?;
        }
        let readings = plan.postures_rad.len() * plan.points_per_posture;
        if plan.points_per_posture < 4 || readings < 10 {
            return Err(invalid(
                f,
                "plan.points_per_posture",
                format!(
                    "expected at least 4 per posture and 10 in all (11 parameters, one constraint), \
                     got {} x {} postures",
                    plan.points_per_posture,
                    plan.postures_rad.len()
                ),
            ));
        }
        if !(plan.cap_half_angle_rad > 0.0 && plan.cap_half_angle_rad < std::f64::consts::FRAC_PI_2)
        {
            return Err(invalid(
                f,
                "plan.cap_half_angle_rad",
                format!(
                    "expected an angle in (0, π/2) radians, got {}",
                    plan.cap_half_angle_rad
                ),
            ));
        }
        non_negative(f, "plan.reading_half_range_m", plan.reading_half_range_m)?;
        if plan.reading_half_range_m >= p.range_m[1].min(-p.range_m[0]) {
            return Err(invalid(
                f,
                "plan.reading_half_range_m",
                format!(
                    "expected less than the probe's range {:?} m on either side, got {}",
                    p.range_m, plan.reading_half_range_m
                ),
            ));
        }
        if plan.readings_per_point == 0 {
            return Err(invalid(f, "plan.readings_per_point", "expected at least 1"));
        }
        let n = &plan.nominal;
        finite(f, "plan.nominal.beam_dir", &n.beam_dir)?;
        let norm = n.beam_dir.iter().map(|v| v * v).sum::<f64>().sqrt();
        if (norm - 1.0).abs() > 1e-6 {
            return Err(invalid(
                f,
                "plan.nominal.beam_dir",
                format!("expected a unit vector, got norm {norm}"),
            ));
        }
        finite(f, "plan.nominal.zero_point_m", &n.zero_point_m)?;
        finite(f, "plan.nominal.sphere_centre_m", &n.sphere_centre_m)?;
        finite(
            f,
            "plan.nominal.b_offset_rad / y_offset_m",
            &[n.b_offset_rad, n.y_offset_m],
        )?;
        let s = &plan.solver;
        if s.ga_population < 4 || s.ga_generations == 0 {
            return Err(invalid(
                f,
                "plan.solver",
                format!(
                    "expected ga_population >= 4 and ga_generations >= 1, got {} and {}",
                    s.ga_population, s.ga_generations
                ),
            ));
        }
        for (key, v) in [
            ("plan.solver.ga_crossover", s.ga_crossover),
            ("plan.solver.ga_mutation", s.ga_mutation),
        ] {
            if !(0.0..=1.0).contains(&v) {
                return Err(invalid(
                    f,
                    key,
                    format!("expected a probability in [0, 1], got {v}"),
                ));
            }
        }
        positive(f, "plan.solver.penalty", s.penalty)?;
        if let Some(sim) = &self.sim {
            for (key, v) in [
                ("sim.b_offset_rad", sim.b_offset_rad),
                ("sim.y_offset_m", sim.y_offset_m),
                ("sim.beam_tilt_rad", sim.beam_tilt_rad),
                ("sim.zero_point_m", sim.zero_point_m),
                ("sim.sphere_centre_m", sim.sphere_centre_m),
            ] {
                non_negative(f, key, v)?;
            }
            let e = &sim.effects.probe_direction;
            if e.enabled && !(e.size.is_finite() && e.size != 0.0 && e.size.abs() < 0.1) {
                return Err(invalid(
                    f,
                    "sim.effects.probe_direction.size",
                    format!(
                        "expected a non-zero relative scale error within ±0.1 when enabled, got {}",
                        e.size
                    ),
                ));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn example() -> String {
        std::fs::read_to_string(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/config/probe-install.toml"
        ))
        .expect("config/probe-install.toml")
    }

    #[test]
    fn the_example_parses() {
        let c = ProbeInstallConfig::parse(&example(), Path::new("probe-install.toml"))
            .expect("example config");
        assert_eq!(c.plan.postures_rad.len(), 4);
    }

    #[test]
    fn errors_name_file_key_and_expectation() {
        let cases = [
            (
                "sphere_radius_m = 6.0e-3",
                "sphere_radius_m = -1.0",
                "plan.sphere_radius_m",
            ),
            (
                "noise_m = 1.0e-6",
                "noise_m = \"x\"",
                "devices.probe.noise_m",
            ),
            (
                "points_per_posture = 25",
                "points_per_posture = 2",
                "plan.points_per_posture",
            ),
            (
                "beam_dir = [0.0, 0.0, -1.0]",
                "beam_dir = [0.0, 0.0, -2.0]",
                "plan.nominal.beam_dir",
            ),
            (
                "[plan.nominal]",
                "[plan.nominal]\nbogus = 1",
                "plan.nominal",
            ),
        ];
        for (from, to, key) in cases {
            let text = example();
            assert!(text.contains(from), "{from}");
            let err = ProbeInstallConfig::parse(&text.replacen(from, to, 1), Path::new("p.toml"))
                .expect_err(to)
                .to_string();
            assert!(err.starts_with("p.toml: key `"), "{err}");
            assert!(err.contains(key), "{to}: {err}");
        }
    }
}
