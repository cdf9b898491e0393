//! The linearised model every diagnosis selects effects in, whatever its structure: a base
//! design (the nominal parameters and the accepted effects) fitted on all rows and per
//! cross-validation fold, the held-out prediction with and without a candidate effect, and a
//! candidate's evaluation (χ² drop, identifiable parameters, θ ± σ, RMS after, held-out mean
//! square and z²). The fits come from a [`LinearDesign`]: the points eliminated block by block
//! for a large network (`schur`), or the dense SVD of a small design (`dense_design`).

use nalgebra::{DMatrix, DVector};

use crate::parallel;

use super::columns::{Columns, ProjectedRows, RowSparse};
use super::downdate::{FoldDowndate, HatRows};
use super::projected::Projected;
use super::stats::EFFECT_RANK_TOL;

/// Below this many entries of a candidate's columns (rows × columns) the folds run one after
/// another: threads would cost more than they save. Each fold on its own thread holds its
/// copy of the columns, so the threads cost memory too.
const THREADED_FOLD_ENTRIES: usize = 20_000;
pub const MAX_FOLD_THREADS: usize = 2;

/// The least-squares fit of a whitened design on a set of its rows.
pub trait LinearFit: Sync {
    /// Rank of the design on the fit's rows.
    fn rank(&self) -> usize;
    /// Least-squares minimum-norm x of X x ≈ y over the fit's rows (y whitened, by position).
    fn solve(&self, y: &DVector<f64>) -> DVector<f64>;
    /// y minus its projection on the design's column space (over the fit's rows).
    fn project_off_vec(&self, y: &DVector<f64>) -> DVector<f64>;
    /// Each column of `m` (over the fit's rows) minus its projection, in place where it can.
    fn project_off_owned(&self, m: DMatrix<f64>) -> DMatrix<f64>;
    /// Whether design row i lies in the fit's row space (its prediction is determined).
    fn in_row_space(&self, i: usize) -> bool;
    /// Variance of each held row's prediction under unit whitened noise (in the squared
    /// units of the rows' prediction).
    fn prediction_variances(&self, held: &[usize]) -> Vec<f64>;
    /// Sparse columns (whitened, over the fit's rows) projected off the design with the
    /// projection kept implicit: their rows are made when asked, the columns never held dense.
    /// Err gives them back where the fit has no such form.
    fn project_off_implicit(&self, m: RowSparse) -> Result<Box<dyn ProjectedRows>, RowSparse> {
        Err(m)
    }
    /// Whether a candidate's projected columns are factorised by the SVD of the tall matrix
    /// (a dense fit) rather than from their Gram matrix or QR.
    fn factorises_by_svd(&self) -> bool;
    /// The hat matrix on each set of the fit's rows (design rows) as blocks plus low rank,
    /// where the fit gives it cheaply: each fold's held-out residuals are then downdated from
    /// this fit instead of refitted. None: the folds are refitted.
    fn hat_rows(&self, _sets: &[&[usize]]) -> Option<Vec<HatRows>> {
        None
    }
}

/// A linearised design over all rows of a diagnosis.
pub trait LinearDesign: Sync {
    type Fit: LinearFit + Send;
    /// Its fit on `rows`.
    fn fit(&self, rows: Vec<usize>) -> Self::Fit;
    /// Whether its fits may be made on any thread (false where a fit depends on the calling
    /// thread's state).
    fn fits_on_any_thread(&self) -> bool {
        true
    }
    /// Row i (in the residuals' units, not whitened) times the parameters x.
    fn predict(&self, i: usize, x: &DVector<f64>) -> f64;
}

/// A base design fitted on a set of rows.
pub struct BaseFit<F> {
    pub rows: Vec<usize>,
    /// Held-out rows whose residual the training rows determine (in the row space of the
    /// training design); a row the training rows leave undetermined cannot be predicted,
    /// only guessed by the minimum-norm solution.
    pub held: Vec<usize>,
    /// Variance of each held-out row's prediction (the noise not included).
    pub held_var: Vec<f64>,
    pub basis: F,
    /// Whitened residual of the fit on `rows` (orthogonal to the basis).
    pub res_w: DVector<f64>,
}

