//! The outside sessions of every plan kind but multilateration (`../shared/sessions/`, written by
//! an independent recorder with its own kinematics, instrument and noise models, each with its
//! `truth.json`): geocal's estimates against the truth, normalised by geocal's own σ.
//!
//! For a correct covariance each normalised error z is N(0, 1): |z| ≤ 4 fails by chance with
//! probability 6e-5 per value, and the pooled mean of z² over n independent values has standard
//! deviation √(2/n); bounds are 3 of those.

use std::path::{Path, PathBuf};

use geocal::method::SolveSettings;
use serde_json::Value;

fn session_dir(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/sessions")
        .join(name)
}

fn truth(name: &str) -> Value {
    let path = session_dir(name).join("truth.json");
    let text = std::fs::read_to_string(&path).expect("truth.json");
    serde_json::from_str(&text).expect("truth json")
}

fn solve(name: &str) -> anyhow::Result<Value> {
    let results = geocal::kinds::solve_file(
        &session_dir(name).join("session.mcap"),
        &SolveSettings::default(),
    )?;
    Ok(serde_json::from_str(&results.to_json_pretty()).expect("results json"))
}

fn f(v: &Value) -> f64 {
    v.as_f64().expect("number")
}

/// Mean z² bound for `n` independent values: 1 ± 3 √(2/n).
fn assert_mean_z2(what: &str, z: &[f64]) {
    let n = z.len() as f64;
    let mean = z.iter().map(|v| v * v).sum::<f64>() / n;
    let band = 3.0 * (2.0 / n).sqrt();
    println!("{what}: mean z² {mean:.3} over {n} values (1 ± {band:.2})");
    assert!(
        (mean - 1.0).abs() <= band,
        "{what}: mean z² {mean:.3} over {n}"
    );
}

/// Location errors and per-angle motion errors against the physical axis of the truth. EXC
/// and EYC are one radial value written along a direction: it counts once (its larger
/// component); a component whose σ is 0 (the direction is perpendicular to it) must be 0.
fn sphere_z(name: &str) -> Vec<f64> {
    let r = solve(name).expect("solve");
    let t = truth(name);
    let mut z = Vec::new();
    for v in r["location"].as_array().expect("location") {
        let name = v["name"].as_str().expect("name");
        let e = f(&v["value"]) - f(&t["pige"]["physical"][name]);
        z.push(e / f(&v["sigma"]));
    }
    let physical = t["pdge"]["physical"].as_array().expect("pdge");
    for m in r["motion"].as_array().expect("motion") {
        let i = m["angle_index"].as_u64().expect("angle_index") as usize;
        let (e, s): (Vec<f64>, Vec<f64>) = (0..6)
            .map(|k| (f(&m["errors"][k]) - f(&physical[i][k]), f(&m["sigma"][k])))
            .unzip();
        let radial = if s[0] >= s[1] { 0 } else { 1 };
        for k in 0..2 {
            if s[k] == 0.0 {
                assert!(e[k].abs() < 1e-12, "{name}: angle {i} component {k}");
            }
        }
        for k in [radial, 2, 3, 4, 5] {
            z.push(e[k] / s[k]);
        }
    }
    for (k, v) in z.iter().enumerate() {
        assert!(
            v.abs() <= 4.0,
            "{name}: value {k} is {v:.2} σ from the truth"
        );
    }
    z
}

#[test]
fn rotary_sphere_on_and_off_the_x_axis_within_sigma() {
    let mut z = sphere_z("outside-sphere-clean-2");
    assert_mean_z2("sphere on +x", &z);
    let off = sphere_z("outside-sphere-offaxis-1");
    assert_mean_z2("sphere off axis", &off);
    z.extend(off);
    assert_mean_z2("both spheres", &z);
}

