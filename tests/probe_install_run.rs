//! Whole simulated runs of the laser-probe installation method (plan kind `probe_install`):
//! the recovered installation must match the simulated truth within what the reported
//! uncertainties allow, the replay of the recorded session must give identical results, every
//! raw reading must be in the session, and bad configurations must give clear errors.

use crate::common;

use std::path::Path;

use geocal::kinds::probe_install::solve::ProbeInstallResults;
use geocal::kinds::solve_file;
use geocal::run::RunOutput;
use geocal::session::kind_messages::TOPIC_MACHINE_POSE;
use geocal::session::messages::RunEvent;
use geocal::session::reader::read_session;
use serde_json::Value;

const EXAMPLE: &str = include_str!("../config/probe-install.toml");

fn run(config_text: &str, dir: &Path) -> (RunOutput, Value) {
    common::run_kind(config_text, dir, "probe-install.toml")
}

/// Every parameter within 4 of its reported sigmas of the truth: for a correct covariance
/// each normalised error is N(0, 1), P(|z| > 4) = 6e-5, so 11 parameters fail by chance with
/// probability < 1e-3. The beam components are judged together with the others (their
/// covariance is rank 2 on the unit sphere, their sigmas are still marginal ones). And the
/// noise model holds: chi²/dof of 90 degrees of freedom has a standard deviation of
/// sqrt(2/90) = 0.15; [0.6, 1.5] is about ±3 of them. Returns the RMS normalised error.
fn assert_recovers_the_truth(r: &ProbeInstallResults, truth: &Value) -> f64 {
    let truth_params = truth["parameters"].as_array().expect("truth parameters");
    let mut sum_z2 = 0.0;
    for (p, t) in r.parameters.iter().zip(truth_params) {
        assert_eq!(t["name"], p.name.as_str());
        let err = p.value - t["value"].as_f64().expect("truth value");
        let z = err / p.sigma.expect("identifiable");
        println!(
            "{:<18} error {err:+.3e}  sigma {:.3e}  z {z:+.2}  (nominal off by {:+.3e})",
            p.name,
            p.sigma.expect("identifiable"),
            p.nominal - t["value"].as_f64().unwrap_or(0.0)
        );
        assert!(z.abs() <= 4.0, "{}: {z:.2} sigma", p.name);
        sum_z2 += z * z;
    }
    let rms_z = (sum_z2 / 11.0).sqrt();
    println!(
        "chi2/dof {:.3}, rms normalised error {rms_z:.2}",
        r.chi2_per_dof.expect("redundant")
    );
    assert!(
        (0.6..=1.5).contains(&r.chi2_per_dof.expect("redundant")),
        "{}",
        r.chi2_per_dof.expect("redundant")
    );
    rms_z
}

