//! The structured diagnosis (points eliminated block by block, `kinds::tracer_plan::diagnosis::schur`) against its
//! dense oracle (the whole design's thin SVD, `kinds::tracer_plan::diagnosis::dense`) on sessions with effects in
//! the data: every figure the diagnosis reports (χ² drops, p, ΔBIC, held-out RMS and ratios,
//! the selection, the effects' estimates and σ, leave-one-station-out, the points level) must
//! agree to 1e-9 relative (an estimate: relative to the larger of its value and its σ). A clean session alone cannot show a departure that only the effect
//! columns cause (their scale is ~1e-7 of the stations' in the whitened design).

use crate::common;

use std::path::Path;

use common::{diagnose_demo, record_session, with_effects};
use geocal::diagnose::DiagnoseOptions;
use geocal::kinds::diagnosis::diagnose_file;
use geocal::kinds::tracer_plan::diagnosis::fit::dense_oracle;
use serde_json::Value;

/// Relative agreement of every number: far above the rounding of either path (~1e-12), far
/// below any figure's meaning.
const RELATIVE: f64 = 1e-9;
/// p-values below this are compared as ln p (see `departures`).
const P_TAIL: f64 = 1e-30;

/// Where two diagnoses (as JSON) differ: numbers beyond `RELATIVE`, anything else unequal.
fn departures(path: &str, a: &Value, b: &Value, out: &mut Vec<String>) {
    match (a, b) {
        (Value::Number(x), Value::Number(y)) => {
            let (x, y) = (
                x.as_f64().unwrap_or(f64::NAN),
                y.as_f64().unwrap_or(f64::NAN),
            );
            let close = |x: f64, y: f64| (x - y).abs() <= RELATIVE * x.abs().max(y.abs());
            // A p-value is the tail of its statistic: far in the tail (p ~ 1e-54, statistic
            // ~ 250) a rounding-level difference of the statistic (1e-11 relative) is 2e-9 of
            // p. There p is compared as ln p, the statistic's own scale.
            let tail = path.ends_with("p_value") && x > 0.0 && y > 0.0 && x.max(y) < P_TAIL;
            if !(close(x, y) || tail && close(x.ln(), y.ln())) {
                out.push(format!("{path}: structured {x:e}, dense {y:e}"));
            }
        }
        (Value::Array(x), Value::Array(y)) if x.len() == y.len() => {
            for (k, (u, v)) in x.iter().zip(y).enumerate() {
                departures(&format!("{path}[{k}]"), u, v, out);
            }
        }
        (Value::Object(x), Value::Object(y)) if x.len() == y.len() => {
            for (key, u) in x {
                // An effect's estimate is rounded on the scale of its σ, not of its value: one
                // near zero against its σ (a rejected candidate's, e.g. 0.015 σ) is compared
                // relative to its σ.
                let sigma = x.get(&format!("{key}.sigma")).and_then(Value::as_f64);
                let within_sigma = match (sigma, u.as_f64(), y.get(key).and_then(Value::as_f64)) {
                    (Some(s), Some(p), Some(q)) => (p - q).abs() <= RELATIVE * s.abs(),
                    _ => false,
                };
                match y.get(key) {
                    Some(_) if within_sigma => {}
                    Some(v) => departures(&format!("{path}.{key}"), u, v, out),
                    None => out.push(format!("{path}.{key}: only in the structured diagnosis")),
                }
            }
        }
        _ if a == b => {}
        _ => out.push(format!("{path}: structured {a}, dense {b}")),
    }
}

/// Rounding of a solved point's coordinates (≈ 1 m, a few ulp of 2.2e-16 m).
const COORDINATE_ROUNDING_M: f64 = 1e-15;

/// `corrected`'s figures are the RMS of differences between two solves' absolute point
/// coordinates (nominal, and with the selected effects): ~40 nm out of ~1 m, so their last
/// digits are the coordinates' rounding (5e-17 m is 1.2e-9 of 40 nm). They are compared to
/// `RELATIVE` plus that rounding; the rest of `corrected` as every other field. Takes the two
/// numbers out of both.
fn corrected_departures(a: &mut Value, b: &mut Value, out: &mut Vec<String>) {
    let take = |v: &mut Value, key: &str| {
        v.get_mut("corrected")
            .and_then(Value::as_object_mut)
            .and_then(|c| c.remove(key))
            .and_then(|x| x.as_f64())
    };
    let (am, bm) = (take(a, "points_moved_rms_m"), take(b, "points_moved_rms_m"));
    let (az, bz) = (
        take(a, "points_moved_rms_sigma"),
        take(b, "points_moved_rms_sigma"),
    );
    match (am, bm, az, bz) {
        (None, None, None, None) => {}
        (Some(am), Some(bm), Some(az), Some(bz)) => {
            // σ of the points: the ratio of the two figures.
            let sigma_m = if az > 0.0 { am / az } else { f64::INFINITY };
            let pairs = [
                ("points_moved_rms_m", am, bm, COORDINATE_ROUNDING_M),
                (
                    "points_moved_rms_sigma",
                    az,
                    bz,
                    COORDINATE_ROUNDING_M / sigma_m,
                ),
            ];
            for (key, x, y, floor) in pairs {
                if (x - y).abs() > RELATIVE * x.abs().max(y.abs()) + floor {
                    out.push(format!(".corrected.{key}: structured {x:e}, dense {y:e}"));
                }
            }
        }
        other => out.push(format!(
            ".corrected: structured and dense differ: {other:?}"
        )),
    }
}

