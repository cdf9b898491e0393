//! Whole simulated runs of the hexapod hinge calibration (plan kind `hexapod`): the 36 hinge
//! coordinates must match the simulated truth within what the reported uncertainties allow,
//! the two-stage result must never be worse than its start or plain LM, the replay of the
//! recorded session must give identical results, and bad configurations clear errors.

use crate::common;

use std::path::Path;

use geocal::kinds::solve_file;
use geocal::method::Results;
use geocal::run::RunOutput;
use geocal::session::kind_messages::{hexapod_legs_topic, hexapod_pose_topic};
use geocal::session::messages::RunEvent;
use geocal::session::reader::read_session;
use serde_json::Value;

const EXAMPLE: &str = include_str!("../config/hexapod.toml");

fn run(config_text: &str, dir: &Path) -> (RunOutput, Value) {
    common::run_kind(config_text, dir, "hexapod.toml")
}

fn xyz(v: &Value) -> [f64; 3] {
    std::array::from_fn(|k| v[k].as_f64().expect("number"))
}

/// Every coordinate within 4 of its reported sigmas: for a correct covariance each normalised
/// error is N(0, 1), P(|z| > 4) = 6e-5, so 36 coordinates fail by chance with probability
/// 0.2 %. Returns the RMS normalised error.
fn assert_hinges_recovered(results: &Results, truth: &Value) -> f64 {
    let Some(r) = results.get::<geocal::kinds::hexapod::solve::HexapodResults>() else {
        panic!("expected hexapod results");
    };
    let mut sum_z2 = 0.0;
    for h in &r.hinges {
        let tb = xyz(&truth["base_m"][h.leg]);
        let tp = xyz(&truth["platform_m"][h.leg]);
        for k in 0..3 {
            for (what, est, sigma, t) in [
                ("B", h.base_m[k], h.base_sigma_m[k], tb[k]),
                ("P", h.platform_m[k], h.platform_sigma_m[k], tp[k]),
            ] {
                let z = (est - t) / sigma;
                assert!(z.abs() <= 4.0, "leg {} {what}{k}: {z:.2} sigma", h.leg);
                sum_z2 += z * z;
            }
        }
    }
    (sum_z2 / 36.0).sqrt()
}

#[test]
fn recovers_the_true_hinges_and_replays_identically() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (output, truth) = run(EXAMPLE, dir.path());
    let Some(r) = output
        .results
        .get::<geocal::kinds::hexapod::solve::HexapodResults>()
    else {
        panic!("expected hexapod results");
    };
    assert_eq!((r.poses, r.readings), (30, 129));
    assert_eq!(r.pose_source, "measured");
    let rms_z = assert_hinges_recovered(&output.results, &truth);
    let (maha, z2, z2_var) = error_against_covariance(&output, &truth);
    println!(
        "config seed: Mahalanobis per dof {:.3} (σ {:.3}), mean z² {z2:.3} ± {:.3}",
        maha / 36.0,
        (2.0f64 / 36.0).sqrt(),
        z2_var.sqrt()
    );
    // chi²/dof of 138 degrees of freedom has a standard deviation of sqrt(2/138) = 0.12;
    // [0.65, 1.35] is about ±3 of them.
    println!(
        "rms normalised error {rms_z:.2}, chi2/dof {:.3}, objective start {:.3e} -> LM {:.3e}, two-stage {:.3e} m²",
        r.chi2_per_dof.unwrap_or(f64::NAN), r.two_stage.objective_initial_m2, r.lm.objective_m2, r.objective_m2
    );
    assert!(
        (0.65..=1.35).contains(&r.chi2_per_dof.unwrap_or(f64::NAN)),
        "{}",
        r.chi2_per_dof.unwrap_or(f64::NAN)
    );
    assert!(r.objective_m2 <= r.two_stage.objective_initial_m2);
    assert!(r.objective_m2 <= r.lm.objective_m2 * (1.0 + 1e-12));

    // Replay: the recorded session alone gives byte-identical results.
    let replay = solve_file(&output.session_path, &Default::default()).expect("solve");
    assert_eq!(replay.to_json_pretty(), output.results.to_json_pretty());
    let written = std::fs::read_to_string(&output.results_path).expect("results.json");
    assert_eq!(written, output.results.to_json_pretty());

    // The session holds every reading and the documented events.
    let session = read_session(&output.session_path).expect("read session");
    assert_eq!(session.header.kind, "hexapod");
    assert_eq!(session.topics[&hexapod_legs_topic("hex0")].len(), 129);
    assert_eq!(session.topics[&hexapod_pose_topic("hex0")].len(), 30);
    let begins = session
        .events
        .iter()
        .filter(|e| matches!(e.msg, RunEvent::PoseBegin { .. }))
        .count();
    let ends = session
        .events
        .iter()
        .filter(|e| matches!(e.msg, RunEvent::PoseEnd { .. }))
        .count();
    assert_eq!((begins, ends), (30, 30));
    assert_eq!(session.ignored, 0);
}

