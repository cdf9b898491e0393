//! The forward selection every diagnosis runs: each round the candidates left are evaluated
//! against the current model (F test against the residual variance left after the candidate,
//! BIC, held-out validation), `Round::decide` names the best passing one or a confounded
//! group, which joins the model, until nothing passes. What a candidate is, its columns, any
//! parameter searched over the data, any constraint it is refitted under and how it is
//! reported are the client's ([`Client`]).

use std::collections::BTreeMap;

use nalgebra::DMatrix;

use super::columns::Columns;
use super::engine::{BaseFit, Engine, Eval, HeldOut, LinearDesign, LinearFit};
use super::progress::Counter;
use super::selection::{Round, Tests};
use super::stats::f_sf;
use super::{Candidate, Gap, CONFOUNDED_COSINE, DECISIVE_BIC};

/// One round's bookkeeping of a candidate.
pub struct Trial<E> {
    pub effect: E,
    pub eval: Eval,
    pub p_value: f64,
    pub bic_delta: f64,
    /// Number of positions a searched parameter was tried at (1 for none).
    pub searched: usize,
}

/// What a diagnosis hands the forward selection.
pub trait Client {
    type Design: LinearDesign;
    /// A candidate effect as it enters the model.
    type Effect: Clone;
    /// Candidates are recorded (and first ordered) by this key.
    type Key: Ord + Clone;

    fn key(&self, effect: &Self::Effect) -> Self::Key;
    fn name(&self, effect: &Self::Effect) -> String;
    /// The nominal design with the `accepted` effects' columns.
    fn design(&self, accepted: &[Self::Effect]) -> Self::Design;
    /// The effect's columns over all rows (in the residuals' units, not whitened).
    fn columns(&self, effect: &Self::Effect) -> DMatrix<f64>;
    /// The same as a candidate is evaluated: sparse where the client makes them so.
    fn candidate_columns(&self, effect: &Self::Effect) -> Columns {
        Columns::Dense(self.columns(effect))
    }
    /// The candidate with any parameter searched over the data set from the base fit (e.g. a
    /// change point's position) and the number of positions tried; None: nothing to test.
    fn search(
        &self,
        effect: &Self::Effect,
        _full: &BaseFit<<Self::Design as LinearDesign>::Fit>,
    ) -> Option<(Self::Effect, usize)> {
        Some((effect.clone(), 1))
    }
    /// A candidate with a constraint linearised at its free estimate `theta`: it is tested
    /// free (no parameter chosen from the data) and predicts the held-out rows constrained,
    /// as it enters the model. None: no constraint.
    fn constrained(&self, _effect: &Self::Effect, _theta: &[f64]) -> Option<Self::Effect> {
        None
    }
    /// The base fit's gap.
    fn gap(
        &self,
        engine: &Engine,
        full: &BaseFit<<Self::Design as LinearDesign>::Fit>,
        heldout: &HeldOut,
    ) -> Gap;
    /// The first round's base fit over every row, when it is made (a client that reports
    /// from the start's fit after the selection keeps what it needs of it).
    fn first_base_fitted(&self, _full: &BaseFit<<Self::Design as LinearDesign>::Fit>) {}
    /// The notes of the first round, given the held-out rows predicted.
    fn cross_validation_notes(&self, engine: &Engine, predicted: usize) -> Vec<String>;
    /// The note of a candidate the nominal model absorbs.
    fn absorbed_note(&self, name: &str) -> String;
    /// The candidate's record.
    fn record(
        &self,
        trial: &Trial<Self::Effect>,
        round: usize,
        status: String,
        confounded_with: Vec<String>,
    ) -> Candidate;
}

/// Where the selection starts.
pub struct Start<C: Client> {
    /// Effects already in the model (tested on data of their own).
    pub accepted: Vec<C::Effect>,
    /// Their records.
    pub records: BTreeMap<C::Key, Candidate>,
    /// The gap before any effect, when an effect is already accepted.
    pub gap_before: Option<Gap>,
    /// Tests of the first round's family besides its candidates (Bonferroni).
    pub extra_first_round_tests: usize,
}