#[test]
fn recovers_the_true_installation_and_replays_identically() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (output, truth) = run(EXAMPLE, dir.path());
    let Some(r) = output
        .results
        .get::<geocal::kinds::probe_install::solve::ProbeInstallResults>()
    else {
        panic!("expected probe_install results");
    };
    assert_eq!(r.kind, "probe_install");
    assert_eq!(
        (r.points, r.readings, r.readings_out_of_range),
        (100, 500, 0)
    );

    assert_recovers_the_truth(r, &truth);

    // The radius: before calibration the mis-installation distorts the measured sphere; after,
    // the fitted radius carries only noise: σ_r ≈ 3·σ_point/√N = 3·0.45 µm/10 ≈ 0.13 µm (cap
    // geometry factor ~3), so 1 µm is about 7 σ_r.
    println!(
        "radius before {:.4} mm, after LM {:.4} mm, after GA {:.4} mm; objective LM {:.3e}, GA {:.3e}",
        r.radius_before_m * 1e3,
        r.radius_after_m * 1e3,
        r.radius_after_ga_m * 1e3,
        r.lm.objective,
        r.ga.objective
    );
    assert!((r.radius_after_m - 6e-3).abs() < 1e-6);
    assert!(
        (r.radius_before_m - 6e-3).abs() > 10e-6,
        "the mis-installation shows"
    );
    // LM reaches the optimum of the same objective: the GA cannot end below it.
    assert!(r.lm.unit_norm_violation.abs() < 1e-12);
    assert!(r.ga.objective >= r.lm.objective * (1.0 - 1e-9));
    assert!(r.ga.unit_norm_violation.abs() < 1e-3);
    assert!(r.lm.converged);

    // Replay: the recorded session alone gives byte-identical results.
    let replay = solve_file(&output.session_path, &Default::default()).expect("solve");
    assert_eq!(replay.to_json_pretty(), output.results.to_json_pretty());
    let written = std::fs::read_to_string(&output.results_path).expect("results.json");
    assert_eq!(written, output.results.to_json_pretty());

    // The session holds every raw reading and the events in their documented order.
    let session = read_session(&output.session_path).expect("read session");
    assert_eq!(session.header.kind, "probe_install");
    assert_eq!(session.probes["laser0"].len(), 500);
    // Readings counted from 1, as docs/session-format.md says; the machine chain as the
    // shared session format defines it (F for the frame).
    let seqs: Vec<u64> = session.probes["laser0"].iter().map(|r| r.msg.seq).collect();
    assert_eq!(seqs, (1..=500).collect::<Vec<u64>>());
    assert_eq!(session.header.machine.structure, "FXYZBA");
    assert_eq!(session.topics[TOPIC_MACHINE_POSE].len(), 100);
    let count = |f: &dyn Fn(&RunEvent) -> bool| session.events.iter().filter(|e| f(&e.msg)).count();
    assert_eq!(count(&|e| matches!(e, RunEvent::PostureBegin { .. })), 4);
    assert_eq!(count(&|e| matches!(e, RunEvent::PostureEnd { .. })), 4);
    assert_eq!(count(&|e| matches!(e, RunEvent::ProbeBegin { .. })), 100);
    assert_eq!(count(&|e| matches!(e, RunEvent::ProbeEnd { .. })), 100);
    assert_eq!(output.summary.samples, 500);
    assert_eq!(session.ignored, 0);
}

/// A probe with a short range: readings beyond it are recorded as nulls with a `fault` event
/// each, nothing is lost, and the points that kept a valid reading still calibrate.
#[test]
fn out_of_range_readings_are_recorded_as_faults() {
    let text = EXAMPLE
        .replace("range_m = [-8.0e-3, 8.0e-3]", "range_m = [-2.5e-3, 2.5e-3]")
        .replace("ga_generations = 2000", "ga_generations = 200");
    let dir = tempfile::tempdir().expect("tempdir");
    let (output, _) = run(&text, dir.path());
    let Some(r) = output
        .results
        .get::<geocal::kinds::probe_install::solve::ProbeInstallResults>()
    else {
        panic!("expected probe_install results");
    };
    let session = read_session(&output.session_path).expect("read session");
    let faults = session
        .events
        .iter()
        .filter(|e| matches!(&e.msg, RunEvent::Fault { code, .. } if code == "out_of_range"))
        .count();
    println!(
        "{} of 500 readings out of range, {} points kept",
        r.readings_out_of_range, r.points
    );
    assert!(r.readings_out_of_range > 0);
    assert_eq!(faults, r.readings_out_of_range);
    assert_eq!(output.summary.faults as usize, faults);
    assert_eq!(r.readings + r.readings_out_of_range, 500);
    assert_eq!(session.probes["laser0"].len(), 500);
    assert!(r.points < 100 && r.points > 20);
}

