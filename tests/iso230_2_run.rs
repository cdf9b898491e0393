//! A simulated multilateration run with ISO 230-2's cycle (`passes = 5`, pseudo-random x
//! targets) and a reversal on the axes: the x axis's figures from `evaluate::of_results`
//! against the simulated truth, within the noise model.

use crate::common;
use crate::iso230_2_common;

use common::{run_with_truth, small_demo, truth_point, xyz};
use geocal::evaluate::of_results;
use geocal::session::reader::read_session;

/// The reversal span drawn per axis lies in [0.5, 1.0] × this, with a random sign.
const REVERSAL_SIZE_M: f64 = 2e-6;

/// 4 stations, x: 7 pseudo-random targets, y and z: 2 each, 5 bidirectional runs, 10 Hz and
/// 1 s dwells (quick), a reversal on every axis.
fn iso_cycle() -> String {
    let text = small_demo()
        .replace(
            "x = { from = 0.1, to = 1.3, count = 3 }",
            "x = { from = 0.1, to = 1.3, count = 7, spacing = \"pseudo_random\" }",
        )
        .replace(
            "y = { from = 0.2, to = 2.2, count = 3 }",
            "y = { from = 0.2, to = 2.2, count = 2 }",
        )
        .replace("passes = [\"forward\", \"backward\"]", "passes = 5")
        .replace("sample_rate_hz = 25.0", "sample_rate_hz = 10.0")
        .replace("dwell_s = 2.0", "dwell_s = 1.0")
        .replace("window_s = 0.6", "window_s = 0.4");
    assert!(text.contains("passes = 5") && text.contains("pseudo_random"));
    format!("{text}\n[sim.effects]\nreversal = {{ enabled = true, size = {REVERSAL_SIZE_M:e} }}\n")
}

#[test]
fn standard_cycle_figures_agree_with_the_simulated_truth() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (output, truth) = run_with_truth(&iso_cycle(), dir.path());
    let session = read_session(&output.session_path).expect("session");
    let iso = of_results(&output.results, &session).expect("ISO 230-2");
    println!("{}", iso.text());
    let x = iso
        .axes
        .iter()
        .find(|a| a.axis == "x")
        .expect("x axis evaluated");
    let e = &x.evaluation;
    // The same curves through the independent numpy evaluation.
    iso230_2_common::assert_agree(&x.curves);
    // Serpentine rows reach the first and last x of a row without moving x: those two
    // targets are not approached from both sides in every run and are left out.
    assert_eq!(e.targets, 5, "{:?}", x.notes);
    // 5 bidirectional runs are 10 passes; the rows of a pass alternate, so every pass
    // reaches each inner target both ways. The first pass is left out: its first homing came
    // before any axis had moved, at another place in the reversal (`homed_otherwise`).
    assert!(
        x.notes.iter().any(|n| n.contains("passes [0] left out")),
        "{:?}",
        x.notes
    );
    assert_eq!((e.runs_up, e.runs_down), (9, 9));
    assert!(
        !e.not_per_iso_230_2
            .iter()
            .any(|w| w.contains("runs") || w.contains("equally")),
        "{:?}",
        e.not_per_iso_230_2
    );
    let f = e.figures();
    let b = f.bidirectional.as_ref().expect("both directions");
    let network = output.results.multilateration().expect("tracer network");

    // Truth along x: at each target, the mean over the grid's lines of the true x deviation
    // (the same lines every target has; the reversal cancels in the bidirectional mean).
    let truth_dev: Vec<f64> = x
        .curves
        .targets
        .iter()
        .map(|&t| {
            let devs: Vec<f64> = network
                .points
                .iter()
                .filter(|p| p.target == "t0" && (p.nominal_m[0] - t).abs() < 1e-9)
                .map(|p| {
                    xyz(&truth_point(&truth, &p.target, p.point)["actual_m"])[0] - p.nominal_m[0]
                })
                .collect();
            assert_eq!(devs.len(), 4, "4 lines per x target");
            devs.iter().sum::<f64>() / devs.len() as f64
        })
        .collect();
    let centred = |v: &[f64]| -> Vec<f64> {
        let mean = v.iter().sum::<f64>() / v.len() as f64;
        v.iter().map(|x| x - mean).collect()
    };
    let (est, tru) = (centred(&b.mean_deviation_i), centred(&truth_dev));
    // Budget: the joint solve's point σ in x (stations and homing distances, common to all
    // runs) plus the scatter of a mean over 2 directions × 10 runs × 2 lines.
    let joint_sigma_x = network
        .points
        .iter()
        .map(|p| p.sigma_m[0])
        .fold(0.0, f64::max);
    let sigma_dev = x.deviation_sigma_median_m.expect("σ");
    let budget = 3.0 * (joint_sigma_x.powi(2) + sigma_dev.powi(2) / 40.0).sqrt();
    let truth_m =
        tru.iter().cloned().fold(f64::MIN, f64::max) - tru.iter().cloned().fold(f64::MAX, f64::min);
    println!(
        "M: estimated {:.3} µm, truth {:.3} µm; budget per target {:.3} µm",
        b.mean_error * 1e6,
        truth_m * 1e6,
        budget * 1e6
    );
    for (i, (a, t)) in est.iter().zip(&tru).enumerate() {
        assert!(
            (a - t).abs() <= budget,
            "x̄_{i}: {:.3} µm, truth {:.3} µm, budget {:.3} µm",
            a * 1e6,
            t * 1e6,
            budget * 1e6
        );
    }
    assert!((b.mean_error - truth_m).abs() <= 2.0 * budget);

    // Reversal: the same span at every target, of the drawn size.
    // B_i: the difference of two means of 10 cells, each a mean over 2 lines.
    let s_b = 3.0 * sigma_dev * 0.1f64.sqrt();
    println!(
        "B: {:.3} µm, B̄ {:.3} µm, B_i {:?} µm",
        b.reversal * 1e6,
        b.mean_reversal * 1e6,
        b.reversal_i
            .iter()
            .map(|v| (v * 1e8).round() / 100.0)
            .collect::<Vec<_>>()
    );
    for bi in &b.reversal_i {
        assert!(
            (bi - b.mean_reversal).abs() <= s_b,
            "B_i {bi:e} vs B̄ {:e}",
            b.mean_reversal
        );
    }
    let span = b.mean_reversal.abs();
    assert!(
        span >= 0.5 * REVERSAL_SIZE_M - s_b && span <= REVERSAL_SIZE_M + s_b,
        "|B̄| = {span:e} m outside the drawn range"
    );

    let (pooled, predicted) = pooled_and_predicted_s(x);
    println!(
        "s pooled {:.4} µm, predicted {:.4} µm; R {:.3} µm",
        pooled * 1e6,
        predicted * 1e6,
        b.repeatability.expect("R") * 1e6
    );
}

