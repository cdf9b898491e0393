//! A simulated rotary_tracer run with ISO 230-2's cycle for the table (`[plan.rotary] runs =
//! 5`, pseudo-random angles, an overshoot before each run) on a table with a reversal and a
//! random positioning scatter: the table's figures from `evaluate::of_results` against the
//! simulated truth, within the noise model.

use crate::common;
use crate::iso230_2_common;

use common::run_with_truth;
use geocal::evaluate::of_results;
use geocal::session::messages::RunEvent;
use geocal::session::reader::read_session;

/// The table's reversal span and positioning scatter in the simulated world, radians (about
/// 4.1″ and 1.0″): both far above a step angle's measurement σ (about 0.1″ here).
const REVERSAL_RAD: f64 = 2e-5;
const REPEATABILITY_RAD: f64 = 5e-6;
const RUNS: usize = 5;
const ANGLES: usize = 9;

/// 9 pseudo-random table angles 40° apart, 5 bidirectional runs (90 table stations) and the
/// station off the table, on a table with a reversal and a positioning scatter.
fn iso_cycle() -> String {
    let text = common::reduced_rotary(
        40f64.to_radians(),
        ANGLES,
        &format!("spacing = \"pseudo_random\"\nruns = {RUNS}"),
    )
    .replace(
        "axis_tilt_rad = 1e-4 }",
        &format!(
            "axis_tilt_rad = 1e-4, reversal_rad = {REVERSAL_RAD:e}, repeatability_rad = {REPEATABILITY_RAD:e} }}"
        ),
    );
    assert!(text.contains("runs = 5") && text.contains("repeatability_rad"));
    text
}

