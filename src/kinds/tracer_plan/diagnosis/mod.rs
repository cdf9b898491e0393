//! Sim-to-real gap diagnosis of a tracer network (`geocal diagnose` of the multilateration
//! and rotary_tracer kinds): where the lengths depart from the nominal multilateration model,
//! which unmodelled effect explains it, and how far the gap shrinks.

pub mod budget;
pub mod correct;
pub mod data;
pub mod dense;
pub mod effects;
pub mod fit;
pub mod locate;
pub mod loso;
#[cfg(test)]
mod oracle;
pub mod points;
pub mod schur;
pub mod settling;
pub mod stations;
pub mod twin;

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;

use anyhow::Context;
use nalgebra::{DMatrix, DVector};
use serde_json::Value;

// The shared machinery, named from this library's modules as their siblings.
use crate::diagnose::columns::Columns;
use crate::diagnose::{engine, forward, progress, selection, stats};
use crate::diagnose::{
    Candidate, CorrectedCalibration, DiagnoseOptions, Diagnosis, Gap, NoiseScale,
    StandardisedResidual, StandardisedResiduals, DIAGNOSIS_FORMAT,
};
use crate::extract::WindowSamples;
use crate::session::reader::Session;
use crate::solve::multilateration::{solve, SolveOptions};
use data::Data;
use effects::{EffectKind, EffectModel, Geometry, Library};
use engine::{BaseFit, Engine, HeldOut};
use fit::Fit;
use forward::{Selection, Start, Trial};
use locate::{best_step, locate, WhereEntry};
use loso::HeldOutStation;
use points::{points_level, PointsGap};
use progress::{selection_units, Counter};
use schur::Design;
use selection::Tests;
use stats::{chi2_isf, chi2_sf};

