//! Protocol drivers and hardware-in-the-loop mode (`[hil]`): which driver kinds fit which
//! device, and what an emulated run needs. See README "HIL mode".

use serde::{Deserialize, Serialize};

use geocal_drivers::grbl::GrblFaults;
use geocal_drivers::hpi3d::FaultConfig;
use geocal_drivers::modbus_table::ModbusTableFaults;

use super::{Config, DriverKind};

/// `[hil]`: geocal hosts the device emulators itself, on pseudo-terminals, backed by the
/// simulated world (`[sim]`), and connects the real protocol drivers (`hpi3d`, `grbl`) to
/// them. The emulators run in real time; the world's clock follows wall time.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct HilConfig {
    /// Host the emulators (true) or talk to the real devices at the configured ports (false,
    /// the same as leaving `[hil]` out).
    #[serde(default = "yes")]
    pub emulate: bool,
    /// Faults the HPI-3D emulator injects (`geocal_drivers::hpi3d::FaultConfig`; windows
    /// in seconds since the emulator started).
    #[serde(default)]
    pub tracer_faults: FaultConfig,
    /// Faults the GRBL emulator injects (`geocal_drivers::grbl::GrblFaults`; line numbers
    /// count G-code lines received).
    #[serde(default)]
    pub machine_faults: GrblFaults,
    /// Faults the Modbus table emulator injects
    /// (`geocal_drivers::modbus_table::ModbusTableFaults`; requests counted from 1).
    #[serde(default)]
    pub table_faults: ModbusTableFaults,
    /// Real-controller HIL (`devices.machine.driver = "linuxcnc"`): the LinuxCNC geocal
    /// starts (docs/linuxcnc.md "Real-controller HIL").
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub linuxcnc: Option<LinuxCncHil>,
}

/// `[hil.linuxcnc]`: the LinuxCNC that geocal starts headless for a real-controller HIL run
/// (driver `linuxcnc` with `[hil] emulate = true`). Travel and velocity come from
/// `[machine] travel_m` and `devices.machine.feed_m_s`; the `[sim] compensation` entries of
/// format `linuxcnc-type0`/`linuxcnc-type1` become the joints' `COMP_FILE`s.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct LinuxCncHil {
    /// `MAX_ACCELERATION` of every joint and axis, m/s² (its dead band scales with it).
    #[serde(default = "default_acceleration")]
    pub max_acceleration_m_s2: f64,
    /// `SERVO_PERIOD`, seconds.
    #[serde(default = "default_servo_period")]
    pub servo_period_s: f64,
    /// Longest wait for LinuxCNC to come up once geocal holds the lock (another instance
    /// holding it is waited for without limit: tests run one LinuxCNC at a time), s.
    #[serde(default = "default_start_timeout")]
    pub start_timeout_s: f64,
    /// Tables handed to LinuxCNC exactly as written, unchecked by geocal (what a user loads by
    /// hand; LinuxCNC reads them its own way): `{ axis = "x", file = "...", type = 0 | 1 }`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub comp_files: Vec<LinuxCncCompFile>,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct LinuxCncCompFile {
    pub axis: String,
    pub file: std::path::PathBuf,
    /// `COMP_FILE_TYPE`.
    #[serde(rename = "type")]
    pub comp_type: u8,
}

fn default_acceleration() -> f64 {
    1.0
}
fn default_servo_period() -> f64 {
    1e-3
}
fn default_start_timeout() -> f64 {
    180.0
}

impl Default for LinuxCncHil {
    fn default() -> Self {
        Self {
            max_acceleration_m_s2: default_acceleration(),
            servo_period_s: default_servo_period(),
            start_timeout_s: default_start_timeout(),
            comp_files: Vec::new(),
        }
    }
}

fn yes() -> bool {
    true
}

impl Config {
    /// True when the run hosts its own device emulators (`[hil] emulate = true`).
    pub fn emulated(&self) -> bool {
        self.hil.as_ref().is_some_and(|h| h.emulate)
    }

    /// A real-controller HIL run: geocal starts LinuxCNC and drives it with the `linuxcnc`
    /// driver; the simulated world follows LinuxCNC's joints.
    pub fn linuxcnc_in_the_loop(&self) -> bool {
        self.emulated() && self.devices.machine.driver == DriverKind::Linuxcnc
    }
}

