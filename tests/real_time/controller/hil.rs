//! Real-controller HIL: geocal starts LinuxCNC headless (its own namespace, under the global
//! lock), drives it with the `linuxcnc` driver over linuxcncrsh, and the simulated world's
//! carriages follow LinuxCNC's `joint.N.motor-pos-cmd`, its compensation trim included; the
//! emulated HPI-3D measures the result. Skips without LinuxCNC (saying why), fails when `CI`
//! is set.

use crate::common;

use common::{
    assert_recovers_truth, calibrate_and_export, generous_timeouts, hil_config, pass_rule,
    run_with_truth, verification_grid,
};
use geocal::compensate::{Calibration, TableFormat, POSITIONING};

/// The HIL configuration with LinuxCNC as the machine: velocity and acceleration such that
/// a run stays short (G0 moves at `feed_m_s`, MAX_ACCELERATION 40 m/s²; the 0.25 ms servo
/// period keeps the dead band from rest at 0.6–1.3 µm: tables without a reversal change
/// only while a joint moves, where the trim follows).
pub fn linuxcnc_config(extra: &str) -> String {
    let text = generous_timeouts(&hil_config(extra))
        .replace(
            "driver = \"grbl\"\nfeed_m_s = 20.0",
            "driver = \"linuxcnc\"\nfeed_m_s = 4.0",
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
    format!("{text}\n[hil.linuxcnc]\nmax_acceleration_m_s2 = 40.0\nservo_period_s = 0.00025\n")
}

pub fn linuxcnc_hil_run_recovers_truth() {
    if !common::linuxcnc_available() {
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
}

/// The closed loop through LinuxCNC: the plan calibrated (virtual time, same truth machine),
/// `geocal compensate` tables loaded by LinuxCNC as `[JOINT_n] COMP_FILE` (x type 1, y type
/// 0, z type 1), the same plan run again through LinuxCNC: every positioning error within
/// the real-time bound (`REAL_TIME_SIGMAS`·RMS(σ) + interpolation error) by LinuxCNC's own
/// application. Then the x table with its sign flipped and the y table with a header line:
/// both fail it.
pub fn linuxcnc_applies_geocal_tables_and_bad_tables_fail_verification() {
    if !common::linuxcnc_available() {
        return;
    }
    let dir = tempfile::tempdir().expect("tempdir");
    let (cal, interp, files) = calibrate_and_export(
        dir.path(),
        &[
            (0, TableFormat::LinuxcncType1, "x1"),
            (1, TableFormat::LinuxcncType0, "y0"),
            (2, TableFormat::LinuxcncType1, "z1"),
        ],
    );
    let tables = dir.path().join("tables");
    let texts: Vec<String> = files
        .iter()
        .map(|files| {
            files
                .iter()
                .find(|f| f.name.starts_with("comp-"))
                .expect("joint table")
                .text
                .clone()
        })
        .collect();
    let good = format!(
        "[sim]\nnoise_seed = 4242\ncompensation = [\n\
         {{ format = \"linuxcnc-type1\", file = \"{}\", axis = \"x\" }},\n\
         {{ format = \"linuxcnc-type0\", file = \"{}\", axis = \"y\" }},\n\
         {{ format = \"linuxcnc-type1\", file = \"{}\", axis = \"z\" }},\n]\n",
        tables.join("x1/comp-x.txt").display(),
        tables.join("y0/comp-y.txt").display(),
        tables.join("z1/comp-z.txt").display()
    );
    let config = |sim: &str| {
        let text = verification_grid(linuxcnc_config(""));
        assert_eq!(text.matches("[sim]\n").count(), 1, "one [sim] table");
        text.replace("[sim]\n", sim)
    };
    let started = std::time::Instant::now();
    let (after, _) = run_with_truth(&config(&good), &dir.path().join("after"));
    println!(
        "LinuxCNC verification run: {:.1} s",
        started.elapsed().as_secs_f64()
    );
    let after_cal = Calibration::load(&after.results_path).expect("after results");
    for k in 0..3 {
        let r = pass_rule(&cal, &after_cal, k, interp[k]);
        // A real-time run: new noise draws every run, hence REAL_TIME_SIGMAS (tests/common).
        let (rms_after, bound, rms_before) = (r.rms_after_m, r.real_time_bound_m, r.rms_before_m);
        println!(
            "{}: RMS before {:.3} µm, after {:.3} µm, RMS σ {:.3} µm, 2σ rule {:.3} µm ({}), \
             asserted bound {:.3} µm",
            POSITIONING[k],
            rms_before * 1e6,
            rms_after * 1e6,
            r.rms_sigma_m * 1e6,
            r.bound_m * 1e6,
            if rms_after <= r.bound_m {
                "pass"
            } else {
                "fail"
            },
            bound * 1e6
        );
        assert!(
            rms_after <= bound && rms_after < 0.5 * rms_before,
            "{}: {:.4} µm left, bound {:.4} µm",
            POSITIONING[k],
            rms_after * 1e6,
            bound * 1e6
        );
    }

    // The session holds the trims LinuxCNC applied at every point, and the verification
    // report shows them: with tables without a reversal, applied = table at every point.
    let session = geocal::session::reader::read_session(&after.session_path).expect("session");
    let mut trims: u64 = 0;
    let mut largest_gap_m: f64 = 0.0;
    let mut largest_applied_m: f64 = 0.0;
    for e in &session.events {
        if let geocal::session::messages::RunEvent::ControllerTrims { joints, .. } = &e.msg {
            trims += 1;
            assert_eq!(joints.len(), 3);
            for j in joints {
                largest_gap_m = largest_gap_m.max((j.table_m - j.applied_m).abs());
                largest_applied_m = largest_applied_m.max(j.applied_m.abs());
            }
        }
    }
    println!(
        "trims at {trims} points: largest applied {:.3} µm, largest |table − applied| {:.2e} µm",
        largest_applied_m * 1e6,
        largest_gap_m * 1e6
    );
    assert_eq!(
        trims, after.summary.points_measured,
        "one trims event per point"
    );
    assert!(largest_applied_m > 1e-6, "LinuxCNC applied the tables");
    let md = dir.path().join("md").join("report.md");
    std::fs::create_dir_all(dir.path().join("md")).expect("md dir");
    let status = std::process::Command::new(env!("CARGO_BIN_EXE_geocal"))
        .args(["report".as_ref(), dir.path().join("after").as_os_str()])
        .args(["--format", "md", "--out"])
        .arg(&md)
        .status()
        .expect("geocal report");
    assert!(status.success());
    let report = std::fs::read_to_string(&md).expect("report.md");
    let verification = &report[report.find("## Verification run").expect("section")..];
    assert!(
        verification.contains("Trims the controller applied at the points"),
        "{verification}"
    );
    if largest_gap_m <= 1e-9 {
        assert!(verification.contains(&format!("At all {trims} points the controller applied")));
    } else {
        assert!(verification.contains("LinuxCNC's dead band"));
    }

    // x with the sign flipped (type 1: the trims negated), y with a header line (LinuxCNC
    // loads an empty table, silently), handed to LinuxCNC as written.
    let flipped: String = texts[0]
        .lines()
        .map(|line| {
            let v: Vec<f64> = line
                .split_whitespace()
                .map(|w| w.parse().expect("number"))
                .collect();
            format!("{} {} {}\n", v[0], -v[1], -v[2])
        })
        .collect();
    let bad = dir.path().join("bad");
    std::fs::create_dir_all(&bad).expect("dir");
    std::fs::write(bad.join("comp-x.txt"), flipped).expect("write");
    std::fs::write(
        bad.join("comp-y.txt"),
        format!("# nominal forward reverse (mm)\n{}", texts[1]),
    )
    .expect("write");
    let raw = format!(
        "[hil.linuxcnc]\ncomp_files = [\n\
         {{ axis = \"x\", file = \"{}\", type = 1 }},\n\
         {{ axis = \"y\", file = \"{}\", type = 0 }},\n]\n",
        bad.join("comp-x.txt").display(),
        bad.join("comp-y.txt").display()
    );
    // z with a reversal of 0.9 µm, inside the dead band from rest at this acceleration and
    // servo period (¼·A·dt² … ½·A·dt² = 0.625 … 1.25 µm): LinuxCNC never follows the jump
    // at a reversal, and the verification must say so instead of blaming the table.
    std::fs::write(
        bad.join("comp-z.txt"),
        format!(
            "-2000 0 {DEAD_BAND_JUMP_MM}\n0 0 {DEAD_BAND_JUMP_MM}\n2000 0 {DEAD_BAND_JUMP_MM}\n"
        ),
    )
    .expect("write");
    let wrong_sim = format!(
        "[sim]\nnoise_seed = 4243\ncompensation = [\n\
         {{ format = \"linuxcnc-type1\", file = \"{}\", axis = \"z\" }},\n]\n",
        bad.join("comp-z.txt").display()
    );
    let wrong_config = config(&wrong_sim).replace("[hil.linuxcnc]\n", &raw);
    assert!(wrong_config.contains("comp_files"));
    let started = std::time::Instant::now();
    let (wrong, _) = run_with_truth(&wrong_config, &dir.path().join("wrong"));
    println!(
        "LinuxCNC run with bad tables: {:.1} s",
        started.elapsed().as_secs_f64()
    );
    let wrong_cal = Calibration::load(&wrong.results_path).expect("results");
    let session = geocal::session::reader::read_session(&wrong.session_path).expect("session");
    for (k, what) in [(0, "flipped sign"), (1, "header line")] {
        let r = pass_rule(&cal, &wrong_cal, k, interp[k]);
        let (rms_after, bound, rms_before) = (r.rms_after_m, r.real_time_bound_m, r.rms_before_m);
        println!(
            "{} ({what}): RMS before {:.3} µm, after {:.3} µm, bound {:.3} µm",
            POSITIONING[k],
            rms_before * 1e6,
            rms_after * 1e6,
            bound * 1e6
        );
        assert!(
            rms_after > bound,
            "{} with a {what} passed: the bad-tables run's curve {:?}, {} points measured, {}",
            POSITIONING[k],
            wrong_cal
                .positioning(k)
                .map(|c| (c.positions_m, c.values, c.sigma)),
            wrong.summary.points_measured,
            trims_summary(&session, k)
        );
    }
    let flipped = pass_rule(&cal, &wrong_cal, 0, interp[0]);
    let (flipped_after, before_x) = (flipped.rms_after_m, flipped.rms_before_m);
    assert!(
        flipped_after > 1.5 * before_x,
        "the flipped table doubles EXX: {:.3} µm after against {:.3} µm before; the bad-tables \
         run's curve {:?}; {}",
        flipped_after * 1e6,
        before_x * 1e6,
        wrong_cal
            .positioning(0)
            .map(|c| (c.positions_m, c.values, c.sigma)),
        trims_summary(&session, 0)
    );

    // The reversal trim of z: the table's value changes from rest at every reversal, and
    // LinuxCNC's applied trim stays where it was.
    let (mut reversed, mut not_applied) = (0, 0);
    for e in &session.events {
        if let geocal::session::messages::RunEvent::ControllerTrims { joints, .. } = &e.msg {
            let z = &joints[2];
            if (z.table_m - DEAD_BAND_JUMP_MM * 1e-3).abs() < 1e-12 {
                reversed += 1;
            }
            if (z.table_m - z.applied_m).abs() > 1e-9 {
                not_applied += 1;
            }
        }
    }
    println!("z reversal trim: table at it at {reversed} points, not applied at {not_applied}");
    assert!(reversed > 0, "the plan reverses z");
    assert_eq!(
        not_applied, reversed,
        "LinuxCNC never follows a jump inside its dead band"
    );
    let md = dir.path().join("md").join("wrong.md");
    let status = std::process::Command::new(env!("CARGO_BIN_EXE_geocal"))
        .args(["report".as_ref(), dir.path().join("wrong").as_os_str()])
        .args(["--format", "md", "--out"])
        .arg(&md)
        .status()
        .expect("geocal report");
    assert!(status.success());
    let report = std::fs::read_to_string(&md).expect("wrong.md");
    let verification = &report[report.find("## Verification run").expect("section")..];
    assert!(
        verification.contains("LinuxCNC's dead band") && verification.contains("joint 2: "),
        "{verification}"
    );
}

/// What LinuxCNC applied to joint `k` over a run: the trims events' count and the RMS of
/// the table's value and of the applied trim, for a failure's message.
fn trims_summary(session: &geocal::session::reader::Session, k: usize) -> String {
    let (mut count, mut table, mut applied) = (0usize, 0.0f64, 0.0f64);
    for e in &session.events {
        if let geocal::session::messages::RunEvent::ControllerTrims { joints, .. } = &e.msg {
            if let Some(j) = joints.iter().find(|j| j.joint == k) {
                count += 1;
                table += j.table_m * j.table_m;
                applied += j.applied_m * j.applied_m;
            }
        }
    }
    let rms = |ss: f64| (ss / count.max(1) as f64).sqrt() * 1e6;
    format!(
        "joint {k}: {count} trims events, RMS table {:.3} µm, RMS applied {:.3} µm",
        rms(table),
        rms(applied)
    )
}

/// A reversal trim inside LinuxCNC's dead band from rest at 40 m/s² and a 0.25 ms servo
/// period, mm.
const DEAD_BAND_JUMP_MM: f64 = 0.0009;

/// The real-controller HIL's configuration errors name their keys (no LinuxCNC needed).
#[test]
fn linuxcnc_hil_configuration_errors_name_their_keys() {
    let parse = |text: &str| {
        geocal::config::Config::parse(text, std::path::Path::new("test.toml"))
            .err()
            .map(|e| e.to_string())
    };
    let ok = linuxcnc_config("");
    assert_eq!(parse(&ok), None, "the test configuration is valid");
    let e = parse(&ok.replace("x = [0.0, 1.4]", "x = [0.1, 1.4]")).expect("travel without 0");
    assert!(
        e.contains("machine.travel_m.x") && e.contains("contain 0"),
        "{e}"
    );
    let e = parse(&ok.replace(
        "[sim]\n",
        "[sim]\ncompensation = [{ format = \"sinumerik\", file = \"Cargo.toml\", axis = \"x\" }]\n",
    ))
    .expect("a SINUMERIK table for LinuxCNC");
    assert!(e.contains("sim.compensation[0]"), "{e}");
    let e = parse(&ok.replace(
        "servo_period_s = 0.00025",
        "servo_period_s = 0.00025\ncomp_files = [{ axis = \"w\", file = \"Cargo.toml\", type = 1 }]",
    ))
    .expect("axis w");
    assert!(e.contains("hil.linuxcnc.comp_files[0].axis"), "{e}");
    let e = parse(&ok.replace(
        "servo_period_s = 0.00025",
        "servo_period_s = 0.00025\ncomp_files = [{ axis = \"x\", file = \"/nonexistent/comp-x.txt\", type = 1 }]",
    ))
    .expect("missing file");
    assert!(e.contains("hil.linuxcnc.comp_files[0].file"), "{e}");
    let without_linuxcnc = ok
        .replace("driver = \"linuxcnc\"", "driver = \"sim\"")
        .replace(
            "[devices.machine.linuxcnc]\nmotion = \"rapid\"\nstatus_interval_s = 0.005\n\
             reply_timeout_s = 30.0\nstall_timeout_s = 30.0\n",
            "",
        );
    assert!(!without_linuxcnc.contains("[devices.machine.linuxcnc]"));
    let e = parse(&without_linuxcnc).expect("[hil.linuxcnc] without LinuxCNC");
    assert!(e.contains("hil.linuxcnc"), "{e}");
}