#[derive(Debug, thiserror::Error)]
pub enum DiagnoseError {
    #[error(transparent)]
    Data(#[from] data::DataError),
    #[error("nominal multilateration fit: {0}")]
    Solve(#[from] crate::solve::multilateration::SolveError),
    #[error(transparent)]
    TooLarge(#[from] budget::TooLarge),
}

/// Read a tracer session file and diagnose it, with the standardised residuals of every
/// length. A clean file is streamed: its tracer samples are never held whole, only each
/// window's settled stretch.
pub fn diagnose_file_detailed(
    path: &Path,
    options: &DiagnoseOptions,
) -> anyhow::Result<(Diagnosis, StandardisedResiduals)> {
    let settled = data::dwells_of_file(path, WindowSamples::Kept)
        .with_context(|| format!("reading {}", path.display()))?
        .map_err(DiagnoseError::from)
        .with_context(|| format!("diagnosing {}", path.display()))?;
    // The settled windows are consumed by the observations (not kept beside them): the
    // corrected calibration, when an effect is selected, reads the file again.
    let mut data = Data::from_dwells(settled)
        .map_err(DiagnoseError::from)
        .with_context(|| format!("diagnosing {}", path.display()))?;
    budget::return_freed_memory();
    let mut detailed = diagnose_data(&mut data, options)
        .map_err(anyhow::Error::from)
        .with_context(|| format!("diagnosing {}", path.display()))?;
    let kind = data.header.kind.clone();
    drop(data);
    let mut diagnosis = detailed.diagnosis;
    match corrected_calibration(&kind, path, &diagnosis.selected) {
        Ok(corrected) => diagnosis.corrected = corrected,
        Err(why) => diagnosis
            .notes
            .push(format!("the calibration with the selected effects: {why}")),
    }
    detailed.progress.finish();
    Ok((diagnosis, detailed.residuals))
}

/// The calibration re-solved with the selected effects that the solve can model, and how far
/// its points moved from the nominal calibration's; None when none was selected. The file's
/// settled windows are read again (only then).
fn corrected_calibration(
    kind: &str,
    path: &Path,
    selected: &[String],
) -> Result<Option<CorrectedCalibration>, String> {
    // The effects the solve models: those on the lengths (not the raw windows' settling, the
    // points level's target offset or an effect on the stations).
    let stations_effect = crate::kinds::kind_named(kind)
        .and_then(|k| k.tracer_diagnosis())
        .and_then(|n| n.stations_effect());
    let known = effects::known_names();
    let kinds = selected
        .iter()
        .filter_map(|s| known.iter().copied().find(|name| name == s))
        .filter(|name| {
            !["settling", "target_offset"].contains(name) && Some(*name) != stations_effect
        })
        .collect::<Vec<_>>();
    if kinds.is_empty() {
        return Ok(None);
    }
    let settled = match data::dwells_of_file(path, WindowSamples::ArrivalOnly) {
        Ok(Ok(settled)) => settled,
        Ok(Err(why)) => return Err(why.to_string()),
        Err(why) => return Err(format!("reading {}: {why}", path.display())),
    };
    let settled = &settled;
    let solve_with = |effects: Vec<&'static str>| {
        let settings = crate::method::SolveSettings {
            effects: correct::fit_named(effects),
            ..Default::default()
        };
        crate::method::multilateration::solve_dwells(settled, &settings)
            .map(|(results, _)| results)
            .map_err(|e| e.to_string())
    };
    let nominal = solve_with(Vec::new())?;
    let corrected = solve_with(kinds.clone())?;
    let (mut moved_m2, mut moved_z2, mut count) = (0.0, 0.0, 0usize);
    for (a, b) in nominal.points.iter().zip(&corrected.points) {
        for k in 0..3 {
            let d = b.actual_m[k] - a.actual_m[k];
            moved_m2 += d * d;
            moved_z2 += (d / b.sigma_m[k]).powi(2);
            count += 1;
        }
    }
    let names = kinds;
    Ok(Some(CorrectedCalibration {
        command: format!(
            "geocal solve {} --effects {}",
            path.display(),
            names.join(",")
        ),
        effects: names.iter().map(|n| n.to_string()).collect(),
        points_moved_rms_m: (moved_m2 / count.max(1) as f64).sqrt(),
        points_moved_rms_sigma: (moved_z2 / count.max(1) as f64).sqrt(),
    }))
}

/// Cross-validation folds of the lengths: fold of a length = (point + station) mod K, so every
/// held-out length has its point seen from the other stations and its station from the other
/// points (K ≥ stations: a fold takes at most one length from a point).
fn folds_of(data: &Data, k: usize) -> Vec<Vec<usize>> {
    (0..k)
        .map(|f| {
            (0..data.obs.len())
                .filter(|&i| (data.obs[i].point + data.obs[i].station) % k == f)
                .collect()
        })
        .collect()
}

/// How many folds the reported gaps (before and after) are held out over: enough that a fold
/// takes, on average, at most a quarter of a point's redundant stations; None when the
/// selection's `selection_folds` already do. A point seen from m stations has m − 3 redundant
/// ones, and a fold takes one (point, station) pair from a share m/K of the points:
/// K ≥ 4m/(m − 3) (10 for points seen from 5 stations, 5 from 16).
///
/// The selection's held-out test uses K = max(5, stations). With K = stations every point
/// loses one length in every fold; where points have few lengths to spare the training fits
/// then predict the held-out lengths with a variance that every added parameter grows, and
/// the held-out RMS measures that more than the model's misfit. That harsher test is kept as
/// the selection's gate, which a flexible candidate that does not predict fails; "how far" is
/// the finer estimate.
fn report_fold_count(data: &Data, selection_folds: usize) -> Option<usize> {
    let stations = data.station_ids.len().max(1);
    let mut pairs: Vec<usize> = data
        .obs
        .iter()
        .map(|o| o.point * stations + o.station)
        .collect();
    pairs.sort_unstable();
    pairs.dedup();
    let points = pairs.chunk_by(|a, b| a / stations == b / stations).count();
    folds_for_stations_per_point(pairs.len(), points, selection_folds)
}

/// [`report_fold_count`] for `pairs` (point, station) pairs over `points` points.
fn folds_for_stations_per_point(
    pairs: usize,
    points: usize,
    selection_folds: usize,
) -> Option<usize> {
    let per_point = pairs as f64 / points.max(1) as f64;
    if per_point <= 3.0 {
        return None;
    }
    let folds = ((4.0 * per_point / (per_point - 3.0)).ceil() as usize).min(pairs);
    (folds > selection_folds).then_some(folds)
}

/// The base fit's gap: the fitted RMS and χ²/dof, the held-out RMS, floor and ratio.
fn gap_of(engine: &Engine, full: &BaseFit<Fit>, heldout: &HeldOut) -> Gap {
    let n = full.rows.len();
    Gap {
        rms_m: engine.rms_reported(&full.res_w, &full.rows),
        heldout_rms_m: heldout.mean_square().sqrt(),
        chi2_per_dof: full.res_w.norm_squared() / (n - full.basis.rank()).max(1) as f64,
        heldout_floor_m: heldout.mean_floor().sqrt(),
        heldout_ratio: heldout.mean_z2().sqrt(),
    }
}

pub(crate) fn hcat(a: &DMatrix<f64>, b: &DMatrix<f64>) -> DMatrix<f64> {
    let mut out = DMatrix::zeros(a.nrows(), a.ncols() + b.ncols());
    out.columns_mut(0, a.ncols()).copy_from(a);
    out.columns_mut(a.ncols(), b.ncols()).copy_from(b);
    out
}

/// The forward selection's view of the lengths: the nominal design at the nominal geometry
/// and the effect models' columns there.
struct LengthsClient<'a> {
    data: &'a Data,
    geom: &'a Geometry,
    nominal: &'a Arc<Design>,
}

impl forward::Client for LengthsClient<'_> {
    type Design = Arc<Design>;
    type Effect = EffectModel;
    type Key = EffectKind;

    fn key(&self, effect: &EffectModel) -> EffectKind {
        effect.kind
    }

    fn name(&self, effect: &EffectModel) -> String {
        effect.kind.name().to_string()
    }

    fn design(&self, accepted: &[EffectModel]) -> Arc<Design> {
        Arc::new(
            self.nominal.with_effect_blocks(
                accepted
                    .iter()
                    .map(|m| m.candidate_columns(self.data, self.geom))
                    .collect(),
            ),
        )
    }

    fn columns(&self, effect: &EffectModel) -> DMatrix<f64> {
        effect.columns(self.data, self.geom)
    }