/// A cross-validation fold's prediction of its held rows from its training rows.
pub enum FoldFit<F> {
    /// Downdated from the fit on all rows: every held row is predicted.
    Downdated(FoldDowndate),
    /// Fitted on the training rows.
    Refit(BaseFit<F>),
}

/// A base design's fit on all rows, its folds and the folds' held-out residuals.
pub type Bases<F> = (BaseFit<F>, Vec<FoldFit<F>>, HeldOut);

/// A candidate effect in the folds' held-out fits: its columns (all rows, not whitened; held
/// where a fold is refitted), their number of entries, the orthonormal basis of its whitened
/// columns projected off the full fit and the full fit's whitened residuals with it (both over
/// all rows).
struct Candidate<'a> {
    a: Option<&'a DMatrix<f64>>,
    entries: usize,
    /// Its columns projected off the full fit, for their orthonormal basis U's rows (where a
    /// fold is downdated).
    projected: Option<&'a Projected>,
    after: After<'a>,
}

/// The full fit's whitened residuals with the candidate.
#[derive(Clone, Copy)]
enum After<'a> {
    /// Over all rows.
    Residuals(&'a DVector<f64>),
    /// As the full fit's residuals minus U c, c = Uᵀ r: made on each fold's held rows from the
    /// rows of U the fold makes anyway (one walk over the candidate's rows fewer).
    Coefficients(&'a DVector<f64>),
}

/// The held-out residuals of the folds: Σ r², Σ (σ² + prediction variance), Σ r²/that, and
/// how many were predicted.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct HeldOut {
    pub ss: f64,
    pub floor: f64,
    pub z2: f64,
    pub count: usize,
}

impl HeldOut {
    pub fn mean_square(&self) -> f64 {
        self.ss / self.count.max(1) as f64
    }

    pub fn mean_floor(&self) -> f64 {
        self.floor / self.count.max(1) as f64
    }

    pub fn mean_z2(&self) -> f64 {
        self.z2 / self.count.max(1) as f64
    }
}

/// The evaluation of adding one effect to a base.
pub struct Eval {
    pub chi2_drop: f64,
    pub df: usize,
    pub theta: DVector<f64>,
    pub theta_sigma: DVector<f64>,
    /// Per parameter: whether the data determine it. One whose every direction the model
    /// absorbs has an estimate and σ that are rounding, reported as null rather than a figure.
    pub identifiable: Vec<bool>,
    /// RMS of the residuals after the effect, in the reported units.
    pub rms_after: f64,
    /// Mean square of the held-out residuals after the effect (the residuals' units).
    pub heldout_ms: f64,
    /// Mean of the held-out residuals squared, each in units of the base model's predicted
    /// variance (noise plus prediction): the selection's held-out criterion, which the few
    /// rows with a poorly determined prediction cannot dominate.
    pub heldout_z2: f64,
}

/// The residuals of the nominal model and the cross-validation folds.
pub struct Engine {
    /// Whitening weights: r_i · w_i is in units of the row's σ.
    pub w: DVector<f64>,
    /// Residuals of the nominal model (the units the held-out figures are in).
    pub r: DVector<f64>,
    /// The reported units' whitening: a whitened residual over this weight is in the units
    /// RMS figures are reported in.
    pub w_report: DVector<f64>,
    /// Per fold: its held-out rows (ascending); the fold trains on all the others.
    pub folds: Vec<Vec<usize>>,
}

impl Engine {
    /// Whether `rows` are every row, in order (then a position is a row).
    fn is_every_row(&self, rows: &[usize]) -> bool {
        rows.len() == self.r.len() && rows.iter().enumerate().all(|(k, &i)| k == i)
    }

