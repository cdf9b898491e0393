//! Configuration files (TOML): machine, devices, plan and simulated world, parsed strictly
//! (unknown keys rejected) and validated, with errors naming the file, the key and what is expected.

mod hil;
pub mod kind_config;
pub mod noise;
pub mod operator;
pub mod passive;
pub mod report;
pub(crate) mod rotary_table;
pub mod sim;
pub mod uncertainty;
mod validate;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

pub use hil::HilConfig;
pub use validate::validate;

/// A configuration error: which file, which key, what was expected.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("{file}: cannot read: {source}")]
    Read {
        file: PathBuf,
        source: std::io::Error,
    },
    #[error("{file}: key `{key}`: {message}")]
    Parse {
        file: PathBuf,
        key: String,
        message: String,
    },
    #[error("{file}: key `{key}`: {message}")]
    Invalid {
        file: PathBuf,
        key: String,
        message: String,
    },
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// Plan kind: `multilateration` or `rotary_tracer` (the tracer stands on a rotary table).
    pub kind: PlanKind,
    pub machine: MachineConfig,
    pub devices: DevicesConfig,
    pub plan: PlanConfig,
    /// The simulated world; required when any device uses the `sim` driver.
    #[serde(default)]
    pub sim: Option<SimConfig>,
    /// Hardware-in-the-loop: host device emulators backed by `[sim]` (see `hil.rs`).
    #[serde(default)]
    pub hil: Option<HilConfig>,
    /// How the operator of a real run acknowledges prompts (`src/devices/operator.rs`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub operator: Option<operator::OperatorConfig>,
    /// Declared standard uncertainties of the inputs (docs/uncertainty.md); defaults if absent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub uncertainty: Option<uncertainty::UncertaintyConfig>,
    /// The scales' CTE for referring positions to 20 °C (docs/uncertainty.md).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub normalisation: Option<uncertainty::NormalisationConfig>,
    /// The tolerances the report checks the errors against (docs/report.md).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub report: Option<report::ReportConfig>,
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum PlanKind {
    Multilateration,
    /// Multilateration with the tracer on a rotary table: the table's axis and the true angle
    /// of every commanded step (DESIGN.md method 3).
    RotaryTracer,
}