    fn candidate_columns(&self, effect: &EffectModel) -> Columns {
        effect.candidate_columns(self.data, self.geom)
    }

    /// A length step's change point: the best position over the passes (Bonferroni over the
    /// positions tried).
    fn search(&self, effect: &EffectModel, full: &BaseFit<Fit>) -> Option<(EffectModel, usize)> {
        if effect.kind != EffectKind::LengthStep {
            return Some((effect.clone(), 1));
        }
        best_step(self.data, &full.basis, &full.res_w, None).map(|(g, k, _, tried)| {
            (
                EffectModel {
                    step: Some((g, k)),
                    ..effect.clone()
                },
                tried,
            )
        })
    }

    /// The eccentricity's one size, linearised at the free estimate's phases.
    fn constrained(&self, effect: &EffectModel, theta: &[f64]) -> Option<EffectModel> {
        Some(effect.linearised_at(theta)).filter(EffectModel::is_linearised)
    }

    fn gap(&self, engine: &Engine, full: &BaseFit<Fit>, heldout: &HeldOut) -> Gap {
        gap_of(engine, full, heldout)
    }

    fn cross_validation_notes(&self, engine: &Engine, count: usize) -> Vec<String> {
        let held_total: usize = engine.folds.iter().map(Vec::len).sum();
        let mut notes = vec![format!(
            "cross-validation: {} folds of (point, station) pairs; {count} of {held_total} held-out lengths are determined by the rest and predicted",
            engine.folds.len()
        )];
        if count == 0 {
            notes.push("no held-out length is predictable: the plan has too few points or stations for cross-validation, so held-out RMS is not a criterion".into());
        }
        notes
    }

    fn absorbed_note(&self, name: &str) -> String {
        format!(
            "{name}: absorbed by the nominal model (projected rank 0), not identifiable from these lengths"
        )
    }

    fn record(
        &self,
        trial: &Trial<EffectModel>,
        round: usize,
        status: String,
        confounded_with: Vec<String>,
    ) -> Candidate {
        candidate_record(self.data, trial, round, status, confounded_with)
    }
}

/// Diagnose a multilateration session: reads only the session.
pub fn diagnose(session: &Session, options: &DiagnoseOptions) -> Result<Diagnosis, DiagnoseError> {
    let mut data = Data::from_session(session)?;
    let mut detailed = diagnose_data(&mut data, options)?;
    detailed.progress.finish();
    Ok(detailed.diagnosis)
}

/// A diagnosis with what the twin comparison needs of its final model.
pub(crate) struct DataDiagnosis {
    pub diagnosis: Diagnosis,
    /// The fitted contribution of the effects in the final model to each recorded length
    /// (settling's window bias included, when accepted).
    pub effect_m: Vec<f64>,
    /// The accepted lengths-level effects' columns (one row per length, metres per unit
    /// parameter) at the final geometry: what their estimates' uncertainty moves.
    pub effect_columns: DMatrix<f64>,
    pub residuals: StandardisedResiduals,
    /// The progress so far; the caller finishes it (the corrected calibration's unit is its).
    pub progress: Counter,
}

