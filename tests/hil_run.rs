//! Hardware-in-the-loop whole runs: geocal hosts the HPI-3D and GRBL emulators on ptys,
//! backed by the simulated world in real time, and drives them with the real protocol
//! drivers. The recovered geometry must match the truth as in the virtual-time demo run,
//! with and without injected faults.

mod common;

use common::{assert_recovers_truth, run_with_truth, small_demo};
use geocal::session::messages::RunEvent;
use geocal::session::reader::read_session;

/// The small demo (4 stations x 3x3x2 points, one pass) over the emulators: a 1000 Hz
/// stream, a fast machine and short dwells so the run takes seconds of real time. The
/// stillstand window holds 30 samples; its tolerance stays the demo's.
fn hil_config(extra: &str) -> String {
    let base = small_demo();
    let text = base
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
            "passes = [\"forward\", \"backward\"]",
            "passes = [\"forward\"]",
        )
        .replace("dwell_s = 2.0", "dwell_s = 0.03")
        .replace("max_dwell_s = 20.0", "max_dwell_s = 2.0")
        .replace("window_s = 0.6", "window_s = 0.03");
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

[hil]
emulate = true
{extra}
"
    )
}

fn events(session: &std::path::Path) -> Vec<RunEvent> {
    read_session(session)
        .expect("session")
        .events
        .into_iter()
        .map(|e| e.msg)
        .collect()
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

#[test]
fn hil_run_recovers_truth() {
    let dir = tempfile::tempdir().expect("tempdir");
    let started = std::time::Instant::now();
    let (output, truth) = run_with_truth(&hil_config(""), dir.path());
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
    let faults_toml = "
[hil.tracer_faults]
seed = 7
drop_fraction = 0.002
corrupt_fraction = 0.002
garbage_fraction = 0.002
silence = { from_s = 3.0, to_s = 3.5 }
beam_break = { from_s = 6.0, to_s = 6.3 }

[hil.machine_faults]
drop_ok_at_lines = [20]
";
    let dir = tempfile::tempdir().expect("tempdir");
    let started = std::time::Instant::now();
    let (output, truth) = run_with_truth(&hil_config(faults_toml), dir.path());
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
