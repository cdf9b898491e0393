//! Hardware-in-the-loop runs of the hexapod hinge calibration: the real Modbus hexapod driver
//! talks over TCP on 127.0.0.1 to the hexapod emulator the run hosts, backed by the simulated
//! hexapod; the 36 hinge coordinates must match the truth within the reported uncertainties,
//! and an unanswered Modbus request must show as its `timeout` and `reconnect` fault events.

use crate::common;

use std::path::Path;

use geocal::kinds::solve_file;
use geocal::method::Results;
use geocal::run::RunOutput;
use geocal::session::kind_messages::{hexapod_legs_topic, hexapod_pose_topic};
use geocal::session::reader::read_session;
use serde_json::Value;

const EXAMPLE: &str = include_str!("../../config/hexapod.toml");

/// The example with the hexapod over Modbus TCP (emulated under `[hil]`), a fast simulated
/// platform, and `faults` for the emulator. The platform's poses are measured by the example's
/// simulated pose sensor: the emulated platform reaches the forward kinematics of its design
/// leg lengths, not the commanded pose, so given (commanded) poses would hide the hinge errors.
fn hil_config(faults: &str) -> String {
    let devices = EXAMPLE;
    let text = devices
        .replacen("\ndriver = \"sim\"", "\ndriver = \"modbus_tcp\"", 1)
        .replace("speed_m_s = 0.01", "speed_m_s = 2.0")
        .replace("angular_speed_rad_s = 0.05", "angular_speed_rad_s = 20.0");
    assert!(text.contains("driver = \"modbus_tcp\"") && text.contains("speed_m_s = 2.0"));
    format!(
        "{text}
[devices.hexapod.modbus]
timeout_s = 0.2
retries = 0                 # every timeout reaches the sequencer as a `fault` event
poll_interval_s = 0.002
[devices.hexapod.modbus.map]
pose_target = {{ address = 100, counts_per_m = 1e7, counts_per_rad = 1e7 }}
legs = {{ address = 200, kind = \"input\", m_per_count = 1e-7 }}
status = {{ address = 300, kind = \"input\", in_position_bit = 0, moving_bit = 1, fault_bit = 2 }}
command = {{ address = 120, go_value = 1, clear_value = 0 }}
ack = {{ bit = 3 }}

[hil]
emulate = true
{faults}
"
    )
}

fn run(config_text: &str, dir: &Path) -> (RunOutput, Value) {
    let started = std::time::Instant::now();
    let run = common::run_kind(config_text, dir, "hexapod-hil.toml");
    println!("run: {:.1} s", started.elapsed().as_secs_f64());
    run
}

/// Every coordinate within 4 of its reported sigmas (as tests/hexapod_run.rs: for a correct
/// covariance each normalised error is N(0, 1); 36 fail by chance with probability 0.2 %),
/// and chi²/dof of the 138 degrees of freedom within ±3 of its standard deviation 0.12.
fn assert_hinges_recovered(results: &Results, truth: &Value) {
    let Some(r) = results.get::<geocal::kinds::hexapod::solve::HexapodResults>() else {
        panic!("expected hexapod results");
    };
    assert_eq!((r.poses, r.readings), (30, 129));
    assert_eq!(r.pose_source, "measured");
    let mut sum_z2 = 0.0;
    for h in &r.hinges {
        for k in 0..3 {
            for (what, est, sigma, t) in [
                (
                    "B",
                    h.base_m[k],
                    h.base_sigma_m[k],
                    &truth["base_m"][h.leg][k],
                ),
                (
                    "P",
                    h.platform_m[k],
                    h.platform_sigma_m[k],
                    &truth["platform_m"][h.leg][k],
                ),
            ] {
                let z = (est - t.as_f64().expect("number")) / sigma;
                assert!(z.abs() <= 4.0, "leg {} {what}{k}: {z:.2} sigma", h.leg);
                sum_z2 += z * z;
            }
        }
    }
    println!(
        "rms normalised error {:.2}, chi2/dof {:.3}",
        (sum_z2 / 36.0).sqrt(),
        r.chi2_per_dof.unwrap_or(f64::NAN)
    );
    assert!(
        (0.65..=1.35).contains(&r.chi2_per_dof.unwrap_or(f64::NAN)),
        "{}",
        r.chi2_per_dof.unwrap_or(f64::NAN)
    );
    assert!(r.objective_m2 <= r.two_stage.objective_initial_m2);
}

#[test]
fn modbus_tcp_hexapod_recovers_the_hinges() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (output, truth) = run(&hil_config(""), dir.path());
    assert_hinges_recovered(&output.results, &truth);
    let session = read_session(&output.session_path).expect("read session");
    let hex = session
        .header
        .devices
        .iter()
        .find(|d| d.kind == "hexapod")
        .expect("hexapod device");
    assert_eq!(hex.driver, "modbus_tcp");
    assert_eq!(hex.extra["modbus"]["emulated"], Value::Bool(true));
    let sensor = session
        .header
        .devices
        .iter()
        .find(|d| d.kind == "pose_sensor")
        .expect("pose sensor device");
    assert_eq!(sensor.driver, "sim");
    assert_eq!(session.topics[&hexapod_legs_topic("hex0")].len(), 129);
    assert_eq!(session.topics[&hexapod_pose_topic("hex0")].len(), 30);
    let events: Vec<_> = session.events.iter().map(|e| e.msg.clone()).collect();
    for code in ["timeout", "reconnect", "protocol"] {
        assert!(common::faults(&events, code).is_empty(), "{code}");
    }
    // The recording alone gives the same results.
    let replay = solve_file(&output.session_path, &Default::default()).expect("solve");
    assert_eq!(replay.to_json_pretty(), output.results.to_json_pretty());
}

#[test]
fn unanswered_modbus_requests_are_timeouts_then_reconnects() {
    let dir = tempfile::tempdir().expect("tempdir");
    // Requests 10 and 100 (of some 300): in the first moves and among the leg readings.
    let (output, truth) = run(
        &hil_config("hexapod_faults = { drop_at_requests = [10, 100] }"),
        dir.path(),
    );
    assert_hinges_recovered(&output.results, &truth);
    let session = read_session(&output.session_path).expect("read session");
    let events: Vec<_> = session.events.iter().map(|e| e.msg.clone()).collect();
    let timeouts = common::faults(&events, "timeout");
    let reconnects = common::faults(&events, "reconnect");
    assert_eq!(timeouts.len(), 2, "{timeouts:?}");
    assert_eq!(reconnects.len(), 2, "{reconnects:?}");
    for (device, message) in timeouts.iter().chain(&reconnects) {
        assert_eq!(*device, "hex0", "{message}");
    }
    assert!(reconnects[0].1.contains("no reply"), "{}", reconnects[0].1);
    // No reading lost: every leg reading the plan asks for is in the session.
    assert_eq!(session.topics[&hexapod_legs_topic("hex0")].len(), 129);
}

#[test]
fn bad_modbus_configs_give_file_key_and_expectation() {
    let example = hil_config("");
    let cases = [
        (
            "\nack = { bit = 3 }",
            "\nack = { bit = 0 }",
            "key `devices.hexapod.modbus`: register map: ack.bit 0 in the status register collides",
        ),
        (
            "\nlegs = { address = 200, kind = \"input\", m_per_count = 1e-7 }",
            "\nlegs = { address = 200, kind = \"input\" }",
            "key `devices.hexapod.modbus`: register map: legs: give exactly one of counts_per_m and m_per_count",
        ),
        (
            "\nemulate = true",
            "\nemulate = false",
            "key `devices.hexapod.modbus.transport`: missing: a real hexapod needs",
        ),
        (
            "\ntimeout_s = 0.2",
            "\ntimeout = 0.2",
            "key `devices.hexapod.modbus.timeout`",
        ),
    ];
    common::assert_run_rejects(env!("CARGO_BIN_EXE_geocal"), &example, &cases);
}

/// An emulated run killed in the middle of pose 15 (after its measured pose, before its leg
/// reading) resumes with `geocal run --resume` on the host clock: the kept messages first,
/// unchanged, the poses from 15 on measured over Modbus again, every pose used once and the
/// hinges recovered.
#[test]
fn a_killed_emulated_run_resumes_at_its_unfinished_pose() {
    use geocal::session::messages::RunEvent;
    let dir = tempfile::tempdir().expect("tempdir");
    let full_dir = dir.path().join("full");
    run(&hil_config(""), &full_dir);
    let killed_dir = dir.path().join("killed");
    let pose_topic = hexapod_pose_topic("hex0");
    let (messages, cut) = common::killed_run_dir(&full_dir, &killed_dir, |messages| {
        messages
            .iter()
            .enumerate()
            .filter(|(_, m)| m.channel.topic == pose_topic)
            .nth(15)
            .map(|(i, _)| i + 1)
            .expect("16 measured poses")
    });
    common::resume_cli(env!("CARGO_BIN_EXE_geocal"), &killed_dir);
    let resumed_path = killed_dir.join("session.mcap");
    let (resumed, resumed_messages) =
        geocal::session::reader::read_session_raw(&resumed_path).expect("resumed session");
    assert!(resumed.completeness.is_complete());
    assert_eq!(&resumed_messages[..cut], &messages[..cut], "kept messages");
    let resume_at = resumed
        .events
        .iter()
        .position(|e| matches!(e.msg, RunEvent::Resume { .. }))
        .expect("a resume event");
    let poses_after: Vec<usize> = resumed.events[resume_at..]
        .iter()
        .filter_map(|e| match e.msg {
            RunEvent::PoseBegin { pose, .. } => Some(pose),
            _ => None,
        })
        .collect();
    assert_eq!(poses_after, (15..30).collect::<Vec<_>>());
    assert!(common::interrupted_files_left(&killed_dir).is_empty());
    let results = solve_file(&resumed_path, &Default::default()).expect("solve");
    let truth: Value = serde_json::from_str(
        &std::fs::read_to_string(killed_dir.join("truth.json")).expect("truth"),
    )
    .expect("truth JSON");
    assert_hinges_recovered(&results, &truth);
}