/// The diagnosis of a session's observations (possibly with lengths and sigmas changed, as
/// the twin comparison does).
/// The raw windows (`Data::windows`) are read by the settling test alone and freed after it.
pub(crate) fn diagnose_data(
    data: &mut Data,
    options: &DiagnoseOptions,
) -> Result<DataDiagnosis, DiagnoseError> {
    let stations = data.station_ids.len();
    budget::check(data, options.memory_limit_bytes)?;
    let solution = match data.nominal.take() {
        Some(solution) => solution,
        None => solve(&data.problem, &SolveOptions::default())?,
    };
    let nobs = data.obs.len();
    let geom = Geometry::from_solution(&solution);
    let w = DVector::from_iterator(nobs, data.obs.iter().map(|o| 1.0 / o.sigma_m));
    let mut engine = Engine {
        w_report: w.clone(),
        w,
        r: DVector::from_iterator(nobs, solution.residuals_m.iter().copied()),
        folds: folds_of(data, options.folds.max(stations)),
    };
    let mut notes = vec![format!(
        "{} lengths from {} stations; {} dwell windows dropped by extraction",
        nobs,
        data.station_ids.len(),
        data.dropped_windows
    )];
    let library = Library::of(data);
    notes.extend(library.notes.iter().cloned());
    let mut available: Vec<EffectModel> = library.lengths.clone();
    let in_library =
        |available: &[EffectModel], k: EffectKind| available.iter().any(|m| m.kind == k);
    if !data.has_env {
        let lacking: Vec<&str> = [EffectKind::AirRefraction, EffectKind::DeadPath]
            .into_iter()
            .filter(|&k| in_library(&available, k))
            .map(|k| k.name())
            .collect();
        available.retain(|m| !matches!(m.kind, EffectKind::AirRefraction | EffectKind::DeadPath));
        if !lacking.is_empty() {
            notes.push(format!(
                "no environment log: {} cannot be tested",
                lacking.join(" and ")
            ));
        }
    }
    if !data.has_material && in_library(&available, EffectKind::ThermalExpansion) {
        available.retain(|m| m.kind != EffectKind::ThermalExpansion);
        notes.push("no material temperature in the log: thermal_expansion cannot be tested".into());
    }
    let settling_in_library = in_library(&available, EffectKind::Settling);
    // Units of work: the settling test, every round the selection may run, the final fit and
    // its levels, the corrected calibration (the caller's).
    let lengths_candidates = available.len() - usize::from(settling_in_library);
    let selection_end = u64::from(settling_in_library) + selection_units(lengths_candidates);
    let mut progress = Counter::new(options.progress.as_ref(), selection_end + 3);
    let offset_in_library = in_library(&available, EffectKind::TargetOffset);
    let nominal_design = Arc::new(Design::nominal(data, &geom));
    let all_rows: Vec<usize> = (0..nobs).collect();

    // Effects in the model before the selection on the means (settling, tested on the raw
    // samples).
    let mut accepted: Vec<EffectModel> = Vec::new();
    let mut records: BTreeMap<EffectKind, Candidate> = BTreeMap::new();
    let mut gap_before: Option<Gap> = None;
    // The gaps reported, before and after the selected effects, over finer folds where the
    // selection's would leave the training fits short of redundancy.
    let report_folds =
        report_fold_count(data, engine.folds.len()).map(|folds| folds_of(data, folds));

    // Settling shows in the raw samples inside the dwell windows, which no other candidate
    // predicts: it is tested there (its own block of data, in the first round's family), and
    // once accepted its bias is taken off the window means before the selection on the means.
    available.retain(|m| m.kind != EffectKind::Settling);
    let settling_fit = if settling_in_library {
        let fit = settling::evaluate(data, &geom);
        progress.tick(1);
        fit
    } else {
        None
    };
    // Not needed by the rounds: their memory is the candidates'. Many small blocks inside the
    // heap: returned, or the rounds' peak would add to them.
    data.windows = Vec::new();
    budget::return_freed_memory();
    let data: &Data = data;
    match &settling_fit {
        Some(fit) => {
            let alpha_each = options.alpha / (available.len() + 1) as f64;
            let tests = Tests {
                p_value: fit.p_value,
                bic_delta: fit.bic_delta,
                heldout_improves: Some(fit.heldout_ms_after_m2 < fit.heldout_ms_base_m2),
            };
            let passes = tests.passes(alpha_each);
            let status = tests.alone_status(alpha_each);
            records.insert(EffectKind::Settling, settling_record(fit, status));
            if passes {
                let finer = report_folds.clone().map(|folds| engine.with_folds(folds));
                let before = finer.as_ref().unwrap_or(&engine);
                let (full, _, heldout) = before.base(&nominal_design, &all_rows);
                gap_before = Some(gap_of(before, &full, &heldout));
                for (r, b) in engine.r.iter_mut().zip(&fit.bias_m) {
                    *r -= b;
                }
                accepted.push(EffectModel {
                    tau_s: Some(fit.tau_s),
                    ..EffectModel::plain(EffectKind::Settling)
                });
            }
        }
        None if settling_in_library => notes.push(
            "settling: no raw dwell window with a move into it, so it cannot be tested".into(),
        ),
        None => {}
    }
    let client = LengthsClient {
        data,
        geom: &geom,
        nominal: &nominal_design,
    };
    let report_engine = report_folds.map(|folds| engine.with_folds(folds));
    if let Some(report) = &report_engine {
        notes.push(format!(
            "the held-out gaps before and after are over {} folds (a fold takes at most a quarter of a point's redundant stations on average), the selection's held-out test over {}",
            report.folds.len(),
            engine.folds.len()
        ));
    }
    let start = Start {
        accepted,
        records,
        gap_before,
        // The first round's family includes the settling test.
        extra_first_round_tests: usize::from(settling_fit.is_some()),
    };
    let Selection {
        mut accepted,
        confounded: confounded_kinds,
        records,
        gap_before,
        last_base,
        final_round,
        notes: selection_notes,
    } = forward::select(
        &client,
        &engine,
        report_engine.as_ref(),
        &available,
        start,
        options.alpha,
        library.names.len(),
        &mut progress,
    );
    notes.extend(selection_notes);
    progress.advance_to(selection_end);
    budget::return_freed_memory();
    // The final model: joint Gauss–Newton of geometry and accepted effects, on the window
    // means with the settling bias (when accepted) taken off.
    let settled = accepted.iter().any(|m| m.kind == EffectKind::Settling);
    let fit_data = match &settling_fit {
        Some(fit) if settled => {
            let mut d = data.clone();
            for (o, b) in d.obs.iter_mut().zip(&fit.bias_m) {
                o.length_m -= b;
            }
            std::borrow::Cow::Owned(d)
        }
        _ => std::borrow::Cow::Borrowed(data),
    };
    // The nominal model's fit (for where the recorded lengths depart) beside the final one.
    let (final_fit, nominal_basis) = crate::parallel::join(
        || {
            let mut final_fit = joint_fit(&fit_data, &geom, &accepted);
            if accepted.iter().any(EffectModel::is_linearised) {
                accepted =
                    EffectModel::all_linearised_at(&accepted, data, final_fit.theta.as_slice());
                final_fit = joint_fit(&fit_data, &geom, &accepted);
            }
            final_fit
        },
        || Fit::new(nominal_design.clone(), (0..nobs).collect()),
    );
    progress.tick(1);
    let residuals =
        standardised_residuals(data, &solution.residuals_m, &final_fit.resid_m, &accepted);
    let chi2: f64 = final_fit
        .resid_m
        .iter()
        .zip(&data.obs)
        .map(|(r, o)| (r / o.sigma_m).powi(2))
        .sum();
    let dof = nobs.saturating_sub(final_fit.basis.rank()).max(1);
    let cv_after = last_base.unwrap_or_else(|| empty_gap(f64::NAN));
    let gap_after = Gap {
        rms_m: rms(&final_fit.resid_m),
        heldout_rms_m: cv_after.heldout_rms_m,
        chi2_per_dof: chi2 / dof as f64,
        heldout_floor_m: cv_after.heldout_floor_m,
        heldout_ratio: cv_after.heldout_ratio,
    };
    let noise_floor_m = (data.obs.iter().map(|o| o.sigma_m.powi(2)).sum::<f64>() / nobs as f64
        * solution.dof as f64
        / nobs as f64)
        .sqrt();
    // `unexplained` is one decision over three tests (the final χ², the final residuals'
    // groups, the points level after the effects): Bonferroni over them, so that its
    // false-alarm rate on data the model holds for is at most alpha.
    let alpha_part = options.alpha / 3.0;
    // Residuals uniformly too large or too small: when σ scaled by k = √(χ²/dof) leaves no
    // group and no points-level structure, the finding is about the noise declaration, not
    // an effect, and every test below uses the scaled σ.
    let noise_scale = noise_scale_candidate(chi2, dof, alpha_part).filter(|scale| {
        let scaled = fit_data.with_sigma_scaled(scale.k);
        let groups = locate(
            &scaled,
            &final_fit.geom,
            &final_fit.resid_m,
            &final_fit.basis,
            alpha_part,
        );
        let effect_columns = accepted.iter().fold(DMatrix::zeros(nobs, 0), |d, m| {
            hcat(&d, &m.columns(&scaled, &final_fit.geom))
        });
        let lengths: Vec<f64> = scaled.obs.iter().map(|o| o.length_m).collect();
        let points_fit = points_level(&scaled, &lengths, &effect_columns, alpha_part)
            .map_or(true, |(level, _)| level.gap.p_value >= alpha_part);
        groups.is_empty() && points_fit
    });
    let (scaled_data, scaled_fit_data);
    let (data, fit_data, chi2) = match &noise_scale {
        Some(scale) => {
            scaled_data = data.with_sigma_scaled(scale.k);
            scaled_fit_data = fit_data.with_sigma_scaled(scale.k);
            notes.push(format!(
                "{}: the tests below use the declared sigma times {:.3}",
                scale.statement, scale.k
            ));
            (&scaled_data, &scaled_fit_data, chi2 / scale.k.powi(2))
        }
        None => (data, fit_data.as_ref(), chi2),
    };
    let (mut where_, remaining) = crate::parallel::join(
        || {
            locate(
                data,
                &geom,
                &solution.residuals_m,
                &nominal_basis,
                options.alpha,
            )
        },
        || {
            locate(
                fit_data,
                &final_fit.geom,
                &final_fit.resid_m,
                &final_fit.basis,
                alpha_part,
            )
        },
    );
    let (held_out, skipped) =
        fit::leave_one_station_out(data, &nominal_design, &solution.residuals_m);
    if !skipped.is_empty() {
        notes.push(format!(
            "leave-one-station-out: without {} the other stations do not determine the points; not predicted",
            skipped.join(", ")
        ));
    }
    let excess = |h: &HeldOutStation| (h.ratio.powi(2) * h.dof as f64 - h.dof as f64).max(0.0);
    let mut failing: Vec<WhereEntry> = held_out
        .iter()
        .filter(|h| h.p_value < options.alpha)
        .map(|h| WhereEntry {
            level: "lengths".into(),
            group: "station".into(),
            key: format!("{} held out", h.station),
            // Its share of the stations' excess held-out χ² (χ² − dof): the held-out sums of
            // squares themselves mostly reflect how well each station's points are determined.
            share: excess(h)
                / held_out
                    .iter()
                    .map(excess)
                    .sum::<f64>()
                    .max(f64::MIN_POSITIVE),
            rms_m: h.heldout_rms_m,
            p_value: h.p_value,
        })
        .collect();
    failing.sort_by(|a, b| b.share.total_cmp(&a.share));
    where_.extend(failing);
    // The points level, before (recorded lengths) and after (fitted effects removed): a
    // machine that departs from the quasi-rigid model is structure no candidate explains.
    let recorded: Vec<f64> = data.obs.iter().map(|o| o.length_m).collect();
    let points_before = match points_level(data, &recorded, &DMatrix::zeros(nobs, 0), options.alpha)
    {
        Ok((level, entries)) => {
            where_.extend(entries);
            Some(level)
        }
        Err(why) => {
            notes.push(format!("points level not tested: {why}"));
            None
        }
    };
    let effect_columns = accepted.iter().fold(DMatrix::zeros(nobs, 0), |d, m| {
        hcat(&d, &m.columns(data, &final_fit.geom))
    });
    let after_level = if accepted.is_empty() {
        points_before.clone()
    } else {
        // From the lengths the final fit saw (the settling bias, if accepted, already off),
        // the accepted effects fitted again with the per-pass points and their uncertainty
        // carried into the points' covariance.
        let lengths: Vec<f64> = fit_data.obs.iter().map(|o| o.length_m).collect();
        points_level(data, &lengths, &effect_columns, options.alpha)
            .ok()
            .map(|(after, _)| after)
    };
    // target_offset is tested at the points level (the lengths level cannot see it), after
    // the lengths-level effects, with the same Bonferroni share as a lengths candidate.
    let offset_test = after_level.as_ref().and_then(|p| p.target_offset.clone());
    let offset_threshold = options.alpha / library.names.len() as f64;
    let offset_test = offset_test.filter(|_| offset_in_library);
    let offset_accepted = offset_test
        .as_ref()
        .is_some_and(|t| t.p_value < offset_threshold && t.bic_delta < 0.0);
    // The points level's gap after the selected effects (and the target shifts, if named).
    let points_level_after = after_level
        .as_ref()
        .map(|p| match (&offset_test, offset_accepted) {
            (Some(t), true) => PointsGap {
                chi2: t.chi2_after,
                dof: t.dof_after,
                chi2_per_dof: t.chi2_after / t.dof_after.max(1) as f64,
                p_value: chi2_sf(t.chi2_after, t.dof_after as f64),
                rank: p.gap.rank + t.df,
                ..p.gap.clone()
            },
            _ => p.gap.clone(),
        });
    let points_after = points_level_after
        .as_ref()
        .filter(|g| g.p_value < alpha_part)
        .map(|g| (g.chi2_per_dof, g.p_value));
    if let Some((ratio, p)) = points_after {
        notes.push(format!(
            "points level after the selected effects: chi2/dof {ratio:.2} (p = {p:.1e}): the measured points depart from the quasi-rigid 21-error model (a local or non-rigid machine error, or an effect no candidate holds)"
        ));
    }
    let chi2_p = chi2_sf(chi2, dof as f64);
    let lengths_unexplained = chi2_p < alpha_part || !remaining.is_empty();
    let unexplained = lengths_unexplained || points_after.is_some();
    if lengths_unexplained {
        notes.push(format!(
            "after the selected effects: chi2/dof {:.2} (p = {:.1e}), {} residual group(s) still fail the noise model{}",
            chi2 / dof as f64,
            chi2_p,
            remaining.len(),
            remaining
                .first()
                .map(|w| format!(", largest {} {}", w.group, w.key))
                .unwrap_or_default()
        ));
    }
    let mut selected: Vec<String> = accepted
        .iter()
        .filter(|m| !confounded_kinds.contains(&m.kind))
        .map(|m| m.kind.name().to_string())
        .collect();
    let mut candidates: Vec<Candidate> = records.into_values().collect();
    // The plan kind's test of the solved stations (e.g. the table stations against their
    // circle), at the geometry of the final model.
    let mut unexplained = unexplained;
    if let Some(network) = library.network {
        let (positions, mut covariance) = if accepted.is_empty() {
            (
                solution.stations.clone(),
                solution.station_joint_covariance.clone(),
            )
        } else {
            let first = 3 * final_fit.geom.points.len();
            let cols: Vec<usize> = (first..first + 3 * final_fit.geom.stations.len()).collect();
            (
                final_fit.geom.stations.clone(),
                final_fit.basis.pinv_block(&cols),
            )
        };
        if let Some(scale) = &noise_scale {
            covariance *= scale.k.powi(2);
        }
        let solved = crate::method::tracer_effects::SolvedStations {
            positions_m: &positions,
            covariance_m2: &covariance,
        };
        match network.stations_level(&data.network_session(), &solved) {
            Ok(Some(level)) => {
                let outcome =
                    stations::judge(&level, options.alpha, library.names.len(), alpha_part);
                where_.extend(outcome.where_);
                notes.extend(outcome.notes);
                if outcome.selected {
                    selected.push(level.effect.to_string());
                }
                unexplained |= outcome.unexplained;
                candidates.push(outcome.candidate);
            }
            Ok(None) => {}
            Err(why) => notes.push(format!(
                "{}: not tested: {why}",
                network.stations_effect().unwrap_or("the stations level")
            )),
        }
    }
    if let Some(t) = &offset_test {
        if offset_accepted {
            selected.push(EffectKind::TargetOffset.name().to_string());
        }
        candidates.push(Candidate {
            effect: EffectKind::TargetOffset.name().to_string(),
            params: t
                .offsets_m
                .iter()
                .map(|(target, o)| (format!("{target}_offset_error_m"), serde_json::json!(o)))
                .collect(),
            rms_after_m: gap_after.rms_m,
            heldout_rms_after_m: gap_after.heldout_rms_m,
            bic_delta: t.bic_delta,
            p_value: t.p_value,
            round: final_round,
            df: t.df,
            chi2_drop: t.chi2_drop,
            status: if offset_accepted {
                "selected (points level)".into()
            } else {
                format!(
                    "rejected (points level): p {:.2e} against {offset_threshold:.2e}, BIC {:+.1}",
                    t.p_value, t.bic_delta
                )
            },
            confounded_with: Vec::new(),
        });
    }
    forward::report_order(&mut candidates, &selected);
    let diagnosis = Diagnosis {
        format: DIAGNOSIS_FORMAT.into(),
        session_id: data.session_id.clone(),
        noise_floor_m,
        gap: gap_before,
        where_,
        candidates,
        selected,
        gap_after,
        unexplained,
        noise_scale,
        corrected: None,
        points_level: points_before,
        points_level_after,
        leave_one_station_out: held_out,
        observations: nobs,
        notes,
        twin: None,
        model: None,
    };
    // The twin comparison takes this off the recorded lengths: settling's bias was taken off
    // before the final fit, so it is added here.
    let mut effect_m = final_fit.effect_m;
    if let (Some(fit), true) = (&settling_fit, settled) {
        for (e, b) in effect_m.iter_mut().zip(&fit.bias_m) {
            *e += b;
        }
    }
    progress.tick(1);
    Ok(DataDiagnosis {
        diagnosis,
        effect_m,
        effect_columns,
        residuals,
        progress,
    })
}