    /// A fold's training rows: every row it does not hold out, ascending.
    pub fn training_rows(&self, fold: usize) -> Vec<usize> {
        let mut held = vec![false; self.r.len()];
        for &h in &self.folds[fold] {
            held[h] = true;
        }
        (0..self.r.len()).filter(|&i| !held[i]).collect()
    }

    fn whitened_rows(&self, m: &DMatrix<f64>, rows: &[usize]) -> DMatrix<f64> {
        DMatrix::from_fn(rows.len(), m.ncols(), |r, c| {
            m[(rows[r], c)] * self.w[rows[r]]
        })
    }

    fn rw(&self, rows: &[usize]) -> DVector<f64> {
        DVector::from_fn(rows.len(), |k, _| self.r[rows[k]] * self.w[rows[k]])
    }

    /// RMS in the reported units of whitened residuals over `rows`.
    pub fn rms_reported(&self, res_w: &DVector<f64>, rows: &[usize]) -> f64 {
        (self.ss_reported(res_w, rows) / rows.len().max(1) as f64).sqrt()
    }

    /// Sum of squares in the reported units of whitened residuals over `rows`.
    fn ss_reported(&self, res_w: &DVector<f64>, rows: &[usize]) -> f64 {
        res_w
            .iter()
            .zip(rows)
            .map(|(r, &i)| (r / self.w_report[i]).powi(2))
            .sum()
    }

    /// Whether the folds hold out every row exactly once.
    fn folds_hold_each_row_once(&self) -> bool {
        let mut held = vec![false; self.r.len()];
        for &h in self.folds.iter().flatten() {
            match held.get_mut(h) {
                Some(seen) if !*seen => *seen = true,
                _ => return false,
            }
        }
        held.into_iter().all(|seen| seen)
    }

    pub fn fit_base<D: LinearDesign>(
        &self,
        design: &D,
        rows: Vec<usize>,
        held: &[usize],
    ) -> BaseFit<D::Fit> {
        let basis = design.fit(rows.clone());
        let res_w = basis.project_off_vec(&self.rw(&rows));
        let held: Vec<usize> = held
            .iter()
            .copied()
            .filter(|&h| basis.in_row_space(h))
            .collect();
        let held_var = basis.prediction_variances(&held);
        BaseFit {
            rows,
            held,
            held_var,
            basis,
            res_w,
        }
    }

    /// Held-out residuals of a fold's fit with an optional extra effect (`a`: its columns
    /// over all rows, not whitened).
    pub fn heldout<D: LinearDesign>(
        &self,
        design: &D,
        fit: &BaseFit<D::Fit>,
        a: Option<&DMatrix<f64>>,
    ) -> HeldOut {
        let rw = self.rw(&fit.rows);
        let (beta, theta) = match a {
            None => (fit.basis.solve(&rw), None),
            Some(a) => {
                let perp = Projected::new(&fit.basis, self.whitened_rows(a, &fit.rows));
                let theta = perp.solve(&fit.res_w);
                drop(perp);
                let a_theta = DVector::from_fn(fit.rows.len(), |k, _| {
                    let i = fit.rows[k];
                    self.w[i] * (0..a.ncols()).map(|c| a[(i, c)] * theta[c]).sum::<f64>()
                });
                let beta = fit.basis.solve(&(rw - a_theta));
                (beta, Some(theta))
            }
        };
        let mut out = HeldOut::default();
        for (&h, prediction_var) in fit.held.iter().zip(&fit.held_var) {
            let mut pred = design.predict(h, &beta);
            if let (Some(a), Some(theta)) = (a, &theta) {
                pred += (0..a.ncols()).map(|c| a[(h, c)] * theta[c]).sum::<f64>();
            }
            let sigma = 1.0 / self.w[h];
            let var = sigma * sigma + prediction_var;
            out.ss += (self.r[h] - pred).powi(2);
            out.floor += var;
            out.z2 += (self.r[h] - pred).powi(2) / var;
            out.count += 1;
        }
        out
    }

