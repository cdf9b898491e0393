//! Hardware-in-the-loop whole runs of the four-axis method: the tracer stands on a Modbus-TCP
//! rotary table. geocal hosts the HPI-3D and GRBL emulators on ptys and the Modbus table
//! emulator on 127.0.0.1, all backed by the simulated world in real time, and drives them
//! with the real drivers. The stations, points and step angles must match the truth as in
//! the virtual-time run (tests/rotary_run.rs), with and without injected faults.

mod common;

use common::{assert_recovers_truth, run_with_truth};
use geocal::method::Results;
use geocal::session::messages::{RunEvent, SessionHeader};
use geocal::session::reader::read_session;

const ROTARY: &str = include_str!("../config/rotary-tracer.toml");

/// The four-axis setup shrunk for real time: 4 table stations 90° apart + 1 off the table,
/// 3 x 3 x 2 points, a 1000 Hz stream, a 20 m/s machine, 30 ms dwells and a fast table.
fn hil_rotary_config(extra: &str) -> String {
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
    format!(
        "{text}
[devices.tracer.hpi3d]
ack_timeout_s = 0.05
retries = 3
stream_timeout_s = 0.2
flag_clear_interval_s = 0.05

[devices.machine.grbl]
port = \"\"
ack_timeout_s = 0.3
status_interval_s = 0.005

# A table counting 1e-7 rad, 32-bit big-endian words, go/ack/clear handshake. No retries
# inside the driver: every timeout reaches the sequencer, which records and retries it.
[devices.rotary_table.modbus]
timeout_s = 0.2
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

[hil]
emulate = true
{extra}
"
    )
}

fn faults<'a>(events: &'a [RunEvent], code: &str) -> Vec<(&'a str, &'a str)> {
    events
        .iter()
        .filter_map(|e| match e {
            RunEvent::Fault {
                device,
                code: c,
                message,
            } if c == code => Some((device.as_str(), message.as_str())),
            _ => None,
        })
        .collect()
}

/// Run, check the truth (points, stations, home distances; step angles within 3 sigma),
/// return the session's events and header.
fn run_and_check(extra: &str, label: &str) -> (Vec<RunEvent>, SessionHeader) {
    let dir = tempfile::tempdir().expect("tempdir");
    let started = std::time::Instant::now();
    let (output, truth) = run_with_truth(&hil_rotary_config(extra), dir.path());
    println!("{label}: {:.1} s", started.elapsed().as_secs_f64());
    let Results::RotaryTracer(results) = &output.results else {
        panic!("expected rotary_tracer results");
    };
    let ml = &results.multilateration;
    assert_eq!(ml.points.len(), 18);
    assert_eq!(ml.stations.len(), 5);
    println!(
        "chi2/dof {:.2} (dof {}), residual RMS {:.3e} m",
        ml.chi2_per_dof, ml.dof, ml.residual_rms_m
    );
    assert_recovers_truth(ml, &truth);

    let truth_steps = truth["rotary"]["steps"].as_array().expect("truth steps");
    assert_eq!(results.rotary.steps.len(), 4);
    let true_error = |k: usize| truth_steps[k]["error_rad"].as_f64().expect("error_rad");
    for (k, step) in results.rotary.steps.iter().enumerate().skip(1) {
        let want = true_error(k) - true_error(0);
        println!(
            "{}: error {:.4e} rad, truth {:.4e} rad, sigma {:.2e} rad",
            step.station, step.error_rad, want, step.sigma_rad
        );
        assert!(
            (step.error_rad - want).abs() <= 3.0 * step.sigma_rad,
            "{}: error {} rad, truth {} rad, sigma {} rad",
            step.station,
            step.error_rad,
            want,
            step.sigma_rad
        );
        // The encoder angle came over Modbus: the command to the register's count.
        let encoder = step.encoder_rad.expect("encoder angle");
        assert!((encoder - step.commanded_rad).abs() <= 0.5e-7 + 1e-12);
    }

    let session = read_session(&output.session_path).expect("session");
    let states = &session.rotary["c"];
    assert!(states.iter().filter(|s| s.msg.in_position).count() >= 4);
    let events: Vec<RunEvent> = session.events.into_iter().map(|e| e.msg).collect();
    let rotations = events
        .iter()
        .filter(|e| matches!(e, RunEvent::Rotation { .. }))
        .count();
    assert_eq!(rotations, 4);
    (events, session.header)
}