#[test]
fn table_cycle_figures_agree_with_the_simulated_truth() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (output, truth) = run_with_truth(&iso_cycle(), dir.path());
    let session = read_session(&output.session_path).expect("session");

    // Every run is entered through its overshoot: one `rotation` event per table station,
    // the first of each run with the angle the table went to first.
    let rotations: Vec<(f64, Option<f64>)> = session
        .events
        .iter()
        .filter_map(|e| match &e.msg {
            RunEvent::Rotation {
                commanded_rad,
                via_rad,
                ..
            } => Some((*commanded_rad, *via_rad)),
            _ => None,
        })
        .collect();
    assert_eq!(rotations.len(), 2 * RUNS * ANGLES);
    let vias = rotations.iter().filter(|r| r.1.is_some()).count();
    assert_eq!(vias, 2 * RUNS);

    let iso = of_results(&output.results, &session).expect("ISO 230-2");
    println!("{}", iso.text());
    let table = iso
        .axes
        .iter()
        .find(|a| a.axis == "c")
        .expect("table evaluated");
    let e = &table.evaluation;
    assert_eq!(e.targets, ANGLES, "{:?}", table.notes);
    assert_eq!((e.runs_up, e.runs_down), (RUNS, RUNS), "{:?}", table.notes);
    assert!(
        e.not_per_iso_230_2.is_empty(),
        "the standard's cycle: {:?}",
        e.not_per_iso_230_2
    );
    // The same curves through the independent numpy evaluation.
    iso230_2_common::assert_agree(&table.curves);

    // The truth's deviations, as the results give them: relative to the first table station.
    let truth_steps = truth["rotary"]["steps"].as_array().expect("truth steps");
    let true_error: Vec<f64> = truth_steps
        .iter()
        .map(|s| s["error_rad"].as_f64().expect("error_rad"))
        .collect();
    assert_eq!(true_error.len(), 2 * RUNS * ANGLES);
    let rotary = output
        .results
        .get::<geocal::kinds::rotary_tracer::solve::RotaryTracerResults>()
        .expect("rotary_tracer results");
    let steps = &rotary.rotary.steps;
    let mut largest_z: f64 = 0.0;
    for (k, step) in steps.iter().enumerate() {
        if k > 0 {
            let z = (step.error_rad - (true_error[k] - true_error[0])) / step.sigma_rad;
            largest_z = largest_z.max(z.abs());
        }
        // Every station of a run is approached from the run's side.
        let run_side = if (k / ANGLES) % 2 == 0 { 1 } else { -1 };
        assert_eq!(step.approach, Some(run_side), "{}", step.station);
    }
    println!("step errors against the truth: largest |error − truth|/σ {largest_z:.2}");
    // 89 steps: beyond 4σ with probability below 0.6 % if their σ are honest.
    assert!(largest_z < 4.0, "a step {largest_z:.2} σ from the truth");

    // Reversal: the truth's B_i is the drawn span plus the runs' scatter at that target.
    let f = e.figures();
    let b = f.bidirectional.as_ref().expect("both directions");
    let up = f.up.as_ref().expect("↑");
    let down = f.down.as_ref().expect("↓");
    let truth_mean = |side: usize, target: usize| -> f64 {
        (0..RUNS)
            .map(|run| {
                let base = (2 * run + side) * ANGLES;
                let position = if side == 0 {
                    target
                } else {
                    ANGLES - 1 - target
                };
                true_error[base + position] - true_error[0]
            })
            .sum::<f64>()
            / RUNS as f64
    };
    let sigma = table.target_sigma_rad.as_ref().expect("σ per target");
    let mut truth_mean_reversal = 0.0;
    for (i, sigma_i) in sigma.iter().enumerate() {
        let (t_up, t_down) = (truth_mean(0, i), truth_mean(1, i));
        truth_mean_reversal += (t_up - t_down) / ANGLES as f64;
        // B_i: the reference station's error cancels; what is left of each step's is at most
        // its σ_i.
        let budget_b = 3.0 * sigma_i * (2.0 / RUNS as f64).sqrt();
        assert!(
            (b.reversal_i[i] - (t_up - t_down)).abs() <= budget_b,
            "B_{i}: {:e} rad, truth {:e}, budget {budget_b:e}",
            b.reversal_i[i],
            t_up - t_down
        );
        // A mean of 5 steps, each known to σ_i; their errors share the reference station's,
        // so the mean's σ lies between σ_i/√5 and σ_i: the larger is taken.
        let budget = 3.0 * sigma_i;
        assert!(
            (up.mean_deviation_i[i] - t_up).abs() <= budget,
            "x̄↑_{i}: {:e} rad, truth {t_up:e}, budget {budget:e}",
            up.mean_deviation_i[i]
        );
        assert!(
            (down.mean_deviation_i[i] - t_down).abs() <= budget,
            "x̄↓_{i}: {:e} rad, truth {t_down:e}, budget {budget:e}",
            down.mean_deviation_i[i]
        );
    }
    println!(
        "B̄ {:.3}″ (truth {:.3}″, drawn reversal {:.3}″), M {:.3}″, E {:.3}″, R {:.3}″, A {:.3}″",
        b.mean_reversal.to_degrees() * 3600.0,
        truth_mean_reversal.to_degrees() * 3600.0,
        REVERSAL_RAD.to_degrees() * 3600.0,
        b.mean_error.to_degrees() * 3600.0,
        b.systematic_error.to_degrees() * 3600.0,
        b.repeatability.expect("R").to_degrees() * 3600.0,
        b.accuracy.expect("A").to_degrees() * 3600.0,
    );
    // Against the drawn reversal, B̄ also carries the table's scatter: it averages 9 targets'
    // differences of two means of 5 positionings, so its σ is √(2/5 / 9) of one step's.
    let step_sd =
        (REPEATABILITY_RAD.powi(2) + sigma.iter().map(|s| s * s).sum::<f64>() / 9.0).sqrt();
    let sigma_mean_reversal = step_sd * (2.0 / 5.0 / 9.0f64).sqrt();
    assert!(
        (b.mean_reversal - REVERSAL_RAD).abs() <= 3.0 * sigma_mean_reversal,
        "B̄ {:e} rad, drawn {REVERSAL_RAD:e} rad, σ {sigma_mean_reversal:e}",
        b.mean_reversal
    );

    // Repeatability: the pooled run-to-run s is the table's scatter with the measurement's.
    let pooled = (up
        .s_i
        .iter()
        .chain(&down.s_i)
        .map(|s| s.expect("s").powi(2))
        .sum::<f64>()
        / (2 * ANGLES) as f64)
        .sqrt();
    println!(
        "s pooled {:.3}″, expected {:.3}″",
        pooled.to_degrees() * 3600.0,
        step_sd.to_degrees() * 3600.0
    );
    // 18 targets-directions × 4 degrees of freedom: s/σ within [0.78, 1.22] with probability
    // 0.99 (χ² with 72 dof).
    assert!(
        pooled / step_sd > 0.78 && pooled / step_sd < 1.22,
        "pooled s {pooled:e} rad, expected {step_sd:e} rad"
    );
}
