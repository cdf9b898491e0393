//! Plan check before measuring: from the plan and the noise model alone, the standard
//! uncertainty of every station, homing distance and point, and what the plan cannot identify.

use nalgebra::{DMatrix, Vector3};
use serde::Serialize;

use crate::config::Config;
use crate::extract::NoiseModel;
use crate::plan::Plan;
use crate::solve::multilateration::{
    solve, LengthObservation, MultilaterationProblem, Segment, SolveError, SolveOptions,
};

/// Dense identifiability analysis (SVD of the whitened Jacobian) up to this many unknowns.
const MAX_DENSE_UNKNOWNS: usize = 3000;
/// Correlations above this (in absolute value) are reported.
const STRONG_CORRELATION: f64 = 0.95;
/// The strongest correlations reported, at most.
const MAX_REPORTED_PAIRS: usize = 20;
/// Rigid-motion freedom that lengths cannot fix (the datum).
const GAUGE_DOF: usize = 6;

#[derive(Debug, thiserror::Error)]
pub enum PlanCheckError {
    #[error("plan.stations[{0}]: the plan check predicts from hint_m; give every station a hint")]
    NoHint(usize),
    #[error("{0}")]
    Solve(#[from] SolveError),
}

#[derive(Debug, Clone, Serialize)]
pub struct PlanCheck {
    pub points: usize,
    pub stations: usize,
    pub targets: usize,
    pub observations: usize,
    pub unknowns: usize,
    /// Observations minus (unknowns - 6 datum freedoms).
    pub redundancy: i64,
    pub samples_per_dwell: usize,
    pub noise_model: NoiseModel,
    /// Empty when the plan cannot be adjusted at all (see warnings).
    pub station_sigmas: Vec<StationSigma>,
    pub point_sigma: Option<PointSigmaSummary>,
    /// Predicted sigma of every identifiable geometric error value, and what is unidentifiable.
    pub geometric_errors: Option<serde_json::Value>,
    pub identifiability: Identifiability,
    /// Things in the plan an engineer should fix before measuring.
    pub warnings: Vec<String>,
}

#[derive(Debug, Clone, Serialize)]
pub struct StationSigma {
    pub id: String,
    pub sigma_m: [f64; 3],
    /// One per target: the homing distance's sigma.
    pub home_distance_sigma_m: Vec<f64>,
}

#[derive(Debug, Clone, Serialize)]
pub struct PointSigmaSummary {
    /// RMS over points of each coordinate's sigma.
    pub rms_sigma_m: [f64; 3],
    pub max_sigma_m: [f64; 3],
    /// The point (target, index) with the largest sigma.
    pub worst_point: (String, usize),
    pub per_point: Vec<PointSigma>,
}

#[derive(Debug, Clone, Serialize)]
pub struct PointSigma {
    pub target: String,
    pub point: usize,
    pub sigma_m: [f64; 3],
}

#[derive(Debug, Clone, Serialize)]
pub struct Identifiability {
    /// False when the problem was too large for the dense analysis (the sigmas above stand).
    pub analysed: bool,
    pub rank: usize,
    pub unknowns: usize,
    /// Rank missing beyond the 6 datum freedoms; 0 for a plan that identifies everything.
    pub deficiency: usize,
    /// Ratio of the largest to the smallest singular value that the datum leaves (whitened).
    pub condition_number: f64,
    /// Parameters that dominate the directions the plan cannot see.
    pub unidentifiable: Vec<String>,
    pub correlated_pairs: Vec<CorrelatedPair>,
}

#[derive(Debug, Clone, Serialize)]
pub struct CorrelatedPair {
    pub a: String,
    pub b: String,
    pub correlation: f64,
}

/// A multilateration problem whose lengths are exact at the nominal geometry (stations at
/// their hints): its solution's covariance is the Cramér–Rao bound the plan predicts.
struct NominalProblem {
    problem: MultilaterationProblem,
    /// (target id, plan point) of each problem point.
    points: Vec<(String, usize)>,
    /// Names of the unknowns in the dense order: stations, homing distances, points.
    names: Vec<String>,
}

fn nominal_problem(
    config: &Config,
    plan: &Plan,
) -> Result<(NominalProblem, usize, NoiseModel), PlanCheckError> {
    let tracer = &config.devices.tracer;
    let noise = tracer.noise_model();
    let samples = ((plan.dwell_s * tracer.sample_rate_hz).floor() as usize).max(1);
    let stations: Vec<Vector3<f64>> = plan
        .stations
        .iter()
        .enumerate()
        .map(|(i, s)| s.hint_m.map(Vector3::from).ok_or(PlanCheckError::NoHint(i)))
        .collect::<Result<_, _>>()?;
    let mut names: Vec<String> = plan
        .stations
        .iter()
        .flat_map(|s| ["x", "y", "z"].map(|c| format!("station {} {c}", s.id)))
        .collect();
    let mut nominal_points = Vec::new();
    let mut points = Vec::new();
    for target in &plan.targets {
        for p in &plan.points {
            nominal_points.push(Vector3::from(plan.nominal_m(p.index, target)));
            points.push((target.id.clone(), p.index));
        }
    }
    let n = plan.points.len();
    let mut segments = Vec::new();
    let mut observations = Vec::new();
    for (j, station) in stations.iter().enumerate() {
        for (t, target) in plan.targets.iter().enumerate() {
            let segment = segments.len();
            segments.push(Segment { station: j });
            names.push(format!(
                "home distance {} {}",
                plan.stations[j].id, target.id
            ));
            let home = (station - nominal_points[t * n]).norm();
            for i in 0..n {
                let beam_m = (station - nominal_points[t * n + i]).norm();
                let length_m = beam_m - home;
                let sigma_m = noise.sample_sigma_m(beam_m) / (samples as f64).sqrt();
                // Every pass measures every point once more.
                for _ in &plan.passes {
                    observations.push(LengthObservation {
                        point: t * n + i,
                        segment,
                        length_m,
                        sigma_m,
                        path_sigma: None,
                    });
                }
            }
        }
    }
    names.extend(
        points
            .iter()
            .flat_map(|(t, i)| ["x", "y", "z"].map(|c| format!("point {t}/{i} {c}"))),
    );
    Ok((
        NominalProblem {
            problem: MultilaterationProblem {
                nominal_points,
                station_hints: stations.into_iter().map(Some).collect(),
                segments,
                observations,
            },
            points,
            names,
        },
        samples,
        noise,
    ))
}

/// Predict the uncertainties of a plan and name what it cannot identify.
pub fn check(config: &Config, plan: &Plan) -> Result<PlanCheck, PlanCheckError> {
    let (nominal, samples, noise) = nominal_problem(config, plan)?;
    let problem = &nominal.problem;
    let unknowns = nominal.names.len();
    let identifiability = identifiability(&nominal);
    let mut warnings = Vec::new();
    if identifiability.deficiency > 0 {
        warnings.push(format!(
            "the plan cannot identify {} direction(s) beyond the datum: {}",
            identifiability.deficiency,
            identifiability.unidentifiable.join(", ")
        ));
    }
    // Stillstand must not mistake noise for motion: ~6 sigma peak to peak at the longest beam.
    let longest_m = problem
        .observations
        .iter()
        .map(|o| {
            let station = problem.station_hints[problem.segments[o.segment].station];
            station.map_or(0.0, |s| (s - problem.nominal_points[o.point]).norm())
        })
        .fold(0.0, f64::max);
    let noise_p2p_m = 6.0 * noise.sample_sigma_m(longest_m);
    if plan.stillstand_tolerance_m < noise_p2p_m {
        warnings.push(format!(
            "plan.stillstand.tolerance_m = {:.2e} m is below 6 sigma of the tracer noise at the longest beam ({longest_m:.2} m): {noise_p2p_m:.2e} m; noise will delay and shorten settled windows",
            plan.stillstand_tolerance_m
        ));
    }
    let (station_sigmas, point_sigma, geometric_errors) =
        match solve(problem, &SolveOptions::default()) {
            Ok(solution) => {
                let (stations, points) = sigmas(plan, &nominal, &solution);
                let geometric = match predicted_geometric_errors(config, plan, &nominal, &solution)
                {
                    Ok(g) => Some(g),
                    Err(why) => {
                        warnings.push(format!("no geometric error prediction: {why}"));
                        None
                    }
                };
                (stations, points, geometric)
            }
            Err(e) => {
                warnings.push(format!(
                    "no uncertainties: the adjustment of this plan fails: {e}"
                ));
                (Vec::new(), None, None)
            }
        };
    Ok(PlanCheck {
        points: plan.points.len(),
        stations: plan.stations.len(),
        targets: plan.targets.len(),
        observations: problem.observations.len(),
        unknowns,
        redundancy: problem.observations.len() as i64 - (unknowns as i64 - GAUGE_DOF as i64),
        samples_per_dwell: samples,
        noise_model: noise,
        station_sigmas,
        point_sigma,
        geometric_errors,
        identifiability,
        warnings,
    })
}

/// The standard uncertainty of each of the 21 geometric error values this plan would give
/// (weighted least squares at the nominal geometry with the predicted point covariance), and
/// the errors it cannot identify.
fn predicted_geometric_errors(
    config: &Config,
    plan: &Plan,
    nominal: &NominalProblem,
    solution: &crate::solve::multilateration::MultilaterationSolution,
) -> Result<serde_json::Value, String> {
    use crate::solve::geometric_errors::{
        decompose_correlated, grid_from_points, DecompositionOptions, PointObservation, Route,
    };
    let structure = crate::model::kinematics::Structure::parse(&config.machine.structure)
        .map_err(|e| e.to_string())?;
    let observations: Vec<PointObservation> = nominal
        .points
        .iter()
        .zip(&solution.point_covariance)
        .map(|((target, point), covariance)| PointObservation {
            axes_m: plan.points[*point].axes_m,
            target_offset_m: config.target_offset(target).unwrap_or([0.0; 3]),
            error_m: [0.0; 3],
            covariance: *covariance,
        })
        .collect();
    let full = crate::solve::multilateration::dense_point_covariance(&nominal.problem, solution);
    let options = DecompositionOptions {
        route: Some(Route::WeightedLeastSquares),
        ..DecompositionOptions::default()
    };
    let grid = grid_from_points(&observations, options.grid_tolerance_m);
    let result = decompose_correlated(&structure, &grid, &observations, full.as_ref(), &options)
        .map_err(|e| e.to_string())?;
    let mut value = serde_json::to_value(&result).map_err(|e| e.to_string())?;
    if let Some(notes) = value["notes"].as_array_mut() {
        notes.push(serde_json::Value::from(
            "prediction by weighted least squares: an error that is identifiable only in \
             combination with another (the results then report the combination, marked \
             `absorbs`) is listed as unidentifiable here",
        ));
    }
    // Only the sigmas and the identifiability are predictions; the zero values are not.
    strip_values(&mut value);
    Ok(value)
}

/// Remove estimate fields (`values`, `value_rad`, residuals) from a predicted decomposition.
fn strip_values(value: &mut serde_json::Value) {
    match value {
        serde_json::Value::Object(map) => {
            for key in [
                "values",
                "value_rad",
                "residual_rms_m",
                "chi2_per_dof",
                "rigid_motion",
            ] {
                map.remove(key);
            }
            map.values_mut().for_each(strip_values);
        }
        serde_json::Value::Array(items) => items.iter_mut().for_each(strip_values),
        _ => {}
    }
}

fn sigmas(
    plan: &Plan,
    nominal: &NominalProblem,
    solution: &crate::solve::multilateration::MultilaterationSolution,
) -> (Vec<StationSigma>, Option<PointSigmaSummary>) {
    let sigma3 =
        |q: &nalgebra::Matrix3<f64>| [q[(0, 0)].sqrt(), q[(1, 1)].sqrt(), q[(2, 2)].sqrt()];
    let targets = plan.targets.len();
    let station_sigmas = plan
        .stations
        .iter()
        .enumerate()
        .map(|(j, s)| StationSigma {
            id: s.id.clone(),
            sigma_m: sigma3(&solution.station_covariance[j]),
            home_distance_sigma_m: (0..targets)
                .map(|t| solution.segment_distance_sigma_m[j * targets + t])
                .collect(),
        })
        .collect();
    let per_point: Vec<PointSigma> = nominal
        .points
        .iter()
        .zip(&solution.point_covariance)
        .map(|((target, point), q)| PointSigma {
            target: target.clone(),
            point: *point,
            sigma_m: sigma3(q),
        })
        .collect();
    let count = per_point.len().max(1) as f64;
    let rms_sigma_m = [0, 1, 2]
        .map(|k| (per_point.iter().map(|p| p.sigma_m[k].powi(2)).sum::<f64>() / count).sqrt());
    let max_sigma_m = [0, 1, 2].map(|k| per_point.iter().map(|p| p.sigma_m[k]).fold(0.0, f64::max));
    let worst_point = per_point
        .iter()
        .max_by(|a, b| norm3(&a.sigma_m).total_cmp(&norm3(&b.sigma_m)))
        .map_or((String::new(), 0), |p| (p.target.clone(), p.point));
    (
        station_sigmas,
        Some(PointSigmaSummary {
            rms_sigma_m,
            max_sigma_m,
            worst_point,
            per_point,
        }),
    )
}

fn norm3(v: &[f64; 3]) -> f64 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}

