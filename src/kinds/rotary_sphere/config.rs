//! Configuration of plan kind `rotary_sphere` (a reference sphere on a rotary table, probed at
//! every commanded angle on several heights): its own strict TOML schema and validation.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::config::{ConfigError, DriverKind, RotaryTableConfig};

pub const KIND: &str = "rotary_sphere";

/// The `kind` of a configuration file, read before its schema is chosen (None when absent).
pub fn peek_kind(path: &Path) -> Result<Option<String>, ConfigError> {
    let text = crate::config::kind_config::read(path)?;
    let value: toml::Table = toml::from_str(&text).map_err(|e| ConfigError::Parse {
        file: path.to_path_buf(),
        key: "(document)".into(),
        message: crate::config::kind_config::toml_error_text(&text, &e),
    })?;
    Ok(value
        .get("kind")
        .and_then(|k| k.as_str())
        .map(str::to_string))
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct RotarySphereConfig {
    /// Must be `rotary_sphere`.
    pub kind: String,
    #[serde(default)]
    pub machine: SphereMachineConfig,
    pub devices: SphereDevicesConfig,
    pub plan: SpherePlanConfig,
    /// The simulated world; required when a device uses the `sim` driver.
    #[serde(default)]
    pub sim: Option<SphereSimConfig>,
    /// Hardware-in-the-loop: the probe's ASCII emulator on a pty, backed by `[sim]`.
    #[serde(default)]
    pub hil: Option<SphereHilConfig>,
    /// Declared standard uncertainties of the budget's contributors (docs/uncertainty.md).
    #[serde(default)]
    pub uncertainty: SphereUncertainty,
    /// The tolerances the report checks against (`[report]`, docs/report.md); the report
    /// reads them from the stored run configuration.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub report: Option<crate::config::report::ReportConfig>,
}

/// `[uncertainty]` of a rotary_sphere run: standard uncertainties (k = 1), each in the unit
/// its key ends with; a key left out leaves its contributor out of the budget.
#[derive(Debug, Clone, Copy, Default, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct SphereUncertainty {
    /// The probe's calibration: relative error of its readings (gain), ppm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub probe_scale_ppm: Option<f64>,
    /// The reference sphere's calibrated radius, m.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sphere_radius_m: Option<f64>,
    /// The reference sphere's form: radial deviation at each point of its surface, independent
    /// between points, m.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sphere_form_m: Option<f64>,
}

impl SphereUncertainty {
    /// Every declared value finite and >= 0, else the key `uncertainty.<key>` and why.
    fn validate(&self) -> Result<(), (&'static str, String)> {
        for (key, value) in [
            ("uncertainty.probe_scale_ppm", self.probe_scale_ppm),
            ("uncertainty.sphere_radius_m", self.sphere_radius_m),
            ("uncertainty.sphere_form_m", self.sphere_form_m),
        ] {
            if let Some(v) = value.filter(|v| !(v.is_finite() && *v >= 0.0)) {
                return Err((
                    key,
                    format!("expected a standard uncertainty >= 0, found {v}"),
                ));
            }
        }
        Ok(())
    }
}

#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SphereMachineConfig {
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
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SphereDevicesConfig {
    pub rotary_table: RotaryTableConfig,
    pub probe: ProbeDeviceConfig,
}

pub use crate::config::ProbeDriverKind;

/// The probe: a displacement sensor on a probing arm; one reading per probed point.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ProbeDeviceConfig {
    /// Id on the `/probe/<id>/reading` topic.
    pub id: String,
    pub driver: ProbeDriverKind,
    /// Repeatability of one reading along the probing direction (1 σ), metres.
    pub noise_m: f64,
    /// `[devices.probe.ascii]`: the driver's settings (port, command, value_pattern,
    /// scale_to_m, ...; driver `ascii`; `id` comes from here).
    #[serde(default)]
    pub ascii: Option<geocal_drivers::probe::ProbeConfig>,
}

/// One height of the sphere on its stand above the table.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SphereHeightConfig {
    /// Nominal sphere centre at commanded angle 0, metres (frame: nominal axis = z).
    pub sphere_m: [f64; 3],
    #[serde(default)]
    pub role: HeightRole,
}

