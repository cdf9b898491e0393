//! Monte Carlo check of the uncertainty budget (GUM Supplement 1 style): the declared
//! contributors are drawn, the simulated machine and tracer measure a positioning error
//! curve with them, the real evaluation (parse, 20 °C normalisation, budget) reports it, and
//! the spread of the reported value must agree with the budget's U within 15 %.
//!
//! Level: one axis measured in line by the tracer, through the simulator's own effect models
//! (`SimEffects`: the scales' thermal expansion at the true CTE and material temperature, the
//! Edlén air error of the beam) and the evaluation path of a report (`evaluate_tracer` on a
//! `geometric_errors` value). The multilateration solve is left out: the contributors drawn
//! here are uniform scale factors and offsets, which the network solve passes to the points
//! unchanged (lengths fix the scale), and its own statistical σ enters the budget as the σ
//! reported with each value; drawing it here as the noise of that value is what the solve
//! would hand on. This keeps 500 draws well under a second and tests what the budget claims:
//! which inputs act, through which sensitivity, on the reported (normalised) value.

use crate::common;

use geocal::config::sim::{EffectSwitch, EffectsConfig};
use geocal::config::uncertainty::{NormalisationConfig, UncertaintyConfig};
use geocal::config::SimEnvironmentConfig;
use geocal::evaluate::normalise::MaterialTemperature;
use geocal::evaluate::tracer::evaluate_tracer;
use geocal::sim::effects::{
    SimEffects, REFERENCE_AIR_TEMP_K, REFERENCE_HUMIDITY_PCT, REFERENCE_PRESSURE_PA,
};
use nalgebra::Vector3;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use serde_json::json;

const DRAWS: usize = 500;
const POSITIONS_M: [f64; 7] = [0.1, 0.3, 0.5, 0.7, 0.9, 1.1, 1.3];
/// The material is 1.2 K warm during the run: the CTE's uncertainty acts.
const MATERIAL_TEMP_K: f64 = 294.35;
/// The solve's σ of each positioning value.
const SIGMA_STAT_M: f64 = 1.5e-7;

/// The machine's true positioning error (before the scales' expansion).
fn true_error_m(x: f64) -> f64 {
    4e-6 * (2.0 * x).sin() - 1.5e-6 * x
}

fn declared() -> UncertaintyConfig {
    UncertaintyConfig {
        tracer_scale_ppm: 0.5,
        tracer_offset_m: 1e-7,
        air_temp_k: 0.3,
        pressure_pa: 50.0,
        humidity_pct: 5.0,
        material_temp_k: 0.1,
        cte_per_k: 1.0e-6,
        reflector_m: 2e-7,
    }
}

struct Draws {
    /// The reported (normalised) EXX at the last position, per draw.
    reported_m: Vec<f64>,
    /// The budget's U at that position, per draw (it depends on the logged temperature).
    expanded_m: Vec<f64>,
    /// The expected value: the true error relative to the reference position.
    truth_m: f64,
}

