//! The four-axis HIL configuration shared by the HIL rotary runs and the two-process
//! `geocal simulate` test: the same devices, emulated in-process or reached by their ports.
#![allow(dead_code)]

const ROTARY: &str = include_str!("../../config/rotary-tracer.toml");

/// The four-axis setup shrunk for real time: 4 table stations 90° apart + 1 off the table,
/// 3 x 3 x 2 points, a 1000 Hz stream, a 20 m/s machine, 30 ms dwells and a fast table.
pub fn rotary_base() -> String {
    let text = ROTARY
        .replace(
            "x = { from = 0.1, to = 0.7, count = 6 }",
            "x = { from = 0.1, to = 0.7, count = 3 }",
        )
        .replace(
            "y = { from = 0.1, to = 0.7, count = 6 }",
            "y = { from = 0.1, to = 0.7, count = 3 }",
        )
        .replace(
            "step_rad = 0.5235987755982988",
            "step_rad = 1.5707963267948966",
        )
        .replace("count = 12", "count = 4")
        .replace(
            "id = \"tracer0\"\ndriver = \"sim\"",
            "id = \"tracer0\"\ndriver = \"hpi3d\"",
        )
        .replace("sample_rate_hz = 25.0", "sample_rate_hz = 1000.0")
        .replace(
            "id = \"env0\"\ndriver = \"sim\"\nsample_rate_hz = 1.0",
            "id = \"env0\"\ndriver = \"hpi3d\"\nsample_rate_hz = 4.0",
        )
        .replace(
            "driver = \"sim\"\nfeed_m_s = 0.3",
            "driver = \"grbl\"\nfeed_m_s = 20.0",
        )
        .replace(
            "id = \"c\"\ndriver = \"sim\"",
            "id = \"c\"\ndriver = \"modbus_tcp\"",
        )
        .replace("dwell_s = 2.0", "dwell_s = 0.03")
        .replace("max_dwell_s = 20.0", "max_dwell_s = 2.0")
        .replace("window_s = 0.6", "window_s = 0.03")
        .replace(
            "axis_tilt_rad = 1e-4 }",
            "axis_tilt_rad = 1e-4, speed_rad_s = 20.0, settle_s = 0.05 }",
        );
    assert!(
        !text.contains("\ndriver = \"sim\""),
        "every device replaced:\n{text}"
    );
    text
}

/// The driver tables: the HPI-3D at `tracer_port`, GRBL at `machine_port`, the Modbus TCP
/// table with `transport` (a TOML inline table, or empty when emulated in-process).
pub fn driver_tables(tracer_port: &str, machine_port: &str, transport: &str) -> String {
    let transport = if transport.is_empty() {
        String::new()
    } else {
        format!("transport = {transport}\n")
    };
    format!(
        "
[devices.tracer.hpi3d]
port = \"{tracer_port}\"
ack_timeout_s = 0.05
retries = 3
stream_timeout_s = 0.2
flag_clear_interval_s = 0.05

[devices.machine.grbl]
port = \"{machine_port}\"
ack_timeout_s = 0.3
status_interval_s = 0.005

# A table counting 1e-7 rad, 32-bit big-endian words, go/ack/clear handshake. No retries
# inside the driver: every timeout reaches the sequencer, which records and retries it.
[devices.rotary_table.modbus]
{transport}timeout_s = 0.2
retries = 0
ack_timeout_s = 1.0
poll_interval_s = 0.01

[devices.rotary_table.modbus.map]
unit_id = 1
target = {{ address = 100, width_bits = 32, word_order = \"big\", counts_per_rad = 1e7 }}
actual = {{ address = 200, kind = \"input\", width_bits = 32, word_order = \"big\", counts_per_rad = 1e7 }}
status = {{ address = 300, kind = \"input\", in_position_bit = 0, moving_bit = 1, fault_bit = 2 }}
command = {{ address = 110, go_value = 1, clear_value = 0 }}
ack = {{ bit = 3 }}
"
    )
}

/// Everything emulated in-process (`[hil] emulate = true`), with `extra` (fault tables).
pub fn hil_rotary_config(extra: &str) -> String {
    format!(
        "{}{}\n[hil]\nemulate = true\n{extra}\n",
        rotary_base(),
        driver_tables("", "", "")
    )
}
