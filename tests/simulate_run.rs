//! `geocal simulate` and `geocal run` as two processes, as on a real machine: simulate hosts
//! the HPI-3D and GRBL emulators on ptys and the Modbus-TCP table on 127.0.0.1; the run's
//! config points its drivers at the printed endpoints (no `[hil]`); the run's console
//! operator prompts are carried out through simulate's operator channel. The results must
//! match the truth simulate writes, within what the noise model predicts.

mod common;

use std::io::{BufRead, BufReader, Write};
use std::process::{Command, Stdio};

use common::assert_recovers_truth;
use common::{driver_tables, hil_rotary_config, rotary_base};

const GEOCAL: &str = env!("CARGO_BIN_EXE_geocal");

#[test]
fn simulate_and_run_as_two_processes() {
    let dir = tempfile::tempdir().expect("tempdir");
    let sim_cfg = dir.path().join("simulate.toml");
    // simulate reads the in-process HIL configuration (its [hil] tables give the faults).
    std::fs::write(&sim_cfg, hil_rotary_config("")).expect("write");
    let truth_path = dir.path().join("truth.json");
    let mut simulate = common::Simulated::start(GEOCAL, &sim_cfg, &truth_path);
    let (tracer, machine, table) = (
        simulate.endpoint("tracer"),
        simulate.endpoint("machine"),
        simulate.endpoint("rotary_table"),
    );
    println!("simulate: tracer {tracer}, machine {machine}, table {table}");
    assert!(table.starts_with("127.0.0.1:"), "{table}");

    // The run: real drivers at those endpoints, nothing emulated in this process.
    let run_cfg = dir.path().join("run.toml");
    let transport = format!("{{ kind = \"tcp\", address = \"{table}\" }}");
    std::fs::write(
        &run_cfg,
        format!(
            "{}{}",
            rotary_base(),
            driver_tables(&tracer, &machine, &transport)
        ),
    )
    .expect("write");
    let out_dir = dir.path().join("out");

    // Without a terminal and without --yes the run refuses to start.
    let refused = Command::new(GEOCAL)
        .args(["run", run_cfg.to_str().expect("path"), "--out"])
        .arg(&out_dir)
        .stdin(Stdio::piped())
        .output()
        .expect("run geocal");
    assert!(!refused.status.success());
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(
        stderr.contains("stdin is not a terminal") && stderr.contains("--yes"),
        "{stderr}"
    );

    let started = std::time::Instant::now();
    let mut run = Command::new(GEOCAL)
        .args([
            "run",
            run_cfg.to_str().expect("path"),
            "--json",
            "--yes",
            "--out",
        ])
        .arg(&out_dir)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start geocal run");
    let mut run_in = run.stdin.take().expect("stdin");
    let run_err = BufReader::new(run.stderr.take().expect("stderr"));
    // The operator: do what the run asks, through simulate's channel, then press Enter.
    let mut steps = Vec::new();
    let mut run_log = String::new();
    for line in run_err.lines() {
        let line = line.expect("run stderr");
        run_log.push_str(&line);
        run_log.push('\n');
        let command =
            if let Some(rest) = line.strip_prefix("[operator] place the tracer on station ") {
                format!(
                    "station {}",
                    rest.split_whitespace().next().expect("station id")
                )
            } else if let Some(rest) = line.strip_prefix("[operator] mount reflector ") {
                format!(
                    "target {}",
                    rest.split_whitespace().next().expect("target id")
                )
            } else {
                continue;
            };
        let reply = simulate.operate(&command);
        assert_eq!(reply, format!("ok {command}"), "simulate refused");
        writeln!(run_in,).expect("Enter");
        steps.push(command);
    }
    let status = run.wait().expect("run exit");
    let mut results_json = String::new();
    std::io::Read::read_to_string(&mut run.stdout.take().expect("stdout"), &mut results_json)
        .expect("results");
    println!(
        "run: {:.1} s, operator steps {steps:?}",
        started.elapsed().as_secs_f64()
    );
    assert!(status.success(), "geocal run failed:\n{run_log}");
    assert_eq!(steps, ["station c01", "target t0", "station s13"]);

    // An unknown command is refused with a reason, then simulate stops on SIGTERM.
    let reply = simulate.operate("station nowhere");
    assert!(
        reply.starts_with("error: unknown station `nowhere`"),
        "{reply}"
    );
    let killed = Command::new("kill")
        .args(["-TERM", &simulate.child.id().to_string()])
        .status()
        .expect("kill");
    assert!(killed.success());
    assert!(simulate.child.wait().expect("simulate exit").success());

    // The run's results against simulate's truth, as the in-process runs are judged.
    let truth: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&truth_path).expect("truth")).expect("json");
    let results = geocal::kinds::solve_file(&out_dir.join("session.mcap"), &Default::default())
        .expect("solve");
    let Some(results) = results.get::<geocal::kinds::rotary_tracer::solve::RotaryTracerResults>()
    else {
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
    let json: serde_json::Value = serde_json::from_str(&results_json).expect("results JSON");
    assert_eq!(json["kind"], "rotary_tracer");
    let session =
        geocal::session::reader::read_session(&out_dir.join("session.mcap")).expect("session");
    let drivers: Vec<(&str, &str)> = session
        .header
        .devices
        .iter()
        .map(|d| (d.id.as_str(), d.driver.as_str()))
        .collect();
    assert!(drivers.contains(&("c", "modbus_tcp")), "{drivers:?}");
    assert!(drivers.contains(&("tracer0", "hpi3d")), "{drivers:?}");
}
