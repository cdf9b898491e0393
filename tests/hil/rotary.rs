//! Hardware-in-the-loop whole runs of the four-axis method: the tracer stands on a Modbus-TCP
//! rotary table. geocal hosts the HPI-3D and GRBL emulators on ptys and the Modbus table
//! emulator on 127.0.0.1, all backed by the simulated world in real time, and drives them
//! with the real drivers. The stations, points and step angles must match the truth as in
//! the virtual-time run (tests/rotary_run.rs), with and without injected faults.

use crate::common;

use common::{assert_recovers_truth, faults, run_with_truth};
use common::{generous_timeouts, hil_rotary_config};
use geocal::session::messages::{RunEvent, SessionHeader};
use geocal::session::reader::read_session;

/// Run, check the truth (points, stations, home distances; step angles jointly) with
/// `table_stations` stations on the table, return the session's events and header.
fn run_and_check(
    config: &str,
    label: &str,
    table_stations: usize,
) -> (Vec<RunEvent>, SessionHeader) {
    let dir = tempfile::tempdir().expect("tempdir");
    let started = std::time::Instant::now();
    let (output, truth) = run_with_truth(config, dir.path());
    println!("{label}: {:.1} s", started.elapsed().as_secs_f64());
    let Some(results) = output
        .results
        .get::<geocal::kinds::rotary_tracer::solve::RotaryTracerResults>()
    else {
        panic!("expected rotary_tracer results");
    };
    let ml = &results.multilateration;
    assert_eq!(ml.points.len(), 18);
    assert_eq!(ml.stations.len(), table_stations + 1);
    println!(
        "chi2/dof {:.2} (dof {}), residual RMS {:.3e} m",
        ml.chi2_per_dof, ml.dof, ml.residual_rms_m
    );
    assert_recovers_truth(ml, &truth);

    let truth_steps = truth["rotary"]["steps"].as_array().expect("truth steps");
    assert_eq!(results.rotary.steps.len(), table_stations);
    let true_error = |k: usize| truth_steps[k]["error_rad"].as_f64().expect("error_rad");
    let mut step_errors = Vec::new();
    for (k, step) in results.rotary.steps.iter().enumerate().skip(1) {
        let want = true_error(k) - true_error(0);
        println!(
            "{}: error {:.4e} rad, truth {:.4e} rad, sigma {:.2e} rad, z {:+.2}",
            step.station,
            step.error_rad,
            want,
            step.sigma_rad,
            (step.error_rad - want) / step.sigma_rad
        );
        step_errors.push(step.error_rad - want);
        // The encoder angle came over Modbus: the command to the register's count.
        let encoder = step.encoder_rad.expect("encoder angle");
        assert!((encoder - step.commanded_rad).abs() <= 0.5e-7 + 1e-12);
    }
    assert_steps_within_their_covariance(&results.rotary, &step_errors);
    let session = read_session(&output.session_path).expect("session");
    let states = &session.rotary["c"];
    assert!(states.iter().filter(|s| s.msg.in_position).count() >= table_stations);
    let events: Vec<RunEvent> = session.events.into_iter().map(|e| e.msg).collect();
    let rotations = events
        .iter()
        .filter(|e| matches!(e, RunEvent::Rotation { .. }))
        .count();
    assert_eq!(rotations, table_stations);
    (events, session.header)
}

/// A run in real time draws different samples every time, so its step angles are held to
/// the truth jointly, at a stated false-alarm rate: their χ² against the steps' covariance
/// (correlated through the reference station) within its quantile at 1e-4. Every step
/// within 3σ alone would fail about one run in a hundred with honest σ. The fixed-seed run
/// in virtual time (tests/rotary_run.rs) holds each step within 3σ.
fn assert_steps_within_their_covariance(
    rotary: &geocal::kinds::rotary_tracer::solve::RotaryResult,
    step_errors: &[f64],
) {
    let n = step_errors.len();
    let covariance = &rotary.error_covariance_rad2;
    assert_eq!(covariance.len(), n + 1, "covariance over every step");
    let c = nalgebra::DMatrix::from_fn(n, n, |j, k| covariance[j + 1][k + 1]);
    for (k, step) in rotary.steps.iter().enumerate().skip(1) {
        assert!((c[(k - 1, k - 1)].sqrt() - step.sigma_rad).abs() <= 1e-9 * step.sigma_rad);
    }
    let e = nalgebra::DVector::from_column_slice(step_errors);
    let chi2 = e.dot(&c.cholesky().expect("positive definite").solve(&e));
    let bound = geocal::diagnose::stats::chi2_isf(1e-4, n as f64);
    println!("steps: chi2 {chi2:.2} on {n} dof, bound {bound:.1}");
    assert!(chi2 <= bound, "steps: chi2 {chi2} on {n} dof above {bound}");
}

#[test]
fn hil_rotary_run_over_modbus_tcp_recovers_truth() {
    let (events, header) = run_and_check(
        &generous_timeouts(&hil_rotary_config("")),
        "HIL rotary run",
        4,
    );
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

/// ISO 230-2's cycle for the table over Modbus (one ↑ and one ↓ run, each entered through its
/// overshoot) on a table with a reversal: two commands per run's first station reach the
/// emulated table, and every step angle, reversal included, matches the truth.
#[test]
fn hil_rotary_cycle_with_overshoots_over_modbus_tcp_recovers_truth() {
    let config = generous_timeouts(&hil_rotary_config(""))
        .replace("count = 4", "count = 4\nruns = 1")
        .replace(
            "settle_s = 0.05 }",
            "settle_s = 0.05, reversal_rad = 2e-5 }",
        );
    assert!(config.contains("runs = 1") && config.contains("reversal_rad"));
    let (events, _) = run_and_check(&config, "HIL rotary cycle", 8);
    let vias: Vec<f64> = events
        .iter()
        .filter_map(|e| match e {
            RunEvent::Rotation { via_rad, .. } => *via_rad,
            _ => None,
        })
        .collect();
    assert_eq!(vias.len(), 2, "one overshoot per run");
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
    let (events, _) = run_and_check(
        &hil_rotary_config(faults_toml),
        "HIL rotary run with faults",
        4,
    );
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