/// One run of the measurement per draw, every declared input drawn from its distribution.
fn monte_carlo(budget_declares: &UncertaintyConfig) -> Draws {
    let u = declared();
    let norm = NormalisationConfig::default();
    let mut rng = ChaCha8Rng::seed_from_u64(20_261_125);
    let n = |s: f64| Normal::new(0.0, s).expect("σ >= 0");
    let station = Vector3::new(-0.5, 0.0, 0.0);
    let x_ref = POSITIONS_M[0];
    let mut out = Draws {
        reported_m: Vec::new(),
        expanded_m: Vec::new(),
        truth_m: true_error_m(POSITIONS_M[6]) - true_error_m(x_ref),
    };
    for _ in 0..DRAWS {
        let scale = 1e-6 * n(u.tracer_scale_ppm).sample(&mut rng);
        let offset_m = n(u.tracer_offset_m).sample(&mut rng);
        let reflector_m = n(u.reflector_m).sample(&mut rng);
        let cte_true = norm.scale_cte_per_k + n(u.cte_per_k).sample(&mut rng);
        let logged_material_k = MATERIAL_TEMP_K + n(u.material_temp_k).sample(&mut rng);
        let bias = (
            n(u.air_temp_k).sample(&mut rng),
            n(u.pressure_pa).sample(&mut rng),
            n(u.humidity_pct).sample(&mut rng),
        );
        // A tracer compensated with sensors that read `bias` high misses dn(true) − dn(read);
        // the sim's Edlén is linear, so its uncompensated-air error at reference − bias is
        // exactly that residual.
        let env = SimEnvironmentConfig {
            air_temp_k: REFERENCE_AIR_TEMP_K - bias.0,
            pressure_pa: REFERENCE_PRESSURE_PA - bias.1,
            humidity_pct: REFERENCE_HUMIDITY_PCT - bias.2,
            material_temp_k: vec![MATERIAL_TEMP_K],
            temp_swing_k: 0.0,
            temp_period_s: 3600.0,
        };
        let effects = EffectsConfig {
            air_refraction: EffectSwitch {
                enabled: true,
                size: 1.0,
            },
            thermal_expansion: EffectSwitch {
                enabled: true,
                size: cte_true,
            },
            ..Default::default()
        };
        let sim = SimEffects::new(&effects, &env, 7, 1, 0);
        let read_m = |x: f64| {
            let axes = sim.actual_axes_m([x + true_error_m(x), 0.0, 0.0], 0.0);
            sim.distance_m(0, &station, &Vector3::from(axes), 0.0, None)
        };
        // Homed at the reference position: the counter reads relative to it.
        let home_m = read_m(x_ref);
        let values: Vec<f64> = POSITIONS_M
            .iter()
            .map(|&x| {
                let counter_m = (read_m(x) - home_m) * (1.0 + scale) + offset_m;
                counter_m - (x - x_ref) + reflector_m + n(SIGMA_STAT_M).sample(&mut rng)
            })
            .collect();
        let sigma = [SIGMA_STAT_M; 7];
        let geometric_errors = json!({"axes": {"x": {"positions_m": POSITIONS_M,
            "errors": {"EXX": {"unit": "m", "values": values, "sigma": sigma}}}}});
        let material = MaterialTemperature::from_values([logged_material_k]);
        let evaluation = evaluate_tracer(
            &[],
            Some(&geometric_errors),
            material.as_ref(),
            budget_declares,
            &norm,
        )
        .expect("evaluation");
        let last = evaluation.positioning[0].budgets[6]
            .as_ref()
            .expect("a budget at the last position");
        out.reported_m.push(last.value);
        out.expanded_m.push(last.expanded_uncertainty);
    }
    out
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len() as f64
}

fn std(v: &[f64]) -> f64 {
    let m = mean(v);
    (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (v.len() - 1) as f64).sqrt()
}

#[test]
fn monte_carlo_spread_agrees_with_the_budget() {
    let d = monte_carlo(&declared());
    let spread_u = 2.0 * std(&d.reported_m);
    let budget_u = mean(&d.expanded_m);
    let ratio = spread_u / budget_u;
    eprintln!(
        "EXX at 1.3 m, {DRAWS} draws: Monte Carlo 2s = {:.3} µm, budget U = {:.3} µm, ratio {ratio:.3}; \
         mean {:.3} µm, truth {:.3} µm",
        spread_u * 1e6,
        budget_u * 1e6,
        mean(&d.reported_m) * 1e6,
        d.truth_m * 1e6
    );
    assert!((ratio - 1.0).abs() <= 0.15, "ratio {ratio}");
    // The normalisation leaves no bias: the mean is the true error within its own
    // standard error (4 of them).
    let standard_error = std(&d.reported_m) / (DRAWS as f64).sqrt();
    assert!(
        (mean(&d.reported_m) - d.truth_m).abs() < 4.0 * standard_error,
        "mean {} truth {}",
        mean(&d.reported_m),
        d.truth_m
    );
}