    /// One fold's held-out residuals: downdated from the full fit where the fold is, else
    /// refitted. None where the training rows nearly lose one of the candidate's directions:
    /// the caller refits that fold with the candidate's columns.
    /// With it, where the candidate's residuals with it were made on the held rows, their sum
    /// of squares in the reported units.
    fn heldout_fold<D: LinearDesign>(
        &self,
        design: &D,
        fold: usize,
        fit: &FoldFit<D::Fit>,
        full_res_w: &DVector<f64>,
        candidate: Option<&Candidate>,
    ) -> Option<(HeldOut, Option<f64>)> {
        let held = &self.folds[fold];
        let mut after_ss = None;
        let (downdate, residuals) = match fit {
            FoldFit::Refit(fit) => {
                return Some((self.heldout(design, fit, candidate.and_then(|c| c.a)), None))
            }
            FoldFit::Downdated(downdate) => {
                let residuals = match candidate {
                    None => downdate.residuals(&full_res_w.select_rows(held)),
                    Some(c) => {
                        let u = c.projected?.u_rows(held);
                        let after = match c.after {
                            After::Residuals(after) => after.select_rows(held),
                            After::Coefficients(coeff) => {
                                let after = full_res_w.select_rows(held) - &u * coeff;
                                after_ss = Some(self.ss_reported(&after, held));
                                after
                            }
                        };
                        downdate.residuals_with(&u, &after)?
                    }
                };
                (downdate, residuals)
            }
        };
        let mut out = HeldOut::default();
        for ((&h, x), inflation) in held.iter().zip(residuals.iter()).zip(downdate.inflation()) {
            let w2 = self.w[h] * self.w[h];
            out.ss += x * x / w2;
            out.floor += inflation / w2;
            out.z2 += x * x / inflation;
            out.count += 1;
        }
        Some((out, after_ss))
    }

    /// The folds' held-out residuals summed in the folds' order. With a candidate on many
    /// rows the folds run on their own threads, each fold's figures computed as alone; a fold
    /// the candidate cannot be downdated in is refitted here, with `columns` (the candidate's,
    /// made again unless held). With them, when every fold made the candidate's residuals on
    /// its held rows, their sum of squares in the reported units.
    fn heldout_sum<D: LinearDesign>(
        &self,
        design: &D,
        fits: &[FoldFit<D::Fit>],
        full_res_w: &DVector<f64>,
        candidate: Option<(&Candidate, &dyn Fn() -> Columns)>,
    ) -> (HeldOut, Option<f64>) {
        let work = candidate.map_or(0, |(c, _)| c.entries);
        let threads = if work >= THREADED_FOLD_ENTRIES {
            parallel::threads(MAX_FOLD_THREADS)
        } else {
            1
        };
        let jobs: Vec<(usize, &FoldFit<D::Fit>)> = fits.iter().enumerate().collect();
        let in_folds = candidate.map(|(c, _)| c);
        let per_fold = parallel::in_groups(&jobs, threads, |&(fold, fit)| {
            self.heldout_fold(design, fold, fit, full_res_w, in_folds)
        });
        let mut columns: Option<DMatrix<f64>> = None;
        let mut sum = HeldOut::default();
        let mut after_ss = Some(0.0);
        for (fold, h) in per_fold.into_iter().enumerate() {
            let (h, fold_after_ss) = h.unwrap_or_else(|| {
                let refit = self.fit_base(design, self.training_rows(fold), &self.folds[fold]);
                let a = match candidate {
                    Some((Candidate { a: Some(a), .. }, _)) => a,
                    Some((_, make)) => &*columns.get_or_insert_with(|| make().into_dense()),
                    None => unreachable!("a base's downdated fold needs no refit"),
                };
                (self.heldout(design, &refit, Some(a)), None)
            });
            sum.ss += h.ss;
            sum.floor += h.floor;
            sum.z2 += h.z2;
            sum.count += h.count;
            after_ss = after_ss.zip(fold_after_ss).map(|(a, b)| a + b);
        }
        (sum, after_ss)
    }

