//! Robust multilateration: Huber loss by iteratively reweighted least squares around the
//! LM adjustment, so that a few outlier lengths cannot pull the points and stations.

use super::multilateration::{
    solve, MultilaterationProblem, MultilaterationSolution, SolveError, SolveOptions,
};

/// Huber loss: quadratic within `threshold_sigma` normalised residuals, linear beyond.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Huber {
    pub threshold_sigma: f64,
}

impl Default for Huber {
    /// 3 sigma: Gaussian data is almost never down-weighted, gross outliers are.
    fn default() -> Self {
        Self {
            threshold_sigma: 3.0,
        }
    }
}

impl Huber {
    fn weight(&self, normalised: f64) -> f64 {
        let a = normalised.abs();
        if a <= self.threshold_sigma {
            1.0
        } else {
            self.threshold_sigma / a
        }
    }
}

#[derive(Debug, Clone)]
pub struct RobustSolution {
    /// The last reweighted adjustment: its covariance uses the effective sigmas sigma/sqrt(w).
    pub solution: MultilaterationSolution,
    /// Final weight of each observation (1 = not down-weighted).
    pub weights: Vec<f64>,
    pub rounds: usize,
}

const MAX_ROUNDS: usize = 30;
const WEIGHT_TOLERANCE: f64 = 1e-4;

pub fn solve_huber(
    problem: &MultilaterationProblem,
    options: &SolveOptions,
    huber: Huber,
) -> Result<RobustSolution, SolveError> {
    if !(huber.threshold_sigma.is_finite() && huber.threshold_sigma > 0.0) {
        return Err(SolveError::InvalidInput(format!(
            "Huber threshold must be a positive number of sigmas, got {}",
            huber.threshold_sigma
        )));
    }
    // The first round weighs every length alike; its σ (path-dependent ones evaluated at that
    // solution) then stay fixed, so the Huber weights are the only thing that changes.
    let mut solution = solve(problem, options)?;
    let base = problem.with_fixed_sigmas(&solution.sigmas_m);
    let mut weighted = base.clone();
    let mut weights: Vec<f64> = vec![1.0; problem.observations.len()];
    let mut rounds = 1;
    loop {
        let mut change: f64 = 0.0;
        for ((w, r), obs) in weights
            .iter_mut()
            .zip(&solution.residuals_m)
            .zip(&base.observations)
        {
            let new = huber.weight(r / obs.sigma_m);
            change = change.max((new - *w).abs());
            *w = new;
        }
        if change < WEIGHT_TOLERANCE || rounds >= MAX_ROUNDS {
            return Ok(RobustSolution {
                solution,
                weights,
                rounds,
            });
        }
        rounds += 1;
        for (obs, (orig, w)) in weighted
            .observations
            .iter_mut()
            .zip(base.observations.iter().zip(&weights))
        {
            obs.sigma_m = orig.sigma_m / w.sqrt();
        }
        solution = solve(&weighted, options)?;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solve::multilateration::best_fit_rigid;
    use crate::solve::multilateration::tests::{stations5, synthetic};

    /// Largest error of any point, after the best rigid fit onto the truth, in units of its sigma.
    fn worst_point_z(sol: &MultilaterationSolution, truth: &[nalgebra::Vector3<f64>]) -> f64 {
        let (r, t) = best_fit_rigid(&sol.points, truth).expect("kabsch");
        sol.points
            .iter()
            .zip(truth)
            .zip(&sol.point_covariance)
            .map(|((x, y), q)| {
                let e = r * x + t - y;
                (0..3)
                    .map(|k| e[k].abs() / q[(k, k)].sqrt())
                    .fold(0.0, f64::max)
            })
            .fold(0.0, f64::max)
    }

    #[test]
    fn an_outlier_length_is_down_weighted_and_harmless() {
        let mut syn = synthetic(21, [4, 4, 3], &stations5(), &[], 30e-9, true);
        // One length 5 um off: 170 sigma, e.g. an unflagged fringe loss.
        let bad = syn
            .problem
            .observations
            .iter()
            .position(|o| o.point == 17)
            .expect("observation of point 17");
        syn.problem.observations[bad].length_m += 5e-6;

        let plain = solve(&syn.problem, &SolveOptions::default()).expect("plain");
        let robust =
            solve_huber(&syn.problem, &SolveOptions::default(), Huber::default()).expect("robust");
        let plain_z = worst_point_z(&plain, &syn.true_points);
        let robust_z = worst_point_z(&robust.solution, &syn.true_points);
        assert!(
            plain_z > 10.0,
            "the outlier should hurt least squares: {plain_z} sigma"
        );
        assert!(
            robust_z < 4.5,
            "robust solution still off by {robust_z} sigma"
        );
        assert!(
            robust.weights[bad] < 0.05,
            "outlier weight {}",
            robust.weights[bad]
        );
        let others_down = robust
            .weights
            .iter()
            .enumerate()
            .filter(|&(i, w)| i != bad && *w < 1.0)
            .count();
        assert!(
            others_down <= 3,
            "{others_down} clean observations down-weighted"
        );
    }

    #[test]
    fn clean_data_is_left_alone() {
        let syn = synthetic(22, [4, 4, 3], &stations5(), &[], 30e-9, true);
        let plain = solve(&syn.problem, &SolveOptions::default()).expect("plain");
        let robust =
            solve_huber(&syn.problem, &SolveOptions::default(), Huber::default()).expect("robust");
        let moved = plain
            .points
            .iter()
            .zip(&robust.solution.points)
            .map(|(a, b)| (a - b).amax())
            .fold(0.0, f64::max);
        let down = robust.weights.iter().filter(|w| **w < 1.0).count();
        // At most a chance 3-sigma residual or two; the points barely move.
        assert!(down <= 2, "{down} down-weighted");
        assert!(moved < 10e-9, "points moved by {moved} m");
    }

    #[test]
    fn a_bad_threshold_is_an_error() {
        let syn = synthetic(23, [4, 4, 2], &stations5(), &[], 30e-9, true);
        let err = solve_huber(
            &syn.problem,
            &SolveOptions::default(),
            Huber {
                threshold_sigma: 0.0,
            },
        )
        .expect_err("must fail");
        assert!(err.to_string().contains("Huber threshold"));
    }
}
