//! Configuration of plan kind `probe_install` (DESIGN.md method 5): a 5-axis CMM (X, Y, Z + A, B)
//! with a 1-D laser displacement probe, a reference sphere probed at several postures.

use std::collections::BTreeMap;
use std::path::Path;

use serde::{Deserialize, Serialize};

use geocal_drivers::grbl::{GrblConfig, GrblFaults};
use geocal_drivers::probe::{ProbeConfig, ProbeFaults};

use crate::config::kind_config::{
    expect_kind, finite, invalid, non_negative, parse_strict, positive,
};
pub use crate::config::ProbeDriverKind;
use crate::config::{ConfigError, DriverKind};
use crate::kinds::probe_install::plan::CMM_AXES;
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
    /// The simulated world; required when a device uses the `sim` driver or under `[hil]`.
    #[serde(default)]
    pub sim: Option<ProbeInstallSim>,
    /// Hardware-in-the-loop: the GRBL and ASCII probe emulators on ptys, backed by `[sim]`.
    #[serde(default)]
    pub hil: Option<ProbeInstallHil>,
    /// Declared standard uncertainties of the budget's contributors (docs/uncertainty.md).
    #[serde(default)]
    pub uncertainty: ProbeInstallUncertainty,
    /// The tolerances the report checks against (`[report]`, docs/report.md); the report
    /// reads them from the stored run configuration.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub report: Option<crate::config::report::ReportConfig>,
}

/// `[uncertainty]` of a `probe_install` run: standard uncertainties (k = 1), each in the unit
/// its key ends with; a key left out leaves its contributor out of the budget.
#[derive(Debug, Clone, Copy, Default, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct ProbeInstallUncertainty {
    /// The probe's calibration: relative error of its readings (gain), ppm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub probe_scale_ppm: Option<f64>,
    /// The reference sphere's calibrated radius, m.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sphere_radius_m: Option<f64>,
    /// The reference sphere's form: radial deviation at each probed point, independent, m.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sphere_form_m: Option<f64>,
    /// The CMM's linear scales: relative error of each axis's reading, independent axes, ppm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub machine_scale_ppm: Option<f64>,
}

impl ProbeInstallUncertainty {
    /// Every declared value finite and >= 0; the error names `uncertainty.<key>`.
    fn validate(&self, f: &Path) -> Result<(), ConfigError> {
        for (key, value) in [
            ("probe_scale_ppm", self.probe_scale_ppm),
            ("sphere_radius_m", self.sphere_radius_m),
            ("sphere_form_m", self.sphere_form_m),
            ("machine_scale_ppm", self.machine_scale_ppm),
        ] {
            if let Some(v) = value {
                non_negative(f, &format!("uncertainty.{key}"), v)?;
            }
        }
        Ok(())
    }
}

/// `[hil]` of a `probe_install` run: geocal hosts the GRBL controller emulator (5 axes) and the
/// ASCII probe emulator on pseudo-terminals, backed by the simulated world, and the real
/// drivers (`grbl`, `ascii`) talk to them in real time.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ProbeInstallHil {
    /// Host the emulators (true) or talk to the real devices at their ports (false, the same
    /// as leaving `[hil]` out).
    #[serde(default = "yes")]
    pub emulate: bool,
    /// Faults the GRBL emulator injects (`geocal_drivers::grbl::GrblFaults`).
    #[serde(default)]
    pub machine_faults: GrblFaults,
    /// Faults the probe emulator injects (`geocal_drivers::probe::ProbeFaults`).
    #[serde(default)]
    pub probe_faults: ProbeFaults,
}