/// The parameters against the truth, each within `bound` of its σ; returns (z of the
/// identifiable ones, names geocal calls not identifiable).
fn probe_z(name: &str, bound: f64) -> (Vec<f64>, Vec<String>) {
    let r = solve(name).expect("solve");
    let t = truth(name);
    assert_eq!(
        r["lm"]["converged"],
        Value::Bool(true),
        "{name}: LM converged"
    );
    let chi2 = f(&r["chi2_per_dof"]);
    let dof = r["dof"].as_f64().expect("dof");
    assert!(
        (chi2 - 1.0).abs() <= 3.0 * (2.0 / dof).sqrt(),
        "{name}: χ²/dof {chi2}"
    );
    let mut z = Vec::new();
    let mut unseen = Vec::new();
    for p in r["parameters"].as_array().expect("parameters") {
        let pname = p["name"].as_str().expect("name");
        let truth_p = t["parameters"]
            .as_array()
            .expect("truth parameters")
            .iter()
            .find(|q| q["name"] == pname)
            .expect("truth of every parameter");
        match p["sigma"].as_f64() {
            Some(s) => {
                let v = (f(&p["value"]) - f(&truth_p["value"])) / s;
                println!("{name}: {pname} {v:+.2} σ");
                assert!(v.abs() <= bound, "{name}: {pname} {v:.2} σ from the truth");
                z.push(v);
            }
            None => unseen.push(pname.to_string()),
        }
        if pname == "b_offset_rad" {
            let b = f(&p["value"]);
            assert!(
                b.abs() <= std::f64::consts::PI,
                "{name}: δB {b} not wrapped"
            );
        }
    }
    (z, unseen)
}

#[test]
fn probe_install_clean_and_blind_plans() {
    let (z, unseen) = probe_z("outside-probe-clean-2", 4.0);
    assert!(unseen.is_empty(), "clean plan: {unseen:?} not identifiable");
    assert_eq!(z.len(), 11);
    // A = 0 at every posture: what the truth calls unseen is named, the rest within 3σ.
    let name = "outside-probe-a0-12";
    let (z, unseen) = probe_z(name, 3.0);
    let t = truth(name);
    let truth_unseen: Vec<String> = t["parameters"]
        .as_array()
        .expect("parameters")
        .iter()
        .filter(|p| p["identifiable"] == Value::Bool(false))
        .map(|p| p["name"].as_str().expect("name").to_string())
        .collect();
    assert_eq!(unseen, truth_unseen);
    assert_eq!(z.len(), 11 - truth_unseen.len());
}

/// Hinges against the truth in units of geocal's σ, each within 4σ; returns the z values.
fn hexapod_z(name: &str) -> Vec<f64> {
    let r = solve(name).expect("solve");
    let t = truth(name);
    assert_eq!(r["pose_source"], "measured", "{name}");
    let mut z = Vec::new();
    for (h, th) in r["hinges"]
        .as_array()
        .expect("hinges")
        .iter()
        .zip(t["hinges"].as_array().expect("truth hinges"))
    {
        for (est, sigma, truth) in [
            ("base_m", "base_sigma_m", "base_m"),
            ("platform_m", "platform_sigma_m", "platform_m"),
        ] {
            for k in 0..3 {
                let v = (f(&h[est][k]) - f(&th[truth][k])) / f(&h[sigma][k]);
                assert!(
                    v.abs() <= 4.0,
                    "{name}: leg {}: {est}[{k}] {v:.2} σ",
                    h["leg"]
                );
                z.push(v);
            }
        }
    }
    z
}

/// The poses under the hexapod's id (geocal's recorder) or under the pose sensor's own id
/// (`/hexapod/trk0/pose`, as the outside recorder names a device's topic): both read, the
/// hinges within σ of the truth.
#[test]
fn hexapod_hinges_within_sigma_on_either_pose_topic() {
    let mut z = hexapod_z("outside-hexapod-clean-2");
    assert_mean_z2("hexapod hinges", &z);
    let sensor_topic = hexapod_z("outside-hexapod-sensor-topic-3");
    assert_mean_z2("hexapod hinges, poses on the sensor's topic", &sensor_topic);
    z.extend(sensor_topic);
    assert_mean_z2("hexapod hinges, both sessions", &z);
}

/// Poses on a topic of neither the hexapod nor the pose sensor, or on both, are refused by
/// name: commanded poses must never silently count as exact.
#[test]
fn hexapod_misplaced_or_ambiguous_poses_are_refused() {
    let base = hexapod_session();
    let poses = base.topics["/hexapod/hex0/pose"].clone();
    let mut s = base.clone();
    s.topics.remove("/hexapod/hex0/pose");
    s.topics.insert("/hexapod/other/pose".into(), poses.clone());
    let err = geocal::kinds::hexapod::solve::solve(&s).expect_err("misplaced poses refused");
    let text = err.to_string();
    assert!(
        text.contains("/hexapod/other/pose") && text.contains("/hexapod/hex0/pose"),
        "{text}"
    );
    let mut s = base;
    s.topics.insert("/hexapod/trk0/pose".into(), poses);
    let err = geocal::kinds::hexapod::solve::solve(&s).expect_err("two pose topics refused");
    let text = err.to_string();
    assert!(
        text.contains("/hexapod/trk0/pose") && text.contains("/hexapod/hex0/pose"),
        "{text}"
    );
}