    /// The folds of a base: downdated from the full fit (on all rows, in order) where its hat
    /// matrix is at hand and the fold keeps every direction, else refitted; on the cores.
    fn fold_fits<D: LinearDesign>(
        &self,
        design: &D,
        full: &BaseFit<D::Fit>,
    ) -> Vec<FoldFit<D::Fit>> {
        let on_all_rows = self.is_every_row(&full.rows);
        let sets: Vec<&[usize]> = self.folds.iter().map(Vec::as_slice).collect();
        let hats = on_all_rows
            .then(|| full.basis.hat_rows(&sets))
            .flatten()
            .filter(|hats| hats.len() == self.folds.len());
        let threads = if design.fits_on_any_thread() {
            parallel::threads(MAX_FOLD_THREADS)
        } else {
            1
        };
        let jobs: Vec<(usize, Option<HatRows>)> = match hats {
            Some(hats) => hats.into_iter().map(Some).enumerate().collect(),
            None => (0..self.folds.len()).map(|k| (k, None)).collect(),
        };
        parallel::in_groups_owned(jobs, threads, |(fold, hat)| {
            match hat.and_then(FoldDowndate::new) {
                Some(downdate) => FoldFit::Downdated(downdate),
                None => FoldFit::Refit(self.fit_base(
                    design,
                    self.training_rows(fold),
                    &self.folds[fold],
                )),
            }
        })
    }

    /// The base fit on `all_rows` and per fold, and the folds' held-out residuals.
    pub fn base<D: LinearDesign>(&self, design: &D, all_rows: &[usize]) -> Bases<D::Fit> {
        let full = self.fit_base(design, all_rows.to_vec(), &[]);
        let fold_fits = self.fold_fits(design, &full);
        let (heldout, _) = self.heldout_sum(design, &fold_fits, &full.res_w, None);
        (full, fold_fits, heldout)
    }

    /// The same residuals and weights over other folds.
    pub fn with_folds(&self, folds: Vec<Vec<usize>>) -> Engine {
        Engine {
            w: self.w.clone(),
            r: self.r.clone(),
            w_report: self.w_report.clone(),
            folds,
        }
    }

    /// The held-out residuals of this engine's folds around `full`, a base fit on every row
    /// of the same residuals and weights (made by another engine with other folds).
    pub fn heldout_of<D: LinearDesign>(&self, design: &D, full: &BaseFit<D::Fit>) -> HeldOut {
        let fold_fits = self.fold_fits(design, full);
        self.heldout_sum(design, &fold_fits, &full.res_w, None).0
    }