/// `[hil.linuxcnc]` and the `[sim]` it goes with, for a real-controller HIL run.
fn validate_linuxcnc_hil(config: &Config) -> Result<(), Invalid> {
    let hil = config.hil.as_ref();
    let lc = hil.and_then(|h| h.linuxcnc.as_ref());
    if !config.linuxcnc_in_the_loop() {
        if lc.is_some() {
            return fail(
                "hil.linuxcnc",
                "settings for a LinuxCNC geocal starts, but the run does not start one \
                 (devices.machine.driver = \"linuxcnc\" with [hil] emulate = true)",
            );
        }
        return Ok(());
    }
    for (k, axis) in crate::compensate::AXES.iter().enumerate() {
        if let Some([lo, hi]) = config.machine.travel_m.get(*axis) {
            if !(*lo <= 0.0 && 0.0 <= *hi) {
                return fail(
                    &format!("machine.travel_m.{axis}"),
                    format!(
                        "LinuxCNC homes joint {k} where it stands, at 0, so the travel must \
                         contain 0; found [{lo}, {hi}]"
                    ),
                );
            }
        }
    }
    if let Some(sim) = &config.sim {
        for (i, c) in sim.compensation.iter().enumerate() {
            if !matches!(
                c.format,
                crate::compensate::TableFormat::LinuxcncType0
                    | crate::compensate::TableFormat::LinuxcncType1
            ) {
                return fail(
                    &format!("sim.compensation[{i}].format"),
                    format!(
                        "LinuxCNC applies its own tables in a real-controller HIL run: expected \
                         \"linuxcnc-type0\" or \"linuxcnc-type1\", found \"{}\"",
                        c.format.name()
                    ),
                );
            }
        }
    }
    let Some(lc) = lc else {
        return Ok(());
    };
    let positive = |key: &str, v: f64| {
        if v.is_finite() && v > 0.0 {
            Ok(())
        } else {
            fail(key, format!("expected a positive number, found {v}"))
        }
    };
    positive(
        "hil.linuxcnc.max_acceleration_m_s2",
        lc.max_acceleration_m_s2,
    )?;
    positive("hil.linuxcnc.servo_period_s", lc.servo_period_s)?;
    positive("hil.linuxcnc.start_timeout_s", lc.start_timeout_s)?;
    for (i, c) in lc.comp_files.iter().enumerate() {
        let key = format!("hil.linuxcnc.comp_files[{i}]");
        if !crate::compensate::AXES.contains(&c.axis.as_str()) {
            return fail(
                &format!("{key}.axis"),
                format!("expected x, y or z, found {:?}", c.axis),
            );
        }
        if c.comp_type > 1 {
            return fail(
                &format!("{key}.type"),
                format!("expected 0 or 1 (COMP_FILE_TYPE), found {}", c.comp_type),
            );
        }
        if !c.file.is_file() {
            return fail(
                &format!("{key}.file"),
                format!("{} does not exist", c.file.display()),
            );
        }
    }
    Ok(())
}

type Invalid = (String, String);

fn fail<T>(key: &str, message: impl Into<String>) -> Result<T, Invalid> {
    Err((key.to_string(), message.into()))
}

fn fraction(key: &str, value: f64) -> Result<(), Invalid> {
    if (0.0..=1.0).contains(&value) {
        Ok(())
    } else {
        fail(key, format!("expected a fraction in [0, 1], found {value}"))
    }
}

