//! Monte Carlo check of the probe_install budget: each draw takes the declared contributors
//! from their distributions (probe scale, sphere radius, sphere form at every point, the
//! CMM's scale per axis) and the readings' noise, the model of the kind's world
//! (`model::probe_install`: the true beam meets the true sphere) makes the observations with
//! them, and the kind's LM solver runs from the nominal installation as `solve` does. The
//! spread 2s of every parameter and of the measured radius must agree with the budget's U
//! within 15 %; a budget that leaves out a contributor must fail the same comparison.
//!
//! Level: the observations are made in memory from the true installation (the published
//! postures, 25 points each, as config/probe-install.toml), not through the sequencer and a
//! recording, so that 200 solves stay quick; the GA is left out (it reports beside LM, its
//! values have no budget).

use crate::budget_mc;

use budget_mc::{ratios, TOLERANCE};
use geocal::kinds::probe_install::budget::budgets;
use geocal::kinds::probe_install::config::ProbeInstallUncertainty;
use geocal::model::probe_install::{beam_in_base, probe_offset, ProbeObservation};
use geocal::solve::probe_install::{
    example_nominal, example_truth, measured_radius_m, published_postures_rad, solve_lm,
    tangent_basis, LmOptions, ProbeInstallProblem,
};
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

const RADIUS_M: f64 = 6e-3;
/// Draws: 1000 (at least the 200 asked), so that the sampling spread of each 2s (about
/// 1/√(2·999) ≈ 2.2 %) stays well inside the 15 % over the 12 quantities.
const DRAWS: usize = 1000;
/// σ of a point's mean reading: 1 µm per reading, 5 readings.
const SIGMA_M: f64 = 1e-6 / 2.236_067_977_499_79;

fn declared() -> ProbeInstallUncertainty {
    ProbeInstallUncertainty {
        probe_scale_ppm: Some(300.0),
        sphere_radius_m: Some(0.5e-6),
        sphere_form_m: Some(0.3e-6),
        machine_scale_ppm: Some(5.0),
    }
}

/// A probed point of the plan: posture, outward normal of the surface, true reading.
struct Layout {
    a_rad: f64,
    b_rad: f64,
    normal: Vector3<f64>,
    reading_m: f64,
}

fn layout() -> Vec<Layout> {
    let truth = example_truth();
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let mut out = Vec::new();
    for (a, b) in published_postures_rad() {
        let w = beam_in_base(&truth, a, b).normalize();
        let (e1, e2) = tangent_basis(&w);
        for _ in 0..25 {
            let cos_min = 40f64.to_radians().cos();
            let ct = 1.0 - rng.random::<f64>() * (1.0 - cos_min);
            let st = (1.0 - ct * ct).max(0.0).sqrt();
            let phi = rng.random::<f64>() * std::f64::consts::TAU;
            out.push(Layout {
                a_rad: a,
                b_rad: b,
                normal: -ct * w + st * (phi.cos() * e1 + phi.sin() * e2),
                reading_m: (2.0 * rng.random::<f64>() - 1.0) * 2e-3,
            });
        }
    }
    out
}

/// One measurement with drawn errors: the true sphere of radius R + δr with a form deviation
/// at each point, the probe reading (1 + g) times the true distance, each machine scale
/// reading (1 + s) times the true position.
/// Also returns the draw's true radius.
fn observe(
    layout: &[Layout],
    rng: &mut ChaCha8Rng,
    u: &ProbeInstallUncertainty,
) -> (Vec<ProbeObservation>, f64) {
    let truth = example_truth();
    let n = |s: Option<f64>| Normal::new(0.0, s.unwrap_or(0.0)).expect("σ >= 0");
    let g = 1e-6 * n(u.probe_scale_ppm).sample(rng);
    let dr = n(u.sphere_radius_m).sample(rng);
    let s: [f64; 3] = std::array::from_fn(|_| 1e-6 * n(u.machine_scale_ppm).sample(rng));
    let noise = n(Some(SIGMA_M));
    let observations = layout
        .iter()
        .map(|p| {
            let form = n(u.sphere_form_m).sample(rng);
            let surface = truth.sphere_centre() + (RADIUS_M + dr + form) * p.normal;
            let machine = surface - probe_offset(&truth, p.a_rad, p.b_rad, p.reading_m);
            ProbeObservation {
                a_rad: p.a_rad,
                b_rad: p.b_rad,
                machine_m: std::array::from_fn(|k| machine[k] * (1.0 + s[k])),
                reading_m: p.reading_m * (1.0 + g) + noise.sample(rng),
                sigma_m: SIGMA_M,
            }
        })
        .collect();
    (observations, RADIUS_M + dr)
}