/// `[sim.effects] probe_direction` (a reading scale error the 11-parameter model cannot hold:
/// its beam direction is a unit vector): off, the LM chi²/dof of 90 dof stays within 4σ of 1
/// (σ = √(2/90) = 0.15); on at 3e-3 (±6 µm over the ±2 mm of nominal readings, against
/// 0.45 µm per point), it rises far above 1 (more than 1 + 10σ).
#[test]
fn probe_direction_effect_shows_in_chi2() {
    let base = EXAMPLE.replace("ga_generations = 2000", "ga_generations = 200");
    let sd = (2.0f64 / 90.0).sqrt();
    let mut chi2 = Vec::new();
    for on in [false, true] {
        let text = if on {
            format!(
                "{base}\n[sim.effects]\nprobe_direction = {{ enabled = true, size = 3.0e-3 }}\n"
            )
        } else {
            base.clone()
        };
        let dir = tempfile::tempdir().expect("tempdir");
        let (output, truth) = run(&text, dir.path());
        let Some(r) = output
            .results
            .get::<geocal::kinds::probe_install::solve::ProbeInstallResults>()
        else {
            panic!("expected probe_install results");
        };
        assert_eq!(r.dof, 90);
        assert_eq!(
            truth["probe_scale_error"].as_f64(),
            Some(if on { 3e-3 } else { 0.0 })
        );
        println!(
            "probe_direction {}: chi2/dof {:.2}, residual rms {:.3} µm",
            if on { "on (3e-3)" } else { "off" },
            r.chi2_per_dof.expect("redundant"),
            r.residual_rms_m * 1e6
        );
        chi2.push(r.chi2_per_dof.expect("redundant"));
    }
    assert!((chi2[0] - 1.0).abs() <= 4.0 * sd, "off: {}", chi2[0]);
    assert!(chi2[1] > 1.0 + 10.0 * sd, "on: {}", chi2[1]);
}

#[test]
fn bad_configs_give_file_key_and_expectation() {
    let cases = [
        (
            "cap_half_angle_rad = 0.6981317007977318",
            "cap_half_angle_rad = 2.0",
            "key `plan.cap_half_angle_rad`: expected an angle in (0, π/2) radians, got 2",
        ),
        (
            "reading_half_range_m = 2.0e-3",
            "reading_half_range_m = 9.0e-3",
            "key `plan.reading_half_range_m`: expected less than the probe's range",
        ),
        (
            "feed_m_s = 0.02",
            "feed_ms = 0.02",
            "key `devices.machine.feed_ms`: line 25, column 1: unknown field `feed_ms`",
        ),
        (
            "driver = \"sim\"                 # or \"grbl\"",
            "driver = \"hpi3d\" #",
            "key `devices.machine.driver`: expected \"sim\" or \"grbl\"",
        ),
        (
            "driver = \"sim\"                 # or \"ascii\"",
            "driver = \"laser\" #",
            "key `devices.probe.driver`: line ",
        ),
        (
            "driver = \"sim\"                 # or \"grbl\"",
            "driver = \"grbl\" #",
            "key `devices.probe.driver`: expected \"ascii\" like devices.machine.driver = \"grbl\"",
        ),
        (
            "kind = \"probe_install\"",
            "kind = \"probe_install\"\n[hil]\nemulate = true",
            "key `hil.emulate`: emulation serves the GRBL controller and the ASCII probe",
        ),
        (
            "sphere_centre_m = 1.0e-3",
            "sphere_centre_m = 1.0e-3\neffects = { probe_direction = { enabled = true, size = 0.5 } }",
            "key `sim.effects.probe_direction.size`: expected a non-zero relative scale error within ±0.1 when enabled, got 0.5",
        ),
        (
            "machine_scale_ppm = 5.0",
            "machine_scale_ppm = nan",
            "key `uncertainty.machine_scale_ppm`: expected a finite number >= 0",
        ),
        (
            "sphere_radius_m = 0.5e-6",
            "sphere_radius = 0.5e-6",
            "key `uncertainty.sphere_radius`",
        ),
    ];
    common::assert_run_rejects(env!("CARGO_BIN_EXE_geocal"), EXAMPLE, &cases);
    // Real drivers: each needs its port table (unless emulated), and the tables are strict.
    let real = EXAMPLE
        .replace(
            "driver = \"sim\"                 # or \"grbl\"",
            "driver = \"grbl\" #",
        )
        .replace(
            "driver = \"sim\"                 # or \"ascii\"",
            "driver = \"ascii\" #",
        );
    let cases = [
        (
            "[devices.probe]",
            "[devices.probe]",
            "key `devices.machine.grbl`: driver \"grbl\" needs [devices.machine.grbl] with at least `port`",
        ),
        (
            "[devices.probe]",
            "[devices.machine.grbl]\nbaud = 115200\n[devices.probe]",
            "key `devices.machine.grbl`: line ",
        ),
        (
            "[devices.probe]",
            "[devices.machine.grbl]\nport = \"/dev/null\"\naxis_letters = { x = \"X\", y = \"Y\", z = \"Z\", a = \"Q\" }\n[devices.probe]",
            "key `devices.machine.grbl.axis_letters.a`: expected a distinct axis letter X, Y, Z, A, B or C",
        ),
    ];
    common::assert_run_rejects(env!("CARGO_BIN_EXE_geocal"), &real, &cases);
    let real = real.replace(
        "[devices.probe]",
        "[devices.machine.grbl]\nport = \"/dev/null\"\n[devices.probe]",
    );
    let cases = [
        (
            "[plan]",
            "[plan]",
            "key `devices.probe.ascii`: driver \"ascii\" needs [devices.probe.ascii] with at least `port`",
        ),
        (
            "[plan]",
            "[devices.probe.ascii]\nport = \"/dev/null\"\nscale_to_m = 0.0\n[plan]",
            "key `devices.probe.ascii`: scale to metres must be finite and non-zero",
        ),
    ];
    common::assert_run_rejects(env!("CARGO_BIN_EXE_geocal"), &real, &cases);
}

