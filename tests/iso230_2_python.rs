//! ISO 230-2 figures of `geocal::evaluate::iso230_2` against an independent numpy
//! implementation (tests/python/iso230_2.py) on the same curves.

use std::path::Path;
use std::process::Command;

use geocal::evaluate::iso230_2::{evaluate, AxisType, Curves};

const INSTALL_HINT: &str = "pip install numpy";

/// Deterministic curves of a machine axis: a scale error, a periodic (pitch) error, a
/// reversal and a per-approach scatter, in metres, at pseudo-random targets.
fn axis_curves(runs: usize, seed: u64) -> Curves {
    let mut state = seed;
    let mut uniform = move || {
        // SplitMix64: a fixed, platform-independent sequence.
        state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    };
    let targets: Vec<f64> = (0..11)
        .map(|i| 0.1 * i as f64 + 0.02 * (uniform() - 0.5))
        .collect();
    let systematic = |p: f64| 4e-6 * p + 0.8e-6 * (p / 0.016 * std::f64::consts::TAU).sin();
    let mut run = |sign: f64, uniform: &mut dyn FnMut() -> f64| -> Vec<f64> {
        targets
            .iter()
            .map(|&p| systematic(p) + sign * 1.5e-6 + 0.6e-6 * (uniform() - 0.5))
            .collect()
    };
    let up = (0..runs).map(|_| run(0.5, &mut uniform)).collect();
    let down = (0..runs).map(|_| run(-0.5, &mut uniform)).collect();
    Curves {
        axis_type: AxisType::Linear,
        targets,
        up,
        down,
    }
}

fn numpy_figures(curves: &Curves) -> serde_json::Value {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("curves.json");
    std::fs::write(&path, serde_json::to_vec(curves).unwrap()).unwrap();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/iso230_2.py");
    let out = Command::new("python3")
        .arg(&script)
        .arg(&path)
        .output()
        .unwrap_or_else(|e| panic!("cannot run python3 ({e}); install Python 3 and {INSTALL_HINT}"));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_ne!(out.status.code(), Some(3), "numpy missing: {INSTALL_HINT}\n{stderr}");
    assert!(out.status.success(), "iso230_2.py failed: {stderr}");
    serde_json::from_slice(&out.stdout).unwrap()
}

fn assert_agree(curves: &Curves) {
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
            assert!((a - t).abs() <= tol, "{name}[{i}]: geocal {a:e}, numpy {t:e}");
        }
    }
    for (i, (a, t)) in up.s_i.iter().zip(py["s_up"].as_array().unwrap()).enumerate() {
        let (a, t) = (a.unwrap(), t.as_f64().unwrap());
        assert!((a - t).abs() <= tol, "s_up[{i}]: geocal {a:e}, numpy {t:e}");
    }
    println!("{}", e.text("x"));
}

#[test]
fn figures_agree_with_numpy_on_the_standard_cycle() {
    let curves = axis_curves(5, 20261125);
    assert_agree(&curves);
    assert!(evaluate(&curves).unwrap().not_per_iso_230_2.is_empty());
}

#[test]
fn figures_agree_with_numpy_on_a_short_cycle() {
    let curves = axis_curves(2, 7);
    assert_agree(&curves);
    let e = evaluate(&curves).unwrap();
    assert!(e.verdict().contains("2 runs ↑"), "{}", e.verdict());
}