#[test]
fn hil_rotary_run_over_modbus_tcp_recovers_truth() {
    let (events, header) = run_and_check("", "HIL rotary run");
    let table = header
        .devices
        .iter()
        .find(|d| d.id == "c")
        .expect("table in the header");
    assert_eq!(table.driver, "modbus_tcp");
    let fault_list: Vec<_> = events
        .iter()
        .filter(|e| matches!(e, RunEvent::Fault { .. }))
        .collect();
    assert!(
        fault_list.is_empty(),
        "faults without injection: {fault_list:?}"
    );
}

#[test]
fn hil_rotary_run_with_every_fault_completes_and_recovers_truth() {
    let faults_toml = "
[hil.tracer_faults]
seed = 11
drop_fraction = 0.002
corrupt_fraction = 0.002
silence = { from_s = 2.0, to_s = 2.5 }
beam_break = { from_s = 5.0, to_s = 5.3 }

[hil.machine_faults]
drop_ok_at_lines = [25]
disconnect_at_line = 40
reconnect_after_s = 0.3
alarm_at_line = 60
alarm_after_s = 0.02
alarm_code = 1

[hil.table_faults]
drop_at_requests = [12]
";
    let (events, _) = run_and_check(faults_toml, "HIL rotary run with faults");
    for e in &events {
        if let RunEvent::Fault { .. } | RunEvent::Rehome { .. } = e {
            println!("{e:?}");
        }
    }
    // Dropped frames and frames that failed their CRC: gaps in the tracer's seq.
    assert!(!faults(&events, "frames_lost").is_empty(), "lost frames");
    let timeouts = faults(&events, "timeout");
    // The silent tracer: stream timeouts, retried.
    assert!(
        timeouts.iter().any(|(d, _)| *d == "tracer0"),
        "tracer timeouts"
    );
    // The lost `ok`: a machine timeout, retried.
    assert!(timeouts.iter().any(|(d, _)| *d == "vmc"), "machine timeout");
    // The unanswered Modbus request: a table timeout; the driver reconnected and the
    // sequencer retried.
    assert!(
        timeouts.iter().any(|(d, _)| *d == "c"),
        "Modbus table timeout"
    );
    // Frames that failed their CRC, counted by the driver.
    assert!(
        faults(&events, "crc").iter().any(|(d, _)| *d == "tracer0"),
        "CRC failures"
    );
    // The pulled GRBL cable: detected, the port reopened by its path, the move re-sent.
    assert_eq!(
        faults(&events, "disconnect"),
        faults(&events, "disconnect")
            .into_iter()
            .filter(|(d, _)| *d == "vmc")
            .collect::<Vec<_>>()
    );
    assert_eq!(faults(&events, "disconnect").len(), 1, "one disconnect");
    let reconnects = faults(&events, "reconnect");
    assert!(
        reconnects.iter().any(|(d, _)| *d == "vmc"),
        "GRBL reconnect"
    );
    // The Modbus timeout: the driver dropped the connection and opened a new one.
    assert!(
        reconnects.iter().any(|(d, _)| *d == "c"),
        "Modbus reconnect"
    );
    // The GRBL alarm: recorded, unlocked, the move commanded again.
    let alarms = faults(&events, "alarm");
    assert_eq!(alarms.len(), 1, "{alarms:?}");
    assert!(alarms[0].0 == "vmc" && alarms[0].1.contains("ALARM:1"));
    // The beam break: a fault, then a re-homing in a new beam segment.
    let breaks = faults(&events, "beam_break").len();
    let rehomes = events
        .iter()
        .filter(|e| matches!(e, RunEvent::Rehome { .. }))
        .count();
    assert!(breaks >= 1, "beam break recorded");
    assert_eq!(rehomes, breaks, "one rehome per beam break");
}
