//! The diagnosis of a kind's residual model (`method::diagnosis::ResidualModel`): small dense
//! problems (tens to a few hundred parameters, hundreds to thousands of residuals). Where
//! (each label group's whitened sum of squares against the noise model), which (forward
//! selection over the kind's effect library with the multilateration diagnosis's statistics:
//! score/F test on the effect's columns projected off the model, BIC, family-wise α, held-out
//! validation on the kind's held-out groups, confounded candidates), and how far (held-out gap
//! before and after, and the calibration re-solved with the selected effects).

mod text;

pub use text::{details, summary};

use std::collections::BTreeMap;

use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};
use serde_json::Value;

use super::blocked::{ModelDesign, ModelFit};
use super::engine::{BaseFit, Engine, HeldOut, LinearDesign, LinearFit};
use super::forward::{self, Selection, Start, Trial};
use super::progress::{selection_units, Counter};
use super::stats::chi2_sf;
use super::{
    Candidate, CorrectedCalibration, DiagnoseOptions, Diagnosis, Gap, StandardisedResidual,
    StandardisedResiduals, WhereEntry, DIAGNOSIS_FORMAT,
};
use crate::method::diagnosis::{
    concat, effect_parameters, joint_fit, Effect, JointFit, LocalBlock, ResidualModel,
};

/// What a diagnosis of a kind's residual model adds to geocal-diagnosis/1.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct ModelDiagnosis {
    /// The session's plan kind.
    pub kind: String,
    /// Unit of each plot row and `where` key (its `rms_m`): "rad" when every residual in it
    /// is an angle, else "m" (the RMS over its length residuals).
    pub residual_units: BTreeMap<String, String>,
    /// The coordinates the residuals are grouped by (`where[].group`).
    pub coordinates: Vec<String>,
    /// The residual plot's x axis.
    pub x_axis: String,
    /// The effect library of the session (the candidates).
    pub library: Vec<String>,
    /// The calibration's parameters nominal → with the selected effects fitted jointly
    /// (empty when nothing is selected).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub parameters_after: Vec<ParameterAfter>,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct ParameterAfter {
    pub name: String,
    pub nominal: f64,
    pub nominal_sigma: f64,
    pub corrected: f64,
    pub sigma: f64,
}

/// The forward selection's view of a residual model: its whitened Jacobian at the nominal
/// parameters and its library's whitened columns there (a candidate is its library index).
struct ResidualsClient<'a> {
    model: &'a dyn ResidualModel,
    library: &'a [Box<dyn Effect + 'a>],
    x: &'a DMatrix<f64>,
    columns: &'a [DMatrix<f64>],
    sigma: &'a DVector<f64>,
    /// The model's local parameter blocks (eliminated group by group).
    blocks: &'a [LocalBlock],
    /// The nominal model's leverages over every row, from the selection's first base fit.
    nominal_leverages: std::sync::OnceLock<Vec<f64>>,
}