impl PlanKind {
    pub fn as_str(self) -> &'static str {
        match self {
            PlanKind::Multilateration => "multilateration",
            PlanKind::RotaryTracer => "rotary_tracer",
        }
    }
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct MachineConfig {
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
    /// ISO 230-1 style chain, e.g. `FYXZ` (letters left of F carry the workpiece).
    pub structure: String,
    /// Travel of each axis `x`, `y`, `z`: [low, high], metres.
    pub travel_m: BTreeMap<String, [f64; 2]>,
    /// Reflector offsets from the tool point.
    pub targets: Vec<TargetConfig>,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct TargetConfig {
    pub id: String,
    pub offset_m: [f64; 3],
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct DevicesConfig {
    pub tracer: TracerConfig,
    #[serde(default)]
    pub environment: Option<EnvironmentConfig>,
    pub machine: MachineDeviceConfig,
    /// The rotary table the tracer stands on (plan kind `rotary_tracer`).
    #[serde(default)]
    pub rotary_table: Option<RotaryTableConfig>,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct RotaryTableConfig {
    /// Axis name, e.g. `c`; the `/rotary/<id>/state` topic and `rotation` events carry it.
    pub id: String,
    pub driver: DriverKind,
    /// `[devices.rotary_table.modbus]`: the Modbus driver's settings (drivers `modbus_tcp`,
    /// `modbus_rtu`; `geocal_drivers::modbus_table::ModbusTableConfig`, `id` from here).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub modbus: Option<geocal_drivers::modbus_table::ModbusTableConfig>,
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum DriverKind {
    Sim,
    /// Lasertex HPI-3D serial protocol (tracer; its meteo stream as environment).
    Hpi3d,
    /// GRBL-style G-code streaming (machine).
    Grbl,
    /// LinuxCNC over linuxcncrsh, its TCP text interface (machine; `[devices.machine.linuxcnc]`).
    Linuxcnc,
    /// Modbus TCP rotary table (register map in `[devices.rotary_table.modbus]`).
    ModbusTcp,
    /// Modbus RTU rotary table on a serial port.
    ModbusRtu,
    /// Machine only: an industrial control runs the program of `geocal export-nc` by itself;
    /// the sequencer detects each stop from the tracer stream (src/sequencer/passive.rs).
    Passive,
}

impl DriverKind {
    pub fn as_str(self) -> &'static str {
        match self {
            DriverKind::Sim => "sim",
            DriverKind::Hpi3d => "hpi3d",
            DriverKind::Grbl => "grbl",
            DriverKind::Linuxcnc => "linuxcnc",
            DriverKind::ModbusTcp => "modbus_tcp",
            DriverKind::ModbusRtu => "modbus_rtu",
            DriverKind::Passive => "passive",
        }
    }
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct TracerConfig {
    pub id: String,
    pub driver: DriverKind,
    /// Per-sample standard deviation: noise_m + noise_ppm * 1e-6 * L_abs, L_abs the absolute
    /// optical path |station − target| + dead_path_m.
    pub noise_m: f64,
    pub noise_ppm: f64,
    /// Samples per second of the length stream.
    pub sample_rate_hz: f64,
    #[serde(default = "default_wavelength")]
    pub wavelength_m: f64,
    #[serde(default)]
    pub dead_path_m: f64,
    /// True when the tracer corrects the air refractive index itself.
    #[serde(default = "default_true")]
    pub compensated: bool,
    /// `[devices.tracer.hpi3d]`: the driver's settings (driver `hpi3d`; `id` comes from here).
    #[serde(default)]
    pub hpi3d: Option<geocal_drivers::hpi3d::Hpi3dConfig>,
}

impl TracerConfig {
    /// The declared per-sample noise (ppm of the absolute optical path, dead path included).
    pub fn noise_model(&self) -> noise::NoiseModel {
        noise::NoiseModel {
            noise_m: self.noise_m,
            noise_ppm: self.noise_ppm,
            dead_path_m: self.dead_path_m,
        }
    }
}

fn default_wavelength() -> f64 {
    632.991e-9
}
fn default_true() -> bool {
    true
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct EnvironmentConfig {
    pub id: String,
    pub driver: DriverKind,
    #[serde(default = "default_env_rate")]
    pub sample_rate_hz: f64,
}

fn default_env_rate() -> f64 {
    1.0
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct MachineDeviceConfig {
    pub id: String,
    pub driver: DriverKind,
    /// Path feed rate, m/s.
    pub feed_m_s: f64,
    /// `[devices.machine.grbl]`: the driver's settings (driver `grbl`; `id` and `feed_m_s`
    /// come from here).
    #[serde(default)]
    pub grbl: Option<geocal_drivers::grbl::GrblConfig>,
    /// `[devices.machine.linuxcnc]`: the LinuxCNC driver's settings (driver `linuxcnc`;
    /// `geocal_drivers::linuxcnc::LinuxCncConfig`: `host`, `port`, `password_file`, `home`,
    /// ...; `id` and `feed_m_s` come from here). Passwords are refused inline.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub linuxcnc: Option<geocal_drivers::linuxcnc::LinuxCncConfig>,
    /// `[devices.machine.passive]`: NC program and stop matching settings (driver `passive`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub passive: Option<passive::PassiveConfig>,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct PlanConfig {
    /// Which targets (by id) the plan measures, in order; each at every station.
    pub targets: Vec<String>,
    pub grid: GridConfig,
    /// Pass directions, in order; every pass starts by homing at point 0. A number n stands
    /// for n bidirectional runs: forward, backward, repeated n times (ISO 230-2's cycle is 5).
    #[serde(deserialize_with = "passes_or_runs")]
    pub passes: Vec<PassDirection>,
    /// Stations the operator places (off the table), measured after the table stations.
    #[serde(default)]
    pub stations: Vec<StationConfig>,
    /// Stations on the rotary table (plan kind `rotary_tracer`), measured first.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rotary: Option<RotaryPlanConfig>,
    /// Minimum dwell at each point, seconds.
    pub dwell_s: f64,
    /// Give up waiting for stillstand after this long (a `fault` event), seconds.
    pub max_dwell_s: f64,
    pub stillstand: StillstandConfig,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct GridConfig {
    pub x: AxisRange,
    pub y: AxisRange,
    pub z: AxisRange,
    #[serde(default)]
    pub order: GridOrder,
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct AxisRange {
    pub from: f64,
    pub to: f64,
    pub count: usize,
    /// How the points lie between `from` and `to` (default: equally spaced).
    #[serde(default, skip_serializing_if = "Spacing::is_equal")]
    pub spacing: Spacing,
}

/// Target spacing along a grid axis.
#[derive(Debug, Clone, Copy, Default, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum Spacing {
    #[default]
    Equal,
    /// Unequal intervals, as ISO 230-2 suggests so that periodic errors are sampled: the
    /// interior points move by a fixed pseudo-random fraction (within ±1/4) of the interval;
    /// the end points stay.
    PseudoRandom,
}

impl Spacing {
    fn is_equal(&self) -> bool {
        *self == Spacing::Equal
    }

    /// The shift of target `i` of `count`, in intervals: 0 when equally spaced and at the
    /// ends; else a fixed fraction in [−1/4, 1/4) (SplitMix64 of i), the same on every
    /// platform, so that neighbours never swap or meet.
    pub fn shift_fraction(&self, i: usize, count: usize) -> f64 {
        if *self == Spacing::Equal || i == 0 || i + 1 >= count {
            return 0.0;
        }
        let mut z = (i as u64)
            .wrapping_add(1)
            .wrapping_mul(0x9E37_79B9_7F4A_7C15);
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        let unit = (z >> 11) as f64 / (1u64 << 53) as f64;
        0.5 * unit - 0.25
    }
}

/// `passes` as a list of directions, or as a number of bidirectional runs.
fn passes_or_runs<'de, D>(deserializer: D) -> Result<Vec<PassDirection>, D::Error>
where
    D: serde::Deserializer<'de>,
{
    #[derive(Deserialize)]
    #[serde(untagged)]
    enum Passes {
        Runs(u32),
        Directions(Vec<PassDirection>),
    }
    match Passes::deserialize(deserializer) {
        Ok(Passes::Directions(d)) => Ok(d),
        Ok(Passes::Runs(n)) => Ok((0..n)
            .flat_map(|_| [PassDirection::Forward, PassDirection::Backward])
            .collect()),
        Err(_) => Err(serde::de::Error::custom(
            "expected a list of pass directions (\"forward\", \"backward\") or a number of bidirectional runs (e.g. 5)",
        )),
    }
}

#[derive(Debug, Clone, Copy, Default, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum GridOrder {
    #[default]
    Serpentine,
    Raster,
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum PassDirection {
    Forward,
    Backward,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct StationConfig {
    pub id: String,
    #[serde(default)]
    pub hint_m: Option<[f64; 3]>,
}

/// The tracer on the rotary table: one station per commanded table angle. The angles are
/// either listed (`angles_rad`) or stepped (`step_rad` and `count`, from `start_rad`).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct RotaryPlanConfig {
    /// Id of the table (must equal `devices.rotary_table.id`).
    pub table: String,
    /// A point on the nominal table axis, machine frame, metres.
    pub axis_point_m: [f64; 3],
    /// Nominal direction of the table axis (positive angles turn right-handed about it).
    pub axis_direction: [f64; 3],
    /// Where the tracer stands when the table is at commanded angle 0, machine frame, metres.
    pub tracer_hint_m: [f64; 3],
    /// Commanded absolute table angles, radians, in the order measured.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub angles_rad: Option<Vec<f64>>,
    /// First commanded angle of the stepped form, radians (default 0).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub start_rad: Option<f64>,
    /// Step between commanded angles of the stepped form, radians.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub step_rad: Option<f64>,
    /// Number of table stations of the stepped form.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub count: Option<usize>,
    /// How the stepped form's angles lie (default: equally spaced); `pseudo_random` moves the
    /// interior angles as a grid axis's (ISO 230-2's unequal intervals).
    #[serde(default, skip_serializing_if = "Spacing::is_equal")]
    pub spacing: Spacing,
    /// ISO 230-2's test cycle: this many bidirectional runs over the angles, each run visiting
    /// them in increasing (↑) or decreasing (↓) order and entering from beyond its first angle
    /// by `overshoot_rad`, so that every angle of a run is approached from the run's side.
    /// Unset: each angle once, in the order given.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub runs: Option<usize>,
    /// How far the table turns beyond a run's first angle before approaching it, radians
    /// (with `runs`; default 0.05 rad, about 2.9°).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub overshoot_rad: Option<f64>,
    /// Table station ids are this prefix and the 1-based step number: `c01`, `c02`, ...
    #[serde(default = "default_station_prefix")]
    pub station_prefix: String,
}

/// One visit of the table: the commanded angle a table station is measured at, and the angle
/// the table is sent to first (the overshoot that fixes its approach direction), if any.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TableVisit {
    pub commanded_rad: f64,
    pub via_rad: Option<f64>,
}

/// Default of `plan.rotary.overshoot_rad`, radians.
pub const DEFAULT_TABLE_OVERSHOOT_RAD: f64 = 0.05;

fn default_station_prefix() -> String {
    String::from("c")
}

impl RotaryPlanConfig {
    /// The target angles, distinct, in the order given (listed, or expanded from the stepped
    /// form with its spacing).
    pub fn commanded_angles_rad(&self) -> Vec<f64> {
        match (&self.angles_rad, self.step_rad, self.count) {
            (Some(angles), _, _) => angles.clone(),
            (None, Some(step), Some(count)) => {
                let start = self.start_rad.unwrap_or(0.0);
                (0..count)
                    .map(|k| start + step * k as f64 + step * self.spacing.shift_fraction(k, count))
                    .collect()
            }
            _ => Vec::new(),
        }
    }

    /// Every table station in measuring order: the angles once as given, or with `runs` the
    /// ISO 230-2 cycle (↑ run, ↓ run, repeated), each run entered through its overshoot.
    pub fn visits(&self) -> Vec<TableVisit> {
        let angles = self.commanded_angles_rad();
        let Some(runs) = self.runs else {
            return angles
                .into_iter()
                .map(|commanded_rad| TableVisit {
                    commanded_rad,
                    via_rad: None,
                })
                .collect();
        };
        let mut up = angles;
        up.sort_by(f64::total_cmp);
        let down: Vec<f64> = up.iter().rev().copied().collect();
        let overshoot = self.overshoot_rad.unwrap_or(DEFAULT_TABLE_OVERSHOOT_RAD);
        let run = |angles: &[f64], via_side: f64| -> Vec<TableVisit> {
            angles
                .iter()
                .enumerate()
                .map(|(i, &commanded_rad)| TableVisit {
                    commanded_rad,
                    via_rad: (i == 0).then_some(commanded_rad + via_side * overshoot),
                })
                .collect()
        };
        (0..runs)
            .flat_map(|_| run(&up, -1.0).into_iter().chain(run(&down, 1.0)))
            .collect()
    }

    /// Id of the table station at step `k` (0-based).
    pub fn station_id(&self, k: usize) -> String {
        format!("{}{:02}", self.station_prefix, k + 1)
    }
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct StillstandConfig {
    /// The readings must stay within `tolerance_m` (peak to peak) for this long, seconds.
    pub window_s: f64,
    pub tolerance_m: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SimConfig {
    pub seed: u64,
    /// True stations lie this far (standard deviation per coordinate) from their hints, metres.
    #[serde(default = "default_station_hint_error")]
    pub station_hint_error_m: f64,
    /// Sizes of the machine's geometric errors.
    #[serde(default)]
    pub errors: sim::ErrorSizes,
    /// Time the operator needs to move the tracer to the next station, seconds.
    #[serde(default = "default_relocation_s")]
    pub relocation_s: f64,
    #[serde(default)]
    pub environment: SimEnvironmentConfig,
    /// The simulated rotary table's errors (plan kind `rotary_tracer`).
    #[serde(default)]
    pub rotary: SimRotaryConfig,
    /// Unmodelled effects of the simulated world (the vocabulary of `geocal diagnose`).
    #[serde(default)]
    pub effects: sim::EffectsConfig,
    /// Seed of the tracer noise alone (default seed + 1): a twin of a recorded run keeps the
    /// machine and stations of `seed` with noise of its own.
    #[serde(default)]
    pub noise_seed: Option<u64>,
    /// The simulated tracer's noise is this many times its declared model (unset: 1): a tracer
    /// noisier or quieter than its declaration, as the diagnosis's `noise_scale` must see.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tracer_noise_factor: Option<f64>,
    /// Run the virtual clock at most this many times faster than wall time (e.g. 20.0);
    /// unset: as fast as possible. For watching a run, or killing it mid-run in a test.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pace: Option<f64>,
    /// The simulated machine of a passive run: unplanned stops and dwell jitter.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub passive: Option<sim::SimPassiveConfig>,
    /// Compensation tables the simulated machine applies as its controller would.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub compensation: Vec<sim::SimCompensation>,
}

/// Truth of the simulated rotary table: where its axis really is and how wrong its angles are.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct SimRotaryConfig {
    /// Peak angular positioning error (smooth harmonics of the angle), radians.
    pub angle_error_rad: f64,
    /// Number of harmonics (1, 2, ... per revolution) in the angular positioning error.
    pub harmonics: usize,
    /// Standard deviation of the true axis location from the nominal, per coordinate, metres.
    pub axis_offset_m: f64,
    /// Standard deviation of the true axis direction from the nominal (tilt), radians.
    pub axis_tilt_rad: f64,
    /// Rotation speed, rad/s.
    pub speed_rad_s: f64,
    /// Time to settle in position after a rotation, seconds.
    pub settle_s: f64,
    /// Reversal (backlash) of the table: in position it stands `reversal_rad`/2 beyond the
    /// commanded angle in the direction of its last move (0 before it ever moved), radians.
    #[serde(skip_serializing_if = "is_zero")]
    pub reversal_rad: f64,
    /// Random scatter of the angle reached at each positioning (standard deviation), radians:
    /// ISO 230-2's repeatability of the table.
    #[serde(skip_serializing_if = "is_zero")]
    pub repeatability_rad: f64,
}

/// Serde's `skip_serializing_if` for optional zero-defaulted values.
pub(crate) fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

impl Default for SimRotaryConfig {
    fn default() -> Self {
        Self {
            angle_error_rad: 2.4e-5,
            harmonics: 4,
            axis_offset_m: 5e-4,
            axis_tilt_rad: 1e-4,
            speed_rad_s: 0.2,
            settle_s: 2.0,
            reversal_rad: 0.0,
            repeatability_rad: 0.0,
        }
    }
}

fn default_station_hint_error() -> f64 {
    0.02
}
fn default_relocation_s() -> f64 {
    120.0
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct SimEnvironmentConfig {
    pub air_temp_k: f64,
    pub pressure_pa: f64,
    pub humidity_pct: f64,
    pub material_temp_k: Vec<f64>,
    /// Slow sinusoidal temperature swing (amplitude, kelvin; period, seconds).
    pub temp_swing_k: f64,
    pub temp_period_s: f64,
}

impl Default for SimEnvironmentConfig {
    fn default() -> Self {
        Self {
            air_temp_k: 293.15,
            pressure_pa: 101_325.0,
            humidity_pct: 45.0,
            material_temp_k: vec![293.2, 293.1],
            temp_swing_k: 0.05,
            temp_period_s: 3600.0,
        }
    }
}

impl Config {
    /// Read, parse and validate a configuration file.
    pub fn load(path: &Path) -> Result<Config, ConfigError> {
        Self::parse(&kind_config::read(path)?, path)
    }

    /// Parse and validate configuration text; `file` names it in errors.
    pub fn parse(text: &str, file: &Path) -> Result<Config, ConfigError> {
        let mut config: Config = kind_config::parse_strict(text, file)?;
        // Compensation tables are named relative to the configuration's folder; kept absolute,
        // so that the stored run configuration and the session header name them wherever
        // they are read from.
        // The LinuxCNC password file likewise.
        if let (Some(lc), Some(dir)) = (config.devices.machine.linuxcnc.as_mut(), file.parent()) {
            if let Some(pw) = lc.password_file.as_mut().filter(|p| p.is_relative()) {
                let joined = dir.join(&*pw);
                *pw = std::path::absolute(&joined).unwrap_or(joined);
            }
        }
        if let (Some(lc), Some(dir)) = (
            config.hil.as_mut().and_then(|h| h.linuxcnc.as_mut()),
            file.parent(),
        ) {
            for c in lc.comp_files.iter_mut().filter(|c| c.file.is_relative()) {
                let joined = dir.join(&c.file);
                c.file = std::path::absolute(&joined).unwrap_or(joined);
            }
        }
        if let (Some(sim), Some(dir)) = (config.sim.as_mut(), file.parent()) {
            for c in &mut sim.compensation {
                if c.file.is_relative() {
                    let joined = dir.join(&c.file);
                    c.file = std::path::absolute(&joined).unwrap_or(joined);
                }
            }
        }
        validate(&config).map_err(|(key, message)| ConfigError::Invalid {
            file: file.to_path_buf(),
            key,
            message,
        })?;
        Ok(config)
    }

    /// The offset of a machine target by id.
    pub fn target_offset(&self, id: &str) -> Option<[f64; 3]> {
        self.machine
            .targets
            .iter()
            .find(|t| t.id == id)
            .map(|t| t.offset_m)
    }
}

/// The driver of a touch or displacement probe.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum ProbeDriverKind {
    Sim,
    /// Line-oriented ASCII request/response readout (drivers/src/probe).
    Ascii,
}

impl ProbeDriverKind {
    pub fn as_str(self) -> &'static str {
        match self {
            ProbeDriverKind::Sim => "sim",
            ProbeDriverKind::Ascii => "ascii",
        }
    }
}