/// Residuals over the declared σ (not rescaled by a noise-scale finding), time from the
/// first length.
fn standardised_residuals(
    data: &Data,
    before_m: &[f64],
    after_m: &[f64],
    final_effects: &[EffectModel],
) -> StandardisedResiduals {
    let t0 = data.obs.iter().map(|o| o.t_s).fold(f64::INFINITY, f64::min);
    let mut final_effects: Vec<String> = final_effects
        .iter()
        .map(|m| m.kind.name().to_string())
        .collect();
    final_effects.dedup();
    // A kind may place its stations in its own coordinates (e.g. the table angle).
    let network = crate::kinds::kind_named(&data.header.kind).and_then(|k| k.tracer_diagnosis());
    let session = data.network_session();
    StandardisedResiduals {
        station_ids: data
            .station_ids
            .iter()
            .map(|id| {
                network
                    .and_then(|n| n.station_label(&session, id))
                    .unwrap_or_else(|| id.clone())
            })
            .collect(),
        lengths: data
            .obs
            .iter()
            .zip(before_m.iter().zip(after_m))
            .map(|(o, (b, a))| StandardisedResidual {
                station: o.station,
                t_s: o.t_s - t0,
                before: b / o.sigma_m,
                after: a / o.sigma_m,
            })
            .collect(),
        final_effects,
        x_axis: None,
    }
}

