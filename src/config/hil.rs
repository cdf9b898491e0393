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
}

fn yes() -> bool {
    true
}

impl Config {
    /// True when the run hosts its own device emulators (`[hil] emulate = true`).
    pub fn emulated(&self) -> bool {
        self.hil.as_ref().is_some_and(|h| h.emulate)
    }
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
    if d.machine.driver == Linuxcnc && emulated {
        return fail(
            "devices.machine.driver",
            "\"linuxcnc\" is a real controller, not emulated: use it without [hil] emulate = true",
        );
    }
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