#[derive(Debug, Clone, Copy, Default, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum HeightRole {
    /// Used to identify the axis.
    #[default]
    Fit,
    /// Kept out of the fit; its centres are predicted and compared.
    Validation,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SpherePlanConfig {
    /// Id of the table (must equal `devices.rotary_table.id`).
    pub table: String,
    /// Calibrated radius of the reference sphere, metres.
    pub sphere_radius_m: f64,
    /// Probed points per sphere (≥ 5: the top pole, four equator poles, then rings).
    pub points: usize,
    /// Readings averaged per point (the paper repeats each sphere three times).
    #[serde(default = "default_one")]
    pub readings_per_point: usize,
    /// Distance from the nominal surface at which the probe starts its approach, metres.
    pub standoff_m: f64,
    /// Commanded angles: first (default 0), step and count, radians.
    #[serde(default)]
    pub start_rad: f64,
    pub step_rad: f64,
    pub count: usize,
    /// Heights in measuring order; at least two with role `fit`.
    pub heights: Vec<SphereHeightConfig>,
    /// Highest harmonic order the solver may choose per error (by BIC).
    #[serde(default = "default_max_order")]
    pub max_harmonic_order: usize,
    /// Longest wait for the table to report in position, seconds.
    #[serde(default = "default_in_position_timeout")]
    pub in_position_timeout_s: f64,
    /// Pause between table state polls on real devices, seconds.
    #[serde(default = "default_poll")]
    pub poll_interval_s: f64,
}

fn default_one() -> usize {
    1
}
fn default_max_order() -> usize {
    8
}
fn default_in_position_timeout() -> f64 {
    600.0
}
fn default_poll() -> f64 {
    0.1
}

impl SpherePlanConfig {
    pub fn angles_rad(&self) -> Vec<f64> {
        (0..self.count)
            .map(|k| self.start_rad + self.step_rad * k as f64)
            .collect()
    }
}

/// Truth of the simulated table and sphere.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SphereSimConfig {
    pub seed: u64,
    /// Highest harmonic of the true motion errors (realistic sizes: location tens of µm and
    /// µrad, radial/axial motion a few µm, tilt a few µrad, positioning some arcseconds).
    #[serde(default = "default_truth_order")]
    pub harmonics: usize,
    /// Standard deviation of the true sphere position from its nominal, per coordinate, m.
    #[serde(default = "default_placement")]
    pub sphere_placement_m: f64,
    /// Table speed, rad/s, and settling time after a rotation, s.
    #[serde(default = "default_speed")]
    pub speed_rad_s: f64,
    #[serde(default = "default_settle")]
    pub settle_s: f64,
    /// Time the arm needs to probe one point, s; to remount the sphere at a new height, s.
    #[serde(default = "default_point_time")]
    pub point_time_s: f64,
    #[serde(default = "default_remount")]
    pub remount_s: f64,
    /// Unmodelled effects, withheld from the solve's model (the diagnosis's library,
    /// docs/diagnosis.md "rotary_sphere"). `probe_lobing`: the probe reads off by
    /// A (cos(3 az) cos(el) + 0.6 (cos² el − 1/2)), (az, el) of the probing direction (metres).
    #[serde(default)]
    pub probe_lobing_m: f64,
    /// `sphere_form`: the sphere's radius varies by Σ c_k Y_k(n) with n in the sphere's own
    /// frame (turning with the table), the 10 non-zonal harmonics of degree 2 and 3 in the
    /// order of docs/diagnosis.md (metres; fewer given: the rest 0).
    #[serde(default)]
    pub sphere_form_m: Vec<f64>,
    /// `thermal_drift`: the sphere (with the axis) moves by v × t (m/s, x y z).
    #[serde(default)]
    pub thermal_drift_m_per_s: [f64; 3],
    /// Out of the library: the probe vibrates, every reading off by a sin(2π t / 7.3 s)
    /// (metres).
    #[serde(default)]
    pub probe_vibration_m: f64,
}

fn default_truth_order() -> usize {
    4
}
fn default_placement() -> f64 {
    5e-4
}
fn default_speed() -> f64 {
    0.2
}
fn default_settle() -> f64 {
    2.0
}
fn default_point_time() -> f64 {
    3.0
}
fn default_remount() -> f64 {
    600.0
}

#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SphereHilConfig {
    /// Host the probe's ASCII emulator on a pty (backed by `[sim]`) and read it with the real
    /// driver (`devices.probe.driver = "ascii"`); a `modbus_tcp` / `modbus_rtu` table gets the
    /// Modbus table emulator (127.0.0.1 / a pty) backed by the same world.
    pub emulate: bool,
    #[serde(default)]
    pub probe_faults: geocal_drivers::probe::ProbeFaults,
    /// Faults of the Modbus table emulator hosted for a `modbus_tcp` / `modbus_rtu` table.
    #[serde(default)]
    pub table_faults: geocal_drivers::modbus_table::ModbusTableFaults,
}

