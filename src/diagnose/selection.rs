//! The forward selection's rule of one round, shared by every diagnosis: when a candidate
//! passes (false-alarm control, BIC, held-out validation), which passing one is selected,
//! which are confounded with it, and the status each candidate is reported with.

use nalgebra::DMatrix;

use super::stats::max_principal_cosine;
use super::{CONFOUNDED_COSINE, DECISIVE_BIC};

/// A candidate's three tests in one round.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tests {
    /// Of the F test, already corrected for any searched parameter.
    pub p_value: f64,
    pub bic_delta: f64,
    /// Whether the held-out residuals improve; None when no held-out residual is predictable
    /// (then the held-out test is not a criterion).
    pub heldout_improves: Option<bool>,
}

impl Tests {
    /// p below the round's share of the false-alarm level, BIC improves, held-out improves.
    pub fn passes(&self, alpha_each: f64) -> bool {
        self.p_value < alpha_each && self.bic_delta < 0.0 && self.heldout_improves != Some(false)
    }

    /// `selected`, or `rejected: ` with every test that fails.
    pub fn alone_status(&self, alpha_each: f64) -> String {
        if self.passes(alpha_each) {
            return "selected".into();
        }
        let mut why = Vec::new();
        if self.p_value >= alpha_each {
            why.push(format!("p {:.2e} >= {:.2e}", self.p_value, alpha_each));
        }
        if self.bic_delta >= 0.0 {
            why.push("BIC does not improve".to_string());
        }
        if self.heldout_improves == Some(false) {
            why.push("held-out RMS does not improve".to_string());
        }
        format!("rejected: {}", why.join("; "))
    }
}

/// What one round decides, in indices of its candidates.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Round {
    /// The passing candidate with the lowest BIC.
    pub winner: Option<usize>,
    /// Other passing candidates whose projected columns are nearly collinear with the winner's
    /// (largest principal-angle cosine above `CONFOUNDED_COSINE`) and whose BIC is within
    /// `DECISIVE_BIC` of it: with them, none of the group is named.
    pub confounded: Vec<usize>,
}

impl Round {
    /// Decide a round: `tests[t]` and `bases[t]` (the orthonormal basis of candidate t's
    /// columns projected off the current model) for each candidate.
    pub fn decide(tests: &[Tests], bases: &[&DMatrix<f64>], alpha_each: f64) -> Round {
        let mut order: Vec<usize> = (0..tests.len()).collect();
        order.sort_by(|&a, &b| tests[a].bic_delta.total_cmp(&tests[b].bic_delta));
        let winner = order.iter().copied().find(|&t| tests[t].passes(alpha_each));
        let mut confounded = Vec::new();
        if let Some(best) = winner {
            for &other in &order {
                if other != best
                    && tests[other].passes(alpha_each)
                    && tests[other].bic_delta - tests[best].bic_delta < DECISIVE_BIC
                    && max_principal_cosine(bases[best], bases[other]) > CONFOUNDED_COSINE
                {
                    confounded.push(other);
                }
            }
        }
        Round { winner, confounded }
    }

    /// The winner when nothing is confounded with it.
    pub fn selected(&self) -> Option<usize> {
        self.winner.filter(|_| self.confounded.is_empty())
    }

    /// The winner and those confounded with it, when there are such.
    pub fn confounded_group(&self) -> Option<Vec<usize>> {
        let best = self.winner.filter(|_| !self.confounded.is_empty())?;
        Some(
            std::iter::once(best)
                .chain(self.confounded.iter().copied())
                .collect(),
        )
    }

    /// Candidate t's status: `selected`, `confounded`, `passed, not the best this round` or
    /// `rejected: ` with the tests it fails.
    pub fn status(&self, t: usize, tests: &Tests, alpha_each: f64) -> String {
        if self.selected() == Some(t) {
            "selected".into()
        } else if self.winner == Some(t) || self.confounded.contains(&t) {
            "confounded".into()
        } else if tests.passes(alpha_each) {
            "passed, not the best this round".into()
        } else {
            tests.alone_status(alpha_each)
        }
    }

    /// The others of candidate t's confounded group (empty when t is not in one).
    pub fn confounded_with(&self, t: usize) -> Vec<usize> {
        self.confounded_group()
            .filter(|group| group.contains(&t))
            .map(|group| group.into_iter().filter(|&o| o != t).collect())
            .unwrap_or_default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tests(p_value: f64, bic_delta: f64, heldout_improves: Option<bool>) -> Tests {
        Tests {
            p_value,
            bic_delta,
            heldout_improves,
        }
    }

    #[test]
    fn each_failed_test_is_named() {
        let t = tests(0.5, 3.0, Some(false));
        assert_eq!(
            t.alone_status(0.01),
            "rejected: p 5.00e-1 >= 1.00e-2; BIC does not improve; held-out RMS does not improve"
        );
        // Without a predictable held-out residual the held-out test is no criterion.
        assert!(tests(1e-9, -20.0, None).passes(0.01));
        assert_eq!(tests(1e-9, -20.0, None).alone_status(0.01), "selected");
    }

    #[test]
    fn lowest_bic_wins_and_collinear_neighbours_are_confounded() {
        let e = |v: [f64; 3]| DMatrix::from_column_slice(3, 1, &v);
        let (a, b, c) = (
            e([1.0, 0.0, 0.0]),
            e([0.999, 0.0447, 0.0]),
            e([0.0, 0.0, 1.0]),
        );
        let all = [
            tests(1e-9, -50.0, Some(true)),
            tests(1e-9, -45.0, Some(true)),
            tests(1e-9, -40.0, Some(true)),
            tests(0.5, 2.0, Some(true)),
        ];
        let bases = [&a, &b, &c, &c];
        let round = Round::decide(&all, &bases, 0.01);
        assert_eq!(round.winner, Some(0));
        assert_eq!(round.confounded, vec![1]);
        assert_eq!(round.selected(), None);
        assert_eq!(round.status(0, &all[0], 0.01), "confounded");
        assert_eq!(round.status(1, &all[1], 0.01), "confounded");
        assert_eq!(round.confounded_with(1), vec![0]);
        assert_eq!(
            round.status(2, &all[2], 0.01),
            "passed, not the best this round"
        );
        assert!(round.status(3, &all[3], 0.01).starts_with("rejected: p"));
        // Apart from b, a is named.
        let round = Round::decide(&all[..1], &bases[..1], 0.01);
        assert_eq!(round.selected(), Some(0));
        assert_eq!(round.status(0, &all[0], 0.01), "selected");
        assert!(round.confounded_with(0).is_empty());
    }
}
