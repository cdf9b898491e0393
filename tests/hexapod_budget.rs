//! Monte Carlo check of the hexapod budget: each draw takes the pose sensor's scale error and
//! the leg encoders' scale error from their declared distributions, and the encoders' noise
//! (each pose's reading and the averaged reference reading); the kind's model
//! (`model::hexapod`: leg lengths of the true hinges at the true poses) makes the readings with
//! them, and the kind's weighted fit runs. The spread 2s of every hinge coordinate must agree
//! with the budget's U within 15 %; a budget without a contributor must fail.
//!
//! Level: readings made in memory (30 poses as config/hexapod.toml: home read 100 times, the
//! others once; a pose sensor without noise), not through the sequencer and a recording. The
//! fit is the kind's last stage (`refine_weighted`) started at the true hinges: the damped
//! least squares and the grid search before it only find the basin, the same one in every
//! draw, and repeating them 200 times would only make the test slow.

use crate::budget_mc;

use budget_mc::{ratios, TOLERANCE};
use geocal::kinds::hexapod::budget::budgets;
use geocal::kinds::hexapod::config::HexapodUncertainty;
use geocal::model::hexapod::{leg_length, HexapodGeometry, Pose, LEGS};
use geocal::solve::hexapod::simulation::{nominal_geometry, perturbed, random_poses};
use geocal::solve::hexapod::HexapodObservations;
use geocal::solve::hexapod_weighted::{refine_weighted, HexapodNoise, PoseNoise};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

const ENCODER_SIGMA_M: f64 = 1e-6;
const REFERENCE_READINGS: usize = 100;
/// Draws: 1000 (at least the 200 asked), so that the sampling spread of each 2s (about
/// 2.2 %) stays well inside the 15 % over the 36 coordinates.
const DRAWS: usize = 1000;

fn declared() -> HexapodUncertainty {
    HexapodUncertainty {
        pose_scale_ppm: Some(20.0),
        leg_scale_ppm: Some(20.0),
    }
}

fn noise(poses: usize) -> HexapodNoise {
    HexapodNoise {
        encoder_sigma_m: ENCODER_SIGMA_M,
        poses: (0..poses)
            .map(|k| PoseNoise {
                readings: if k == 0 { REFERENCE_READINGS } else { 1 },
                translation_sigma_m: 0.0,
                rotation_sigma_rad: 0.0,
            })
            .collect(),
    }
}

/// One measurement with drawn errors: the sensor reports every translation (1 + s_p) times the
/// true one, the encoders every length change (1 + s_l) times the true one, plus noise.
fn observe(
    truth: &HexapodGeometry,
    poses: &[Pose],
    rng: &mut ChaCha8Rng,
    u: &HexapodUncertainty,
) -> HexapodObservations {
    let n = |s: Option<f64>| Normal::new(0.0, s.unwrap_or(0.0)).expect("σ >= 0");
    let s_p = 1e-6 * n(u.pose_scale_ppm).sample(rng);
    let s_l = 1e-6 * n(u.leg_scale_ppm).sample(rng);
    let reading = |k: usize, rng: &mut ChaCha8Rng| -> [f64; LEGS] {
        let readings = if k == 0 { REFERENCE_READINGS } else { 1 };
        let sigma = ENCODER_SIGMA_M / (readings as f64).sqrt();
        std::array::from_fn(|i| leg_length(&truth.leg(i), &poses[k]).0 + n(Some(sigma)).sample(rng))
    };
    let reference = reading(0, rng);
    let delta_lengths_m = (0..poses.len())
        .map(|k| {
            let l = reading(k, rng);
            std::array::from_fn(|i| (l[i] - reference[i]) * (1.0 + s_l))
        })
        .collect();
    HexapodObservations {
        poses: poses
            .iter()
            .map(|p| Pose {
                rotation: p.rotation,
                translation_m: p.translation_m * (1.0 + s_p),
            })
            .collect(),
        delta_lengths_m,
        sigma_m: ENCODER_SIGMA_M * (1.0 + 1.0 / REFERENCE_READINGS as f64).sqrt(),
        search_poses: None,
    }
}

/// The draws' 36 coordinates, the budget's U (of the first draw's data) and the names.
fn monte_carlo(budget_declares: &HexapodUncertainty) -> (Vec<Vec<f64>>, Vec<f64>, Vec<String>) {
    let mut rng = ChaCha8Rng::seed_from_u64(424_242);
    let truth = perturbed(&mut rng, &nominal_geometry(), 2e-3);
    let poses = random_poses(&mut rng, 30, 10.0);
    let noise = noise(poses.len());
    let first = observe(&truth, &poses, &mut rng, &declared());
    let fit = refine_weighted(&first, &noise, &truth).expect("fit");
    let b = budgets(
        &first,
        &noise,
        &fit.geometry,
        &fit.sigmas_m(),
        budget_declares,
    )
    .expect("budget");
    let expanded = b.budgets.iter().map(|b| b.expanded_uncertainty).collect();
    let names = b.budgets.iter().map(|b| b.quantity.clone()).collect();
    let draws = (0..DRAWS)
        .map(|_| {
            let obs = observe(&truth, &poses, &mut rng, &declared());
            refine_weighted(&obs, &noise, &truth)
                .expect("fit")
                .geometry
                .to_vec()
        })
        .collect();
    (draws, expanded, names)
}

#[test]
fn monte_carlo_spread_agrees_with_the_budget() {
    let (draws, expanded, names) = monte_carlo(&declared());
    let r = ratios(&draws, &expanded);
    let (lo, hi) = r
        .iter()
        .fold((f64::MAX, f64::MIN), |(lo, hi), v| (lo.min(*v), hi.max(*v)));
    eprintln!(
        "hexapod, {DRAWS} draws: Monte Carlo 2s / U over the 36 coordinates from {lo:.3} to {hi:.3}, \
         mean {:.3}",
        budget_mc::mean(&r)
    );
    for (name, ratio) in names.iter().zip(&r) {
        assert!((ratio - 1.0).abs() <= TOLERANCE, "{name}: ratio {ratio}");
    }
}

/// The check has power: a budget without the pose sensor's scale, or without the encoders'
/// scale, misses coordinates they act on.
#[test]
fn monte_carlo_catches_a_budget_missing_a_contributor() {
    for (left_out, incomplete) in [
        (
            "pose_scale_ppm",
            HexapodUncertainty {
                pose_scale_ppm: None,
                ..declared()
            },
        ),
        (
            "leg_scale_ppm",
            HexapodUncertainty {
                leg_scale_ppm: None,
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
            .expect("coordinates");
        eprintln!("hexapod budget without {left_out}: largest 2s / U = {ratio:.3} ({worst})");
        assert!(
            ratio - 1.0 > TOLERANCE,
            "without {left_out}: largest ratio {ratio}"
        );
    }
}
