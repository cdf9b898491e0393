//! The rotary table's driver settings (`[devices.rotary_table.modbus]`) and the Modbus table
//! emulator's faults (`[hil.table_faults]`): strict checks with errors naming the key.

use geocal_drivers::modbus_table::{ModbusTableFaults, ModbusTransport};

use super::{DriverKind, RotaryTableConfig};

type Invalid = (String, String);

fn fail<T>(key: &str, message: impl Into<String>) -> Result<T, Invalid> {
    Err((key.to_string(), message.into()))
}

/// Driver kind against driver settings and transport; `emulated`: the run hosts the table
/// emulator itself, so the transport may be left out (it is ignored).
pub(super) fn validate(table: &RotaryTableConfig, emulated: bool) -> Result<(), Invalid> {
    const KEY: &str = "devices.rotary_table.modbus";
    let modbus_kind = matches!(table.driver, DriverKind::ModbusTcp | DriverKind::ModbusRtu);
    let Some(modbus) = &table.modbus else {
        if modbus_kind {
            return fail(
                KEY,
                format!(
                    "missing: driver \"{}\" needs a [devices.rotary_table.modbus] table with the register map (`map`) and, for a real table, the `transport`",
                    table.driver.as_str()
                ),
            );
        }
        return Ok(());
    };
    if !modbus_kind {
        return fail(
            KEY,
            format!(
                "driver settings for \"modbus_tcp\" / \"modbus_rtu\", but devices.rotary_table.driver is \"{}\"",
                table.driver.as_str()
            ),
        );
    }
    if modbus.id != "rotary" && modbus.id != table.id {
        return fail(
            &format!("{KEY}.id"),
            format!(
                "the table's id comes from devices.rotary_table.id (\"{}\"): leave `id` out here, found \"{}\"",
                table.id, modbus.id
            ),
        );
    }
    let mut checked = modbus.clone();
    checked.id = table.id.clone();
    if let Err(e) = checked.validate() {
        // The driver's own check names the setting ("timeout_s ...", "register map: ...").
        let message = e.to_string();
        let message = message
            .split_once(": protocol error: ")
            .map_or(message.as_str(), |(_, m)| m);
        return fail(KEY, message.to_string());
    }
    match (&modbus.transport, table.driver) {
        (None, _) if emulated => Ok(()),
        (None, kind) => fail(
            &format!("{KEY}.transport"),
            format!(
                "missing: a real table needs `transport = {{ kind = \"{}\", {} }}` (or set [hil] emulate = true)",
                if kind == DriverKind::ModbusTcp { "tcp" } else { "rtu" },
                if kind == DriverKind::ModbusTcp {
                    "address = \"192.168.0.20:502\""
                } else {
                    "port = \"/dev/ttyUSB1\""
                }
            ),
        ),
        (Some(ModbusTransport::Tcp { .. }), DriverKind::ModbusTcp) => Ok(()),
        (Some(ModbusTransport::Rtu { port, baud }), DriverKind::ModbusRtu) => {
            if port.is_empty() && !emulated {
                return fail(
                    &format!("{KEY}.transport.port"),
                    "expected the serial port of the table, e.g. \"/dev/ttyUSB1\"",
                );
            }
            if *baud == 0 {
                return fail(
                    &format!("{KEY}.transport.baud"),
                    "expected a baud rate > 0",
                );
            }
            Ok(())
        }
        (Some(t), kind) => fail(
            &format!("{KEY}.transport.kind"),
            format!(
                "expected \"{}\" for driver \"{}\", found \"{}\"",
                if kind == DriverKind::ModbusTcp { "tcp" } else { "rtu" },
                kind.as_str(),
                match t {
                    ModbusTransport::Tcp { .. } => "tcp",
                    ModbusTransport::Rtu { .. } => "rtu",
                }
            ),
        ),
    }
}

/// `[hil.table_faults]`: probabilities in [0, 1], durations finite and not negative.
pub(crate) fn validate_faults(f: &ModbusTableFaults) -> Result<(), Invalid> {
    if !(0.0..=1.0).contains(&f.drop_probability) {
        return fail(
            "hil.table_faults.drop_probability",
            format!(
                "expected a fraction in [0, 1], found {}",
                f.drop_probability
            ),
        );
    }
    if !(f.silence_s.is_finite() && f.silence_s >= 0.0) {
        return fail(
            "hil.table_faults.silence_s",
            format!("expected a number >= 0, found {}", f.silence_s),
        );
    }
    if let Some(t) = f.fault_at_s {
        if !(t.is_finite() && t >= 0.0) {
            return fail(
                "hil.table_faults.fault_at_s",
                format!("expected seconds >= 0, found {t}"),
            );
        }
    }
    if f.drop_at_requests.contains(&0) || f.exception_at_requests.contains(&0) {
        return fail(
            "hil.table_faults",
            "request numbers count from 1: found 0 in drop_at_requests or exception_at_requests",
        );
    }
    Ok(())
}