/// Driver kinds per device, driver settings, and the `[hil]` section.
pub(super) fn validate_drivers(config: &Config) -> Result<(), Invalid> {
    let d = &config.devices;
    let kinds = |allowed: &[DriverKind]| {
        allowed
            .iter()
            .map(|k| format!("\"{}\"", k.as_str()))
            .collect::<Vec<_>>()
            .join(" or ")
    };
    let check = |key: &str, kind: DriverKind, allowed: &[DriverKind]| {
        if allowed.contains(&kind) {
            Ok(())
        } else {
            fail(
                key,
                format!("expected {}, found \"{}\"", kinds(allowed), kind.as_str()),
            )
        }
    };
    use DriverKind::{Grbl, Hpi3d, Linuxcnc, ModbusRtu, ModbusTcp, Passive, Sim};
    check("devices.tracer.driver", d.tracer.driver, &[Sim, Hpi3d])?;
    check(
        "devices.machine.driver",
        d.machine.driver,
        &[Sim, Grbl, Linuxcnc, Passive],
    )?;
    if d.machine.driver == Passive && config.plan.rotary.is_some() {
        return fail(
            "devices.machine.driver",
            "\"passive\" does not turn a rotary table: plan.rotary needs an active machine",
        );
    }
    if let Some(p) = &d.machine.passive {
        if d.machine.driver != Passive {
            return fail(
                "devices.machine.passive",
                "settings for \"passive\", but devices.machine.driver is not \"passive\"",
            );
        }
        if !(p.dwell_margin_s.is_finite() && p.dwell_margin_s >= 0.0) {
            return fail(
                "devices.machine.passive.dwell_margin_s",
                format!("expected a number >= 0, found {}", p.dwell_margin_s),
            );
        }
        if !(p.hint_tolerance_m.is_finite() && p.hint_tolerance_m > 0.0) {
            return fail(
                "devices.machine.passive.hint_tolerance_m",
                format!("expected a positive number, found {}", p.hint_tolerance_m),
            );
        }
    }
    if d.machine.driver == Passive && config.emulated() {
        return fail(
            "devices.machine.driver",
            "\"passive\" is not emulated: use it without [hil] emulate = true",
        );
    }
    if let Some(env) = &d.environment {
        check("devices.environment.driver", env.driver, &[Sim, Hpi3d])?;
        if env.driver == Hpi3d && d.tracer.driver != Hpi3d {
            return fail(
                "devices.environment.driver",
                "\"hpi3d\" reads the tracer's meteo stream, so devices.tracer.driver must be \"hpi3d\"",
            );
        }
    }
    if let Some(table) = &d.rotary_table {
        check(
            "devices.rotary_table.driver",
            table.driver,
            &[Sim, ModbusTcp, ModbusRtu],
        )?;
        super::rotary_table::validate(table, config.emulated())?;
    }
    if d.tracer.hpi3d.is_some() && d.tracer.driver != Hpi3d {
        return fail(
            "devices.tracer.hpi3d",
            "driver settings for \"hpi3d\", but devices.tracer.driver is not \"hpi3d\"",
        );
    }
    if d.machine.grbl.is_some() && d.machine.driver != Grbl {
        return fail(
            "devices.machine.grbl",
            "driver settings for \"grbl\", but devices.machine.driver is not \"grbl\"",
        );
    }
    if let Some(lc) = &d.machine.linuxcnc {
        if d.machine.driver != Linuxcnc {
            return fail(
                "devices.machine.linuxcnc",
                "driver settings for \"linuxcnc\", but devices.machine.driver is not \"linuxcnc\"",
            );
        }
        let mut checked = lc.clone();
        checked.feed_m_s = d.machine.feed_m_s;
        if let Err(e) = checked.validate() {
            let message = match e {
                geocal_drivers::DeviceError::Protocol { message, .. } => message,
                other => other.to_string(),
            };
            return fail("devices.machine.linuxcnc", message);
        }
    }
    let emulated = config.emulated();
    // "linuxcnc" with [hil] emulate = true: geocal starts a real LinuxCNC headless and the
    // simulated world follows its joints (real-controller HIL).
    validate_linuxcnc_hil(config)?;
    if !emulated {
        if d.tracer.driver == Hpi3d && d.tracer.hpi3d.as_ref().is_none_or(|c| c.port.is_empty()) {
            return fail(
                "devices.tracer.hpi3d.port",
                "missing: a real HPI-3D needs its serial port (or set [hil] emulate = true)",
            );
        }
        if d.machine.driver == Grbl && d.machine.grbl.as_ref().is_none_or(|c| c.port.is_empty()) {
            return fail(
                "devices.machine.grbl.port",
                "missing: a real GRBL controller needs its serial port (or set [hil] emulate = true)",
            );
        }
        if d.machine.driver == Linuxcnc
            && d.machine
                .linuxcnc
                .as_ref()
                .is_none_or(|c| c.host.is_empty())
        {
            return fail(
                "devices.machine.linuxcnc.host",
                "missing: geocal connects to linuxcncrsh at host (and port, 5007 by default)",
            );
        }
    }
    let Some(hil) = config.hil.as_ref().filter(|h| h.emulate) else {
        return Ok(());
    };
    if config.sim.is_none() {
        return fail(
            "hil.emulate",
            "the emulators are backed by the simulated world, so a [sim] table is expected",
        );
    }
    if d.tracer.driver != Hpi3d {
        return fail(
            "devices.tracer.driver",
            "with [hil] emulate = true expected \"hpi3d\": the emulated tracer's stream runs the world's clock in real time",
        );
    }
    let f = &hil.tracer_faults;
    fraction("hil.tracer_faults.drop_fraction", f.drop_fraction)?;
    fraction("hil.tracer_faults.corrupt_fraction", f.corrupt_fraction)?;
    fraction("hil.tracer_faults.garbage_fraction", f.garbage_fraction)?;
    fraction("hil.tracer_faults.ack_drop_fraction", f.ack_drop_fraction)?;
    let m = &hil.machine_faults;
    fraction(
        "hil.machine_faults.drop_ok_probability",
        m.drop_ok_probability,
    )?;
    fraction("hil.machine_faults.error_probability", m.error_probability)?;
    if !(m.silence_s.is_finite() && m.silence_s >= 0.0) {
        return fail(
            "hil.machine_faults.silence_s",
            format!("expected a number >= 0, found {}", m.silence_s),
        );
    }
    for (key, value) in [
        ("hil.machine_faults.reconnect_after_s", m.reconnect_after_s),
        ("hil.machine_faults.alarm_at_s", m.alarm_at_s),
        ("hil.machine_faults.alarm_after_s", Some(m.alarm_after_s)),
    ] {
        if let Some(v) = value.filter(|v| !(v.is_finite() && *v >= 0.0)) {
            return fail(key, format!("expected seconds >= 0, found {v}"));
        }
    }
    super::rotary_table::validate_faults(&hil.table_faults)
}
