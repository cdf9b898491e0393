//! Configuration of plan kind `hexapod` (DESIGN.md method 6): a 6-leg parallel machine with
//! universal joints, its design hinges, leg encoders, a pose sensor and the poses to visit.

use std::path::Path;

use serde::{Deserialize, Serialize};

use geocal_drivers::modbus::ModbusFaults;
use geocal_drivers::modbus_hexapod::ModbusHexapodConfig;

use crate::config::kind_config::{
    expect_kind, finite, invalid, non_negative, parse_strict, positive,
};
use crate::config::ConfigError;
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
    /// Host the hexapod's Modbus emulator backed by `[sim]` and run the real driver on it.
    #[serde(default)]
    pub hil: Option<HexapodHil>,
    /// Declared standard uncertainties of the budget's contributors (docs/uncertainty.md).
    #[serde(default)]
    pub uncertainty: HexapodUncertainty,
    /// The tolerances the report checks against (`[report]`, docs/report.md); the report
    /// reads them from the stored run configuration.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub report: Option<crate::config::report::ReportConfig>,
}

/// `[uncertainty]` of a hexapod run: standard uncertainties (k = 1), each in the unit its key
/// ends with; a key left out leaves its contributor out of the budget.
#[derive(Debug, Clone, Copy, Default, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct HexapodUncertainty {
    /// The pose sensor's length calibration: relative error of the measured translations, ppm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pose_scale_ppm: Option<f64>,
    /// The leg encoders' calibration: relative error of the measured length changes, ppm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub leg_scale_ppm: Option<f64>,
}

impl HexapodUncertainty {
    /// Every declared value finite and >= 0; the error names `uncertainty.<key>`.
    fn validate(&self, f: &Path) -> Result<(), ConfigError> {
        for (key, value) in [
            ("pose_scale_ppm", self.pose_scale_ppm),
            ("leg_scale_ppm", self.leg_scale_ppm),
        ] {
            if let Some(v) = value {
                non_negative(f, &format!("uncertainty.{key}"), v)?;
            }
        }
        Ok(())
    }
}

/// `[hil]` of a hexapod run: the Modbus hexapod emulator on 127.0.0.1 (TCP) or a pty (RTU),
/// backed by the simulated hexapod; the driver of `devices.hexapod.driver` talks to it.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct HexapodHil {
    /// Host the emulator (true) or talk to the real controller at its transport (false, the
    /// same as leaving `[hil]` out).
    #[serde(default = "yes")]
    pub emulate: bool,
    /// Faults the emulator injects (`geocal_drivers::modbus::ModbusFaults`, requests from 1).
    #[serde(default)]
    pub hexapod_faults: ModbusFaults,
}

fn yes() -> bool {
    true
}

/// The hexapod's driver.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum HexapodDriver {
    /// The simulated hexapod in virtual time (needs `[sim]`).
    Sim,
    /// A controller over Modbus TCP (`[devices.hexapod.modbus]`).
    ModbusTcp,
    /// A controller over Modbus RTU on a serial port.
    ModbusRtu,
}

impl HexapodDriver {
    pub fn as_str(self) -> &'static str {
        match self {
            HexapodDriver::Sim => "sim",
            HexapodDriver::ModbusTcp => "modbus_tcp",
            HexapodDriver::ModbusRtu => "modbus_rtu",
        }
    }
}

/// Where the measured platform poses come from.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum PoseSensorDriver {
    /// The simulated instrument (needs `[sim]`), with `noise_m` / `noise_rad`.
    Sim,
    /// The commanded poses, recorded as measured and taken as exact (no instrument).
    Given,
}

impl PoseSensorDriver {
    pub fn as_str(self) -> &'static str {
        match self {
            PoseSensorDriver::Sim => "sim",
            PoseSensorDriver::Given => "given",
        }
    }
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct HexapodMachine {
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
    pub driver: HexapodDriver,
    /// Standard deviation of one leg encoder reading, metres (the solver's noise model).
    pub encoder_noise_m: f64,
    /// The simulated hexapod's motion and reading period (ignored by a real controller).
    #[serde(default = "default_speed")]
    pub speed_m_s: f64,
    #[serde(default = "default_angular_speed")]
    pub angular_speed_rad_s: f64,
    #[serde(default = "default_reading_period")]
    pub reading_period_s: f64,
    /// Driver settings of `modbus_tcp` / `modbus_rtu`
    /// (`geocal_drivers::modbus_hexapod::ModbusHexapodConfig`; `id` comes from here).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub modbus: Option<ModbusHexapodConfig>,
}