/// The pooled s over every target and direction, and the σ the declared noise predicts for
/// it: a cell is the mean over 2 lines of one pass.
fn pooled_and_predicted_s(x: &geocal::evaluate::AxisIso) -> (f64, f64) {
    let f = x.evaluation.figures();
    let up = f.up.as_ref().expect("up");
    let down = f.down.as_ref().expect("down");
    let pooled = (up
        .s_i
        .iter()
        .chain(&down.s_i)
        .map(|s| s.expect("s").powi(2))
        .sum::<f64>()
        / (up.s_i.len() + down.s_i.len()) as f64)
        .sqrt();
    let target_sigma = x.target_sigma_m.as_ref().expect("σ per target");
    let predicted =
        (target_sigma.iter().map(|s| s * s / 2.0).sum::<f64>() / target_sigma.len() as f64).sqrt();
    (pooled, predicted)
}

/// The run-to-run scatter of the per-pass deviations is the declared noise's. It was 1.37×
/// that (0.101 vs 0.073 µm) while the first pass was a run: its first homing (station s1)
/// came before any axis had moved, so with the reversal on its home point, and the counter's
/// zero, sat half a reversal span away on every axis from every later homing's, an offset of
/// all of s1's lengths in that pass that no homing distance of the solve holds. The runs
/// leave such a pass out (`deviations::homed_otherwise`).
#[test]
fn repeatability_matches_the_declared_noise() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (output, _) = run_with_truth(&iso_cycle(), dir.path());
    let session = read_session(&output.session_path).expect("session");
    let iso = of_results(&output.results, &session).expect("ISO 230-2");
    let x = iso.axes.iter().find(|a| a.axis == "x").expect("x");
    let (pooled, predicted) = pooled_and_predicted_s(x);
    // 10 targets-directions × 9 degrees of freedom: the ratio of a pooled s to its σ lies
    // within [0.8, 1.2] with probability > 0.99.
    assert!(
        pooled / predicted > 0.8 && pooled / predicted < 1.2,
        "pooled s {pooled:e} m, predicted {predicted:e} m"
    );
}
