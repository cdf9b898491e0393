//! The calibration with named effects modelled (`geocal solve --effects`): their parameters
//! fitted jointly with the geometry (the diagnosis's final model), the lengths corrected by
//! their contribution, and the covariance their uncertainty adds to the points.

use std::collections::BTreeMap;
use std::sync::Arc;

use nalgebra::{DMatrix, DVector, Matrix6, Vector3, Vector6};

use super::data::Data;
use super::effects::{known_names, EffectKind, EffectModel, Geometry, Library};
use super::fit::Fit;
use super::locate::best_step;
use super::schur::Design;
use super::{joint_fit, DiagnoseError};
use crate::extract::SettledDwells;
pub use crate::method::effects::EffectCorrection;
use crate::method::effects::EffectsFit;
use crate::solve::multilateration::{generator, solve, SolveOptions};

#[derive(Debug, thiserror::Error)]
pub enum CorrectionError {
    #[error("{0}")]
    Name(String),
    #[error(
        "effect `{0}` cannot be modelled in the calibration: {1}; use `geocal diagnose` to test it"
    )]
    Unsupported(&'static str, &'static str),
    #[error(transparent)]
    Diagnose(#[from] DiagnoseError),
    #[error("effects fit: {0}")]
    Fit(String),
}

/// Parse a comma-separated list of effect names (unknown names list the known ones: every
/// plan kind's library). Whether the session's kind models a name is decided at the fit.
pub fn parse_effects(names: &[String]) -> Result<Option<Arc<dyn EffectsFit>>, CorrectionError> {
    let known = known_names();
    let mut chosen: Vec<&'static str> = Vec::new();
    for name in names.iter().flat_map(|n| n.split(',')) {
        let name = name.trim();
        if name.is_empty() {
            continue;
        }
        let Some(&known_name) = known.iter().find(|k| **k == name) else {
            return Err(CorrectionError::Name(format!(
                "unknown effect `{name}`; known effects: {}",
                known.join(", ")
            )));
        };
        if let Some(why) = unsupported(known_name) {
            return Err(why);
        }
        if !chosen.contains(&known_name) {
            chosen.push(known_name);
        }
    }
    Ok(fit_named(chosen))
}

/// Why an effect of the libraries cannot be modelled in the calibration, if it cannot.
fn unsupported(name: &'static str) -> Option<CorrectionError> {
    let why = match name {
        "settling" => "its bias is fitted on the raw samples inside the dwell windows, not on the settled lengths",
        "target_offset" => "the free points of the calibration absorb it (it is seen only at the points level)",
        _ => return None,
    };
    Some(CorrectionError::Unsupported(name, why))
}

/// Effect parameters whose responses are solved together.
const SOLVED_TOGETHER: usize = 4;

/// Fit `kinds` jointly with the geometry of a multilateration session (its settled windows).
pub fn correction(
    settled: &SettledDwells,
    kinds: &[EffectKind],
) -> Result<EffectCorrection, CorrectionError> {
    let names: Vec<&'static str> = kinds.iter().map(|k| k.name()).collect();
    correction_named(settled, &names)
}