/// A run killed in the middle of a posture (the killed file is the first messages of a full
/// run, up to its 301st probe reading: posture 2, point 10) resumes with `geocal run --resume`:
/// the kept messages come first, unchanged; the run continues at the unfinished posture,
/// measured again in full; the solve uses every point once and recovers the truth.
#[test]
fn a_killed_run_resumes_at_its_unfinished_posture() {
    let text = EXAMPLE.replace("ga_generations = 2000", "ga_generations = 200");
    let dir = tempfile::tempdir().expect("tempdir");
    let full_dir = dir.path().join("full");
    run(&text, &full_dir);
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
    let killed = read_session(&killed_dir.join("session.mcap")).expect("killed session");
    let interrupted_posture = killed
        .events
        .iter()
        .rev()
        .find_map(|e| match e.msg {
            RunEvent::PostureBegin { posture, .. } => Some(posture),
            _ => None,
        })
        .expect("a posture begun");
    assert_eq!(interrupted_posture, 2, "the cut lies inside posture 2");

    common::resume_cli(env!("CARGO_BIN_EXE_geocal"), &killed_dir);
    let resumed_path = killed_dir.join("session.mcap");
    let (resumed, resumed_messages) =
        geocal::session::reader::read_session_raw(&resumed_path).expect("resumed session");
    assert!(resumed.completeness.is_complete());
    assert_eq!(
        &resumed_messages[..cut],
        &messages[..cut],
        "kept messages first, unchanged"
    );
    let last_kept_ns = messages[..cut].iter().map(|m| m.log_time_ns).max();
    assert!(
        resumed_messages[cut..]
            .iter()
            .all(|m| Some(m.log_time_ns) > last_kept_ns),
        "the simulated clock goes on after the interruption"
    );
    let resume_at = resumed
        .events
        .iter()
        .position(|e| matches!(e.msg, RunEvent::Resume { .. }))
        .expect("a resume event");
    let RunEvent::Resume {
        posture,
        messages_kept,
        ..
    } = resumed.events[resume_at].msg
    else {
        unreachable!("found as a resume event")
    };
    assert_eq!(
        (posture, messages_kept),
        (Some(interrupted_posture), cut as u64)
    );
    let postures_after: Vec<usize> = resumed.events[resume_at..]
        .iter()
        .filter_map(|e| match e.msg {
            RunEvent::PostureBegin { posture, .. } => Some(posture),
            _ => None,
        })
        .collect();
    assert_eq!(
        postures_after,
        (interrupted_posture..4).collect::<Vec<_>>(),
        "the finished postures are not measured again"
    );
    let seqs: Vec<u64> = resumed.probes["laser0"].iter().map(|r| r.msg.seq).collect();
    assert!(
        seqs.windows(2).all(|w| w[0] < w[1]),
        "reading numbers go on after the resume"
    );
    assert!(
        common::interrupted_files_left(&killed_dir).is_empty(),
        "interrupted files deleted"
    );

    let results = solve_file(&resumed_path, &Default::default()).expect("solve");
    let Some(r) = results.get::<geocal::kinds::probe_install::solve::ProbeInstallResults>() else {
        panic!("expected probe_install results");
    };
    assert_eq!(
        (r.points, r.readings, r.readings_out_of_range),
        (100, 500, 0),
        "every point used once"
    );
    let truth: Value = serde_json::from_str(
        &std::fs::read_to_string(killed_dir.join("truth.json")).expect("truth"),
    )
    .expect("truth JSON");
    let rms_z = assert_recovers_the_truth(r, &truth);
    println!(
        "resumed at posture {interrupted_posture} after {cut} of {} messages; rms normalised \
         error {rms_z:.2}, chi2/dof {:.3}",
        messages.len(),
        r.chi2_per_dof.expect("redundant")
    );
}