/// Confidence level of the noise scale's interval.
const NOISE_SCALE_CONFIDENCE: f64 = 0.95;

/// k = √(χ²/dof) when χ² departs from its distribution under the declared noise at `alpha`
/// on either side (the same level at which a large χ² would make the data unexplained); its
/// interval from the χ² quantiles.
fn noise_scale_candidate(chi2: f64, dof: usize, alpha: f64) -> Option<NoiseScale> {
    let nu = dof as f64;
    let upper = chi2_sf(chi2, nu);
    if upper >= alpha && 1.0 - upper >= alpha {
        return None;
    }
    let k = (chi2 / nu).sqrt();
    let tail = 0.5 * (1.0 - NOISE_SCALE_CONFIDENCE);
    let statement = if k > 1.0 {
        format!("the declared noise model is {k:.2}x too small")
    } else {
        format!("the declared noise model is {:.2}x too large", 1.0 / k)
    };
    Some(NoiseScale {
        k,
        k_low: (chi2 / chi2_isf(tail, nu)).sqrt(),
        k_high: (chi2 / chi2_isf(1.0 - tail, nu)).sqrt(),
        confidence: NOISE_SCALE_CONFIDENCE,
        dof,
        statement,
    })
}

fn empty_gap(v: f64) -> Gap {
    Gap {
        rms_m: v,
        heldout_rms_m: v,
        chi2_per_dof: v,
        heldout_floor_m: v,
        heldout_ratio: v,
    }
}