/// Given poses (no pose sensor: the commanded poses are used, and the sim platform reaches them
/// exactly, `exact_poses`) and a hinge error of ±5 mm: the truth is still recovered and the
/// two-stage result is not worse than its start.
#[test]
fn commanded_poses_and_larger_errors() {
    let cut = EXAMPLE
        .find("[devices.pose_sensor]")
        .expect("pose sensor table");
    let end = EXAMPLE[cut..].find("\n[plan]").expect("[plan]") + cut;
    let text = format!("{}{}", &EXAMPLE[..cut], &EXAMPLE[end..])
        .replace("hinge_error_m = 2.0e-3", "hinge_error_m = 5.0e-3")
        .replace("seed = 424242", "seed = 7\nexact_poses = true");
    let dir = tempfile::tempdir().expect("tempdir");
    let (output, truth) = run(&text, dir.path());
    let Some(r) = output
        .results
        .get::<geocal::kinds::hexapod::solve::HexapodResults>()
    else {
        panic!("expected hexapod results");
    };
    assert_eq!(r.pose_source, "commanded");
    let rms_z = assert_hinges_recovered(&output.results, &truth);
    println!(
        "±5 mm: rms normalised error {rms_z:.2}, chi2/dof {:.3}",
        r.chi2_per_dof.unwrap_or(f64::NAN)
    );
    assert!(r.objective_m2 <= r.two_stage.objective_initial_m2);
}

/// The 36-coordinate error of one run against its reported covariance: eᵀ Cov⁻¹ e (χ² with 36
/// dof for an honest covariance), the mean squared normalised marginal error (mean 1) and that
/// mean's variance as the reported correlations give it (2 Σ ρ²/36²: the legs' coordinates are
/// strongly correlated, so one run's marginal RMS scatters far more than √(2/36)).
fn error_against_covariance(output: &RunOutput, truth: &Value) -> (f64, f64, f64) {
    let Some(r) = output
        .results
        .get::<geocal::kinds::hexapod::solve::HexapodResults>()
    else {
        panic!("expected hexapod results");
    };
    let coords = |base: &dyn Fn(usize) -> [f64; 3], platform: &dyn Fn(usize) -> [f64; 3]| {
        (0..12)
            .flat_map(|k| if k < 6 { base(k) } else { platform(k - 6) })
            .collect::<Vec<f64>>()
    };
    let t = coords(&|k| xyz(&truth["base_m"][k]), &|k| {
        xyz(&truth["platform_m"][k])
    });
    let est = coords(&|k| r.hinges[k].base_m, &|k| r.hinges[k].platform_m);
    let n = t.len();
    let cov = nalgebra::DMatrix::from_fn(n, n, |i, j| r.covariance_m2[i][j]);
    let e = nalgebra::DVector::from_fn(n, |i, _| est[i] - t[i]);
    let info = cov.clone().try_inverse().expect("covariance inverse");
    let s = |i: usize| cov[(i, i)].sqrt();
    let z2 = (0..n).map(|i| (e[i] / s(i)).powi(2)).sum::<f64>() / n as f64;
    let rho2: f64 = (0..n)
        .flat_map(|i| (0..n).map(move |j| (i, j)))
        .map(|(i, j)| (cov[(i, j)] / (s(i) * s(j))).powi(2))
        .sum();
    (
        (e.transpose() * info * &e)[(0, 0)],
        z2,
        2.0 * rho2 / (n * n) as f64,
    )
}