/// The check has power: a budget that leaves out one declared contributor (the CTE's) is
/// caught by the same comparison.
#[test]
fn monte_carlo_catches_a_budget_missing_a_contributor() {
    let incomplete = UncertaintyConfig {
        cte_per_k: 0.0,
        ..declared()
    };
    let d = monte_carlo(&incomplete);
    let ratio = 2.0 * std(&d.reported_m) / mean(&d.expanded_m);
    eprintln!("budget without the CTE: Monte Carlo 2s / U = {ratio:.3}");
    assert!((ratio - 1.0).abs() > 0.15, "ratio {ratio}");
}

/// End to end through a whole simulated run: the same machine measured at 20 °C and with its
/// scales 1 K warm (the sim's `thermal_expansion` at steel's CTE); the warm run's EXX
/// referred to 20 °C must match the cold run's raw EXX within the statistical σ of the two,
/// while the warm run's raw EXX is off by the expansion.
#[test]
fn a_warm_run_normalised_matches_the_run_at_20_c() {
    use geocal::evaluate::tracer::evaluate_session;
    use geocal::method::multilateration::MultilaterationResults;
    use geocal::session::reader::read_session;
    use std::path::Path;

    let evaluate = |material_k: f64, expansion: bool| {
        let text = format!(
            "{}\n[sim.environment]\nmaterial_temp_k = [{material_k}]\ntemp_swing_k = 0.0\n\n\
             [sim.effects]\nthermal_expansion = {{ enabled = {expansion}, size = 11.5e-6 }}\n\n\
             [normalisation]\nscale_cte_per_k = 11.5e-6\n",
            common::DEMO
        );
        let config = geocal::config::Config::parse(&text, Path::new("warm.toml")).expect("config");
        let dir = tempfile::tempdir().expect("tempdir");
        let (output, _) = common::run_with_truth(&text, dir.path());
        let results = output
            .results
            .get::<MultilaterationResults>()
            .expect("tracer results")
            .clone();
        let session = read_session(&output.session_path).expect("session");
        evaluate_session(&session, &results, Some(&config)).expect("evaluation")
    };
    let cold = evaluate(293.15, false);
    assert!(
        !cold.positioning.is_empty(),
        "no positioning curves: {:?}",
        cold.notes
    );
    let warm = evaluate(294.15, true);
    let (c, w) = (&cold.positioning[0].curve, &warm.positioning[0].curve);
    assert_eq!((c.error.as_str(), w.error.as_str()), ("EXX", "EXX"));
    let warm_k = warm.material_temperature.expect("logged").mean_k;
    assert!((warm_k - 294.15).abs() < 1e-9, "{warm_k}");
    let last = c.positions_m.len() - 1;
    let rel = |v: &[Option<f64>]| v[last].expect("value") - v[0].expect("value");
    let sigma = |v: &[Option<f64>]| {
        let s = |i: usize| v[i].expect("sigma");
        (s(0).powi(2) + s(last).powi(2)).sqrt()
    };
    let both_sigma = (sigma(&c.sigma_m).powi(2) + sigma(&w.sigma_m).powi(2)).sqrt();
    let expansion_m = 11.5e-6 * (c.positions_m[last] - c.positions_m[0]);
    let (cold_raw, warm_raw, warm_norm) = (rel(&c.raw_m), rel(&w.raw_m), rel(&w.normalised_m));
    eprintln!(
        "EXX(last) − EXX(first): cold raw {:.3} µm, warm raw {:.3} µm, warm normalised {:.3} µm; \
         expansion {:.3} µm, σ of the difference {:.3} µm",
        cold_raw * 1e6,
        warm_raw * 1e6,
        warm_norm * 1e6,
        expansion_m * 1e6,
        both_sigma * 1e6
    );
    assert!((warm_norm - cold_raw).abs() < 3.0 * both_sigma);
    assert!((warm_raw - cold_raw - expansion_m).abs() < 3.0 * both_sigma);
}
