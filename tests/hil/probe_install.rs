//! Hardware-in-the-loop run of the laser-probe installation method: the real GRBL driver (a
//! 5-axis controller, X Y Z in mm and A B in degrees on the wire) and the real ASCII probe
//! driver talk over pseudo-terminals to their emulators, backed by the simulated world. The
//! run must recover the 11 installation parameters within the reported uncertainties, match
//! the virtual-time simulated run of the same seed up to the wire's resolution, and record
//! every injected fault the drivers or the sequencer recover from as its `fault` event.

use crate::common;

use std::path::Path;

use geocal::run::{RunOptions, RunOutput};
use geocal::session::reader::read_session;
use serde_json::Value;

const EXAMPLE: &str = include_str!("../../config/probe-install.toml");

/// The example with a fast machine (the emulators run in real time) and a short GA (the GA
/// is not what this test is about).
fn fast_example() -> String {
    EXAMPLE
        .replace("feed_m_s = 0.02", "feed_m_s = 1.0")
        .replace("rotary_speed_rad_s = 0.5", "rotary_speed_rad_s = 20.0")
        .replace("ga_generations = 2000", "ga_generations = 100")
}

/// The same plan on the GRBL and ASCII drivers against their emulators, with faults.
fn hil_config(faults: &str) -> String {
    fast_example()
        .replace(
            "driver = \"sim\"                 # or \"grbl\"",
            "driver = \"grbl\" #",
        )
        .replace(
            "driver = \"sim\"                 # or \"ascii\"",
            "driver = \"ascii\" #",
        )
        .replace(
            "[devices.probe]",
            "poll_interval_s = 0.002\n\
             [devices.machine.grbl]\n\
             port = \"(emulated)\"\n\
             ack_timeout_s = 0.5\n\
             status_interval_s = 0.002\n\
             [devices.probe]",
        )
        .replace(
            "[plan]",
            "[devices.probe.ascii]\nport = \"(emulated)\"\ntimeout_s = 0.5\n[plan]",
        )
        + "\n[hil]\nemulate = true\n"
        + faults
}

fn run(config_text: &str, dir: &Path) -> (RunOutput, Value) {
    common::run_kind(config_text, dir, "probe-install.toml")
}

#[test]
fn grbl_and_ascii_probe_over_ptys_recover_the_installation_through_faults() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (sim, _) = run(&fast_example(), &dir.path().join("sim"));
    // GRBL lines count from 1 (moves and `$X`): a lost `ok` on line 7, a pulled cable on line
    // 30 (plugged back after 0.2 s), a limit alarm on line 60; the probe ignores request 10
    // and answers request 40 with garbage.
    let faults = "machine_faults = { drop_ok_at_lines = [7], disconnect_at_line = 30, \
                  reconnect_after_s = 0.2, alarm_at_line = 60 }\n\
                  probe_faults = { no_answer_at_requests = [10], garbage_at_requests = [40] }\n";
    let (hil, truth) = run(&hil_config(faults), &dir.path().join("hil"));
    type ProbeInstallResults = geocal::kinds::probe_install::solve::ProbeInstallResults;
    let (Some(s), Some(r)) = (
        sim.results.get::<ProbeInstallResults>(),
        hil.results.get::<ProbeInstallResults>(),
    ) else {
        panic!("expected probe_install results");
    };
    assert_eq!(
        (r.points, r.readings, r.readings_out_of_range),
        (100, 500, 0)
    );

    // Each parameter within 4 of its reported sigmas of the truth (11 normalised errors,
    // each N(0, 1) for a correct covariance: P(any |z| > 4) < 1e-3); and the HIL estimate
    // equals the virtual-time run's up to the wire's rounding (readings to 0.1 µm, positions
    // to 0.1 µm and 1e-5°, about a tenth of the 0.45 µm noise of a point): within 0.2 σ.
    let truth_params = truth["parameters"].as_array().expect("truth parameters");
    let mut sum_z2 = 0.0;
    for ((p, q), t) in r.parameters.iter().zip(&s.parameters).zip(truth_params) {
        assert_eq!(t["name"], p.name.as_str());
        let z =
            (p.value - t["value"].as_f64().expect("truth value")) / p.sigma.expect("identifiable");
        let d = (p.value - q.value) / p.sigma.expect("identifiable");
        println!("{:<18} z {z:+.2}  HIL - sim {d:+.3} sigma", p.name);
        assert!(z.abs() <= 4.0, "{}: {z:.2} sigma from the truth", p.name);
        assert!(d.abs() <= 0.2, "{}: {d:.3} sigma from the sim run", p.name);
        sum_z2 += z * z;
    }
    // chi²/dof of 90 degrees of freedom: standard deviation 0.15; [0.6, 1.5] is about ±3.
    println!(
        "chi2/dof {:.3} (sim {:.3}), rms normalised error {:.2}, radius after {:.4} mm",
        r.chi2_per_dof.expect("redundant"),
        s.chi2_per_dof.expect("redundant"),
        (sum_z2 / 11.0).sqrt(),
        r.radius_after_m * 1e3
    );
    assert!(
        (0.6..=1.5).contains(&r.chi2_per_dof.expect("redundant")),
        "{}",
        r.chi2_per_dof.expect("redundant")
    );
    assert!((r.radius_after_m - 6e-3).abs() < 1e-6);

    // Every fault as its event, in the order the run met them.
    let session = read_session(&hil.session_path).expect("read session");
    assert_eq!(session.header.devices[0].driver, "grbl");
    assert_eq!(session.header.devices[1].driver, "ascii");
    assert_eq!(session.probes["laser0"].len(), 500);
    let events: Vec<_> = session.events.iter().map(|e| e.msg.clone()).collect();
    let cmm = common::faults(&events, "timeout")
        .into_iter()
        .filter(|(d, _)| *d == "cmm")
        .count();
    let probe_timeouts = common::faults(&events, "timeout")
        .into_iter()
        .filter(|(d, _)| *d == "laser0")
        .count();
    println!("faults: {:?}", common::faults(&events, "protocol"));
    assert_eq!(cmm, 1, "the lost `ok`");
    assert_eq!(probe_timeouts, 1, "the unanswered request");
    assert_eq!(
        common::faults(&events, "protocol").len(),
        1,
        "the garbage reply"
    );
    assert_eq!(common::faults(&events, "disconnect").len(), 1);
    assert_eq!(common::faults(&events, "reconnect").len(), 1);
    assert_eq!(common::faults(&events, "alarm").len(), 1);
    assert_eq!(hil.summary.faults, 6);

    // The recording alone gives the same results (`geocal solve`).
    let replay = geocal::kinds::solve_file(&hil.session_path, &Default::default()).expect("solve");
    assert_eq!(replay.to_json_pretty(), hil.results.to_json_pretty());
}