/// 8 seeds without pose noise, and 8 with pose-sensor noise 5× the encoder noise (5 µm per
/// translation coordinate, 10 µrad per rotation-vector component ≈ 2 µm at the platform
/// hinges). With an honest covariance the pooled eᵀ Cov⁻¹ e per dof is 1 ± √(2/288) = 0.083,
/// the pooled weighted χ²/dof (8·138 dof) 1 ± 0.038, the mean squared normalised marginal error
/// 1 ± (its variance from the reported correlations); each within 4σ. With the pose noise left
/// out of the weights (poses taken as exact) the Mahalanobis figure is ~26.
#[test]
fn uncertainties_are_honest_with_and_without_pose_noise() {
    let seeds = 8;
    for (noise_m, noise_rad) in [(0.0, 0.0), (5e-6, 1e-5)] {
        let (mut maha, mut chi2, mut dof, mut z2, mut z2_var) = (0.0, 0.0, 0, 0.0, 0.0);
        for seed in 0..seeds {
            let text = EXAMPLE
                .replace("noise_m = 0.0", &format!("noise_m = {noise_m:e}"))
                .replace("noise_rad = 0.0", &format!("noise_rad = {noise_rad:e}"))
                .replace("seed = 424242", &format!("seed = {}", 1000 + seed))
                .replace("seed = 5,", &format!("seed = {},", 50 + seed));
            let dir = tempfile::tempdir().expect("tempdir");
            let (output, truth) = run(&text, dir.path());
            let Some(r) = output
                .results
                .get::<geocal::kinds::hexapod::solve::HexapodResults>()
            else {
                panic!("expected hexapod results");
            };
            assert_eq!((r.pose_sigma_m, r.pose_sigma_rad), (noise_m, noise_rad));
            assert_hinges_recovered(&output.results, &truth);
            let (m, z, v) = error_against_covariance(&output, &truth);
            maha += m;
            z2 += z;
            z2_var += v;
            chi2 += r.chi2_per_dof.unwrap_or(f64::NAN) * r.dof as f64;
            dof += r.dof;
        }
        let k = (seeds * 36) as f64;
        let (maha, chi2_dof) = (maha / k, chi2 / dof as f64);
        let (z2, z2_sd) = (z2 / seeds as f64, z2_var.sqrt() / seeds as f64);
        println!(
            "pose noise {noise_m:e} m, {noise_rad:e} rad: Mahalanobis per dof {maha:.3} (σ {:.3}), \
             chi2/dof {chi2_dof:.3} (σ {:.3}), rms normalised error {:.3} (mean z² {z2:.3} ± {z2_sd:.3})",
            (2.0 / k).sqrt(),
            (2.0 / dof as f64).sqrt(),
            z2.sqrt()
        );
        assert!((maha - 1.0).abs() <= 4.0 * (2.0 / k).sqrt(), "{maha}");
        assert!(
            (chi2_dof - 1.0).abs() <= 4.0 * (2.0 / dof as f64).sqrt(),
            "{chi2_dof}"
        );
        assert!((z2 - 1.0).abs() <= 4.0 * z2_sd, "{z2} ± {z2_sd}");
    }
}

fn pose_of(v: &Value) -> geocal::model::hexapod::Pose {
    geocal::kinds::hexapod::sim::to_pose(&geocal_drivers::PlatformPose {
        translation_m: xyz(&v["translation_m"]),
        rotation_vector_rad: xyz(&v["rotation_vector_rad"]),
    })
}