/// Whitened Jacobian at the nominal geometry, columns in `NominalProblem::names` order.
fn whitened_jacobian(nominal: &NominalProblem) -> DMatrix<f64> {
    let problem = &nominal.problem;
    let m = problem.station_hints.len();
    let s = problem.segments.len();
    let cols = nominal.names.len();
    let mut jac = DMatrix::zeros(problem.observations.len(), cols);
    for (row, obs) in problem.observations.iter().enumerate() {
        let j = problem.segments[obs.segment].station;
        let station = problem.station_hints[j].unwrap_or_default();
        let point = problem.nominal_points[obs.point];
        // Predicted length |P - X| - d: d/dP = u, d/dX = -u, d/dd = -1.
        let u = (station - point).normalize() / obs.sigma_m;
        for k in 0..3 {
            jac[(row, 3 * j + k)] = u[k];
            jac[(row, 3 * m + s + 3 * obs.point + k)] = -u[k];
        }
        jac[(row, 3 * m + obs.segment)] = -1.0 / obs.sigma_m;
    }
    jac
}

fn identifiability(nominal: &NominalProblem) -> Identifiability {
    let unknowns = nominal.names.len();
    let not_analysed = Identifiability {
        analysed: false,
        rank: 0,
        unknowns,
        deficiency: 0,
        condition_number: f64::NAN,
        unidentifiable: Vec::new(),
        correlated_pairs: Vec::new(),
    };
    if unknowns > MAX_DENSE_UNKNOWNS {
        return not_analysed;
    }
    let svd = whitened_jacobian(nominal).svd(false, true);
    let Some(v_t) = svd.v_t else {
        return not_analysed;
    };
    let mut order: Vec<usize> = (0..svd.singular_values.len()).collect();
    order.sort_by(|&a, &b| svd.singular_values[b].total_cmp(&svd.singular_values[a]));
    let largest = order.first().map_or(0.0, |&i| svd.singular_values[i]);
    let tolerance = largest * 1e-9 * unknowns as f64;
    let rank = order
        .iter()
        .filter(|&&i| svd.singular_values[i] > tolerance)
        .count();
    let deficiency = unknowns.saturating_sub(rank).saturating_sub(GAUGE_DOF);
    // Smallest singular value the datum leaves: the (unknowns - 6)-th largest.
    let kept = unknowns.saturating_sub(GAUGE_DOF).min(order.len());
    let smallest = if kept > 0 {
        svd.singular_values[order[kept - 1]]
    } else {
        0.0
    };
    let condition_number = if smallest > 0.0 {
        largest / smallest
    } else {
        f64::INFINITY
    };

    // Directions beyond the datum that the data cannot see: name their dominant parameters.
    let mut unidentifiable = Vec::new();
    for &i in order.iter().skip(rank).take(deficiency) {
        let row = v_t.row(i);
        let (col, _) = row.iter().enumerate().fold((0, 0.0f64), |best, (c, v)| {
            if v.abs() > best.1 {
                (c, v.abs())
            } else {
                best
            }
        });
        if !unidentifiable.contains(&nominal.names[col]) {
            unidentifiable.push(nominal.names[col].clone());
        }
    }

    // Correlations among stations and homing distances, in the minimum-norm datum.
    let station_cols = 3 * nominal.problem.station_hints.len() + nominal.problem.segments.len();
    let mut covariance = DMatrix::zeros(station_cols, station_cols);
    for &i in order.iter().take(rank) {
        let s2 = svd.singular_values[i].powi(2);
        let v = v_t.row(i).columns(0, station_cols).transpose();
        covariance += &v * v.transpose() / s2;
    }
    let mut correlated_pairs = Vec::new();
    for a in 0..station_cols {
        for b in (a + 1)..station_cols {
            let denom = (covariance[(a, a)] * covariance[(b, b)]).sqrt();
            if denom > 0.0 {
                let rho = covariance[(a, b)] / denom;
                if rho.abs() > STRONG_CORRELATION {
                    correlated_pairs.push(CorrelatedPair {
                        a: nominal.names[a].clone(),
                        b: nominal.names[b].clone(),
                        correlation: rho,
                    });
                }
            }
        }
    }
    correlated_pairs.sort_by(|x, y| y.correlation.abs().total_cmp(&x.correlation.abs()));
    correlated_pairs.truncate(MAX_REPORTED_PAIRS);
    Identifiability {
        analysed: true,
        rank,
        unknowns,
        deficiency,
        condition_number,
        unidentifiable,
        correlated_pairs,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const DEMO: &str = include_str!("../../config/demo-multilateration.toml");

    fn check_text(text: &str) -> PlanCheck {
        let config = Config::parse(text, std::path::Path::new("test.toml")).expect("config");
        check(&config, &Plan::from_config(&config)).expect("plan check")
    }

    #[test]
    fn demo_plan_identifies_everything() {
        let c = check_text(DEMO);
        assert!(c.identifiability.analysed);
        assert_eq!(
            c.identifiability.deficiency, 0,
            "{:?}",
            c.identifiability.unidentifiable
        );
        assert_eq!(c.identifiability.rank, c.unknowns - GAUGE_DOF);
        assert!(c.warnings.is_empty(), "{:?}", c.warnings);
        assert_eq!(c.samples_per_dwell, 50);
        // Sub-micrometre everywhere for this plan and noise.
        let geometric = c
            .geometric_errors
            .as_ref()
            .expect("geometric error prediction");
        // One offset: the four rotations of ref1 cannot be seen (and the errors they mix
        // with only in combination); the rest carry a sigma.
        let unidentifiable: Vec<&str> = geometric["unidentifiable"]
            .as_array()
            .expect("list")
            .iter()
            .filter_map(|v| v.as_str())
            .collect();
        for name in ["ECX", "EAZ", "EBZ", "ECZ"] {
            assert!(unidentifiable.contains(&name), "{unidentifiable:?}");
        }
        let exx = geometric["axes"]["x"]["errors"]["EXX"]["sigma"][1]
            .as_f64()
            .expect("sigma");
        assert!(exx > 0.0 && exx < 1e-6, "EXX sigma {exx}");
        let points = c.point_sigma.expect("sigmas");
        assert!(points.max_sigma_m.iter().all(|s| *s > 0.0 && *s < 1e-6));
    }

    #[test]
    fn three_offsets_off_one_line_identify_all_21_errors() {
        let text = DEMO
            .replace(
                "targets = [{ id = \"t0\", offset_m = [0.0, 0.0, -0.12] }]",
                "targets = [{ id = \"t0\", offset_m = [0.0, 0.0, -0.12] }, { id = \"t1\", offset_m = [0.15, 0.10, -0.12] }, { id = \"t2\", offset_m = [-0.10, 0.12, -0.20] }]",
            )
            .replace("targets = [\"t0\"]", "targets = [\"t0\", \"t1\", \"t2\"]");
        let c = check_text(&text);
        let geometric = c.geometric_errors.expect("geometric error prediction");
        assert_eq!(geometric["unidentifiable"], serde_json::json!([]));
        assert!(c.warnings.is_empty(), "{:?}", c.warnings);
    }

    #[test]
    fn stations_in_the_plane_of_the_points_leave_heights_unidentified() {
        // One layer of points at z = 0.5 (offset 0) and every station in that plane too.
        let mut text = DEMO
            .replace(
                "z = { from = 0.15, to = 0.95, count = 4 }",
                "z = { from = 0.5, to = 0.5, count = 1 }",
            )
            .replace("offset_m = [0.0, 0.0, -0.12]", "offset_m = [0.0, 0.0, 0.0]");
        for (old, new) in [
            ("[-0.15, -0.10, -0.30]", "[-0.15, -0.10, 0.5]"),
            ("[1.55, 0.05, -0.15]", "[1.55, 0.05, 0.5]"),
            ("[1.50, 2.55, -0.35]", "[1.50, 2.55, 0.5]"),
            ("[-0.10, 2.45, -0.05]", "[-0.10, 2.45, 0.5]"),
            ("[0.70, 1.20, -0.40]", "[0.70, 3.20, 0.5]"),
        ] {
            assert!(text.contains(old));
            text = text.replace(old, new);
        }
        let c = check_text(&text);
        assert!(c.identifiability.deficiency > 0);
        assert!(
            c.identifiability
                .unidentifiable
                .iter()
                .all(|n| n.ends_with(" z")),
            "{:?}",
            c.identifiability.unidentifiable
        );
        assert!(
            c.warnings.iter().any(|w| w.contains("cannot identify")),
            "{:?}",
            c.warnings
        );
    }

    #[test]
    fn a_stillstand_tolerance_below_the_noise_is_flagged() {
        let c = check_text(&DEMO.replace("tolerance_m = 5e-6", "tolerance_m = 5e-7"));
        assert!(
            c.warnings
                .iter()
                .any(|w| w.contains("plan.stillstand.tolerance_m")),
            "{:?}",
            c.warnings
        );
    }
}