impl forward::Client for ResidualsClient<'_> {
    type Design = ModelDesign;
    type Effect = usize;
    type Key = usize;

    fn key(&self, effect: &usize) -> usize {
        *effect
    }

    fn name(&self, effect: &usize) -> String {
        self.library[*effect].name().to_string()
    }

    fn design(&self, accepted: &[usize]) -> ModelDesign {
        ModelDesign::new(
            accepted
                .iter()
                .fold(self.x.clone(), |d, &e| concat(&d, &self.columns[e])),
            self.blocks.to_vec(),
        )
    }

    fn columns(&self, effect: &usize) -> DMatrix<f64> {
        self.columns[*effect].clone()
    }

    fn gap(&self, _engine: &Engine, full: &BaseFit<ModelFit>, heldout: &HeldOut) -> Gap {
        let n = self.sigma.len();
        Gap {
            rms_m: rms_in_metres(self.model, &full.res_w.component_mul(self.sigma)),
            heldout_rms_m: heldout.mean_square().sqrt(),
            chi2_per_dof: full.res_w.norm_squared()
                / n.saturating_sub(full.basis.rank()).max(1) as f64,
            heldout_floor_m: 1.0,
            heldout_ratio: heldout.mean_z2().sqrt(),
        }
    }

    fn first_base_fitted(&self, full: &BaseFit<ModelFit>) {
        // The selection starts from the nominal model: its first base is the nominal fit.
        let _ = self.nominal_leverages.set(full.basis.leverages());
    }

    fn cross_validation_notes(&self, _engine: &Engine, count: usize) -> Vec<String> {
        vec![format!(
            "cross-validation: {count} held-out residuals determined by the rest and predicted (held-out figures are in units of each residual's σ)"
        )]
    }

    fn absorbed_note(&self, name: &str) -> String {
        format!("{name}: absorbed by the nominal model (projected rank 0), not identifiable here")
    }

    fn record(
        &self,
        trial: &Trial<usize>,
        round: usize,
        status: String,
        confounded_with: Vec<String>,
    ) -> Candidate {
        let eval = &trial.eval;
        let mut params = BTreeMap::new();
        for (k, name) in self.library[trial.effect]
            .parameter_names()
            .into_iter()
            .enumerate()
        {
            params.insert(name.clone(), Value::from(eval.theta[k]));
            params.insert(format!("{name}.sigma"), Value::from(eval.theta_sigma[k]));
        }
        Candidate {
            effect: self.name(&trial.effect),
            params,
            rms_after_m: eval.rms_after,
            heldout_rms_after_m: eval.heldout_ms.sqrt(),
            bic_delta: trial.bic_delta,
            p_value: trial.p_value,
            round,
            df: eval.df,
            chi2_drop: eval.chi2_drop,
            status,
            confounded_with,
        }
    }
}

/// Whitened effect columns at parameters `p`.
fn whitened_columns(effect: &dyn Effect, p: &DVector<f64>, sigma: &DVector<f64>) -> DMatrix<f64> {
    let mut a = effect.columns(p);
    for (i, s) in sigma.iter().enumerate() {
        a.row_mut(i).scale_mut(1.0 / s);
    }
    a
}