/// Diagnose `session` structured and dense; panics with every departure.
fn assert_matches_the_dense_oracle(session: &Path) {
    if let Err(why) = compare_with_the_dense_oracle(session) {
        panic!("{why}");
    }
}

/// Diagnose `session` structured and dense; every departure, with both reports.
fn compare_with_the_dense_oracle(session: &Path) -> Result<(), String> {
    let options = DiagnoseOptions::default();
    let structured = diagnose_file(session, &options).expect("structured diagnosis");
    let dense = dense_oracle(|| diagnose_file(session, &options)).expect("dense diagnosis");
    let (mut a, mut b) = (
        serde_json::to_value(&structured).expect("json"),
        serde_json::to_value(&dense).expect("json"),
    );
    let mut out = Vec::new();
    corrected_departures(&mut a, &mut b, &mut out);
    departures("", &a, &b, &mut out);
    if out.is_empty() {
        return Ok(());
    }
    Err(format!(
        "{}: {} departures from the dense oracle:\n{}\n\nstructured:\n{}\ndense:\n{}",
        session.display(),
        out.len(),
        out.join("\n"),
        geocal::diagnose::text(&structured),
        geocal::diagnose::text(&dense)
    ))
}

fn simulated_comparison(seed: u64, line: &str) -> Result<(), String> {
    let dir = tempfile::tempdir().expect("tempdir");
    let session = record_session(&with_effects(&diagnose_demo(), seed, line), dir.path());
    compare_with_the_dense_oracle(&session).map_err(|why| format!("seed {seed}, {line:?}: {why}"))
}

fn simulated(seed: u64, line: &str) {
    if let Err(why) = simulated_comparison(seed, line) {
        panic!("{why}");
    }
}

/// Air refraction's column (dn·L, ~1e-7 m per unit) and dead path's (dn per station) are the
/// smallest in the design: a rank cut that depends on the columns' scale drops them.
#[test]
fn air_refraction_matches_the_dense_oracle() {
    simulated(14, "air_refraction = { enabled = true, size = 1.0 }");
}

#[test]
fn dead_path_matches_the_dense_oracle() {
    simulated(17, "dead_path = { enabled = true, size = 2.0 }");
}

/// A session of the independent recorder (each in its own test: they run side by side).
fn assert_outside_session_matches_the_dense_oracle(name: &str) {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/outside");
    assert_matches_the_dense_oracle(&root.join(name).join("session.mcap"));
}

/// The independent recorder's session with a reversal in the data.
#[test]
fn outside_session_with_a_reversal_matches_the_dense_oracle() {
    assert_outside_session_matches_the_dense_oracle("outside-reversal-8");
}

/// The independent recorder's clean session.
#[test]
fn outside_clean_session_matches_the_dense_oracle() {
    assert_outside_session_matches_the_dense_oracle("outside-clean-7");
}

/// Every effect case of `tests/diagnose.rs` (its seeds and sizes) and the shipped
/// multilateration example (`config/demo-multilateration.toml`): a longer check, run by hand
/// after a change to the structured algebra (`cargo test --test integration diagnose_oracle:: -- --ignored`).
#[test]
#[ignore = "about 20 simulated runs and dense diagnoses; run by hand"]
fn every_effect_case_matches_the_dense_oracle() {
    let mut failures = Vec::new();
    for (seed, line) in [
        (11, "station_drift = { enabled = true, size = 5e-9 }"),
        (12, "reversal = { enabled = true, size = 1e-6 }"),
        (13, "length_step = { enabled = true, size = 1e-6 }"),
        (
            15,
            "tracer_eccentricity = { enabled = true, size_m = 4e-6, z_size_m = 2e-6 }",
        ),
        (16, "thermal_drift = { enabled = true, size = 4e-9 }"),
        (18, "thermal_expansion = { enabled = true, size = 2e-6 }"),
        (
            19,
            "settling = { enabled = true, size_m = 3e-6, tau_s = 0.5 }",
        ),
        (20, "target_offset = { enabled = true, size_m = 1e-3 }"),
        (100, ""),
        (101, ""),
    ] {
        if let Err(why) = simulated_comparison(seed, line) {
            failures.push(why);
        }
    }
    // The config/ example the diagnosis applies to (multilateration), as shipped.
    let dir = tempfile::tempdir().expect("tempdir");
    let demo = record_session(common::DEMO, dir.path());
    if let Err(why) = compare_with_the_dense_oracle(&demo) {
        failures.push(format!("config/demo-multilateration.toml: {why}"));
    }
    assert!(failures.is_empty(), "{}", failures.join("\n\n"));
}