/// Fit the effects called `names` (of the session's kind's library) jointly with the geometry
/// of a tracer-network session (its settled windows).
pub fn correction_named(
    settled: &SettledDwells,
    names: &[&'static str],
) -> Result<EffectCorrection, CorrectionError> {
    let data = Data::of_dwells(settled).map_err(DiagnoseError::from)?;
    let library = Library::of(&data);
    let nominal = solve(&data.problem, &SolveOptions::default()).map_err(DiagnoseError::from)?;
    let geom = Geometry::from_solution(&nominal);
    let nobs = data.obs.len();
    let w = DVector::from_iterator(nobs, data.obs.iter().map(|o| 1.0 / o.sigma_m));
    let stations_effect = library.network.and_then(|n| n.stations_effect());
    let models: Vec<EffectModel> = names
        .iter()
        .map(|&name| {
            if Some(name) == stations_effect {
                return Err(CorrectionError::Unsupported(
                    name,
                    "it moves the table stations off their circle, not the lengths, and leaves the step angles as they are (its tangential part is the step angle itself); `geocal diagnose` fits it on the stations and reports its parameters",
                ));
            }
            let model = library.model(name).map_err(CorrectionError::Name)?;
            if model.kind != EffectKind::LengthStep {
                return Ok(model);
            }
            // The step's place: the best change point of any pass in the nominal residuals
            // (the names are distinct: one step, one nominal fit).
            let nominal_basis =
                Fit::new(Arc::new(Design::nominal(&data, &geom)), (0..nobs).collect());
            let r = DVector::from_fn(nobs, |i, _| nominal.residuals_m[i] * w[i]);
            let res_w = nominal_basis.project_off_vec(&r);
            let (g, k, _, _) = best_step(&data, &nominal_basis, &res_w, None)
                .ok_or_else(|| CorrectionError::Fit("no pass to place a length step in".into()))?;
            Ok(EffectModel {
                step: Some((g, k)),
                ..model
            })
        })
        .collect::<Result<_, CorrectionError>>()?;
    // A model linearised about its own parameters (the eccentricity's shared size) is
    // fitted free first, then at that estimate, then once more at the refined one.
    let mut models: Vec<EffectModel> = models;
    let mut fit = joint_fit(&data, &geom, &models);
    for _ in 0..2 {
        let refined = EffectModel::all_linearised_at(&models, &data, fit.theta.as_slice());
        if !refined.iter().any(EffectModel::is_linearised) {
            break;
        }
        models = refined;
        fit = joint_fit(&data, &geom, &models);
    }
    let np = fit.geom.len();
    let parameters = fit.theta.len();
    // Covariance of the effects' parameters: their block of the joint pseudo-inverse.
    let effect_cols: Vec<usize> = (np..np + parameters).collect();
    let theta_cov = fit.basis.pinv_block(&effect_cols);
    if (0..parameters).any(|c| theta_cov[(c, c)] <= 0.0) {
        return Err(CorrectionError::Fit(
            "an effect parameter is not identifiable from these lengths (the geometry absorbs it)"
                .into(),
        ));
    }
    let mut effects: BTreeMap<String, BTreeMap<String, f64>> = BTreeMap::new();
    let mut column = 0;
    for model in &models {
        let entry = effects.entry(model.kind.name().to_string()).or_default();
        for name in model.param_names(&data) {
            entry.insert(name.clone(), fit.theta[column]);
            entry.insert(format!("{name}.sigma"), theta_cov[(column, column)].sqrt());
            column += 1;
        }
    }
    // How each parameter moves the points when the lengths are corrected by its column
    // (the geometry's least-squares response, S-transformed to the points' datum); the
    // columns are the joint fit's, at its geometry.
    let design = fit.basis.design();
    let geometry_basis = Fit::new(
        Arc::new(Design::nominal(&data, &fit.geom)),
        (0..nobs).collect(),
    );
    let (n, m) = (fit.geom.points.len(), fit.geom.stations.len());
    let mut response = DMatrix::zeros(3 * n, parameters);
    let mut station_response = DMatrix::zeros(3 * m, parameters);
    // The parameters' columns solved a group at a time (one walk over the lengths per step
    // for the group; a group's right-hand sides and residuals in memory, not all of them),
    // the groups on the cores.
    let all: Vec<usize> = (0..parameters).collect();
    let groups: Vec<&[usize]> = all.chunks(SOLVED_TOGETHER).collect();
    let solved =
        crate::parallel::in_groups(&groups, crate::parallel::threads(groups.len()), |group| {
            let mut a_w = DMatrix::zeros(nobs, group.len());
            let mut row = vec![0.0; parameters];
            for i in 0..nobs {
                design.effect_row_into(i, &mut row);
                for (k, &c) in group.iter().enumerate() {
                    a_w[(i, k)] = row[c] * w[i];
                }
            }
            geometry_basis.solve_columns(a_w)
        });
    for (steps, group) in solved.iter().zip(&groups) {
        for (step, &c) in steps.column_iter().zip(group.iter()) {
            let (moved, stations) = without_rigid_motion(
                &data,
                &step.as_slice()[..3 * n],
                &fit.geom.stations,
                &step.as_slice()[3 * n..3 * n + 3 * m],
            );
            response.column_mut(c).copy_from(&moved);
            station_response.column_mut(c).copy_from(&stations);
        }
    }
    let station_covariance_m2 = &station_response * &theta_cov * station_response.transpose();
    Ok(EffectCorrection {
        length_correction_m: fit.effect_m,
        effects,
        parameters,
        point_response: response,
        parameter_covariance: theta_cov,
        station_covariance_m2,
    })
}

/// Point displacements (3n, point-major) with their best-fit rigid motion about the nominal
/// points' centre taken off: the inner-constraint datum the calibration reports points in;
/// the stations' displacements (3m) with the same rigid motion taken off.
fn without_rigid_motion(
    data: &Data,
    moved: &[f64],
    stations: &[Vector3<f64>],
    stations_moved: &[f64],
) -> (DVector<f64>, DVector<f64>) {
    let nominal: Vec<Vector3<f64>> = data.problem.nominal_points.clone();
    let centre = nominal.iter().sum::<Vector3<f64>>() / nominal.len().max(1) as f64;
    let mut normal = Matrix6::<f64>::zeros();
    let mut rhs = Vector6::<f64>::zeros();
    for (i, p) in nominal.iter().enumerate() {
        let g = generator(p, &centre);
        let d = Vector3::new(moved[3 * i], moved[3 * i + 1], moved[3 * i + 2]);
        normal += g.transpose() * g;
        rhs += g.transpose() * d;
    }
    let motion = normal
        .try_inverse()
        .map_or(Vector6::zeros(), |inv| inv * rhs);
    let points = DVector::from_fn(moved.len(), |k, _| {
        let g = generator(&nominal[k / 3], &centre);
        moved[k] - (g * motion)[k % 3]
    });
    let stations = DVector::from_fn(stations_moved.len(), |k, _| {
        let g = generator(&stations[k / 3], &centre);
        stations_moved[k] - (g * motion)[k % 3]
    });
    (points, stations)
}

/// The diagnosis's effect models as the solve fits them (`SolveSettings::effects`): None when
/// no effect is named.
pub fn fit(kinds: Vec<EffectKind>) -> Option<Arc<dyn EffectsFit>> {
    fit_named(kinds.into_iter().map(|k| k.name()).collect())
}

/// As [`fit`], by name (of the session's kind's library).
pub fn fit_named(names: Vec<&'static str>) -> Option<Arc<dyn EffectsFit>> {
    (!names.is_empty()).then(|| Arc::new(FittedEffects(names)) as Arc<dyn EffectsFit>)
}

/// Effects of the session's kind's library, fitted jointly with the geometry.
#[derive(Debug)]
pub struct FittedEffects(pub Vec<&'static str>);

impl EffectsFit for FittedEffects {
    fn names(&self) -> Vec<&'static str> {
        self.0.clone()
    }

    fn correction(
        &self,
        settled: &SettledDwells,
    ) -> Result<EffectCorrection, Box<dyn std::error::Error + Send + Sync>> {
        correction_named(settled, &self.0).map_err(Into::into)
    }
}