/// The sim platform's true pose is the forward kinematics, with the true hinges, of the leg
/// lengths the controller computed with the design hinges. Per pose: the reached pose gives
/// exactly those lengths (< 1 nm), and its offset from the commanded pose is what the
/// linearised kinematics predicts from the hinge errors, Δp = −A⁻¹(L_true(c) − L_design(c)),
/// to within its second-order term (5 % of the offset: the offsets reach ~5 mm and ~30 mrad,
/// and the pose Jacobian's condition number is ~30). The solver, on measured poses, recovers the
/// truth within its σ (the main test); on the commanded poses it cannot.
#[test]
fn platform_reaches_the_forward_kinematics_of_the_design_lengths() {
    use geocal::model::hexapod::{leg_length, pose_jacobian, HexapodGeometry, LEGS};
    let dir = tempfile::tempdir().expect("tempdir");
    let (_, truth) = run(EXAMPLE, dir.path());
    let config = geocal::kinds::hexapod::config::HexapodConfig::parse(EXAMPLE, Path::new("h.toml"))
        .expect("config");
    let design = config.machine.nominal();
    let coords = |key: &str| -> Vec<f64> { (0..LEGS).flat_map(|i| xyz(&truth[key][i])).collect() };
    let true_geometry =
        HexapodGeometry::from_slice(&[coords("base_m"), coords("platform_m")].concat());
    let poses = truth["poses"].as_array().expect("poses");
    assert_eq!(poses.len(), 31, "power-on home and 30 commanded poses");
    let (mut max_t, mut max_r, mut max_deviation) = (0.0f64, 0.0f64, 0.0f64);
    for p in poses {
        let (c, reached) = (pose_of(&p["commanded"]), pose_of(&p["reached"]));
        let design_l: [f64; LEGS] = std::array::from_fn(|i| leg_length(&design.leg(i), &c).0);
        let miss = nalgebra::Vector6::from_fn(|i, _| {
            leg_length(&true_geometry.leg(i), &c).0 - design_l[i]
        });
        for (i, l) in design_l.iter().enumerate() {
            let closure = leg_length(&true_geometry.leg(i), &reached).0 - l;
            assert!(closure.abs() < 1e-9, "leg {i}: {closure:e} m");
        }
        let predicted = -pose_jacobian(&true_geometry, &c)
            .try_inverse()
            .expect("jacobian inverse")
            * miss;
        let dt = reached.translation_m - c.translation_m;
        let dw = reached.rotation.scaled_axis() - c.rotation.scaled_axis();
        let actual = nalgebra::Vector6::new(dt[0], dt[1], dt[2], dw[0], dw[1], dw[2]);
        let deviation = (actual - predicted).norm() / predicted.norm();
        assert!(
            deviation <= 0.05,
            "{deviation}: {actual:?} vs {predicted:?}"
        );
        max_deviation = max_deviation.max(deviation);
        max_t = max_t.max(dt.norm());
        max_r = max_r.max(dw.norm());
    }
    println!(
        "commanded vs reached: up to {:.3} mm and {:.3} mrad; linear prediction off by up to \
         {:.1} % of the offset",
        max_t * 1e3,
        max_r * 1e3,
        max_deviation * 100.0
    );
    // Hinge errors of ±2 mm move the platform by millimetres and milliradians.
    assert!(max_t > 1e-3 && max_r > 1e-3, "{max_t} m, {max_r} rad");

    // Without the pose sensor the commanded poses are used. The encoders then read exactly the
    // design geometry's length changes between commanded poses, so the fit returns the design
    // hinges with a fine chi²: the hinge errors are invisible without measured poses.
    let cut = EXAMPLE.find("[devices.pose_sensor]").expect("pose sensor");
    let end = EXAMPLE[cut..].find("\n[plan]").expect("[plan]") + cut;
    let text = format!("{}{}", &EXAMPLE[..cut], &EXAMPLE[end..]);
    let dir = tempfile::tempdir().expect("tempdir");
    let (output, truth) = run(&text, dir.path());
    let Some(r) = output
        .results
        .get::<geocal::kinds::hexapod::solve::HexapodResults>()
    else {
        panic!("expected hexapod results");
    };
    let (maha, _, _) = error_against_covariance(&output, &truth);
    let off_design = r
        .hinges
        .iter()
        .flat_map(|h| (0..3).map(move |k| (h.base_m[k] - h.nominal_base_m[k]).abs()))
        .fold(0.0, f64::max);
    println!(
        "commanded poses: chi2/dof {:.2}, Mahalanobis error per dof {:.0}, largest base hinge \
         change from the design {:.1} µm",
        r.chi2_per_dof.unwrap_or(f64::NAN),
        maha / 36.0,
        off_design * 1e6
    );
    assert!(maha / 36.0 > 100.0, "{maha}");
}

