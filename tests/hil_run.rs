//! Hardware-in-the-loop whole runs: geocal hosts the HPI-3D and GRBL emulators on ptys,
//! backed by the simulated world in real time, and drives them with the real protocol
//! drivers. The recovered geometry must match the truth as in the virtual-time demo run,
//! with and without injected faults.

mod common;

use common::{
    assert_recovers_truth, faults, generous_timeouts, hil_config, run_with_truth, HIL_FAULTS,
};
use geocal::session::messages::RunEvent;
use geocal::session::reader::read_session;

fn events(session: &std::path::Path) -> Vec<RunEvent> {
    read_session(session)
        .expect("session")
        .events
        .into_iter()
        .map(|e| e.msg)
        .collect()
}

#[test]
fn hil_run_recovers_truth() {
    let dir = tempfile::tempdir().expect("tempdir");
    let started = std::time::Instant::now();
    let (output, truth) = run_with_truth(&generous_timeouts(&hil_config("")), dir.path());
    println!("HIL run: {:.1} s", started.elapsed().as_secs_f64());
    let results = output.results.multilateration().expect("tracer results");
    assert_eq!(results.points.len(), 18);
    println!(
        "chi2/dof {:.2} (dof {}), residual RMS {:.3e} m",
        results.chi2_per_dof, results.dof, results.residual_rms_m
    );
    assert_recovers_truth(results, &truth);
    let events = events(&output.session_path);
    let fault_list: Vec<_> = events
        .iter()
        .filter(|e| matches!(e, RunEvent::Fault { .. }))
        .collect();
    assert!(
        fault_list.is_empty(),
        "faults without injection: {fault_list:?}"
    );
    assert!(output.summary.env_samples > 0, "meteo stream recorded");
}

#[test]
fn hil_run_with_faults_completes_and_recovers_truth() {
    let dir = tempfile::tempdir().expect("tempdir");
    let started = std::time::Instant::now();
    let (output, truth) = run_with_truth(&hil_config(HIL_FAULTS), dir.path());
    println!(
        "HIL run with faults: {:.1} s",
        started.elapsed().as_secs_f64()
    );
    let results = output.results.multilateration().expect("tracer results");
    assert_eq!(results.points.len(), 18);
    println!(
        "chi2/dof {:.2} (dof {}), residual RMS {:.3e} m",
        results.chi2_per_dof, results.dof, results.residual_rms_m
    );
    assert_recovers_truth(results, &truth);

    let events = events(&output.session_path);
    for e in &events {
        if let RunEvent::Fault { .. } | RunEvent::Rehome { .. } = e {
            println!("{e:?}");
        }
    }
    // Dropped and corrupted frames: gaps in the tracer's seq.
    assert!(!faults(&events, "frames_lost").is_empty(), "lost frames");
    // The silent tracer: stream timeouts, retried.
    assert!(
        faults(&events, "timeout")
            .iter()
            .any(|(device, _)| *device == "tracer0"),
        "tracer timeouts"
    );
    // The lost `ok`: a machine timeout, retried.
    assert!(
        faults(&events, "timeout")
            .iter()
            .any(|(device, _)| *device == "cmm"),
        "machine timeout"
    );
    // The beam break: a fault, then a re-homing in a new beam segment.
    let breaks = faults(&events, "beam_break").len();
    let rehomes = events
        .iter()
        .filter(|e| matches!(e, RunEvent::Rehome { .. }))
        .count();
    assert!(breaks >= 1, "beam break recorded");
    assert_eq!(rehomes, breaks, "one rehome per beam break");
    println!(
        "windows repeated after the beam break: {}",
        results.extraction.windows_repeated
    );
}