fn yes() -> bool {
    true
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct CmmConfig {
    #[serde(default)]
    pub name: String,
    /// The machine's serial number, where declared: with the name, it tells the machine's
    /// runs apart in its history (docs/history.md).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub serial: Option<String>,
    /// A declared machine id: where given, it alone is the machine's identity (name and
    /// serial may then change), docs/fleet.md.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub id: Option<String>,
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
    /// Speed of the rotary axes A and B, rad/s (of the simulated CMM).
    pub rotary_speed_rad_s: f64,
    /// `[devices.machine.grbl]`: the GRBL driver's settings (`geocal_drivers::grbl::GrblConfig`:
    /// `port`, `ack_timeout_s`, `status_interval_s`, `axis_letters`, ...; driver `grbl`). `id` and
    /// `feed_m_s` come from `[devices.machine]`; axes `a` and `b` map to `A` and `B` unless set.
    #[serde(default)]
    pub grbl: Option<GrblConfig>,
    /// Pause between two state polls of a real (or emulated) machine, seconds.
    #[serde(default = "default_poll_interval")]
    pub poll_interval_s: f64,
}

fn default_poll_interval() -> f64 {
    0.01
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct LaserProbeConfig {
    pub id: String,
    /// `sim` or `ascii` (a line-oriented request/response displacement sensor).
    pub driver: ProbeDriverKind,
    /// Standard deviation of one reading, metres.
    pub noise_m: f64,
    /// Measuring range of the probe [low, high], metres from its zero point.
    pub range_m: [f64; 2],
    /// Time between readings, seconds.
    pub reading_period_s: f64,
    /// `[devices.probe.ascii]`: the ASCII driver's settings (`geocal_drivers::probe::ProbeConfig`:
    /// `port`, `command`, `value_pattern`, `error_pattern`, `scale_to_m`, `timeout_s`, ...;
    /// driver `ascii`). `id` comes from `[devices.probe]`.
    #[serde(default)]
    pub ascii: Option<ProbeConfig>,
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
    /// `reading_scale` (the diagnosis's library, docs/diagnosis.md): the probe reports
    /// (1 + k) × the true distance; adds to `probe_direction`'s size.
    pub reading_scale: f64,
    /// `a_axis_tilt`: the A axis turns about (1, 0, τ) instead of (1, 0, 0), τ in radians.
    pub a_axis_tilt_rad: f64,
    /// `sphere_form`: the reference sphere's radius varies with the direction n from its
    /// centre by Σ c_k Y_k(n), the 12 real harmonics of degree 2 and 3 in the order of
    /// docs/diagnosis.md (metres; fewer given: the rest 0).
    pub sphere_form_m: Vec<f64>,
    /// `thermal_drift`: the sphere moves against the machine by v × t (m/s, x y z).
    pub thermal_drift_m_per_s: [f64; 3],
    /// Out of the library: the machine's x scale has a periodic error, the true x =
    /// reported x + a sin(2π x / 1 mm) (metres).
    pub x_periodic_error_m: f64,
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
        let direction = if e.enabled { e.size } else { 0.0 };
        direction + self.reading_scale
    }
}

/// What a driver's settings check says, without the device id it prefixes.
fn driver_message(e: geocal_drivers::DeviceError) -> String {
    use geocal_drivers::DeviceError::{Protocol, Rejected};
    match e {
        Protocol { message, .. } | Rejected { message, .. } => message,
        other => other.to_string(),
    }
}

impl ProbeInstallConfig {
    /// True when the run hosts its own emulators (`[hil] emulate = true`).
    pub fn emulated(&self) -> bool {
        self.hil.as_ref().is_some_and(|h| h.emulate)
    }

    /// True when both devices are the simulated ones (a run in virtual time).
    pub fn all_sim(&self) -> bool {
        self.devices.machine.driver == DriverKind::Sim
            && self.devices.probe.driver == ProbeDriverKind::Sim
    }

    /// The GRBL driver's settings: `[devices.machine.grbl]` (defaults when emulated and left
    /// out) with `id` and `feed_m_s` from `[devices.machine]`, and axes `a`, `b` mapped to the
    /// letters `A`, `B` unless the table maps them.
    pub fn grbl_config(&self) -> GrblConfig {
        let m = &self.devices.machine;
        let mut c = m.grbl.clone().unwrap_or_default();
        c.id = m.id.clone();
        c.feed_m_s = m.feed_m_s;
        for (axis, letter) in [("a", 'A'), ("b", 'B')] {
            c.axis_letters.entry(axis.to_string()).or_insert(letter);
        }
        c
    }

    /// The ASCII probe driver's settings, `id` from `[devices.probe]`.
    pub fn probe_config(&self) -> ProbeConfig {
        let p = &self.devices.probe;
        let mut c = p.ascii.clone().unwrap_or_default();
        c.id = p.id.clone();
        c
    }

    /// Driver kinds, their settings, `[hil]` and `[sim]`: the first problem found.
    fn validate_drivers(&self, f: &Path) -> Result<(), ConfigError> {
        let m = &self.devices.machine;
        let p = &self.devices.probe;
        let emulate = self.emulated();
        if !matches!(m.driver, DriverKind::Sim | DriverKind::Grbl) {
            return Err(invalid(
                f,
                "devices.machine.driver",
                format!(
                    "expected \"sim\" or \"grbl\" (a 5-axis controller streamed as G-code), found \"{}\"",
                    m.driver.as_str()
                ),
            ));
        }
        let machine_sim = m.driver == DriverKind::Sim;
        let probe_sim = p.driver == ProbeDriverKind::Sim;
        if machine_sim != probe_sim {
            return Err(invalid(
                f,
                "devices.probe.driver",
                format!(
                    "expected {} like devices.machine.driver = \"{}\": a run is either simulated in \
                     virtual time (both \"sim\") or on real or emulated devices (\"grbl\" and \"ascii\")",
                    if machine_sim { "\"sim\"" } else { "\"ascii\"" },
                    m.driver.as_str()
                ),
            ));
        }
        if emulate && machine_sim {
            return Err(invalid(
                f,
                "hil.emulate",
                "emulation serves the GRBL controller and the ASCII probe: expected \
                 devices.machine.driver = \"grbl\" and devices.probe.driver = \"ascii\"",
            ));
        }
        if m.grbl.is_some() && m.driver != DriverKind::Grbl {
            return Err(invalid(
                f,
                "devices.machine.grbl",
                format!(
                    "settings for driver \"grbl\", but devices.machine.driver is \"{}\"",
                    m.driver.as_str()
                ),
            ));
        }
        if p.ascii.is_some() && p.driver != ProbeDriverKind::Ascii {
            return Err(invalid(
                f,
                "devices.probe.ascii",
                "settings for driver \"ascii\", but devices.probe.driver is \"sim\"",
            ));
        }
        if m.driver == DriverKind::Grbl {
            if m.grbl.is_none() && !emulate {
                return Err(invalid(
                    f,
                    "devices.machine.grbl",
                    "driver \"grbl\" needs [devices.machine.grbl] with at least `port` (the \
                     controller's serial device), or [hil] emulate = true",
                ));
            }
            let c = self.grbl_config();
            c.validate()
                .map_err(|e| invalid(f, "devices.machine.grbl", driver_message(e)))?;
            let mut used = Vec::new();
            for (axis, letter) in &c.axis_letters {
                let l = letter.to_ascii_uppercase();
                if !"XYZABC".contains(l) || used.contains(&l) {
                    return Err(invalid(
                        f,
                        &format!("devices.machine.grbl.axis_letters.{axis}"),
                        format!(
                            "expected a distinct axis letter X, Y, Z, A, B or C, found {letter:?}"
                        ),
                    ));
                }
                used.push(l);
            }
            if let Some(axis) = CMM_AXES.iter().find(|a| !c.axis_letters.contains_key(**a)) {
                return Err(invalid(
                    f,
                    "devices.machine.grbl.axis_letters",
                    format!(
                        "expected a letter for every CMM axis (x, y, z, a, b); `{axis}` has none"
                    ),
                ));
            }
            positive(f, "devices.machine.poll_interval_s", m.poll_interval_s)?;
        }
        if p.driver == ProbeDriverKind::Ascii {
            if p.ascii.is_none() && !emulate {
                return Err(invalid(
                    f,
                    "devices.probe.ascii",
                    "driver \"ascii\" needs [devices.probe.ascii] with at least `port` (the \
                     sensor's serial device), or [hil] emulate = true",
                ));
            }
            self.probe_config()
                .protocol()
                .map_err(|e| invalid(f, "devices.probe.ascii", driver_message(e)))?;
            let t = self.probe_config().timeout_s;
            positive(f, "devices.probe.ascii.timeout_s", t)?;
        }
        if let Some(h) = &self.hil {
            for (key, v) in [
                (
                    "hil.machine_faults.drop_ok_probability",
                    h.machine_faults.drop_ok_probability,
                ),
                (
                    "hil.machine_faults.error_probability",
                    h.machine_faults.error_probability,
                ),
                (
                    "hil.probe_faults.garbage_probability",
                    h.probe_faults.garbage_probability,
                ),
                (
                    "hil.probe_faults.no_answer_probability",
                    h.probe_faults.no_answer_probability,
                ),
            ] {
                if !(0.0..=1.0).contains(&v) {
                    return Err(invalid(
                        f,
                        key,
                        format!("expected a probability in [0, 1], found {v}"),
                    ));
                }
            }
        }
        if (machine_sim || emulate) && self.sim.is_none() {
            return Err(invalid(
                f,
                "sim",
                "the `sim` drivers and [hil] emulation need a [sim] table (the simulated world)",
            ));
        }
        Ok(())
    }

    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        Self::parse(&crate::config::kind_config::read(path)?, path)
    }

    pub fn parse(text: &str, file: &Path) -> Result<Self, ConfigError> {
        let c: Self = parse_strict(text, file)?;
        c.validate(file)?;
        Ok(c)
    }

    fn validate(&self, f: &Path) -> Result<(), ConfigError> {
        expect_kind(f, &self.kind, KIND)?;
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
        self.validate_drivers(f)?;
        self.uncertainty.validate(f)?;
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

    /// The example with the real drivers instead of the simulated ones.
    fn real() -> String {
        example()
            .replace(
                "driver = \"sim\"                 # or \"grbl\"",
                "driver = \"grbl\" #",
            )
            .replace(
                "driver = \"sim\"                 # or \"ascii\"",
                "driver = \"ascii\" #",
            )
    }

    #[test]
    fn real_drivers_need_their_ports_unless_emulated() {
        let parse = |text: &str| ProbeInstallConfig::parse(text, Path::new("p.toml"));
        let err = parse(&real()).expect_err("no ports").to_string();
        assert!(
            err.contains("key `devices.machine.grbl`: driver \"grbl\" needs"),
            "{err}"
        );
        let with_ports = real()
            .replace(
                "[devices.probe]",
                "[devices.machine.grbl]\nport = \"/dev/ttyUSB0\"\n[devices.probe]",
            )
            .replace(
                "[plan]",
                "[devices.probe.ascii]\nport = \"/dev/ttyUSB1\"\ncommand = \"MEAS?\\n\"\n\
                 value_pattern = '^MEASURE=(-?[0-9.]+)$'\nscale_to_m = 1e-6\n[plan]",
            );
        let c = parse(&with_ports).expect("real devices");
        assert!(!c.all_sim() && !c.emulated());
        let grbl = c.grbl_config();
        assert_eq!((grbl.id.as_str(), grbl.feed_m_s), ("cmm", 0.02));
        assert_eq!((grbl.axis_letters["a"], grbl.axis_letters["b"]), ('A', 'B'));
        let probe = c.probe_config();
        assert_eq!(
            (probe.id.as_str(), probe.port.as_str()),
            ("laser0", "/dev/ttyUSB1")
        );
        assert_eq!(probe.scale_to_m, 1e-6);
        // A real run needs no [sim]; emulated ones do, and leave the ports out.
        let no_sim = &with_ports[..with_ports.find("\n[sim]").expect("[sim]")];
        parse(no_sim).expect("real devices without [sim]");
        let emulated = real() + "\n[hil]\nmachine_faults = { drop_ok_at_lines = [3] }\n";
        let c = parse(&emulated).expect("emulated");
        assert!(c.emulated());

        let cases = [
            (
                "[devices.probe]",
                "[devices.machine.grbl]\nbaud = 9600\n[devices.probe]",
                "missing field `port`",
            ),
            (
                "[devices.probe]",
                "[devices.machine.grbl]\nport = \"p\"\nack_timeout_s = -1.0\n[devices.probe]",
                "key `devices.machine.grbl`: ack_timeout_s must be between 0 and 1e6 s",
            ),
            (
                "[plan]",
                "[devices.probe.ascii]\nport = \"p\"\nvalue_pattern = \"no group\"\n[plan]",
                "key `devices.probe.ascii`: value pattern must have a capture group",
            ),
            (
                "[plan]",
                "[devices.probe.ascii]\nport = \"p\"\nbogus = 1\n[plan]",
                "unknown field `bogus`",
            ),
            (
                "[plan]",
                "[plan]",
                "key `devices.probe.ascii`: driver \"ascii\" needs [devices.probe.ascii]",
            ),
        ];
        let grbl_ok = real().replace(
            "[devices.probe]",
            "[devices.machine.grbl]\nport = \"p\"\n[devices.probe]",
        );
        for (from, to, want) in cases {
            let base = if to.contains("[devices.machine.grbl]") {
                real()
            } else {
                grbl_ok.clone()
            };
            let err = parse(&base.replacen(from, to, 1))
                .expect_err(to)
                .to_string();
            assert!(err.starts_with("p.toml: key `"), "{err}");
            assert!(err.contains(want), "{to}: {err}");
        }
    }

    #[test]
    fn emulation_needs_the_real_drivers_and_the_sim_world() {
        let parse = |text: &str| ProbeInstallConfig::parse(text, Path::new("p.toml"));
        let err = parse(&(example() + "\n[hil]\n"))
            .expect_err("sim + hil")
            .to_string();
        assert!(err.contains("key `hil.emulate`"), "{err}");
        let text = real();
        let without_sim = format!("{}\n[hil]\n", &text[..text.find("\n[sim]").expect("[sim]")]);
        let err = parse(&without_sim).expect_err("no [sim]").to_string();
        assert!(err.contains("key `sim`"), "{err}");
        let err = parse(&(real() + "\n[hil]\nprobe_faults = { garbage_probability = 2.0 }\n"))
            .expect_err("probability")
            .to_string();
        assert!(
            err.contains("key `hil.probe_faults.garbage_probability`"),
            "{err}"
        );
    }
}