/// Real devices at their ports (no `[hil]`): the drivers open the serial paths named in the
/// configuration and the run is stamped by the system clock. Here the "devices" are the same
/// emulators, hosted by the test on its own runtime as another process would host them, with
/// the simulated world behind them; its truth grades the result.
#[test]
fn real_ports_without_hil_are_opened_by_path() {
    use std::sync::{Arc, Mutex};

    use geocal::kinds::probe_install::config::ProbeInstallConfig;
    use geocal::kinds::probe_install::hil_source::{WorldCmmSink, WorldLaserSource};
    use geocal::kinds::probe_install::sim::ProbeInstallWorld;
    use geocal::sim::hil::HilTime;
    use geocal_drivers::grbl::{GrblEmulator, GrblEmulatorConfig};
    use geocal_drivers::probe::{ProbeEmulator, ProbeEmulatorConfig};

    let dir = tempfile::tempdir().expect("tempdir");
    let sim_config = ProbeInstallConfig::parse(&fast_example(), Path::new("probe-install.toml"))
        .expect("config");
    let world = Arc::new(Mutex::new(ProbeInstallWorld::new(
        &sim_config,
        Arc::new(geocal::clock::VirtualClock::new(0)),
    )));
    let time = Arc::new(HilTime::new(0));
    let devices = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .expect("runtime");
    let (grbl, probe) = devices.block_on(async {
        let grbl = GrblEmulator::spawn_pty(
            GrblEmulatorConfig {
                travel_min_m: [0.0, 0.0, -0.3],
                travel_max_m: [0.3, 0.3, 0.0],
                ..GrblEmulatorConfig::default()
            },
            Box::new(WorldCmmSink::new(world.clone(), time.clone())),
        )
        .expect("GRBL emulator");
        let probe = ProbeEmulator::spawn_pty(
            ProbeEmulatorConfig::default(),
            Box::new(WorldLaserSource::new(world.clone(), time.clone())),
        )
        .expect("probe emulator");
        (grbl, probe)
    });
    let grbl_port = grbl.slave_path().expect("GRBL pty path").to_string();
    let probe_port = probe.slave_path().expect("probe pty path").to_string();
    // The real configuration: the two drivers at those ports, no [sim], no [hil].
    let text = hil_config("");
    let text = text[..text.find("\n[sim]").expect("[sim]")]
        .replace(
            "port = \"(emulated)\"\nack_timeout_s",
            &format!("port = \"{grbl_port}\"\nack_timeout_s"),
        )
        .replace(
            "port = \"(emulated)\"\ntimeout_s",
            &format!("port = \"{probe_port}\"\ntimeout_s"),
        );
    assert!(!text.contains("(emulated)") && !text.contains("\n[hil]"));
    let path = dir.path().join("real.toml");
    std::fs::write(&path, &text).expect("write config");
    let output = geocal::kinds::run_file(
        &path,
        &RunOptions {
            out_dir: dir.path().to_path_buf(),
            truth: None,
            progress: false,
            settings: Default::default(),
            control: Default::default(),
        },
    )
    .expect("run")
    .expect("probe_install");
    let Some(r) = output
        .results
        .get::<geocal::kinds::probe_install::solve::ProbeInstallResults>()
    else {
        panic!("expected probe_install results");
    };
    assert_eq!((r.points, r.readings), (100, 500));
    let truth = world.lock().expect("world").truth();
    for (p, t) in r.parameters.iter().zip(&truth.parameters) {
        let z = (p.value - t.value) / p.sigma.expect("identifiable");
        assert!(z.abs() <= 4.0, "{}: {z:.2} sigma from the truth", p.name);
    }
    assert!(
        (0.6..=1.5).contains(&r.chi2_per_dof.expect("redundant")),
        "{}",
        r.chi2_per_dof.expect("redundant")
    );
    let session = read_session(&output.session_path).expect("session");
    assert_eq!(session.header.devices[0].driver, "grbl");
    let faults = session
        .events
        .iter()
        .filter(|e| matches!(e.msg, geocal::session::messages::RunEvent::Fault { .. }))
        .count();
    assert_eq!(faults, 0);
    drop((grbl, probe));
}