fn rms(v: &[f64]) -> f64 {
    (v.iter().map(|r| r * r).sum::<f64>() / v.len().max(1) as f64).sqrt()
}

fn candidate_record(
    data: &Data,
    trial: &Trial<EffectModel>,
    round: usize,
    status: String,
    confounded_with: Vec<String>,
) -> Candidate {
    let mut params: BTreeMap<String, Value> = BTreeMap::new();
    for (((name, v), s), identifiable) in trial
        .effect
        .param_names(data)
        .into_iter()
        .zip(trial.eval.theta.iter())
        .zip(trial.eval.theta_sigma.iter())
        .zip(&trial.eval.identifiable)
    {
        let (v, s) = if *identifiable {
            ((*v).into(), (*s).into())
        } else {
            (Value::Null, Value::Null)
        };
        params.insert(name.clone(), v);
        params.insert(format!("{name}.sigma"), s);
    }
    if let Some((g, k)) = trial.effect.step {
        params.insert("pass".into(), data.pass_names[g].clone().into());
        params.insert("after_t_s".into(), data.obs[data.passes[g][k]].t_s.into());
        params.insert("positions_searched".into(), trial.searched.into());
    }
    Candidate {
        effect: trial.effect.kind.name().into(),
        params,
        rms_after_m: trial.eval.rms_after,
        heldout_rms_after_m: trial.eval.heldout_ms.sqrt(),
        bic_delta: trial.bic_delta,
        p_value: trial.p_value,
        round,
        df: trial.eval.df,
        chi2_drop: trial.eval.chi2_drop,
        status,
        confounded_with,
    }
}