    /// Adding the effect whose columns `columns` makes (all rows, not whitened) to the base.
    /// Where every fold is downdated the columns are whitened in place and not kept, and
    /// sparse columns stay sparse where the fit keeps their projection implicit.
    pub fn evaluate<D: LinearDesign>(
        &self,
        design: &D,
        full: &BaseFit<D::Fit>,
        fold_fits: &[FoldFit<D::Fit>],
        columns: &dyn Fn() -> Columns,
    ) -> Eval {
        let any_refit = fold_fits.iter().any(|f| matches!(f, FoldFit::Refit(_)));
        let (a, perp, coeff) = if any_refit || !self.is_every_row(&full.rows) {
            let a = columns().into_dense();
            let aw = self.whitened_rows(&a, &full.rows);
            let perp = Projected::new(&full.basis, aw);
            let coeff = perp.ut(&full.res_w);
            (Some(a), perp, coeff)
        } else {
            let (perp, coeff) = self.projected_in_place(&full.basis, columns(), &full.res_w);
            (None, perp, coeff)
        };
        let (n_columns, entries) = (perp.vt.ncols(), full.rows.len() * perp.vt.ncols());
        let chi2_drop = coeff.norm_squared();
        // Every fold downdated, each row held out once: the folds make the residuals after.
        let after_w = (any_refit || !self.folds_hold_each_row_once())
            .then(|| &full.res_w - perp.u_times(&coeff));
        // θ = V S⁻¹ Uᵀ r, from the coefficients Uᵀ r already at hand.
        let theta = perp.v_scaled(&coeff);
        // Cov(θ) = V S⁻² Vᵀ of the projected (Frisch–Waugh) design.
        let theta_sigma = DVector::from_fn(n_columns, |c, _| {
            (0..perp.rank())
                .map(|k| (perp.vt[(k, c)] / perp.s[k]).powi(2))
                .sum::<f64>()
                .sqrt()
        });
        // The parameter's unit direction inside the identified row space (1 when fully
        // determined), against the same cut as the directions'.
        let identifiable = (0..n_columns)
            .map(|c| {
                (0..perp.rank())
                    .map(|k| perp.vt[(k, c)].powi(2))
                    .sum::<f64>()
                    > EFFECT_RANK_TOL * EFFECT_RANK_TOL
            })
            .collect();
        let df = perp.rank();
        // The downdated folds need the projected columns, the refitted ones nothing of the
        // full fit's.
        let any_downdated = fold_fits.iter().any(|f| matches!(f, FoldFit::Downdated(_)));
        let perp = any_downdated.then_some(perp);
        let candidate = Candidate {
            a: a.as_ref(),
            entries,
            projected: perp.as_ref(),
            after: match &after_w {
                Some(after_w) => After::Residuals(after_w),
                None => After::Coefficients(&coeff),
            },
        };
        let (heldout, folds_after_ss) =
            self.heldout_sum(design, fold_fits, &full.res_w, Some((&candidate, columns)));
        let rms_after = match (&after_w, folds_after_ss) {
            (Some(after_w), _) => self.rms_reported(after_w, &full.rows),
            (None, Some(ss)) => (ss / full.rows.len().max(1) as f64).sqrt(),
            // A fold refitted after all: the residuals after made whole (every fold was
            // downdated when this route was taken, so the projection is held).
            (None, None) => {
                let after_w = match &perp {
                    Some(perp) => &full.res_w - perp.u_times(&coeff),
                    None => full.res_w.clone(),
                };
                self.rms_reported(&after_w, &full.rows)
            }
        };
        Eval {
            chi2_drop,
            df,
            theta,
            theta_sigma,
            identifiable,
            rms_after,
            heldout_ms: heldout.mean_square(),
            heldout_z2: heldout.mean_z2(),
        }
    }

    /// Columns over every row whitened and projected off `fit`: dense ones in place, sparse
    /// ones implicitly where the fit can.
    /// With Uᵀ b for the `b` given over every row.
    fn projected_in_place<F: LinearFit>(
        &self,
        fit: &F,
        columns: Columns,
        b: &DVector<f64>,
    ) -> (Projected, DVector<f64>) {
        let projected = match columns {
            Columns::Dense(mut aw) => {
                for (i, mut row) in aw.row_iter_mut().enumerate() {
                    row *= self.w[i];
                }
                Projected::new(fit, aw)
            }
            Columns::Sparse(mut m) => {
                m.scale_rows(&self.w);
                let reference = m.column_norm_max();
                match fit.project_off_implicit(m) {
                    Ok(rows) => return Projected::from_rows(rows, reference, b),
                    Err(m) => Projected::new(fit, m.to_dense()),
                }
            }
        };
        let ut = projected.ut(b);
        (projected, ut)
    }

    /// Orthonormal basis of the candidate's columns projected off the full fit (for the
    /// confounding test).
    pub fn projected_basis<F: LinearFit>(
        &self,
        full: &BaseFit<F>,
        a: &DMatrix<f64>,
    ) -> DMatrix<f64> {
        Projected::new(&full.basis, self.whitened_rows(a, &full.rows)).into_u()
    }
}