fn problem(observations: Vec<ProbeObservation>) -> ProbeInstallProblem {
    ProbeInstallProblem {
        nominal: example_nominal(),
        sphere_radius_m: RADIUS_M,
        observations,
    }
}

/// The errors of one draw's reported quantities: the LM parameters from the nominal start
/// and the radius measured with them, each minus its truth (the drawn radius is the truth of
/// the measured one).
fn solve(p: &ProbeInstallProblem, true_radius_m: f64) -> Vec<f64> {
    let lm = solve_lm(p, &p.nominal, &LmOptions::default()).expect("lm");
    let truth = example_truth().to_vector();
    let mut q: Vec<f64> = (lm.params.to_vector() - truth).iter().copied().collect();
    q.push(measured_radius_m(&lm.params, &p.observations).expect("radius") - true_radius_m);
    q
}

/// The draws' quantities and the budget's U (of the first draw's data, budget as declared).
fn monte_carlo(
    budget_declares: &ProbeInstallUncertainty,
) -> (Vec<Vec<f64>>, Vec<f64>, Vec<String>) {
    let layout = layout();
    let mut rng = ChaCha8Rng::seed_from_u64(20_261_125);
    let first = problem(observe(&layout, &mut rng, &declared()).0);
    let lm = solve_lm(&first, &first.nominal, &LmOptions::default()).expect("lm");
    let b = budgets(&first, &lm.params, &lm.sigma, budget_declares).expect("budget");

    let expanded = b.budgets.iter().map(|b| b.expanded_uncertainty).collect();
    let names = b.budgets.iter().map(|b| b.quantity.clone()).collect();
    let draws = (0..DRAWS)
        .map(|_| {
            let (observations, true_radius_m) = observe(&layout, &mut rng, &declared());
            solve(&problem(observations), true_radius_m)
        })
        .collect();
    (draws, expanded, names)
}

#[test]
fn monte_carlo_spread_agrees_with_the_budget() {
    let (draws, expanded, names) = monte_carlo(&declared());
    let r = ratios(&draws, &expanded);
    for (name, ratio) in names.iter().zip(&r) {
        eprintln!("probe_install {name}: Monte Carlo 2s / U = {ratio:.3} ({DRAWS} draws)");
    }
    for (name, ratio) in names.iter().zip(&r) {
        assert!((ratio - 1.0).abs() <= TOLERANCE, "{name}: ratio {ratio}");
    }
}

/// The check has power: a budget without the probe's scale, or without the sphere radius,
/// misses quantities they act on.
#[test]
fn monte_carlo_catches_a_budget_missing_a_contributor() {
    for (left_out, incomplete) in [
        (
            "probe_scale_ppm",
            ProbeInstallUncertainty {
                probe_scale_ppm: None,
                ..declared()
            },
        ),
        (
            "sphere_radius_m",
            ProbeInstallUncertainty {
                sphere_radius_m: None,
                ..declared()
            },
        ),
    ] {
        let (draws, expanded, names) = monte_carlo(&incomplete);
        let r = ratios(&draws, &expanded);
        let (worst, ratio) = names
            .iter()
            .zip(&r)
            .max_by(|a, b| a.1.total_cmp(b.1))
            .expect("quantities");
        eprintln!("probe_install budget without {left_out}: largest 2s / U = {ratio:.3} ({worst})");
        assert!(
            ratio - 1.0 > TOLERANCE,
            "without {left_out}: largest ratio {ratio}"
        );
    }
}