fn hexapod_session() -> geocal::session::reader::Session {
    geocal::session::reader::read_session(
        &session_dir("outside-hexapod-clean-2").join("session.mcap"),
    )
    .expect("session")
}

/// A measuring pose sensor must declare its noise: each missing key is refused by name.
#[test]
fn hexapod_pose_sensor_without_its_noise_is_refused() {
    let base = hexapod_session();
    let sensor = base
        .header
        .devices
        .iter()
        .position(|d| d.kind == "pose_sensor")
        .expect("a pose sensor");
    let mut s = base.clone();
    s.header.devices[sensor].noise_m = None;
    let err = geocal::kinds::hexapod::solve::solve(&s).expect_err("no noise_m");
    assert!(err.to_string().contains("`noise_m`"), "{err}");
    let mut s = base;
    s.header.devices[sensor].extra.remove("noise_rad");
    let err = geocal::kinds::hexapod::solve::solve(&s).expect_err("no noise_rad");
    assert!(err.to_string().contains("`noise_rad`"), "{err}");
}

/// Two pose messages per window, p + δ and p − δ: their mean is the one pose with σ/√2, so
/// the solve equals that of the one pose per window with the sensor's noise declared /√2.
#[test]
fn hexapod_several_pose_messages_per_window_are_averaged() {
    let base = hexapod_session();
    let topic = "/hexapod/hex0/pose";
    let mut s = base.clone();
    let poses = s.topics.get_mut(topic).expect("pose topic");
    let mut doubled = Vec::new();
    for m in poses.iter() {
        for sign in [1.0, -1.0] {
            let mut c = m.clone();
            for key in ["translation_m", "rotation_vector_rad"] {
                for k in 0..3 {
                    let v = c.msg[key][k].as_f64().expect("number");
                    c.msg[key][k] = (v + sign * 1e-6).into();
                }
            }
            c.log_time_ns += if sign > 0.0 { 0 } else { 1 };
            doubled.push(c);
        }
    }
    *poses = doubled;
    let averaged = geocal::kinds::hexapod::solve::solve(&s).expect("solve");
    let mut quieter = base;
    let sensor = quieter
        .header
        .devices
        .iter_mut()
        .find(|d| d.kind == "pose_sensor")
        .expect("a pose sensor");
    let root2 = 2f64.sqrt();
    sensor.noise_m = sensor.noise_m.map(|v| v / root2);
    let rad = sensor.extra["noise_rad"].as_f64().expect("noise_rad");
    sensor
        .extra
        .insert("noise_rad".into(), (rad / root2).into());
    let expected = geocal::kinds::hexapod::solve::solve(&quieter).expect("solve");
    for (a, b) in averaged.hinges.iter().zip(&expected.hinges) {
        for k in 0..3 {
            assert!((a.base_m[k] - b.base_m[k]).abs() < 1e-9, "leg {}", a.leg);
            let ratio = a.base_sigma_m[k] / b.base_sigma_m[k];
            assert!((ratio - 1.0).abs() < 1e-6, "leg {}: σ ratio {ratio}", a.leg);
        }
    }
}

/// Seven poses (home and six): 36 unknowns from 36 changes, no redundancy: χ²/dof is null.
#[test]
fn hexapod_chi2_per_dof_is_null_without_redundancy() {
    use geocal::session::messages::RunEvent;
    let mut s = hexapod_session();
    let last_kept = s
        .events
        .iter()
        .position(|e| matches!(e.msg, RunEvent::PoseBegin { pose: 7, .. }))
        .expect("pose 7");
    s.events.truncate(last_kept);
    let r = geocal::kinds::hexapod::solve::solve(&s).expect("solve");
    assert_eq!((r.poses, r.dof), (7, 0));
    assert_eq!(r.chi2_per_dof, None);
}