#[test]
fn bad_configs_give_file_key_and_expectation() {
    let cases = [
        (
            "shrink = 0.5",
            "shrink = 2.0",
            "key `plan.solver.shrink`: expected a factor in (0, 1), got 2",
        ),
        (
            "count = 29",
            "count = 4",
            "key `plan.poses`: expected at least 6 poses besides home",
        ),
        (
            "    [0.133826, 0.148629, 0.000000],\n]",
            "]",
            "key `machine.platform_hinges_m`: expected 6 hinges",
        ),
        (
            "encoder_noise_m = 1.0e-6",
            "encoder_noise = 1.0e-6",
            "key `devices.hexapod.encoder_noise`",
        ),
        (
            "leg_scale_ppm = 10.0",
            "leg_scale_ppm = -10.0",
            "key `uncertainty.leg_scale_ppm`: expected a finite number >= 0, got -10",
        ),
        (
            "pose_scale_ppm = 5.0",
            "pose_scale_m = 5.0",
            "key `uncertainty.pose_scale_m`",
        ),
    ];
    common::assert_run_rejects(env!("CARGO_BIN_EXE_geocal"), EXAMPLE, &cases);
}

/// A run killed in the middle of a pose (the killed file is the first messages of a full run,
/// up to the measured pose of pose 15, before its leg reading) resumes with `geocal run
/// --resume`: the kept messages come first, unchanged; the run continues at the unfinished
/// pose; the solve uses every pose once and recovers the truth.
#[test]
fn a_killed_run_resumes_at_its_unfinished_pose() {
    let dir = tempfile::tempdir().expect("tempdir");
    let full_dir = dir.path().join("full");
    run(EXAMPLE, &full_dir);
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
    let killed = read_session(&killed_dir.join("session.mcap")).expect("killed session");
    let finished = killed
        .events
        .iter()
        .filter(|e| matches!(e.msg, RunEvent::PoseEnd { .. }))
        .count();
    assert_eq!(finished, 15, "the cut lies inside pose 15");

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
        pose,
        messages_kept,
        ..
    } = resumed.events[resume_at].msg
    else {
        unreachable!("found as a resume event")
    };
    assert_eq!((pose, messages_kept), (Some(15), cut as u64));
    let poses_after: Vec<usize> = resumed.events[resume_at..]
        .iter()
        .filter_map(|e| match e.msg {
            RunEvent::PoseBegin { pose, .. } => Some(pose),
            _ => None,
        })
        .collect();
    assert_eq!(
        poses_after,
        (15..30).collect::<Vec<_>>(),
        "the finished poses are not measured again"
    );
    assert!(
        common::interrupted_files_left(&killed_dir).is_empty(),
        "interrupted files deleted"
    );

    let results = solve_file(&resumed_path, &Default::default()).expect("solve");
    let Some(r) = results.get::<geocal::kinds::hexapod::solve::HexapodResults>() else {
        panic!("expected hexapod results");
    };
    assert_eq!((r.poses, r.readings), (30, 129), "every pose used once");
    let truth: Value = serde_json::from_str(
        &std::fs::read_to_string(killed_dir.join("truth.json")).expect("truth"),
    )
    .expect("truth JSON");
    // Power-on home, the 16 poses the killed run commanded, the 15 of the continuation.
    assert_eq!(truth["poses"].as_array().map(Vec::len), Some(1 + 16 + 15));
    let rms_z = assert_hinges_recovered(&results, &truth);
    println!(
        "resumed at pose 15 after {cut} of {} messages; rms normalised error {rms_z:.2}, \
         chi2/dof {:.3}",
        messages.len(),
        r.chi2_per_dof.unwrap_or(f64::NAN)
    );
    // As for an unbroken run: chi²/dof of 138 dof, ±3 of its σ = 0.12.
    assert!(
        (0.65..=1.35).contains(&r.chi2_per_dof.unwrap_or(f64::NAN)),
        "{}",
        r.chi2_per_dof.unwrap_or(f64::NAN)
    );
}