fn default_speed() -> f64 {
    0.01
}
fn default_angular_speed() -> f64 {
    0.05
}
fn default_reading_period() -> f64 {
    0.01
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct PoseSensorConfig {
    pub id: String,
    pub driver: PoseSensorDriver,
    /// Standard deviation per translation coordinate, metres (`sim`, in the solver's weights; 0 for `given`).
    #[serde(default)]
    pub noise_m: f64,
    /// Standard deviation per rotation-vector component, radians (`sim`, in the solver's weights; 0 for `given`).
    #[serde(default)]
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
    /// Unmodelled effects in the simulated world, withheld from the solve's model (the
    /// diagnosis's library, docs/diagnosis.md "hexapod"). `leg_scale`: leg i's encoder reads
    /// (1 + k_i) × its change since home.
    #[serde(default)]
    pub leg_scale: [f64; 6],
    /// `leg_backlash`: leg i's reading is off by b_i (m) × the sign of its last motion.
    #[serde(default)]
    pub leg_backlash_m: [f64; 6],
    /// `sensor_drift`: the pose sensor's reading drifts by v × t (t since power-on): m/s for
    /// x, y, z, rad/s for the rotation vector's components.
    #[serde(default)]
    pub sensor_drift: [f64; 6],
    /// Out of the library: the platform deflects elastically with its pose: each leg's
    /// length grows by sag × (tilt / 0.1 rad)² × the leg direction's vertical component
    /// (metres at a 0.1 rad tilt).
    #[serde(default)]
    pub platform_sag_m: f64,
}

impl HexapodConfig {
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
        self.uncertainty.validate(f)?;
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
        if let Some(s) = &self.devices.pose_sensor {
            non_negative(f, "devices.pose_sensor.noise_m", s.noise_m)?;
            non_negative(f, "devices.pose_sensor.noise_rad", s.noise_rad)?;
        }
        self.validate_devices(f)?;
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

impl HexapodConfig {
    /// True when the run hosts the hexapod's Modbus emulator (`[hil] emulate = true`).
    pub fn emulated(&self) -> bool {
        self.hil.as_ref().is_some_and(|h| h.emulate)
    }

    /// Driver kinds against driver settings, `[sim]` and `[hil]`.
    fn validate_devices(&self, f: &Path) -> Result<(), ConfigError> {
        const KEY: &str = "devices.hexapod.modbus";
        let h = &self.devices.hexapod;
        let emulated = self.emulated();
        let has_sim = self.sim.is_some();
        let modbus_kind = h.driver != HexapodDriver::Sim;
        match (&h.modbus, modbus_kind) {
            (Some(_), false) => {
                return Err(invalid(
                    f,
                    KEY,
                    "driver settings for \"modbus_tcp\" / \"modbus_rtu\", but devices.hexapod.driver is \"sim\"",
                ))
            }
            (None, true) => {
                return Err(invalid(
                    f,
                    KEY,
                    format!(
                        "missing: driver \"{}\" needs a [devices.hexapod.modbus] table with the register map (`map`) and, for a real controller, the `transport`",
                        h.driver.as_str()
                    ),
                ))
            }
            _ => {}
        }
        if !modbus_kind {
            if emulated {
                return Err(invalid(
                    f,
                    "hil.emulate",
                    "nothing to emulate: devices.hexapod.driver is \"sim\"; expected \"modbus_tcp\" or \"modbus_rtu\" with [hil] emulate = true",
                ));
            }
            if !has_sim {
                return Err(invalid(f, "sim", "the `sim` hexapod needs a [sim] table"));
            }
        }
        if let Some(modbus) = &h.modbus {
            self.validate_modbus(f, modbus, emulated)?;
            if emulated && !has_sim {
                return Err(invalid(
                    f,
                    "hil.emulate",
                    "the emulator is backed by the simulated hexapod, so a [sim] table is expected",
                ));
            }
            if !emulated && has_sim {
                return Err(invalid(
                    f,
                    "sim",
                    "a real hexapod (no [hil] emulate = true) does not use [sim]: remove it, or set [hil] emulate = true to run against the emulator",
                ));
            }
        }
        if let Some(s) = &self.devices.pose_sensor {
            match s.driver {
                PoseSensorDriver::Sim if !(h.driver == HexapodDriver::Sim || emulated) => {
                    return Err(invalid(
                        f,
                        "devices.pose_sensor.driver",
                        "\"sim\" measures the simulated platform, but the hexapod is real: expected \"given\"",
                    ))
                }
                PoseSensorDriver::Given if s.noise_m != 0.0 || s.noise_rad != 0.0 => {
                    return Err(invalid(
                        f,
                        "devices.pose_sensor.noise_m",
                        "expected no noise_m / noise_rad (or 0) for \"given\": the commanded poses are taken as exact",
                    ))
                }
                _ => {}
            }
        }
        if let Some(hil) = &self.hil {
            crate::config::rotary_table::validate_faults(&hil.hexapod_faults).map_err(
                |(key, m)| {
                    invalid(
                        f,
                        &key.replacen("hil.table_faults", "hil.hexapod_faults", 1),
                        m,
                    )
                },
            )?;
        }
        Ok(())
    }

    fn validate_modbus(
        &self,
        f: &Path,
        modbus: &ModbusHexapodConfig,
        emulated: bool,
    ) -> Result<(), ConfigError> {
        use geocal_drivers::modbus::ModbusTransport;
        const KEY: &str = "devices.hexapod.modbus";
        let h = &self.devices.hexapod;
        if modbus.id != "hexapod" && modbus.id != h.id {
            return Err(invalid(
                f,
                &format!("{KEY}.id"),
                format!(
                    "the hexapod's id comes from devices.hexapod.id (\"{}\"): leave `id` out here, found \"{}\"",
                    h.id, modbus.id
                ),
            ));
        }
        let mut checked = modbus.clone();
        checked.id = h.id.clone();
        if let Err(e) = checked.validate() {
            // The driver's own check names the setting ("timeout_s ...", "register map: ...").
            let message = e.to_string();
            let message = message
                .split_once(": protocol error: ")
                .map_or(message.as_str(), |(_, m)| m);
            return Err(invalid(f, KEY, message));
        }
        let tcp = h.driver == HexapodDriver::ModbusTcp;
        match &modbus.transport {
            None if emulated => Ok(()),
            None => Err(invalid(
                f,
                &format!("{KEY}.transport"),
                format!(
                    "missing: a real hexapod needs `transport = {{ kind = \"{}\", {} }}` (or set [hil] emulate = true)",
                    if tcp { "tcp" } else { "rtu" },
                    if tcp { "address = \"192.168.0.30:502\"" } else { "port = \"/dev/ttyUSB2\"" }
                ),
            )),
            Some(ModbusTransport::Tcp { .. }) if tcp => Ok(()),
            Some(ModbusTransport::Rtu { port, baud }) if !tcp => {
                if port.is_empty() && !emulated {
                    return Err(invalid(
                        f,
                        &format!("{KEY}.transport.port"),
                        "expected the serial port of the controller, e.g. \"/dev/ttyUSB2\"",
                    ));
                }
                if *baud == 0 {
                    return Err(invalid(
                        f,
                        &format!("{KEY}.transport.baud"),
                        "expected a baud rate > 0",
                    ));
                }
                Ok(())
            }
            Some(t) => Err(invalid(
                f,
                &format!("{KEY}.transport.kind"),
                format!(
                    "expected \"{}\" for driver \"{}\", found \"{}\"",
                    if tcp { "tcp" } else { "rtu" },
                    h.driver.as_str(),
                    match t {
                        ModbusTransport::Tcp { .. } => "tcp",
                        ModbusTransport::Rtu { .. } => "rtu",
                    }
                ),
            )),
        }
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

    /// The example on a Modbus hexapod: `driver`, the map, and `tail`: driver settings
    /// (`transport`, `id`) or a table after the map (`[hil]`).
    fn modbus(driver: &str, tail: &str) -> String {
        let (settings, tail) = if tail.starts_with('[') {
            ("", tail)
        } else {
            (tail, "")
        };
        let text = example().replacen("driver = \"sim\"", &format!("driver = \"{driver}\""), 1);
        format!(
            "{text}
[devices.hexapod.modbus]
timeout_s = 0.2
{settings}
[devices.hexapod.modbus.map]
pose_target = {{ address = 100, counts_per_m = 1e7, counts_per_rad = 1e7 }}
legs = {{ address = 200, kind = \"input\", m_per_count = 1e-7 }}
status = {{ address = 300, kind = \"input\", in_position_bit = 0, fault_bit = 2 }}
command = {{ address = 120, go_value = 1 }}
ack = {{ bit = 3 }}
{tail}
"
        )
    }

    /// A real controller: no [sim], the pose sensor `given`, the transport set.
    fn real(tail: &str) -> String {
        modbus("modbus_tcp", tail)
            .replace("[sim]\nseed = 424242\nhinge_error_m = 2.0e-3\n", "")
            .replace(
                "driver = \"sim\"\nnoise_m = 0.0\nnoise_rad = 0.0",
                "driver = \"given\"",
            )
    }

    fn error_of(text: &str) -> String {
        HexapodConfig::parse(text, Path::new("h.toml"))
            .expect_err("rejected")
            .to_string()
    }

    #[test]
    fn modbus_drivers_parse_real_and_emulated() {
        let c = HexapodConfig::parse(
            &real("transport = { kind = \"tcp\", address = \"192.168.0.30:502\" }"),
            Path::new("real.toml"),
        )
        .expect("real controller");
        assert_eq!(c.devices.hexapod.driver, HexapodDriver::ModbusTcp);
        assert!(c.sim.is_none() && !c.emulated());
        let sensor = c.devices.pose_sensor.as_ref().expect("sensor");
        assert_eq!(sensor.driver, PoseSensorDriver::Given);
        let c = HexapodConfig::parse(&modbus("modbus_rtu", "[hil]\n"), Path::new("hil.toml"))
            .expect("emulated RTU");
        assert!(c.emulated());
    }

    #[test]
    fn bad_driver_settings_name_the_key() {
        let tcp = "transport = { kind = \"tcp\", address = \"192.168.0.30:502\" }";
        let cases = [
            (
                example().replacen("driver = \"sim\"", "driver = \"modbus_tcp\"", 1),
                "devices.hexapod.modbus`: missing: driver \"modbus_tcp\" needs",
            ),
            (
                modbus("sim", ""),
                "devices.hexapod.modbus`: driver settings for \"modbus_tcp\"",
            ),
            (
                example().replacen("driver = \"sim\"", "driver = \"modbus\"", 1),
                "devices.hexapod.driver",
            ),
            (
                format!("{}\n[hil]\n", example()),
                "hil.emulate`: nothing to emulate",
            ),
            (
                real(""),
                "devices.hexapod.modbus.transport`: missing: a real hexapod needs",
            ),
            (
                real("transport = { kind = \"rtu\", port = \"/dev/ttyUSB2\" }"),
                "devices.hexapod.modbus.transport.kind`: expected \"tcp\"",
            ),
            (
                modbus("modbus_tcp", tcp),
                "key `sim`: a real hexapod (no [hil] emulate = true) does not use [sim]",
            ),
            (
                real(tcp).replace("driver = \"given\"", "driver = \"sim\""),
                "devices.pose_sensor.driver`: \"sim\" measures the simulated platform",
            ),
            (
                real(tcp).replace("driver = \"given\"", "driver = \"given\"\nnoise_m = 1e-6"),
                "devices.pose_sensor.noise_m`: expected no noise_m",
            ),
            (
                real(&format!("id = \"other\"\n{tcp}")),
                "devices.hexapod.modbus.id`: the hexapod's id comes from devices.hexapod.id",
            ),
            (
                real(tcp).replace("timeout_s = 0.2", "timeout_s = 0.0"),
                "devices.hexapod.modbus`: timeout_s must be positive",
            ),
            (
                modbus(
                    "modbus_tcp",
                    "[hil]\nhexapod_faults = { drop_probability = 2.0 }",
                ),
                "hil.hexapod_faults.drop_probability`: expected a fraction in [0, 1]",
            ),
            (
                modbus("modbus_tcp", "[hil]\nhexapod_faults = { drop_at = [3] }"),
                "hil.hexapod_faults.drop_at",
            ),
        ];
        for (text, want) in cases {
            let err = error_of(&text);
            assert!(err.starts_with("h.toml: key `"), "{err}");
            assert!(err.contains(want), "{want}\n{err}");
        }
    }
}