/// The `where` groups of whitened residuals `rw` with leverages `h`: each group's Σ r² tested
/// as χ² with Σ(1 − h) degrees of freedom, Bonferroni over the groups; those failing at
/// `alpha`, largest excess first, or, given `explained` (the accepted effects' fitted
/// contribution, whitened), largest share of it times its mean square first: where the effect
/// acts, not where the noise happens to add most.
fn locate(
    model: &dyn ResidualModel,
    rw: &DVector<f64>,
    raw: &DVector<f64>,
    leverage: &[f64],
    alpha: f64,
    explained: Option<&DVector<f64>>,
) -> Vec<WhereEntry> {
    let mut groups: BTreeMap<(&'static str, String), Vec<usize>> = BTreeMap::new();
    for (i, label) in model.labels().iter().enumerate() {
        for (g, key) in &label.groups {
            groups.entry((*g, key.clone())).or_default().push(i);
        }
    }
    let total: f64 = rw.norm_squared().max(f64::MIN_POSITIVE);
    let tests = groups.len().max(1) as f64;
    let mut out: Vec<(f64, WhereEntry)> = Vec::new();
    for ((group, key), members) in &groups {
        let ss: f64 = members.iter().map(|&i| rw[i] * rw[i]).sum();
        let dof: f64 = members.iter().map(|&i| (1.0 - leverage[i]).max(0.0)).sum();
        if dof < 0.5 {
            continue;
        }
        let p = (chi2_sf(ss, dof) * tests).min(1.0);
        if p < alpha {
            // In metres over the group's length residuals; radians when it has none.
            let labels = model.labels();
            let metres: Vec<usize> = members
                .iter()
                .copied()
                .filter(|&i| labels[i].unit == "m")
                .collect();
            let used = if metres.is_empty() { members } else { &metres };
            let rms =
                (used.iter().map(|&i| raw[i] * raw[i]).sum::<f64>() / used.len() as f64).sqrt();
            let rank = match explained {
                // Its share of the contribution times its concentration (mean square): a
                // sub-group ranks above its group only where the effect concentrates in it.
                Some(e) => {
                    members.iter().map(|&i| e[i] * e[i]).sum::<f64>().powi(2) / members.len() as f64
                }
                None => ss - dof,
            };
            out.push((
                rank,
                WhereEntry {
                    level: "residuals".into(),
                    group: group.to_string(),
                    key: key.clone(),
                    share: ss / total,
                    rms_m: rms,
                    p_value: p,
                },
            ));
        }
    }
    out.sort_by(|a, b| b.0.total_cmp(&a.0));
    out.into_iter().map(|(_, w)| w).collect()
}

fn rms_in_metres(model: &dyn ResidualModel, r: &DVector<f64>) -> f64 {
    let (mut ss, mut n) = (0.0, 0usize);
    for (v, l) in r.iter().zip(model.labels()) {
        if l.unit == "m" {
            ss += v * v;
            n += 1;
        }
    }
    (ss / n.max(1) as f64).sqrt()
}

/// Diagnose a kind's residual model.
pub fn diagnose(
    model: &dyn ResidualModel,
    options: &DiagnoseOptions,
) -> (Diagnosis, StandardisedResiduals) {
    let library = model.effects();
    // Units of work: the nominal fit, every round the selection may run, the final fit.
    let selection_end = 1 + selection_units(library.len());
    let mut progress = Counter::new(options.progress.as_ref(), selection_end + 1);
    let sigma = DVector::from_column_slice(model.sigma());
    let n = sigma.len();
    let start = model.start();
    let nominal = joint_fit(model, &[], &start);
    progress.tick(1);
    let p0 = nominal.params.clone();
    let mut x = model.jacobian(&p0);
    for (i, s) in sigma.iter().enumerate() {
        x.row_mut(i).scale_mut(1.0 / s);
    }
    let rw = nominal.residuals.component_div(&sigma);
    // Folds of the held-out groups: group g → fold g mod K.
    let groups: std::collections::BTreeSet<usize> =
        model.labels().iter().filter_map(|l| l.holdout).collect();
    let k_folds = options.folds.max(2).min(groups.len().max(1));
    let folds: Vec<Vec<usize>> = (0..k_folds)
        .map(|f| {
            (0..n)
                .filter(|&i| matches!(model.labels()[i].holdout, Some(g) if g % k_folds == f))
                .collect()
        })
        .collect();
    // The rows are whitened already: the held-out figures are in units of each σ.
    let engine = Engine {
        w: DVector::repeat(n, 1.0),
        r: rw.clone(),
        w_report: sigma.map(|s| 1.0 / s),
        folds,
    };
    let columns: Vec<DMatrix<f64>> = library
        .iter()
        .map(|e| whitened_columns(e.as_ref(), &p0, &sigma))
        .collect();
    let mut notes = vec![format!(
        "{n} residuals of kind {} against {} parameters; {} held-out groups in {k_folds} folds",
        model.kind(),
        p0.len(),
        groups.len()
    )];
    let blocks = model.local_blocks();
    let mut client = ResidualsClient {
        model,
        library: &library,
        x: &x,
        columns: &columns,
        sigma: &sigma,
        blocks: &blocks,
        nominal_leverages: std::sync::OnceLock::new(),
    };
    let Selection {
        accepted,
        confounded: confounded_set,
        records,
        gap_before,
        last_base: last,
        notes: selection_notes,
        ..
    } = forward::select(
        &client,
        &engine,
        None,
        &(0..library.len()).collect::<Vec<usize>>(),
        Start::default(),
        options.alpha,
        library.len(),
        &mut progress,
    );
    notes.extend(selection_notes);
    progress.advance_to(selection_end);
    // The final model: the model's parameters and the accepted effects fitted jointly.
    let accepted_effects: Vec<&dyn Effect> =
        accepted.iter().map(|&e| library[e].as_ref()).collect();
    let final_fit = if accepted.is_empty() {
        nominal.clone()
    } else {
        joint_fit(model, &accepted_effects, &p0)
    };
    let rw_after = final_fit.residuals.component_div(&sigma);
    let leverage = |fit: &JointFit| -> Vec<f64> {
        let mut design = model.jacobian(&fit.params);
        if !accepted.is_empty() {
            let a = accepted.iter().fold(DMatrix::zeros(n, 0), |d, &e| {
                concat(&d, &library[e].columns(&fit.params))
            });
            design = concat(&design, &a);
        }
        for (i, s) in sigma.iter().enumerate() {
            design.row_mut(i).scale_mut(1.0 / s);
        }
        ModelDesign::new(design, blocks.clone())
            .fit((0..n).collect())
            .leverages()
    };
    let nominal_leverage = client.nominal_leverages.take().unwrap_or_else(|| {
        ModelDesign::new(x.clone(), blocks.clone())
            .fit((0..n).collect())
            .leverages()
    });
    let explained =
        (!accepted.is_empty()).then(|| final_fit.effect_contribution.component_div(&sigma));
    let where_ = locate(
        model,
        &rw,
        &nominal.residuals,
        &nominal_leverage,
        options.alpha,
        explained.as_ref(),
    );
    let alpha_part = options.alpha / 2.0;
    let remaining = locate(
        model,
        &rw_after,
        &final_fit.residuals,
        &leverage(&final_fit),
        alpha_part,
        None,
    );
    let chi2_p = chi2_sf(final_fit.chi2, final_fit.dof.max(1) as f64);
    let unexplained = chi2_p < alpha_part || !remaining.is_empty();
    if unexplained {
        notes.push(format!(
            "after the selected effects: chi2/dof {:.2} (p = {chi2_p:.1e}), {} residual group(s) still fail the noise model{}",
            final_fit.chi2 / final_fit.dof.max(1) as f64,
            remaining.len(),
            remaining
                .first()
                .map(|w| format!(", largest {} {}", w.group, w.key))
                .unwrap_or_default()
        ));
    }
    let cv_after = last.unwrap_or_else(|| gap_before.clone());
    let gap_after = Gap {
        rms_m: rms_in_metres(model, &final_fit.residuals),
        heldout_rms_m: cv_after.heldout_rms_m,
        chi2_per_dof: final_fit.chi2 / final_fit.dof.max(1) as f64,
        heldout_floor_m: 1.0,
        heldout_ratio: cv_after.heldout_ratio,
    };
    let noise_floor_m = {
        let metres: Vec<f64> = model
            .labels()
            .iter()
            .zip(sigma.iter())
            .filter(|(l, _)| l.unit == "m")
            .map(|(_, s)| s * s)
            .collect();
        (metres.iter().sum::<f64>() / metres.len().max(1) as f64 * nominal.dof as f64 / n as f64)
            .sqrt()
    };
    let selected: Vec<String> = accepted
        .iter()
        .filter(|e| !confounded_set.contains(e))
        .map(|&e| library[e].name().to_string())
        .collect();
    // The calibration re-solved with the selected effects: its reported parameters ± σ.
    let names = model.parameter_names();
    let reported = model.reported_parameters();
    let (parameters_after, corrected) = if selected.is_empty() {
        (Vec::new(), None)
    } else {
        let after: Vec<ParameterAfter> = reported
            .iter()
            .map(|&j| ParameterAfter {
                name: names[j].clone(),
                nominal: nominal.params[j],
                nominal_sigma: nominal.sigma(j),
                corrected: final_fit.params[j],
                sigma: final_fit.sigma(j),
            })
            .collect();
        let count = after.len().max(1) as f64;
        let moved_m = (after
            .iter()
            .map(|a| (a.corrected - a.nominal).powi(2))
            .sum::<f64>()
            / count)
            .sqrt();
        let moved_sigma = (after
            .iter()
            .map(|a| ((a.corrected - a.nominal) / a.sigma.max(f64::MIN_POSITIVE)).powi(2))
            .sum::<f64>()
            / count)
            .sqrt();
        (
            after,
            Some(CorrectedCalibration {
                command: format!("geocal solve SESSION --effects {}", selected.join(",")),
                effects: selected.clone(),
                points_moved_rms_m: moved_m,
                points_moved_rms_sigma: moved_sigma,
            }),
        )
    };
    let selected_effects: Vec<&dyn Effect> = accepted
        .iter()
        .filter(|e| !confounded_set.contains(e))
        .map(|&e| library[e].as_ref())
        .collect();
    if !selected_effects.is_empty() {
        // The final fit's effects are the accepted ones; report the selected ones' estimates.
        let offset = p0.len();
        let fitted = effect_parameters(&accepted_effects, &final_fit, offset);
        for e in &selected_effects {
            if let Some(p) = fitted.get(e.name()) {
                notes.push(format!(
                    "{} fitted jointly with the calibration: {}",
                    e.name(),
                    p.iter()
                        .filter(|(k, _)| !k.ends_with(".sigma"))
                        .map(|(k, v)| format!("{k} {v:.4e} ± {:.1e}", p[&format!("{k}.sigma")]))
                        .collect::<Vec<_>>()
                        .join(", ")
                ));
            }
        }
    }
    let mut candidates: Vec<Candidate> = records.into_values().collect();
    forward::report_order(&mut candidates, &selected);
    let mut residual_units = BTreeMap::new();
    let mut coordinates: Vec<String> = Vec::new();
    for l in model.labels() {
        // A row's or a group's unit: radians only when every residual in it is an angle.
        for key in std::iter::once(&l.row).chain(l.groups.iter().map(|(_, k)| k)) {
            let unit = residual_units
                .entry(key.clone())
                .or_insert_with(|| l.unit.to_string());
            if unit != l.unit {
                *unit = "m".into();
            }
        }
        for (g, _) in &l.groups {
            if !coordinates.iter().any(|c| c == g) {
                coordinates.push(g.to_string());
            }
        }
    }
    let mut rows: Vec<String> = Vec::new();
    let lengths = model
        .labels()
        .iter()
        .enumerate()
        .map(|(i, l)| {
            let row = rows.iter().position(|r| *r == l.row).unwrap_or_else(|| {
                rows.push(l.row.clone());
                rows.len() - 1
            });
            StandardisedResidual {
                station: row,
                t_s: l.x,
                before: rw[i],
                after: rw_after[i],
            }
        })
        .collect();
    let residuals = StandardisedResiduals {
        station_ids: rows,
        lengths,
        final_effects: accepted
            .iter()
            .map(|&e| library[e].name().to_string())
            .collect(),
        x_axis: Some(model.x_axis().to_string()),
    };
    let diagnosis = Diagnosis {
        format: DIAGNOSIS_FORMAT.into(),
        session_id: model.session_id().to_string(),
        noise_floor_m,
        gap: gap_before,
        where_,
        candidates,
        selected,
        gap_after,
        unexplained,
        noise_scale: None,
        corrected,
        points_level: None,
        points_level_after: None,
        leave_one_station_out: Vec::new(),
        twin: None,
        observations: n,
        notes,
        model: Some(ModelDiagnosis {
            kind: model.kind().to_string(),
            residual_units,
            coordinates,
            x_axis: model.x_axis().to_string(),
            library: library.iter().map(|e| e.name().to_string()).collect(),
            parameters_after,
        }),
    };
    progress.finish();
    (diagnosis, residuals)
}
