//! Real-controller HIL: geocal starts LinuxCNC headless (its own namespace, under the global
//! lock), drives it with the `linuxcnc` driver over linuxcncrsh, and the simulated world's
//! carriages follow LinuxCNC's `joint.N.motor-pos-cmd`, its compensation trim included; the
//! emulated HPI-3D measures the result. Skips without LinuxCNC (saying why), fails when `CI`
//! is set.

mod common;

use common::{assert_recovers_truth, generous_timeouts, hil_config, run_with_truth};
use geocal::compensate::{export, Calibration, ExportOptions, TableFormat, POSITIONING};

fn available() -> bool {
    match geocal::sim::linuxcnc::unavailable() {
        None => true,
        Some(why) if std::env::var_os("CI").is_some() => {
            panic!("CI must run the LinuxCNC tests, but {why}")
        }
        Some(why) => {
            eprintln!("skipping the LinuxCNC tests: {why}");
            false
        }
    }
}

/// The HIL configuration with LinuxCNC as the machine: velocity and acceleration such that
/// a run takes a minute (G0 moves at `feed_m_s`, MAX_ACCELERATION 20 m/s², a 0.25 ms servo
/// period keeps the dead band at 0.3–0.6 µm).
pub fn linuxcnc_config(extra: &str) -> String {
    let text = generous_timeouts(&hil_config(extra))
        .replace(
            "driver = \"grbl\"\nfeed_m_s = 20.0",
            "driver = \"linuxcnc\"\nfeed_m_s = 2.0",
        )
        .replace(
            "[devices.machine.grbl]\nport = \"\"\nack_timeout_s = 2.0\nstatus_interval_s = 0.005\n",
            "[devices.machine.linuxcnc]\nmotion = \"rapid\"\nstatus_interval_s = 0.005\n\
             reply_timeout_s = 30.0\nstall_timeout_s = 30.0\n",
        );
    assert!(
        text.contains("driver = \"linuxcnc\"") && !text.contains("[devices.machine.grbl]"),
        "{text}"
    );
    format!("{text}\n[hil.linuxcnc]\nmax_acceleration_m_s2 = 20.0\nservo_period_s = 0.00025\n")
}

#[test]
fn linuxcnc_hil_run_recovers_truth() {
    if !available() {
        return;
    }
    let dir = tempfile::tempdir().expect("tempdir");
    let started = std::time::Instant::now();
    let (output, truth) = run_with_truth(&linuxcnc_config(""), dir.path());
    println!("LinuxCNC HIL run: {:.1} s", started.elapsed().as_secs_f64());
    let results = output.results.multilateration().expect("tracer results");
    assert_eq!(results.points.len(), 18);
    println!(
        "chi2/dof {:.2} (dof {}), residual RMS {:.3e} m",
        results.chi2_per_dof, results.dof, results.residual_rms_m
    );
    assert_recovers_truth(results, &truth);
    let _ = (
        export,
        Calibration::load,
        ExportOptions::default,
        TableFormat::Csv,
        POSITIONING,
    );
}
