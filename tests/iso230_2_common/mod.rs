//! The independent numpy evaluation (tests/python/iso230_2.py) and the comparison with
//! geocal's figures, shared by the ISO 230-2 tests.
#![allow(dead_code)]

use std::path::Path;
use std::process::Command;

use geocal::evaluate::iso230_2::{evaluate, Curves};

const INSTALL_HINT: &str = "pip install numpy";

pub fn numpy_figures(curves: &Curves) -> serde_json::Value {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("curves.json");
    std::fs::write(&path, serde_json::to_vec(curves).unwrap()).unwrap();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/iso230_2.py");
    let out = Command::new("python3")
        .arg(&script)
        .arg(&path)
        .output()
        .unwrap_or_else(|e| {
            panic!("cannot run python3 ({e}); install Python 3 and {INSTALL_HINT}")
        });
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_ne!(
        out.status.code(),
        Some(3),
        "numpy missing: {INSTALL_HINT}\n{stderr}"
    );
    assert!(out.status.success(), "iso230_2.py failed: {stderr}");
    serde_json::from_slice(&out.stdout).unwrap()
}

/// Every figure of geocal equals numpy's to rounding.
pub fn assert_agree(curves: &Curves) {
    let e = evaluate(curves).unwrap();
    let f = e.figures();
    let (up, down, b) = (
        f.up.as_ref().unwrap(),
        f.down.as_ref().unwrap(),
        f.bidirectional.as_ref().unwrap(),
    );
    let py = numpy_figures(curves);
    let ours = [
        ("E_up", up.systematic_error),
        ("E_down", down.systematic_error),
        ("R_up", up.repeatability.unwrap()),
        ("R_down", down.repeatability.unwrap()),
        ("A_up", up.accuracy.unwrap()),
        ("A_down", down.accuracy.unwrap()),
        ("B", b.reversal),
        ("B_mean", b.mean_reversal),
        ("E", b.systematic_error),
        ("M", b.mean_error),
        ("R", b.repeatability.unwrap()),
        ("A", b.accuracy.unwrap()),
    ];
    // Both sides sum the same few numbers in double precision: agreement to rounding.
    let tol = 1e-12 * 1e-6;
    for (name, value) in ours {
        let theirs = py[name].as_f64().unwrap();
        assert!(
            (value - theirs).abs() <= tol,
            "{name}: geocal {value:e}, numpy {theirs:e}"
        );
    }
    for (name, ours) in [
        ("mean_up", &up.mean_deviation_i),
        ("mean_down", &down.mean_deviation_i),
        ("B_i", &b.reversal_i),
    ] {
        for (i, (a, t)) in ours.iter().zip(py[name].as_array().unwrap()).enumerate() {
            let t = t.as_f64().unwrap();
            assert!(
                (a - t).abs() <= tol,
                "{name}[{i}]: geocal {a:e}, numpy {t:e}"
            );
        }
    }
    for (i, (a, t)) in up
        .s_i
        .iter()
        .zip(py["s_up"].as_array().unwrap())
        .enumerate()
    {
        let (a, t) = (a.unwrap(), t.as_f64().unwrap());
        assert!((a - t).abs() <= tol, "s_up[{i}]: geocal {a:e}, numpy {t:e}");
    }
    println!("{}", e.text("x"));
}
