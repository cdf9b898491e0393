//! Multilateration method: settled point lengths from the session, the station/point
//! adjustment, and the geocal-results/1 record of stations and point errors.

use std::collections::BTreeMap;

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use crate::solve::misfit::Misfit;

use crate::extract::{
    extract_points, ExtractOptions, Extraction, LengthMeasurement, LengthStream, Lengths,
    NoiseModel, SettledDwells, SettledSession,
};
use crate::method::SolveSettings;
use crate::model::kinematics::Structure;
use crate::session::messages::{MachineInfo, RunEvent, SessionHeader};
use crate::session::reader::{DamagedChunk, KeepingEvents, Session};
use crate::solve::geometric_errors::{
    decompose_correlated, grid_from_points, DecompositionOptions, PointObservation,
};
use crate::solve::multilateration::dense_point_covariance;
use crate::solve::multilateration::{
    solve as adjust, LengthObservation, MultilaterationProblem, MultilaterationSolution, Segment,
    SolveError, SolveOptions,
};
use crate::solve::robust::solve_huber;

pub const RESULTS_FORMAT: &str = "geocal-results/1";

#[derive(Debug, thiserror::Error)]
pub enum MultilaterationError {
    #[error("point extraction: {0}")]
    Extract(#[from] crate::extract::points::ExtractError),
    #[error("no settled point windows in the session ({dropped} dropped)")]
    NoPoints { dropped: usize },
    #[error(transparent)]
    Effects(Box<dyn std::error::Error + Send + Sync>),
    #[error("multilateration: {0}")]
    Solve(#[from] SolveError),
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct MultilaterationResults {
    pub format: String,
    pub kind: String,
    pub session_id: String,
    pub residual_rms_m: f64,
    pub chi2_per_dof: f64,
    pub dof: usize,
    pub iterations: usize,
    pub converged: bool,
    /// How the datum (position and orientation) was fixed.
    pub gauge: String,
    /// Where the observation sigmas came from.
    pub noise_model: String,
    pub stations: Vec<StationResult>,
    pub points: Vec<PointResult>,
    pub extraction: ExtractionSummary,
    /// The 21 geometric errors of the machine from the volumetric errors, when the plan allows
    /// (see docs/kinematics.md, "Decomposition"); null with a note otherwise.
    pub geometric_errors: Option<serde_json::Value>,
    /// What the engineer should know about how these results were obtained.
    pub notes: Vec<String>,
    /// The unmodelled effects fitted jointly with the geometry (`geocal solve --effects`):
    /// effect → parameter → value, with `<parameter>.sigma` beside each (SI units).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub effects: BTreeMap<String, BTreeMap<String, f64>>,
    /// Present when a robust loss was used: what it down-weighted.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub robust: Option<RobustReport>,
    /// Present when χ²/dof is improbable for its degrees of freedom (p < 1e-3): the σ are
    /// then not trustworthy; `sigma_scale` = √(χ²/dof) (docs/uncertainty.md, "Misfit").
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub misfit: Option<crate::solve::misfit::Misfit>,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct RobustReport {
    pub loss: String,
    pub threshold_sigma: f64,
    pub rounds: usize,
    /// Observations with weight < 1, largest normalised residual first.
    pub downweighted: Vec<DownWeighted>,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct DownWeighted {
    pub station: String,
    pub target: String,
    pub point: usize,
    pub pass: usize,
    pub weight: f64,
    pub residual_m: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct StationResult {
    pub id: String,
    pub position_m: [f64; 3],
    /// |P - A_0| of the first beam segment (first target).
    pub home_distance_m: f64,
    pub sigma_m: [f64; 3],
    pub segments: Vec<SegmentResult>,
    pub observations: usize,
    pub residual_rms_m: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct SegmentResult {
    pub target: String,
    pub beam_segment: u32,
    pub home_distance_m: f64,
    pub sigma_m: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct PointResult {
    pub point: usize,
    pub target: String,
    pub nominal_m: [f64; 3],
    pub actual_m: [f64; 3],
    pub error_m: [f64; 3],
    pub sigma_m: [f64; 3],
    pub observations: usize,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct ExtractionSummary {
    pub tracer: String,
    pub windows_used: usize,
    pub windows_dropped: usize,
    /// Windows cut short by a beam break and measured again after re-homing.
    #[serde(default)]
    pub windows_repeated: usize,
    /// Why windows were dropped, with counts.
    pub dropped_reasons: BTreeMap<String, usize>,
    pub samples_used: usize,
    /// Chunks of the session file that could not be read (their windows are dropped).
    #[serde(default)]
    pub damaged_chunks: Vec<DamagedChunk>,
}

fn arr(v: &Vector3<f64>) -> [f64; 3] {
    [v.x, v.y, v.z]
}

/// Solve a multilateration session.
pub fn solve(
    session: &Session,
    settings: &SolveSettings,
) -> Result<MultilaterationResults, MultilaterationError> {
    Ok(solve_detailed(session, settings)?.0)
}

/// Solve a multilateration session; also return the adjustment itself (for methods built on
/// it that need more than the results record, e.g. the stations' joint covariance). Station
/// `j` of the solution is `results.stations[j]`.
pub fn solve_detailed(
    session: &Session,
    settings: &SolveSettings,
) -> Result<(MultilaterationResults, MultilaterationSolution), MultilaterationError> {
    let tracer_id = match session.tracers.keys().next() {
        Some(id) if session.tracers.len() == 1 => id.clone(),
        _ => {
            // Let extraction report the precise problem (none or several tracers).
            extract_points(session, None, None, &ExtractOptions::default())?;
            String::new()
        }
    };
    let declared_noise = NoiseModel::from_header(&session.header, &tracer_id);
    let options = ExtractOptions::from_header(&session.header);
    let extraction = extract_points(session, Some(&tracer_id), declared_noise, &options)?;
    let lengths = Lengths::of_extraction(&extraction);
    drop(extraction);
    // The effects' fit reads the settled windows (the same extraction), not their samples.
    if settings.effects.is_some() {
        let settled = SettledDwells::of_settled(SettledSession::of_session(session)?);
        return solve_dwells(&settled.without_window_samples(), settings);
    }
    let extracted = Extracted {
        header: &session.header,
        damaged: &session.damaged,
        lengths: &lengths,
        tracer_id,
        declared_noise,
    };
    solve_extracted(extracted, settings, None)
}

/// Solve a multilateration session reduced to its settled windows (`SettledSession`, streamed
/// or of a whole read): the results `solve` gives of that session, without effects (their fit
/// reads the compact windows: `solve_dwells`).
pub fn solve_settled(
    settled: &SettledSession,
    settings: &SolveSettings,
) -> Result<(MultilaterationResults, MultilaterationSolution), MultilaterationError> {
    let extracted = Extracted {
        header: &settled.header,
        damaged: &settled.damaged,
        lengths: &Lengths::of_extraction(&settled.extraction),
        tracer_id: settled.tracer_id.clone(),
        declared_noise: settled.noise,
    };
    solve_extracted(extracted, settings, None)
}

/// Solve a multilateration session reduced to its compact settled windows (`SettledDwells`,
/// streamed or of a whole read): the results `solve` gives of that session. What the effects'
/// fit reads.
pub fn solve_dwells(
    settled: &SettledDwells,
    settings: &SolveSettings,
) -> Result<(MultilaterationResults, MultilaterationSolution), MultilaterationError> {
    let extracted = Extracted {
        header: &settled.header,
        damaged: &settled.damaged,
        lengths: &settled.lengths,
        tracer_id: settled.tracer_id.clone(),
        declared_noise: settled.noise,
    };
    solve_extracted(extracted, settings, Some(settled))
}

/// Solve a multilateration session file as `geocal solve` does, streaming it: the tracer
/// samples go straight to the point extraction and are never held whole. None when the file
/// cannot be streamed exactly (not a clean multilateration session with one tracer, a
/// repaired copy): read it whole then. Effects to fit stream the settled windows their fit
/// reads (`SettledDwells`, without their raw samples).
pub fn solve_file_streaming(
    path: &std::path::Path,
    settings: &SolveSettings,
) -> Option<Result<MultilaterationResults, MultilaterationError>> {
    if settings.effects.is_some() {
        let settled = crate::extract::stream_dwells(
            path,
            is_multilateration,
            crate::extract::WindowSamples::ArrivalOnly,
        )?;
        return Some(solve_dwells(&settled, settings).map(|(results, _)| results));
    }
    let kind = crate::config::PlanKind::Multilateration.as_str();
    let solved = solve_file_streaming_detailed(path, settings, kind, |_| false)?;
    Some(solved.map(|(results, _, _)| results))
}

/// The solve of a session file of plan kind `kind` whose method builds on the multilateration
/// and also reads the run events `keep` selects: streamed as `solve_file_streaming`, with the
/// solution and the streamed session (every stream but the tracer samples; its events the
/// kept ones). None when the file cannot be streamed exactly, or effects are to be fitted.
pub fn solve_file_streaming_detailed(
    path: &std::path::Path,
    settings: &SolveSettings,
    kind: &str,
    keep: fn(&RunEvent) -> bool,
) -> Option<Result<(MultilaterationResults, MultilaterationSolution, Session), MultilaterationError>>
{
    if settings.effects.is_some() {
        return None;
    }
    let mut sink = KeepingEvents::new(LengthStream::new(kind), keep);
    let streamed = crate::session::reader::stream_session_reporting(
        path,
        &mut sink,
        settings.read_progress.as_ref(),
    )?;
    let (lengths, tracer_id, declared_noise) = sink.inner.finish()?;
    let mut session = streamed.session;
    session.events = sink.kept;
    let extracted = Extracted {
        header: &session.header,
        damaged: &session.damaged,
        lengths: &lengths,
        tracer_id,
        declared_noise,
    };
    let solved = solve_extracted(extracted, settings, None);
    Some(solved.map(|(results, solution)| (results, solution, session)))
}

/// Whether a session's plan kind is this method's.
pub(crate) fn is_multilateration(kind: &str) -> bool {
    kind == crate::config::PlanKind::Multilateration.as_str()
}

/// A session's extracted lengths and what the results say about them.
struct Extracted<'a> {
    header: &'a SessionHeader,
    damaged: &'a [DamagedChunk],
    lengths: &'a Lengths,
    tracer_id: String,
    declared_noise: Option<NoiseModel>,
}

/// The adjustment of extracted lengths; `settled` is needed only for the effects' fit.
fn solve_extracted(
    extracted: Extracted<'_>,
    settings: &SolveSettings,
    settled: Option<&SettledDwells>,
) -> Result<(MultilaterationResults, MultilaterationSolution), MultilaterationError> {
    let Extracted {
        header,
        damaged,
        lengths: extraction,
        tracer_id,
        declared_noise,
    } = extracted;
    if extraction.measurements.is_empty() {
        return Err(MultilaterationError::NoPoints {
            dropped: extraction.dropped.len(),
        });
    }
    // Effects modelled: the lengths corrected by their jointly fitted contribution (the
    // geometry of the joint optimum is the solve of the corrected lengths). The fit builds
    // its own problem: this one is built after it.
    let correction = match (&settings.effects, settled) {
        (Some(effects), Some(settled)) => Some(
            effects
                .correction(settled)
                .map_err(MultilaterationError::Effects)?,
        ),
        (Some(_), None) => {
            return Err(MultilaterationError::Effects(
                "fitting effects needs the settled windows of the session".into(),
            ))
        }
        (None, _) => None,
    };
    let mut problem = Problem::of_lengths(extraction);
    if let Some(c) = &correction {
        for (obs, dl) in problem
            .problem
            .observations
            .iter_mut()
            .zip(&c.length_correction_m)
        {
            obs.length_m -= dl;
        }
    }
    let (mut solution, robust) = match settings.huber {
        None => (adjust(&problem.problem, &SolveOptions::default())?, None),
        Some(huber) => {
            let r = solve_huber(&problem.problem, &SolveOptions::default(), huber)?;
            let mut downweighted: Vec<DownWeighted> = r
                .weights
                .iter()
                .zip(&r.solution.residuals_m)
                .zip(&extraction.measurements)
                .filter(|((w, _), _)| **w < 1.0)
                .map(|((w, res), m)| DownWeighted {
                    station: extraction.station(m).to_owned(),
                    target: extraction.target(m).to_owned(),
                    point: m.point,
                    pass: m.pass,
                    weight: *w,
                    residual_m: *res,
                })
                .collect();
            downweighted.sort_by(|a, b| a.weight.total_cmp(&b.weight));
            let report = RobustReport {
                loss: "huber".into(),
                threshold_sigma: huber.threshold_sigma,
                rounds: r.rounds,
                downweighted,
            };
            (r.solution, Some(report))
        }
    };

    // The effects' uncertainty moves the points too.
    if let Some(c) = &correction {
        for (i, cov) in solution.point_covariance.iter_mut().enumerate() {
            *cov += c.point_covariance_block(i);
        }
        if c.station_covariance_m2.shape() == solution.station_joint_covariance.shape() {
            solution.station_joint_covariance += &c.station_covariance_m2;
            for (j, cov) in solution.station_covariance.iter_mut().enumerate() {
                *cov += c.station_covariance_m2.fixed_view::<3, 3>(3 * j, 3 * j);
            }
        }
    }
    let effect_parameters = correction.as_ref().map_or(0, |c| c.parameters);
    let dof = solution.dof.saturating_sub(effect_parameters);
    let mut per_station = vec![(0usize, 0.0f64); problem.problem.station_hints.len()];
    let mut per_point = vec![0usize; problem.points.len()];
    for (obs, r) in problem
        .problem
        .observations
        .iter()
        .zip(&solution.residuals_m)
    {
        let station = problem.problem.segments[obs.segment].station;
        per_station[station].0 += 1;
        per_station[station].1 += r * r;
        per_point[obs.point] += 1;
    }
    let stations = extraction
        .stations
        .iter()
        .enumerate()
        .map(|(j, seen)| {
            let segments: Vec<SegmentResult> = problem
                .segments
                .iter()
                .enumerate()
                .filter(|(_, (station, _, _))| *station == j)
                .map(|(s, (_, target, beam_segment))| SegmentResult {
                    target: target.clone(),
                    beam_segment: *beam_segment,
                    home_distance_m: solution.segment_distance_m[s],
                    sigma_m: solution.segment_distance_sigma_m[s],
                })
                .collect();
            let cov = solution.station_covariance[j];
            let (count, ss) = per_station[j];
            StationResult {
                id: seen.id.clone(),
                position_m: arr(&solution.stations[j]),
                home_distance_m: segments.first().map_or(f64::NAN, |s| s.home_distance_m),
                sigma_m: [cov[(0, 0)].sqrt(), cov[(1, 1)].sqrt(), cov[(2, 2)].sqrt()],
                segments,
                observations: count,
                residual_rms_m: if count > 0 {
                    (ss / count as f64).sqrt()
                } else {
                    0.0
                },
            }
        })
        .collect();
    let points = problem
        .points
        .iter()
        .enumerate()
        .map(|(i, (target, point, nominal))| {
            let actual = arr(&solution.points[i]);
            let cov = solution.point_covariance[i];
            PointResult {
                point: *point,
                target: target.clone(),
                nominal_m: *nominal,
                actual_m: actual,
                error_m: std::array::from_fn(|k| actual[k] - nominal[k]),
                sigma_m: [cov[(0, 0)].sqrt(), cov[(1, 1)].sqrt(), cov[(2, 2)].sqrt()],
                observations: per_point[i],
            }
        })
        .collect();
    let mut notes = Vec::new();
    let geometric_errors =
        match geometric_errors(header, &problem, &solution, correction.as_ref(), &mut notes) {
            Ok(value) => Some(value),
            Err(why) => {
                notes.push(format!("no geometric errors: {why}"));
                None
            }
        };
    let mut dropped_reasons = BTreeMap::new();
    for d in &extraction.dropped {
        *dropped_reasons.entry(d.reason.clone()).or_insert(0) += 1;
    }
    let results = MultilaterationResults {
        format: RESULTS_FORMAT.into(),
        kind: "multilateration".into(),
        session_id: header.session_id.clone(),
        residual_rms_m: solution.residual_rms_m,
        chi2_per_dof: if dof > 0 {
            solution.chi2 / dof as f64
        } else {
            f64::NAN
        },
        dof,
        iterations: solution.iterations,
        misfit: Misfit::check(solution.chi2, dof),
        converged: solution.converged,
        gauge: solution.gauge.to_string(),
        noise_model: match declared_noise {
            Some(n) => format!(
                "declared by the session: sigma = {} m + {} ppm * (|station - point| + dead path {} m) per sample, divided by sqrt(samples averaged); the beam re-evaluated as the solve moves the stations",
                n.noise_m, n.noise_ppm, n.dead_path_m
            ),
            None => "none declared: each point's sigma is the scatter of its settled samples / sqrt(count)".into(),
        },
        stations,
        points,
        extraction: ExtractionSummary {
            tracer: tracer_id,
            windows_used: extraction.measurements.len(),
            windows_dropped: extraction.dropped.len(),
            windows_repeated: extraction.repeated.len(),
            dropped_reasons,
            samples_used: extraction.measurements.iter().map(|m| m.samples).sum(),
            damaged_chunks: damaged.to_vec(),
        },
        effects: correction.map(|c| c.effects).unwrap_or_default(),
        geometric_errors,
        notes,
        robust,
    };
    Ok((results, solution))
}

/// Largest decomposition (unknowns) done: its design matrix is dense.
const MAX_DECOMPOSITION_PARAMETERS: usize = 1500;
/// Bound on equations x unknowns² (about a second of dense linear algebra per 1e8).
const MAX_DECOMPOSITION_WORK: f64 = 1e9;

/// Decompose the measured volumetric errors into the machine's geometric errors.
fn geometric_errors(
    header: &SessionHeader,
    problem: &Problem,
    solution: &MultilaterationSolution,
    effect_correction: Option<&crate::method::effects::EffectCorrection>,
    notes: &mut Vec<String>,
) -> Result<serde_json::Value, String> {
    let machine = &header.machine;
    let structure = Structure::parse(&machine.structure).map_err(|e| e.to_string())?;
    let observations = point_observations(machine, &problem.points, &problem.axes_m, solution)?;
    let options = DecompositionOptions::default();
    let grid = grid_from_points(&observations, options.grid_tolerance_m);
    // Error functions are sampled at the grid positions: 6 per axis position, 3 squareness,
    // 6 rigid motion. Points off a grid give as many unknowns as data (and a huge dense
    // system); such a plan measures volumetric errors only.
    let parameters = 6 * grid.iter().map(Vec::len).sum::<usize>() + 9;
    let equations = 3 * observations.len();
    if equations as f64 * (parameters as f64).powi(2) > MAX_DECOMPOSITION_WORK {
        return Err(format!(
            "{equations} equations x {parameters} unknowns is beyond the dense decomposition \
             (its QR/SVD and cross-validation grow as equations x unknowns^2); decompose a \
             subset of the points, or wait for the sparse version"
        ));
    }
    if parameters > MAX_DECOMPOSITION_PARAMETERS || 2 * parameters > equations {
        return Err(format!(
            "the points are not on an axis grid the 21-error model can use: {} x {} x {} \
             distinct axis positions give {parameters} unknowns for {equations} equations \
             (needs at most {MAX_DECOMPOSITION_PARAMETERS} and at most half the equations)",
            grid[0].len(),
            grid[1].len(),
            grid[2].len()
        ));
    }
    // The points share stations, so their errors are correlated: use the full covariance
    // where the dense algebra is affordable, else the per-point blocks (and say so).
    let full =
        dense_point_covariance(&problem.problem, solution).map(|q| match effect_correction {
            Some(extra) if extra.point_response.nrows() == q.nrows() => {
                q + extra.point_covariance_m2()
            }
            _ => q,
        });
    if full.is_none() {
        notes.push(
            "geometric error sigmas use per-point covariance blocks only (the plan is too large for \
             the dense covariance): correlations between points through shared stations are ignored"
                .into(),
        );
    }
    let result = decompose_correlated(&structure, &grid, &observations, full.as_ref(), &options)
        .map_err(|e| e.to_string())?;
    serde_json::to_value(&result).map_err(|e| e.to_string())
}

/// The solved points as observations of the 21-error model: commanded axes, reflector offset
/// from the header's targets, error = solved − nominal and its 3x3 covariance. `points[i]`
/// (target, plan point, nominal) and `axes_m[i]` belong to `solution.points[i]`.
pub fn point_observations(
    machine: &MachineInfo,
    points: &[(String, usize, [f64; 3])],
    axes_m: &[Option<[f64; 3]>],
    solution: &MultilaterationSolution,
) -> Result<Vec<PointObservation>, String> {
    let mut observations = Vec::with_capacity(points.len());
    for (i, (target, point, nominal)) in points.iter().enumerate() {
        let axes_m = axes_m[i].ok_or_else(|| {
            format!(
                "point {point} of target {target} has no commanded axes x, y, z in its point_begin"
            )
        })?;
        let offset = machine
            .targets
            .iter()
            .find(|t| &t.id == target)
            .map(|t| t.offset_m)
            .ok_or_else(|| {
                format!("target `{target}` is not in the session header's machine.targets")
            })?;
        observations.push(PointObservation {
            axes_m,
            target_offset_m: offset,
            error_m: std::array::from_fn(|k| solution.points[i][k] - nominal[k]),
            covariance: solution.point_covariance[i],
        });
    }
    Ok(observations)
}

/// The adjustment problem of a session's settled windows, with the bookkeeping that maps it
/// back to session names. Observation `i` is `extraction.measurements[i]`. The diagnosis
/// builds its nominal fit from the same problem, so it is the one `geocal solve` reports.
pub struct Problem {
    pub problem: MultilaterationProblem,
    /// (target, plan point index, nominal) of each problem point.
    pub points: Vec<(String, usize, [f64; 3])>,
    /// Commanded axis positions x, y, z of each problem point.
    pub axes_m: Vec<Option<[f64; 3]>>,
    /// (station index, target, beam segment) of each problem segment: every homing distance
    /// differs per target, even if another recorder did not start a new beam segment.
    pub segments: Vec<(usize, String, u32)>,
}

impl Problem {
    pub fn build(extraction: &Extraction) -> Problem {
        Problem::of_lengths(&Lengths::of_extraction(extraction))
    }

    pub fn of_lengths(extraction: &Lengths) -> Problem {
        let target = |m: &LengthMeasurement| extraction.targets[m.target].as_str();
        // Targets by the rank of their id, so that the maps below compare integers.
        let mut ids: Vec<&str> = extraction.targets.iter().map(String::as_str).collect();
        ids.sort_unstable();
        ids.dedup();
        let rank: Vec<usize> = extraction
            .targets
            .iter()
            .map(|t| ids.partition_point(|id| *id < t.as_str()))
            .collect();
        // Point order: by target, then plan index, so results read in plan order.
        let mut point_index: BTreeMap<(usize, usize), usize> = BTreeMap::new();
        for (i, m) in extraction.measurements.iter().enumerate() {
            point_index.entry((rank[m.target], m.point)).or_insert(i);
        }
        let mut points = Vec::with_capacity(point_index.len());
        let mut axes_m = Vec::with_capacity(point_index.len());
        for (k, first) in point_index.values_mut().enumerate() {
            let m = &extraction.measurements[*first];
            points.push((target(m).to_owned(), m.point, m.nominal_m));
            axes_m.push(m.axes_m);
            *first = k;
        }
        let mut segment_index: BTreeMap<(usize, usize, u32), usize> = BTreeMap::new();
        let mut segments = Vec::new();
        let mut observations = Vec::with_capacity(extraction.measurements.len());
        for m in &extraction.measurements {
            let segment = *segment_index
                .entry((m.station_index, rank[m.target], m.beam_segment))
                .or_insert_with(|| {
                    segments.push((m.station_index, target(m).to_owned(), m.beam_segment));
                    segments.len() - 1
                });
            observations.push(LengthObservation {
                point: point_index[&(rank[m.target], m.point)],
                segment,
                length_m: m.length_m,
                sigma_m: m.sigma_m,
                path_sigma: m.path_sigma,
            });
        }
        let problem = MultilaterationProblem {
            nominal_points: points.iter().map(|p| Vector3::from(p.2)).collect(),
            station_hints: extraction
                .stations
                .iter()
                .map(|s| s.hint_m.map(Vector3::from))
                .collect(),
            segments: segments
                .iter()
                .map(|&(station, _, _)| Segment { station })
                .collect(),
            observations,
        };
        Problem {
            problem,
            points,
            axes_m,
            segments,
        }
    }
}
