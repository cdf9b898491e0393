//! The rotary table's driver kinds (`modbus_tcp`, `modbus_rtu`), their settings and the table
//! emulator's faults: valid forms parse, every malformed one fails naming the key.

use std::path::Path;

use geocal::config::{Config, DriverKind};

const ROTARY: &str = include_str!("../config/rotary-tracer.toml");
const FILE: &str = "config/table.toml";

const MAP: &str = "
[devices.rotary_table.modbus.map]
target = { address = 100, counts_per_rad = 1e7 }
actual = { address = 200, kind = \"input\", counts_per_rad = 1e7 }
status = { address = 300, kind = \"input\", in_position_bit = 0, fault_bit = 2 }
command = { address = 110, go_value = 1, clear_value = 0 }
ack = { bit = 3 }
";

/// The rotary example with the table on `driver`, `modbus` lines in its table (before the
/// map), and `tail` appended.
fn with_table(driver: &str, modbus: &str, tail: &str) -> String {
    let text = ROTARY.replace(
        "id = \"c\"\ndriver = \"sim\"",
        &format!("id = \"c\"\ndriver = \"{driver}\""),
    );
    format!("{text}\n[devices.rotary_table.modbus]\n{modbus}\n{MAP}\n{tail}")
}

fn error_of(text: &str) -> String {
    match Config::parse(text, Path::new(FILE)) {
        Ok(_) => panic!("config unexpectedly valid:\n{text}"),
        Err(e) => e.to_string(),
    }
}

fn assert_mentions(message: &str, parts: &[&str]) {
    for part in parts {
        assert!(
            message.contains(part),
            "error {message:?} does not mention {part:?}"
        );
    }
}

#[test]
fn modbus_tcp_and_rtu_tables_parse() {
    let tcp = with_table(
        "modbus_tcp",
        "transport = { kind = \"tcp\", address = \"192.168.0.20:502\" }",
        "",
    );
    let config = Config::parse(&tcp, Path::new(FILE)).expect("tcp table");
    let table = config.devices.rotary_table.as_ref().expect("table");
    assert_eq!(table.driver, DriverKind::ModbusTcp);
    assert_eq!(table.driver.as_str(), "modbus_tcp");
    let rtu = with_table(
        "modbus_rtu",
        "transport = { kind = \"rtu\", port = \"/dev/ttyUSB1\", baud = 38400 }",
        "",
    );
    let config = Config::parse(&rtu, Path::new(FILE)).expect("rtu table");
    assert_eq!(
        config.devices.rotary_table.as_ref().map(|t| t.driver),
        Some(DriverKind::ModbusRtu)
    );
    // Emulated: the transport may be left out (the emulator's address is used).
    let emulated = with_table(
        "modbus_tcp",
        "",
        "[hil]\nemulate = true\n[hil.table_faults]\ndrop_at_requests = [3]\n",
    )
    .replace(
        "id = \"tracer0\"\ndriver = \"sim\"",
        "id = \"tracer0\"\ndriver = \"hpi3d\"",
    );
    Config::parse(&emulated, Path::new(FILE)).expect("emulated table");
}

#[test]
fn malformed_table_settings_name_the_key() {
    let cases: Vec<(String, Vec<&str>)> = vec![
        (
            // A Modbus driver without its settings.
            ROTARY.replace(
                "id = \"c\"\ndriver = \"sim\"",
                "id = \"c\"\ndriver = \"modbus_tcp\"",
            ),
            vec!["devices.rotary_table.modbus", "missing", "register map"],
        ),
        (
            with_table("sim", "", ""),
            vec![
                "devices.rotary_table.modbus",
                "devices.rotary_table.driver is \"sim\"",
            ],
        ),
        (
            with_table("modbus_tcp", "", ""),
            vec![
                "devices.rotary_table.modbus.transport",
                "missing",
                "kind = \"tcp\"",
            ],
        ),
        (
            with_table(
                "modbus_tcp",
                "transport = { kind = \"rtu\", port = \"/dev/ttyUSB1\" }",
                "",
            ),
            vec![
                "devices.rotary_table.modbus.transport.kind",
                "expected \"tcp\"",
            ],
        ),
        (
            with_table(
                "modbus_rtu",
                "transport = { kind = \"rtu\", port = \"\" }",
                "",
            ),
            vec!["devices.rotary_table.modbus.transport.port", "serial port"],
        ),
        (
            with_table(
                "modbus_tcp",
                "transport = { kind = \"tcp\", address = \"192.168.0.20:502\" }\ntimeout_s = -1.0",
                "",
            ),
            vec!["devices.rotary_table.modbus", "timeout_s"],
        ),
        (
            with_table(
                "modbus_tcp",
                "transport = { kind = \"tcp\", address = \"192.168.0.20:502\" }\nid = \"other\"",
                "",
            ),
            vec!["devices.rotary_table.modbus.id", "devices.rotary_table.id"],
        ),
        (
            with_table(
                "modbus_tcp",
                "transport = { kind = \"tcp\", address = \"192.168.0.20:502\" }\ntimout_s = 1.0",
                "",
            ),
            vec!["devices.rotary_table.modbus", "unknown field `timout_s`"],
        ),
        (
            with_table(
                "modbus_tcp",
                "transport = { kind = \"tcp\", address = \"not an address\" }",
                "",
            ),
            vec!["devices.rotary_table.modbus.transport"],
        ),
        (
            with_table(
                "modbus_tcp",
                "transport = { kind = \"tcp\", address = \"192.168.0.20:502\" }",
                "",
            )
            .replace("fault_bit = 2", "fault_bit = 0"),
            vec!["devices.rotary_table.modbus", "register map"],
        ),
        (
            with_table(
                "modbus_tcp",
                "",
                "[hil]\nemulate = true\n[hil.table_faults]\ndrop_probability = 1.5\n",
            )
            .replace(
                "id = \"tracer0\"\ndriver = \"sim\"",
                "id = \"tracer0\"\ndriver = \"hpi3d\"",
            ),
            vec!["hil.table_faults.drop_probability", "[0, 1]"],
        ),
        (
            with_table(
                "modbus_tcp",
                "",
                "[hil]\nemulate = true\n[hil.table_faults]\ndrop_at_requests = [0]\n",
            )
            .replace(
                "id = \"tracer0\"\ndriver = \"sim\"",
                "id = \"tracer0\"\ndriver = \"hpi3d\"",
            ),
            vec!["hil.table_faults", "count from 1"],
        ),
        (
            with_table(
                "modbus_tcp",
                "",
                "[hil]\nemulate = true\n[hil.machine_faults]\nreconnect_after_s = -1.0\n",
            )
            .replace(
                "id = \"tracer0\"\ndriver = \"sim\"",
                "id = \"tracer0\"\ndriver = \"hpi3d\"",
            ),
            vec!["hil.machine_faults.reconnect_after_s", "seconds >= 0"],
        ),
        (
            ROTARY.replace(
                "id = \"c\"\ndriver = \"sim\"",
                "id = \"c\"\ndriver = \"modbus\"",
            ),
            vec!["devices.rotary_table.driver", "modbus_tcp"],
        ),
    ];
    for (text, parts) in cases {
        let message = error_of(&text);
        println!("{message}");
        assert_mentions(&message, &[FILE]);
        assert_mentions(&message, &parts);
    }
}