impl RotarySphereConfig {
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        Self::parse(&crate::config::kind_config::read(path)?, path)
    }

    /// Parse and validate configuration text; `file` names it in errors.
    pub fn parse(text: &str, file: &Path) -> Result<Self, ConfigError> {
        let config: Self = crate::config::kind_config::parse_strict(text, file)?;
        config
            .validate()
            .map_err(|(key, message)| ConfigError::Invalid {
                file: file.to_path_buf(),
                key: key.into(),
                message,
            })?;
        Ok(config)
    }

    /// The keys and what they should be; the first problem found.
    fn validate(&self) -> Result<(), (&'static str, String)> {
        let plan = &self.plan;
        let positive = |key: &'static str, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err((key, format!("expected a positive number, found {v}")))
            }
        };
        if self.kind != KIND {
            return Err((
                "kind",
                format!("expected \"{KIND}\", found {:?}", self.kind),
            ));
        }
        if plan.table != self.devices.rotary_table.id {
            return Err((
                "plan.table",
                format!(
                    "expected the id of devices.rotary_table ({:?}), found {:?}",
                    self.devices.rotary_table.id, plan.table
                ),
            ));
        }
        self.uncertainty.validate()?;
        positive("plan.sphere_radius_m", plan.sphere_radius_m)?;
        positive("plan.standoff_m", plan.standoff_m)?;
        positive("plan.in_position_timeout_s", plan.in_position_timeout_s)?;
        if !(plan.poll_interval_s.is_finite() && plan.poll_interval_s >= 0.0) {
            return Err((
                "plan.poll_interval_s",
                format!("expected seconds ≥ 0, found {}", plan.poll_interval_s),
            ));
        }
        if plan.points < 5 {
            return Err((
                "plan.points",
                format!(
                    "expected at least 5 points per sphere (the top pole and four equator \
                     poles), found {}",
                    plan.points
                ),
            ));
        }
        if plan.readings_per_point == 0 {
            return Err(("plan.readings_per_point", "expected at least 1".into()));
        }
        if plan.count < 3 {
            return Err((
                "plan.count",
                format!("expected at least 3 commanded angles, found {}", plan.count),
            ));
        }
        if !plan.start_rad.is_finite() {
            return Err((
                "plan.start_rad",
                "expected a finite angle in radians".into(),
            ));
        }
        positive("plan.step_rad", plan.step_rad)?;
        // Distinct angles: the per-angle motion errors and the harmonic fit need them.
        if plan.step_rad * (plan.count - 1) as f64 >= std::f64::consts::TAU - 1e-9 {
            return Err((
                "plan.step_rad",
                format!(
                    "expected {} distinct angles within one turn: step × (count − 1) must be \
                     below 2π rad",
                    plan.count
                ),
            ));
        }
        let fit = plan
            .heights
            .iter()
            .filter(|h| h.role == HeightRole::Fit)
            .count();
        if fit < 2 {
            return Err((
                "plan.heights",
                format!(
                    "expected at least 2 heights with role \"fit\" (tilts need two heights), \
                     found {fit}"
                ),
            ));
        }
        for h in &plan.heights {
            if h.sphere_m.iter().any(|v| !v.is_finite()) {
                return Err(("plan.heights.sphere_m", "expected finite metres".into()));
            }
            if h.sphere_m[0].hypot(h.sphere_m[1]) <= plan.sphere_radius_m {
                return Err((
                    "plan.heights.sphere_m",
                    format!(
                        "expected the sphere off the axis (radius from the axis > sphere \
                         radius {} m), found {:?}",
                        plan.sphere_radius_m, h.sphere_m
                    ),
                ));
            }
        }
        if plan.max_harmonic_order > (plan.count - 1) / 2 {
            return Err((
                "plan.max_harmonic_order",
                format!(
                    "expected at most (count − 1) / 2 = {} for {} angles, found {}",
                    (plan.count - 1) / 2,
                    plan.count,
                    plan.max_harmonic_order
                ),
            ));
        }
        let probe = &self.devices.probe;
        positive("devices.probe.noise_m", probe.noise_m)?;
        let emulate = self.hil.as_ref().is_some_and(|h| h.emulate);
        match probe.driver {
            ProbeDriverKind::Ascii if probe.ascii.is_none() && !emulate => {
                return Err((
                    "devices.probe.ascii",
                    "driver \"ascii\" needs [devices.probe.ascii] with at least `port`".into(),
                ))
            }
            ProbeDriverKind::Sim if emulate => {
                return Err((
                    "hil.emulate",
                    "emulation serves the ASCII probe: expected devices.probe.driver = \"ascii\""
                        .into(),
                ))
            }
            _ => {}
        }
        if let Some(ascii) = &probe.ascii {
            ascii
                .protocol()
                .map_err(|e| ("devices.probe.ascii", e.to_string()))?;
        }
        let table_sim = self.devices.rotary_table.driver == DriverKind::Sim;
        let table = &self.devices.rotary_table;
        match table.driver {
            DriverKind::Sim => {}
            DriverKind::ModbusTcp | DriverKind::ModbusRtu => {
                if table.modbus.is_none() {
                    return Err((
                        "devices.rotary_table.modbus",
                        format!(
                            "driver \"{}\" needs [devices.rotary_table.modbus] (register map)",
                            table.driver.as_str()
                        ),
                    ));
                }
                if self.sim.is_some() && !emulate {
                    return Err((
                        "devices.rotary_table.driver",
                        "a Modbus table with [sim] needs [hil] emulate = true (the emulator \
                         backed by the simulated world); without [sim] the table is real"
                            .into(),
                    ));
                }
            }
            other => {
                return Err((
                    "devices.rotary_table.driver",
                    format!(
                        "expected \"sim\", \"modbus_tcp\" or \"modbus_rtu\", found \"{}\"",
                        other.as_str()
                    ),
                ))
            }
        }
        if (table_sim || probe.driver == ProbeDriverKind::Sim || emulate) && self.sim.is_none() {
            return Err((
                "sim",
                "a `sim` device or [hil] emulation needs the [sim] section".into(),
            ));
        }
        if let Some(sim) = &self.sim {
            positive("sim.speed_rad_s", sim.speed_rad_s)?;
            for (key, v) in [
                ("sim.sphere_placement_m", sim.sphere_placement_m),
                ("sim.settle_s", sim.settle_s),
                ("sim.point_time_s", sim.point_time_s),
                ("sim.remount_s", sim.remount_s),
            ] {
                if !(v.is_finite() && v >= 0.0) {
                    return Err((key, format!("expected a number ≥ 0, found {v}")));
                }
            }
            // The probe must still meet the sphere when it is misplaced by a few σ.
            if 5.0 * sim.sphere_placement_m >= plan.standoff_m.min(plan.sphere_radius_m) {
                return Err((
                    "sim.sphere_placement_m",
                    format!(
                        "expected well below the standoff ({} m): 5 σ must stay inside it",
                        plan.standoff_m
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

    #[test]
    fn the_example_config_is_valid() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rotary-sphere.toml");
        let c = RotarySphereConfig::load(&path).expect("example config");
        assert_eq!(c.plan.angles_rad().len(), 36);
        assert_eq!(peek_kind(&path).expect("kind").as_deref(), Some(KIND));
    }

    #[test]
    fn a_modbus_table_needs_its_map_and_with_sim_the_emulator() {
        let text = include_str!("../../../config/rotary-sphere.toml").replacen(
            "id = \"c\"\ndriver = \"sim\"",
            "id = \"c\"\ndriver = \"modbus_tcp\"",
            1,
        );
        let err = |t: &str| {
            RotarySphereConfig::parse(t, Path::new("s.toml"))
                .expect_err("invalid")
                .to_string()
        };
        let e = err(&text);
        assert!(
            e.contains("key `devices.rotary_table.modbus`") && e.contains("register map"),
            "{e}"
        );
        let with_map = text.replace(
            "[plan]",
            "[devices.rotary_table.modbus]\n[devices.rotary_table.modbus.map]\nunit_id = 1\n\
             target = { address = 100, width_bits = 32, word_order = \"big\", counts_per_rad = 1e7 }\n\
             actual = { address = 200, kind = \"input\", width_bits = 32, word_order = \"big\", counts_per_rad = 1e7 }\n\
             status = { address = 300, kind = \"input\", in_position_bit = 0, moving_bit = 1, fault_bit = 2 }\n\
             command = { address = 110, go_value = 1, clear_value = 0 }\nack = { bit = 3 }\n\n[plan]",
        );
        let e = err(&with_map);
        assert!(
            e.contains("key `devices.rotary_table.driver`") && e.contains("[hil] emulate = true"),
            "{e}"
        );
    }
}