/// A plan blind to most parameters (A = 0 at every posture, as the outside session
/// `outside-probe-a0-12`), 3 seeds: LM converges, what the postures cannot see is named
/// (σ null), the held parameters stay at nominal, and every parameter given a σ (beam n, the
/// sphere's x and y at least) is within 4σ of the truth (P(|z| > 4) = 6e-5 each).
#[test]
fn a_blind_plan_names_its_unseen_parameters_and_converges_on_the_rest() {
    let dir = tempfile::tempdir().expect("temp dir");
    let blind = "postures_rad = [\n    [0.0, 0.0],\n    [0.0, 1.5707963267948966],\n    \
                 [0.0, -1.5707963267948966],\n    [0.0, 0.7853981633974483],\n]";
    let start = EXAMPLE.find("postures_rad = [").expect("postures");
    let end = start + EXAMPLE[start..].find("\n]").expect("list end") + 2;
    let base = format!("{}{blind}{}", &EXAMPLE[..start], &EXAMPLE[end..])
        .replace("ga_generations = 2000", "ga_generations = 50");
    for seed in 0..3 {
        let text = base.replace("seed = 20110501", &format!("seed = {}", 3000 + seed));
        let (output, truth) = run(&text, &dir.path().join(format!("s{seed}")));
        let r = output
            .results
            .get::<ProbeInstallResults>()
            .expect("probe_install results");
        assert!(r.lm.converged, "seed {seed}: LM did not converge");
        // Always unseen with A = 0: δB alone at the design (with the beam and zero point
        // turned about z at the installed one), y32 with y43, z43 with the sphere's z. The
        // beam's l, m and x43 take part in the δB direction in proportion to the installed
        // beam's and zero point's tilt: named when that part matters (> 1e-3 of the
        // gradient, scaled), otherwise identifiable and judged below.
        for name in [
            "b_offset_rad",
            "y_offset_m",
            "zero_point_y_m",
            "zero_point_z_m",
            "sphere_centre_z_m",
        ] {
            assert!(
                r.not_identifiable.iter().any(|n| n == name),
                "seed {seed}: {name} not named in {:?}",
                r.not_identifiable
            );
        }
        for name in ["beam_n", "sphere_centre_x_m", "sphere_centre_y_m"] {
            assert!(
                !r.not_identifiable.iter().any(|n| n == name),
                "seed {seed}: {name} named unseen"
            );
        }
        assert_eq!(
            r.held_at_nominal.len(),
            3,
            "seed {seed}: {:?}",
            r.held_at_nominal
        );
        let chi2 = r.chi2_per_dof.expect("redundant");
        assert!((0.6..=1.5).contains(&chi2), "seed {seed}: χ²/dof {chi2}");
        let truth_params = truth["parameters"].as_array().expect("truth parameters");
        for (p, t) in r.parameters.iter().zip(truth_params) {
            if r.held_at_nominal.contains(&p.name) {
                assert_eq!(p.value, p.nominal, "seed {seed}: {} held", p.name);
            }
            if let Some(s) = p.sigma {
                let z = (p.value - t["value"].as_f64().expect("truth value")) / s;
                println!("seed {seed}: {:<18} z {z:+.2}", p.name);
                assert!(z.abs() <= 4.0, "seed {seed}: {} {z:.2} σ", p.name);
            }
        }
    }
}