/// An emulated run killed in the middle of posture 2 (after its 301st probe reading) resumes
/// with `geocal run --resume` on the host clock: the kept messages first, unchanged, postures
/// 2 and 3 measured over the ptys again, every point used once and the installation
/// recovered (each parameter within 4 of its sigmas, chi²/dof in [0.6, 1.5], as above).
#[test]
fn a_killed_emulated_run_resumes_at_its_unfinished_posture() {
    use geocal::session::messages::RunEvent;
    let dir = tempfile::tempdir().expect("tempdir");
    let full_dir = dir.path().join("full");
    run(&hil_config(""), &full_dir);
    let killed_dir = dir.path().join("killed");
    let (messages, cut) = common::killed_run_dir(&full_dir, &killed_dir, |messages| {
        messages
            .iter()
            .enumerate()
            .filter(|(_, m)| m.channel.topic.starts_with("/probe/"))
            .nth(300)
            .map(|(i, _)| i + 1)
            .expect("301 readings")
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
    let postures_after: Vec<usize> = resumed.events[resume_at..]
        .iter()
        .filter_map(|e| match e.msg {
            RunEvent::PostureBegin { posture, .. } => Some(posture),
            _ => None,
        })
        .collect();
    assert_eq!(postures_after, vec![2, 3]);
    assert!(common::interrupted_files_left(&killed_dir).is_empty());
    let results = geocal::kinds::solve_file(&resumed_path, &Default::default()).expect("solve");
    let Some(r) = results.get::<geocal::kinds::probe_install::solve::ProbeInstallResults>() else {
        panic!("expected probe_install results");
    };
    assert_eq!(
        (r.points, r.readings, r.readings_out_of_range),
        (100, 500, 0)
    );
    let truth: Value = serde_json::from_str(
        &std::fs::read_to_string(killed_dir.join("truth.json")).expect("truth"),
    )
    .expect("truth JSON");
    let truth_params = truth["parameters"].as_array().expect("truth parameters");
    for (p, t) in r.parameters.iter().zip(truth_params) {
        assert_eq!(t["name"], p.name.as_str());
        let z =
            (p.value - t["value"].as_f64().expect("truth value")) / p.sigma.expect("identifiable");
        assert!(z.abs() <= 4.0, "{}: {z:.2} sigma from the truth", p.name);
    }
    println!(
        "resumed emulated run: chi2/dof {:.3}",
        r.chi2_per_dof.expect("redundant")
    );
    assert!(
        (0.6..=1.5).contains(&r.chi2_per_dof.expect("redundant")),
        "{}",
        r.chi2_per_dof.expect("redundant")
    );
}