/// The settling test's record: its figures are those of the within-window block (raw
/// samples minus their window mean), not of the means.
fn settling_record(fit: &settling::SettlingFit, status: String) -> Candidate {
    let mut params: BTreeMap<String, Value> = BTreeMap::new();
    for ((name, v), s) in ["sx_m", "sy_m", "sz_m"]
        .iter()
        .zip(fit.s_m)
        .zip(fit.s_sigma_m)
    {
        params.insert(name.to_string(), v.into());
        params.insert(format!("{name}.sigma"), s.into());
    }
    params.insert("tau_s".into(), fit.tau_s.into());
    params.insert("tau_s_searched".into(), settling::TAU_GRID_S.len().into());
    params.insert("windows".into(), fit.windows.into());
    params.insert("within_window_dof".into(), fit.dof.into());
    Candidate {
        effect: EffectKind::Settling.name().into(),
        params,
        rms_after_m: fit.rms_after_m,
        heldout_rms_after_m: fit.heldout_ms_after_m2.sqrt(),
        bic_delta: fit.bic_delta,
        p_value: fit.p_value,
        round: 0,
        df: fit.df,
        chi2_drop: fit.chi2_drop,
        status,
        confounded_with: Vec::new(),
    }
}

pub(crate) struct JointFit {
    pub geom: Geometry,
    pub resid_m: Vec<f64>,
    /// The accepted effects' fitted contribution to each length (m).
    pub effect_m: Vec<f64>,
    /// The effects' parameters (in the models' column order).
    pub theta: DVector<f64>,
    /// The whitened joint design's fit (geometry, then the effects' columns), all lengths.
    pub basis: Fit,
}

/// Gauss–Newton on the geometry and the effects' parameters together, relinearising the
/// effect columns at the updated geometry (they depend on it through beam directions).
pub(crate) fn joint_fit(data: &Data, start: &Geometry, models: &[EffectModel]) -> JointFit {
    let nobs = data.obs.len();
    let mut geom = start.clone();
    let widths: Vec<usize> = models.iter().map(|m| m.param_names(data).len()).collect();
    let mut theta = DVector::zeros(widths.iter().sum());
    let w = DVector::from_iterator(nobs, data.obs.iter().map(|o| 1.0 / o.sigma_m));
    let design = |geom: &Geometry| {
        // Side by side; an effect per station by rows, not dense.
        let effects = models
            .iter()
            .map(|m| m.candidate_columns(data, geom))
            .collect();
        Arc::new(Design::nominal(data, geom).with_effect_blocks(effects))
    };
    let residual = |geom: &Geometry, a: &Design, theta: &DVector<f64>| {
        let np = geom.len();
        let mut x = DVector::zeros(np + theta.len());
        x.rows_mut(np, theta.len()).copy_from(theta);
        // Only the effects' part of the linear prediction: the geometry's is nonlinear.
        DVector::from_fn(nobs, |i, _| {
            data.obs[i].length_m - geom.predicted_m(data, i) - a.predict(i, &x)
        })
    };
    let all_rows: Vec<usize> = (0..nobs).collect();
    for _ in 0..10 {
        let a = design(&geom);
        let r = residual(&geom, &a, &theta);
        let basis = Fit::new(a, all_rows.clone());
        let step = basis.solve(&r.component_mul(&w));
        let np = geom.len();
        geom.apply(&step.as_slice()[..np]);
        for c in 0..theta.len() {
            theta[c] += step[np + c];
        }
        // Converged when no length moves by more than a thousandth of a nanometre.
        if step.rows(0, np).amax() < 1e-12 {
            break;
        }
    }
    let a = design(&geom);
    let r = residual(&geom, &a, &theta);
    let np = geom.len();
    let mut x = DVector::zeros(np + theta.len());
    x.rows_mut(np, theta.len()).copy_from(&theta);
    let effect_m = (0..nobs).map(|i| a.predict(i, &x)).collect();
    JointFit {
        effect_m,
        basis: Fit::new(a, all_rows),
        geom,
        resid_m: r.iter().copied().collect(),
        theta,
    }
}

#[cfg(test)]
mod report_folds_tests {
    use super::folds_for_stations_per_point;

    #[test]
    fn finer_folds_where_points_have_few_stations_to_spare() {
        // 27 points from 5 stations: 2 redundant stations a point, 10 folds (5 would take
        // half of them in every fold).
        assert_eq!(folds_for_stations_per_point(135, 27, 5), Some(10));
        // 16 stations: the selection's 16 folds take a 13th of them already.
        assert_eq!(folds_for_stations_per_point(16_000, 1_000, 16), None);
        // 4 stations: one redundant station a point, 16 folds.
        assert_eq!(folds_for_stations_per_point(72, 18, 5), Some(16));
        // No redundancy: nothing to hold out.
        assert_eq!(folds_for_stations_per_point(54, 18, 5), None);
        // Never more folds than pairs.
        assert_eq!(folds_for_stations_per_point(7, 2, 1), Some(7));
    }
}