impl<C: Client> Default for Start<C> {
    fn default() -> Self {
        Start {
            accepted: Vec::new(),
            records: BTreeMap::new(),
            gap_before: None,
            extra_first_round_tests: 0,
        }
    }
}

/// What the selection decided.
pub struct Selection<C: Client> {
    /// Effects in the model: the named ones and the members of confounded groups.
    pub accepted: Vec<C::Effect>,
    /// The keys of the confounded groups' members (in the model, never named).
    pub confounded: Vec<C::Key>,
    pub records: BTreeMap<C::Key, Candidate>,
    /// The nominal model's gap.
    pub gap_before: Gap,
    /// The last base's gap (the model the selection stopped at); None if every round
    /// accepted an effect.
    pub last_base: Option<Gap>,
    pub final_round: usize,
    pub notes: Vec<String>,
}

/// Forward selection over `available` at family-wise `alpha` per round, at most `max_rounds`
/// + 1 rounds; `progress` ticks once per base fit and per candidate.
///
/// The gaps it returns are held out over `report`'s folds when given (its residuals and
/// weights are `engine`'s, so the base fits on every row serve both), else over the
/// selection's.
#[allow(clippy::too_many_arguments)]
pub fn select<C: Client>(
    client: &C,
    engine: &Engine,
    report: Option<&Engine>,
    available: &[C::Effect],
    start: Start<C>,
    alpha: f64,
    max_rounds: usize,
    progress: &mut Counter,
) -> Selection<C> {
    let Start {
        mut accepted,
        mut records,
        mut gap_before,
        extra_first_round_tests,
    } = start;
    let mut confounded: Vec<C::Key> = Vec::new();
    let mut notes = Vec::new();
    let mut last_base = None;
    let mut final_round = 0;
    let nrows = engine.r.len();
    let all_rows: Vec<usize> = (0..nrows).collect();
    let ln_n = (nrows as f64).ln();
    for round in 0..=max_rounds {
        final_round = round;
        let design = client.design(&accepted);
        let (full, fold_fits, heldout) = engine.base(&design, &all_rows);
        progress.tick(1);
        let base_gap = client.gap(engine, &full, &heldout);
        let reported_gap = || match report {
            Some(report) => client.gap(report, &full, &report.heldout_of(&design, &full)),
            None => base_gap.clone(),
        };
        let base_heldout_z2 = heldout.mean_z2();
        let count = heldout.count;
        if round == 0 {
            client.first_base_fitted(&full);
            notes.extend(client.cross_validation_notes(engine, count));
        }
        let mut round_gap = None;
        if gap_before.is_none() {
            round_gap = Some(reported_gap());
            gap_before.clone_from(&round_gap);
        }
        let candidates: Vec<C::Effect> = available
            .iter()
            .filter(|e| !accepted.iter().any(|a| client.key(a) == client.key(e)))
            .cloned()
            .collect();
        let mut trials: Vec<Trial<C::Effect>> = Vec::new();
        for candidate in &candidates {
            progress.tick(1);
            let Some((effect, searched)) = client.search(candidate, &full) else {
                continue;
            };
            let mut eval = engine.evaluate(&design, &full, &fold_fits, &|| {
                client.candidate_columns(&effect)
            });
            let effect = match client.constrained(&effect, eval.theta.as_slice()) {
                Some(constrained) => {
                    let held = engine.evaluate(&design, &full, &fold_fits, &|| {
                        client.candidate_columns(&constrained)
                    });
                    eval.heldout_ms = held.heldout_ms;
                    eval.heldout_z2 = held.heldout_z2;
                    constrained
                }
                None => effect,
            };
            if eval.df == 0 {
                if round == 0 {
                    notes.push(client.absorbed_note(&client.name(&effect)));
                }
                continue;
            }
            // The test scales by the residual variance left after the candidate (F test,
            // likelihood ratio with the noise scale profiled out): structure that no
            // candidate expresses then inflates the denominator instead of making every
            // flexible candidate look significant. A searched parameter: Bonferroni over the
            // positions tried, one more parameter in the BIC.
            let chi2_base = full.res_w.norm_squared();
            let chi2_after = (chi2_base - eval.chi2_drop).max(f64::MIN_POSITIVE);
            let dof_after = nrows.saturating_sub(full.basis.rank() + eval.df).max(1) as f64;
            let f_stat = (eval.chi2_drop / eval.df as f64) / (chi2_after / dof_after);
            let p_value = (f_sf(f_stat, eval.df as f64, dof_after) * searched as f64).min(1.0);
            let params_counted = eval.df + usize::from(searched > 1);
            let bic_delta =
                nrows as f64 * (chi2_after / chi2_base).ln() + params_counted as f64 * ln_n;
            trials.push(Trial {
                effect,
                eval,
                p_value,
                bic_delta,
                searched,
            });
        }
        // Bonferroni over the candidates of this round: family-wise false selection ≤ alpha.
        let tested = candidates.len()
            + if round == 0 {
                extra_first_round_tests
            } else {
                0
            };
        let alpha_each = alpha / tested.max(1) as f64;
        let tests: Vec<Tests> = trials
            .iter()
            .map(|t| Tests {
                p_value: t.p_value,
                bic_delta: t.bic_delta,
                heldout_improves: (count > 0).then_some(t.eval.heldout_z2 < base_heldout_z2),
            })
            .collect();
        // The projected bases only of the candidates that pass: the confounding test compares
        // no other (rows × parameters each, so not kept for every candidate of the round).
        let bases: Vec<DMatrix<f64>> = trials
            .iter()
            .zip(&tests)
            .map(|(t, tests)| match tests.passes(alpha_each) {
                true => engine.projected_basis(&full, &client.columns(&t.effect)),
                false => DMatrix::zeros(nrows, 0),
            })
            .collect();
        let bases: Vec<&DMatrix<f64>> = bases.iter().collect();
        let decided = Round::decide(&tests, &bases, alpha_each);
        for (t, trial) in trials.iter().enumerate() {
            let status = decided.status(t, &tests[t], alpha_each);
            let confounded_with = decided
                .confounded_with(t)
                .into_iter()
                .map(|o| client.name(&trials[o].effect))
                .collect();
            records.insert(
                client.key(&trial.effect),
                client.record(trial, round, status, confounded_with),
            );
        }
        match (decided.selected(), decided.confounded_group()) {
            (Some(best), _) => accepted.push(trials[best].effect.clone()),
            (None, Some(group)) => {
                // None of the group is named, but the signal they share is in the data: the
                // whole group joins the model (unnamed), so that the next rounds do not hand
                // the same signal to a less likely neighbour (e.g. a drift per group, which
                // nests a common drift) and the gap after counts it as explained by the group.
                let group: Vec<C::Effect> = group
                    .into_iter()
                    .map(|t| trials[t].effect.clone())
                    .collect();
                notes.push(format!(
                    "confounded in this session (projected columns cosine > {CONFOUNDED_COSINE}, BIC within {DECISIVE_BIC}): {}; none is named, their common signal is fitted by the group",
                    group.iter().map(|e| client.name(e)).collect::<Vec<_>>().join(", ")
                ));
                confounded.extend(group.iter().map(|e| client.key(e)));
                accepted.extend(group);
            }
            (None, None) => {
                last_base = Some(round_gap.unwrap_or_else(reported_gap));
                break;
            }
        }
    }
    Selection {
        accepted,
        confounded,
        records,
        gap_before: gap_before.expect("the first round ran"),
        last_base,
        final_round,
        notes,
    }
}

/// The candidates in report order: the selected ones in their order of selection, then the
/// others by BIC.
pub fn report_order(candidates: &mut [Candidate], selected: &[String]) {
    let rank_of = |c: &Candidate| {
        selected
            .iter()
            .position(|s| *s == c.effect)
            .unwrap_or(usize::MAX)
    };
    candidates.sort_by(|a, b| {
        rank_of(a)
            .cmp(&rank_of(b))
            .then(a.bic_delta.total_cmp(&b.bic_delta))
    });
}
