//! ISO 230-2 figures of `geocal::evaluate::iso230_2` against an independent numpy
//! implementation (tests/python/iso230_2.py) on the same curves.

use crate::iso230_2_common;

use geocal::evaluate::iso230_2::{evaluate, AxisType, Curves};
use iso230_2_common::assert_agree;

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
    let run = |sign: f64, uniform: &mut dyn FnMut() -> f64| -> Vec<f64> {
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
