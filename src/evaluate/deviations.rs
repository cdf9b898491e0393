//! Where ISO 230-2 deviations come from: per-run, per-direction positioning deviations of the
//! linear axes from a tracer network (each pass's points re-estimated with the stations
//! fixed), and the rotary table's step errors; read from a kind's results, naming no kind.

use std::collections::BTreeMap;

use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

use super::iso230_2::{evaluate, AxisType, Curves, CurvesError, Evaluation};
use crate::extract::{extract_points, ExtractOptions, Extraction, NoiseModel, PointMeasurement};
use crate::method::multilateration::MultilaterationResults;
use crate::method::Results;
use crate::session::messages::AxisMap;
use crate::session::reader::Session;
use crate::solve::multilateration::PathSigma;

const AXES: [&str; 3] = ["x", "y", "z"];

#[derive(Debug, thiserror::Error)]
pub enum DeviationError {
    #[error("ISO 230-2: point extraction: {0}")]
    Extract(#[from] crate::extract::points::ExtractError),
    #[error("ISO 230-2: the session has {0} tracers, expected one")]
    Tracers(usize),
    #[error("ISO 230-2: results JSON: {0}")]
    Json(#[from] serde_json::Error),
    #[error("ISO 230-2: results key `{key}`: {what}")]
    Results { key: String, what: String },
    #[error(transparent)]
    Curves(#[from] CurvesError),
}

/// The ISO 230-2 evaluation of one axis and how its deviations were obtained.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct AxisIso {
    /// "x", "y", "z", or the rotary table's id.
    pub axis: String,
    /// The reflector target the linear deviations were measured with.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub target: Option<String>,
    pub source: String,
    /// Median standard uncertainty of one deviation (linear axes).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub deviation_sigma_median_m: Option<f64>,
    /// Per target of `curves`, the RMS standard uncertainty of one point's deviation in one
    /// pass (linear axes).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub target_sigma_m: Option<Vec<f64>>,
    /// Median standard uncertainty of one deviation (rotary axes).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub deviation_sigma_median_rad: Option<f64>,
    /// Per target of `curves`, the RMS standard uncertainty of one step's deviation (rotary
    /// axes; the reference station's is 0).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub target_sigma_rad: Option<Vec<f64>>,
    pub notes: Vec<String>,
    pub curves: Curves,
    pub evaluation: Evaluation,
}

/// Every axis a kind's results give positioning deviations for.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct Iso230_2 {
    pub axes: Vec<AxisIso>,
    /// Axes left out, and why.
    pub notes: Vec<String>,
}

impl Iso230_2 {
    pub fn text(&self) -> String {
        let mut out = String::new();
        for a in &self.axes {
            let name = match &a.target {
                Some(t) => format!("{} (target {t})", a.axis),
                None => a.axis.clone(),
            };
            out += &a.evaluation.text(&name);
            for n in &a.notes {
                out += &format!("  note: {n}\n");
            }
        }
        for n in &self.notes {
            out += &format!("ISO 230-2: {n}\n");
        }
        out
    }
}

/// The ISO 230-2 figures of every axis the results measured: the linear axes of a tracer
/// network (per pass, with the stations fixed) and a rotary table's steps.
pub fn of_results(results: &Results, session: &Session) -> Result<Iso230_2, DeviationError> {
    let extraction = match results.multilateration() {
        Some(_) => Some(tracer_extraction(session)?),
        None => None,
    };
    of_results_extracted(results, extraction.as_ref())
}

/// `of_results` with the session's point extraction given (its only tracer, the header's
/// noise model and stillstand settings): a streamed session's, whose samples are not held.
pub fn of_results_extracted(
    results: &Results,
    extraction: Option<&Extraction>,
) -> Result<Iso230_2, DeviationError> {
    let mut out = Iso230_2::default();
    if let (Some(network), Some(extraction)) = (results.multilateration(), extraction) {
        tracer_axes(network, extraction, &mut out)?;
    }
    let json = results.to_json_value()?;
    if let Some(rotary) = json.get("rotary").filter(|r| !r.is_null()) {
        out.axes.push(rotary_axis(rotary)?);
    }
    if out.axes.is_empty() && out.notes.is_empty() {
        out.notes
            .push("these results hold no positioning deviations".to_owned());
    }
    Ok(out)
}

/// One pass's estimate of one point.
#[derive(Debug, Clone)]
struct RunPoint {
    pass: usize,
    axes_m: [f64; 3],
    approach: [i8; 3],
    deviation_m: [f64; 3],
    sigma_m: [f64; 3],
}

/// The point extraction of the session's only tracer.
fn tracer_extraction(session: &Session) -> Result<Extraction, DeviationError> {
    if session.tracers.len() != 1 {
        return Err(DeviationError::Tracers(session.tracers.len()));
    }
    let tracer_id = session.tracers.keys().next().cloned().unwrap_or_default();
    let noise = NoiseModel::from_header(&session.header, &tracer_id);
    Ok(extract_points(
        session,
        Some(&tracer_id),
        noise,
        &ExtractOptions::from_header(&session.header),
    )?)
}

fn tracer_axes(
    network: &MultilaterationResults,
    extraction: &Extraction,
    out: &mut Iso230_2,
) -> Result<(), DeviationError> {
    let mut general = Vec::new();
    if !network.effects.is_empty() {
        general.push(
            "the solve fitted unmodelled effects; the per-pass points use the raw lengths"
                .to_owned(),
        );
    }
    if network.robust.is_some() {
        general.push(
            "the solve down-weighted outliers; the per-pass points weigh every length alike"
                .to_owned(),
        );
    }
    // A run is a pass of every station, each zeroed at the home point; a pass in which some
    // station was homed otherwise than in the other passes has another zero there, and is left
    // out unless fewer than two runs would remain.
    let homed_otherwise = homed_otherwise(&extraction.measurements);
    let mut left_out: std::collections::BTreeSet<usize> =
        homed_otherwise.iter().map(|h| h.3).collect();
    if !left_out.is_empty() {
        let named: Vec<String> = homed_otherwise
            .iter()
            .map(|(station, _, _, pass)| format!("{station} in pass {pass}"))
            .collect();
        let passes: std::collections::BTreeSet<usize> =
            extraction.measurements.iter().map(|m| m.pass).collect();
        let list: Vec<usize> = left_out.iter().copied().collect();
        if passes.len() - left_out.len() >= 2 {
            general.push(format!(
                "passes {list:?} left out of the runs: homed at point 0 with another \
                 approach than the other passes ({}; a first homing comes before the axes \
                 moved), so with a reversal their counter's zero sits elsewhere",
                named.join(", ")
            ));
        } else {
            general.push(format!(
                "passes {list:?} kept (fewer than 2 runs otherwise) though homed with another \
                 approach ({}): with a reversal their zero differs",
                named.join(", ")
            ));
            left_out.clear();
        }
    }
    let mut groups: BTreeMap<(String, usize, usize), Vec<&PointMeasurement>> = BTreeMap::new();
    for m in &extraction.measurements {
        if left_out.contains(&m.pass) {
            continue;
        }
        groups
            .entry((m.target.clone(), m.point, m.pass))
            .or_default()
            .push(m);
    }
    let mut by_target: BTreeMap<String, Vec<RunPoint>> = BTreeMap::new();
    let mut unsolved = 0usize;
    for ((target, point, pass), lengths) in &groups {
        let Some(joint) = network
            .points
            .iter()
            .find(|p| &p.target == target && p.point == *point)
        else {
            unsolved += 1;
            continue;
        };
        let Some((p, cov)) = point_of_pass(network, lengths, Vector3::from(joint.actual_m)) else {
            unsolved += 1;
            continue;
        };
        let first = lengths[0];
        let axes = AXES.map(|a| first.axes.get(a).copied());
        let [Some(x), Some(y), Some(z)] = axes else {
            unsolved += 1;
            continue;
        };
        by_target.entry(target.clone()).or_default().push(RunPoint {
            pass: *pass,
            axes_m: [x, y, z],
            approach: AXES.map(|a| first.approach.get(a).copied().unwrap_or(0)),
            deviation_m: std::array::from_fn(|k| p[k] - joint.nominal_m[k]),
            sigma_m: std::array::from_fn(|k| cov[(k, k)].max(0.0).sqrt()),
        });
    }
    if unsolved > 0 {
        general.push(format!(
            "{unsolved} point passes left out (fewer than 3 lengths, or no joint estimate)"
        ));
    }
    for (target, points) in &by_target {
        for (k, axis) in AXES.iter().enumerate() {
            match axis_curves(points, k) {
                Ok((curves, mut notes)) => {
                    let evaluation = evaluate(&curves)?;
                    notes.extend(general.iter().cloned());
                    let mut sigmas: Vec<f64> = points.iter().map(|p| p.sigma_m[k]).collect();
                    let target_sigma_m = curves
                        .targets
                        .iter()
                        .map(|t| {
                            let at: Vec<f64> = points
                                .iter()
                                .filter(|p| (p.axes_m[k] - t).abs() < 1e-9)
                                .map(|p| p.sigma_m[k].powi(2))
                                .collect();
                            (at.iter().sum::<f64>() / at.len().max(1) as f64).sqrt()
                        })
                        .collect();
                    out.axes.push(AxisIso {
                        axis: (*axis).to_owned(),
                        target: Some(target.clone()),
                        source: format!(
                            "each pass's points estimated from its lengths with the stations and homing distances of the joint solve; deviation along {axis} = estimated − nominal, with the other axes' offsets of every grid line removed (a line through the grid's mean {})",
                            other_axes(k)
                        ),
                        deviation_sigma_median_m: Some(median(&mut sigmas)),
                        target_sigma_m: Some(target_sigma_m),
                        deviation_sigma_median_rad: None,
                        target_sigma_rad: None,
                        notes,
                        curves,
                        evaluation,
                    });
                }
                Err(why) => out
                    .notes
                    .push(format!("axis {axis} (target {target}): {why}")),
            }
        }
    }
    Ok(())
}

/// A station's beam segment of one target: (station, target, beam segment).
type Segment = (String, String, u32);

/// A station's pass of one target and beam segment: (station, target, beam segment, pass).
type StationPass = (String, String, u32, usize);

/// The approach of each axis at a point: the sign of its last move.
type Approach = AxisMap<i8>;

/// The station passes whose homing (the dwell at point 0, where the counter is zeroed) was
/// approached otherwise than the segment's usual homing (of the same station, target and beam
/// segment: one after every axis has moved, the most frequent of those). The
/// joint solve holds one homing distance per segment, so every pass must be zeroed at the same
/// place; an axis with a reversal puts the home point elsewhere when approached otherwise
/// (the run's first homing comes before any axis moved), a zero the solve does not have.
fn homed_otherwise(measurements: &[PointMeasurement]) -> std::collections::BTreeSet<StationPass> {
    let mut homings: BTreeMap<Segment, Vec<(usize, &Approach)>> = BTreeMap::new();
    for m in measurements.iter().filter(|m| m.point == 0) {
        homings
            .entry((m.station.clone(), m.target.clone(), m.beam_segment))
            .or_default()
            .push((m.pass, &m.approach));
    }
    let mut out = std::collections::BTreeSet::new();
    for ((station, target, segment), passes) in homings {
        let count = |a: &Approach| passes.iter().filter(|(_, b)| *b == a).count();
        // The segment's zero: a homing after every axis has moved (an approach of 0 means an
        // axis that never moved), then the most frequent, then the earliest pass's.
        let Some(reference) = passes
            .iter()
            .map(|(_, a)| *a)
            .rev()
            .max_by_key(|a| (a.values().all(|&s| s != 0), count(a)))
        else {
            continue;
        };
        for (pass, approach) in &passes {
            if *approach != reference {
                out.insert((station.clone(), target.clone(), segment, *pass));
            }
        }
    }
    out
}

fn other_axes(k: usize) -> String {
    let o: Vec<&str> = (0..3).filter(|&j| j != k).map(|j| AXES[j]).collect();
    o.join(", ")
}

fn median(values: &mut [f64]) -> f64 {
    values.sort_by(f64::total_cmp);
    match values.len() {
        0 => f64::NAN,
        n if n % 2 == 1 => values[n / 2],
        n => 0.5 * (values[n / 2 - 1] + values[n / 2]),
    }
}

/// Gauss–Newton on the point alone: lengths |S − P| − d with the stations S and homing
/// distances d of the joint solve. None without 3 lengths or a regular normal matrix.
fn point_of_pass(
    network: &MultilaterationResults,
    lengths: &[&PointMeasurement],
    start: Vector3<f64>,
) -> Option<(Vector3<f64>, Matrix3<f64>)> {
    struct Length {
        station_m: Vector3<f64>,
        home_m: f64,
        length_m: f64,
        path: Option<PathSigma>,
        sigma_m: f64,
    }
    let obs: Vec<Length> = lengths
        .iter()
        .filter_map(|m| {
            let station = network.stations.iter().find(|s| s.id == m.station)?;
            let segment = station
                .segments
                .iter()
                .find(|s| s.target == m.target && s.beam_segment == m.beam_segment)?;
            Some(Length {
                station_m: Vector3::from(station.position_m),
                home_m: segment.home_distance_m,
                length_m: m.length_m,
                path: m.path_sigma,
                sigma_m: m.sigma_m,
            })
        })
        .collect();
    if obs.len() < 3 {
        return None;
    }
    let mut p = start;
    let mut cov = Matrix3::zeros();
    for _ in 0..20 {
        let mut a = Matrix3::zeros();
        let mut b = Vector3::zeros();
        for o in &obs {
            let diff = p - o.station_m;
            let beam = diff.norm();
            let u = diff / beam;
            let sigma = o.path.map_or(o.sigma_m, |ps| ps.sigma_m(beam));
            let w = 1.0 / (sigma * sigma);
            let r = beam - o.home_m - o.length_m;
            a += w * u * u.transpose();
            b += w * u * r;
        }
        cov = a.try_inverse()?;
        let step = cov * b;
        p -= step;
        if step.norm() < 1e-13 {
            break;
        }
    }
    Some((p, cov))
}

/// The ISO curves of axis `k`: per pass and approach direction, the deviation at every
/// target of the axis along the grid's mean line. Each point of the grid (a line of the other
/// axes at a target) is referred to its own reference, the mean of its runs with the two
/// approach directions weighted alike: that removes what the point keeps in every run (the
/// other axes' errors at that line, the axis's angular errors over that line's lever), so that
/// runs measured on different lines (a serpentine's ↑ and ↓ rows) compare alike. The mean of
/// the references over the lines is added back: deviation(pass, direction, target) = mean over
/// the cell's points of (deviation − reference) + the mean line's. A point seen from one side
/// only (a row's first target, a homing) has no reference and is left out: at it, a reversal
/// cannot be told from the point's own geometry.
fn axis_curves(points: &[RunPoint], k: usize) -> Result<(Curves, Vec<String>), String> {
    let key = |v: f64| (v * 1e9).round() as i64;
    let mut targets: Vec<f64> = points.iter().map(|p| p.axes_m[k]).collect();
    targets.sort_by(f64::total_cmp);
    targets.dedup_by(|a, b| key(*a) == key(*b));
    if targets.len() < 2 {
        return Err(format!(
            "{} target position, nothing to evaluate",
            targets.len()
        ));
    }
    let target_of = |v: f64| targets.iter().position(|t| key(*t) == key(v));
    let mut lines: BTreeMap<(i64, i64), usize> = BTreeMap::new();
    // (cell (pass, direction, target), line, deviation)
    let mut obs: Vec<((usize, i8, usize), usize, f64)> = Vec::new();
    for p in points {
        let dir = p.approach[k];
        let Some(ti) = target_of(p.axes_m[k]) else {
            continue;
        };
        if dir == 0 {
            continue;
        }
        let others: Vec<f64> = (0..3).filter(|&j| j != k).map(|j| p.axes_m[j]).collect();
        let n = lines.len();
        let line = *lines.entry((key(others[0]), key(others[1]))).or_insert(n);
        obs.push(((p.pass, dir, ti), line, p.deviation_m[k]));
    }
    // Per point (line, target): the sums of its ↑ and ↓ deviations; a point seen from both
    // sides has its reference, the mean of the two sides' means.
    let mut by_point: BTreeMap<(usize, usize), [(f64, usize); 2]> = BTreeMap::new();
    for ((_, dir, ti), line, v) in &obs {
        let side = &mut by_point.entry((*line, *ti)).or_default()[usize::from(*dir < 0)];
        side.0 += v;
        side.1 += 1;
    }
    let balanced: BTreeMap<(usize, usize), f64> = by_point
        .into_iter()
        .filter(|(_, [up, down])| up.1 > 0 && down.1 > 0)
        .map(|(point, [up, down])| (point, 0.5 * (up.0 / up.1 as f64 + down.0 / down.1 as f64)))
        .collect();
    // The mean line: the references as mean line + line offset (backfitting, the offsets
    // summing to zero), so that a target whose points lie on fewer lines is not moved by
    // those lines' own offsets.
    let mut mean_line = vec![0.0; targets.len()];
    let mut offset = vec![0.0; lines.len()];
    for _ in 0..500 {
        let mut at_target = vec![(0.0, 0usize); targets.len()];
        for ((line, ti), r) in &balanced {
            at_target[*ti].0 += r - offset[*line];
            at_target[*ti].1 += 1;
        }
        mean_line = at_target
            .iter()
            .map(|(s, n)| s / (*n).max(1) as f64)
            .collect();
        let mut on_line = vec![(0.0, 0usize); lines.len()];
        for ((line, ti), r) in &balanced {
            on_line[*line].0 += r - mean_line[*ti];
            on_line[*line].1 += 1;
        }
        let seen: Vec<f64> = on_line
            .iter()
            .filter(|(_, n)| *n > 0)
            .map(|(s, n)| s / *n as f64)
            .collect();
        let mean = seen.iter().sum::<f64>() / seen.len().max(1) as f64;
        let new: Vec<f64> = on_line
            .iter()
            .map(|(s, n)| if *n > 0 { s / *n as f64 - mean } else { 0.0 })
            .collect();
        let change = new
            .iter()
            .zip(&offset)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        offset = new;
        if change < 1e-16 {
            break;
        }
    }
    let mut sum: BTreeMap<(usize, i8, usize), (f64, usize)> = BTreeMap::new();
    for (cell, line, v) in &obs {
        if let Some(reference) = balanced.get(&(*line, cell.2)) {
            let e = sum.entry(*cell).or_default();
            e.0 += v - reference;
            e.1 += 1;
        }
    }
    let f: BTreeMap<(usize, i8, usize), f64> = sum
        .into_iter()
        .map(|(cell, (s, n))| (cell, s / n as f64 + mean_line[cell.2]))
        .collect();
    if f.is_empty() {
        return Err("no point approached from both sides, nothing to evaluate".to_owned());
    }
    // A run per pass and direction; a target stays if every such run reached it.
    let runs = |dir: i8| -> Vec<usize> {
        let mut passes: Vec<usize> = f.keys().filter(|c| c.1 == dir).map(|c| c.0).collect();
        passes.dedup();
        passes
    };
    let (up_runs, down_runs) = (runs(1), runs(-1));
    let mut notes = Vec::new();
    let mut kept = Vec::new();
    for (ti, t) in targets.iter().enumerate() {
        let missing: Vec<&str> = [("↑", 1i8, &up_runs), ("↓", -1i8, &down_runs)]
            .iter()
            .filter(|(_, d, passes)| passes.iter().any(|p| !f.contains_key(&(*p, *d, ti))))
            .map(|(name, _, _)| *name)
            .collect();
        if missing.is_empty() {
            kept.push(ti);
        } else {
            notes.push(format!(
                "{} = {t:.4} m left out: not every {} run reaches it at a point approached from both sides (the plan has no overshoot past it)",
                AXES[k],
                missing.join(" and ")
            ));
        }
    }
    if kept.len() < 2 {
        return Err(format!(
            "{} of {} targets approached alike in every run, nothing to evaluate",
            kept.len(),
            targets.len()
        ));
    }
    let curve = |dir: i8, passes: &[usize]| -> Vec<Vec<f64>> {
        passes
            .iter()
            .map(|p| kept.iter().map(|ti| f[&(*p, dir, *ti)]).collect())
            .collect()
    };
    notes.push(format!(
        "runs are passes: ↑ runs from passes {up_runs:?}, ↓ runs from passes {down_runs:?} (a pass whose rows alternate gives both)"
    ));
    Ok((
        Curves {
            axis_type: AxisType::Linear,
            targets: kept.iter().map(|ti| targets[*ti]).collect(),
            up: curve(1, &up_runs),
            down: curve(-1, &down_runs),
        },
        notes,
    ))
}

/// One table step as the results give it.
#[derive(Debug, Clone, Copy)]
struct TableStep {
    commanded_rad: f64,
    error_rad: f64,
    sigma_rad: f64,
    approach: Option<i8>,
}

/// Commanded angles closer than this are one target position, radians.
const SAME_TARGET_RAD: f64 = 1e-9;

fn table_steps(rotary: &serde_json::Value) -> Result<(String, Vec<TableStep>), DeviationError> {
    let bad = |key: &str, what: &str| DeviationError::Results {
        key: key.to_owned(),
        what: what.to_owned(),
    };
    let table = rotary
        .get("table")
        .and_then(|t| t.as_str())
        .ok_or_else(|| bad("rotary.table", "expected the table id"))?;
    let steps = rotary
        .get("steps")
        .and_then(|s| s.as_array())
        .ok_or_else(|| bad("rotary.steps", "expected a list of steps"))?;
    let mut out = Vec::new();
    for (i, s) in steps.iter().enumerate() {
        let num = |name: &str| {
            s.get(name)
                .and_then(|v| v.as_f64())
                .ok_or_else(|| bad(&format!("rotary.steps[{i}].{name}"), "expected a number"))
        };
        let approach = match s.get("approach") {
            None | Some(serde_json::Value::Null) => None,
            Some(v) => match v.as_i64() {
                Some(1) => Some(1),
                Some(-1) => Some(-1),
                _ => {
                    return Err(bad(
                        &format!("rotary.steps[{i}].approach"),
                        "expected 1 or -1",
                    ))
                }
            },
        };
        out.push(TableStep {
            commanded_rad: num("commanded_rad")?,
            error_rad: num("error_rad")?,
            sigma_rad: num("sigma_rad")?,
            approach,
        });
    }
    Ok((table.to_owned(), out))
}

/// The steps split into runs: consecutive steps approached from one side that visit the
/// angles monotonically in that direction. A step whose approach is unknown (the first
/// station of a plan without overshoot, a station where the table did not move) takes the
/// side of the step after it, else the one before it, else the direction of the commands.
fn table_runs(steps: &[TableStep]) -> Vec<(i8, Vec<TableStep>)> {
    let mut side: Vec<Option<i8>> = steps.iter().map(|s| s.approach).collect();
    for i in (0..side.len().saturating_sub(1)).rev() {
        side[i] = side[i].or(side[i + 1]);
    }
    for i in 1..side.len() {
        side[i] = side[i].or(side[i - 1]);
    }
    let commanded_sense = match steps {
        [first, second, ..] if second.commanded_rad < first.commanded_rad => -1,
        _ => 1,
    };
    let mut runs: Vec<(i8, Vec<TableStep>)> = Vec::new();
    for (step, side) in steps.iter().zip(side) {
        let side = side.unwrap_or(commanded_sense);
        match runs.last_mut() {
            Some((run_side, run))
                if *run_side == side
                    && run.last().is_some_and(|last| {
                        f64::from(side) * (step.commanded_rad - last.commanded_rad)
                            > SAME_TARGET_RAD
                    }) =>
            {
                run.push(*step)
            }
            _ => runs.push((side, vec![*step])),
        }
    }
    runs
}

/// The ISO 230-2 evaluation of a rotary table from the `rotary` object of a kind's results
/// (its steps: commanded angle, error, σ, approach side).
pub fn rotary_axis(rotary: &serde_json::Value) -> Result<AxisIso, DeviationError> {
    let (table, steps) = table_steps(rotary)?;
    let runs = table_runs(&steps);
    let mut angles: Vec<f64> = steps.iter().map(|s| s.commanded_rad).collect();
    angles.sort_by(f64::total_cmp);
    angles.dedup_by(|a, b| (*a - *b).abs() <= SAME_TARGET_RAD);
    let error_at = |run: &[TableStep], target: f64| {
        run.iter()
            .find(|s| (s.commanded_rad - target).abs() <= SAME_TARGET_RAD)
            .map(|s| s.error_rad)
    };
    let (kept, left_out): (Vec<f64>, Vec<f64>) = angles
        .iter()
        .partition(|&&t| runs.iter().all(|(_, run)| error_at(run, t).is_some()));
    let curve = |side: i8| -> Vec<Vec<f64>> {
        runs.iter()
            .filter(|(s, _)| *s == side)
            .map(|(_, run)| kept.iter().filter_map(|&t| error_at(run, t)).collect())
            .collect()
    };
    let curves = Curves {
        axis_type: AxisType::Rotary,
        targets: kept.clone(),
        up: curve(1),
        down: curve(-1),
    };
    let evaluation = evaluate(&curves)?;
    let target_sigma_rad: Vec<f64> = kept
        .iter()
        .map(|&t| {
            let sigmas: Vec<f64> = steps
                .iter()
                .filter(|s| (s.commanded_rad - t).abs() <= SAME_TARGET_RAD)
                .map(|s| s.sigma_rad)
                .collect();
            (sigmas.iter().map(|s| s * s).sum::<f64>() / sigmas.len() as f64).sqrt()
        })
        .collect();
    let mut notes = vec![if runs.len() == 1 {
        "one run: the table visits each commanded angle once, in one direction".to_owned()
    } else {
        format!(
            "{} ↑ and {} ↓ runs: consecutive table stations approached from one side, visiting the angles in that direction",
            curves.up.len(),
            curves.down.len()
        )
    }];
    if steps.first().is_some_and(|s| s.approach.is_none()) {
        notes.push(
            "the first table station's approach is not recorded (no overshoot before it): counted with its run".to_owned(),
        );
    }
    if !left_out.is_empty() {
        notes.push(format!(
            "angles {:?} rad left out: not measured in every run",
            left_out
        ));
    }
    let mut sigmas: Vec<f64> = steps.iter().map(|s| s.sigma_rad).collect();
    Ok(AxisIso {
        axis: table,
        target: None,
        source: "the table's step errors (measured − commanded angle, relative to the first table station) from the circle through the table stations".to_owned(),
        deviation_sigma_median_m: None,
        target_sigma_m: None,
        deviation_sigma_median_rad: Some(median(&mut sigmas)),
        target_sigma_rad: Some(target_sigma_rad),
        notes,
        curves,
        evaluation,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn step(commanded_rad: f64, approach: Option<i8>) -> TableStep {
        TableStep {
            commanded_rad,
            error_rad: 1e-6 * commanded_rad + 1e-7 * f64::from(approach.unwrap_or(0)),
            sigma_rad: 1e-7,
            approach,
        }
    }

    #[test]
    fn table_runs_split_at_a_reversal_and_at_a_new_pass() {
        // A plan without overshoot: one ↑ run, its first step's approach unknown.
        let legacy = [step(0.0, None), step(0.5, Some(1)), step(1.0, Some(1))];
        let runs = table_runs(&legacy);
        assert_eq!(runs.len(), 1);
        assert_eq!((runs[0].0, runs[0].1.len()), (1, 3));
        // ISO cycle: ↑ ↓ ↑ ↓, every run entered through its overshoot.
        let up = [step(0.0, Some(1)), step(0.5, Some(1)), step(1.0, Some(1))];
        let down = [
            step(1.0, Some(-1)),
            step(0.5, Some(-1)),
            step(0.0, Some(-1)),
        ];
        let cycle: Vec<TableStep> = [up, down, up, down].concat();
        let sides: Vec<(i8, usize)> = table_runs(&cycle)
            .iter()
            .map(|(side, run)| (*side, run.len()))
            .collect();
        assert_eq!(sides, [(1, 3), (-1, 3), (1, 3), (-1, 3)]);
        // Two ↑ runs in a row start again where the angles stop increasing.
        let twice: Vec<TableStep> = [up, up].concat();
        assert_eq!(table_runs(&twice).len(), 2);
    }

    #[test]
    fn table_cycle_gives_both_directions_and_the_reversal() {
        let up = [step(0.0, Some(1)), step(0.5, Some(1)), step(1.0, Some(1))];
        let down = [
            step(1.0, Some(-1)),
            step(0.5, Some(-1)),
            step(0.0, Some(-1)),
        ];
        let steps: Vec<serde_json::Value> = [up, down, up, down]
            .concat()
            .iter()
            .map(|s| {
                serde_json::json!({
                    "commanded_rad": s.commanded_rad, "error_rad": s.error_rad,
                    "sigma_rad": s.sigma_rad, "approach": s.approach,
                })
            })
            .collect();
        let axis =
            rotary_axis(&serde_json::json!({"table": "c", "steps": steps})).expect("rotary axis");
        assert_eq!(axis.curves.targets, [0.0, 0.5, 1.0]);
        assert_eq!((axis.curves.up.len(), axis.curves.down.len()), (2, 2));
        let b = axis.evaluation.figures();
        let b = b.bidirectional.as_ref().expect("both directions");
        assert!(
            (b.mean_reversal - 2e-7).abs() < 1e-15,
            "{}",
            b.mean_reversal
        );
        // A bad approach is named by its key.
        let bad = serde_json::json!({"table": "c", "steps": [
            {"commanded_rad": 0.0, "error_rad": 0.0, "sigma_rad": 0.0, "approach": 2}]});
        let err = rotary_axis(&bad).expect_err("approach 2");
        assert!(
            err.to_string().contains("rotary.steps[0].approach"),
            "{err}"
        );
    }

    /// Deviation = g(target) + line offset + reversal·direction/2; rows alternate direction
    /// (serpentine) and the first target of a row is reached without moving the axis.
    #[test]
    fn line_offsets_and_directions_are_separated() {
        let xs = [0.1, 0.33, 0.52, 0.8];
        let g = |x: f64| 3e-6 * x * x;
        let reversal = 2e-6;
        let mut points = Vec::new();
        for pass in 0..2 {
            for (row, line) in [(0.0, 0.0), (0.5, 0.0), (0.0, 0.4), (0.5, 0.4)]
                .iter()
                .enumerate()
            {
                let up = (row + pass) % 2 == 0;
                for &x in &xs {
                    // Interior targets by the row's direction; the ends as the sim reaches them.
                    let dir: i8 = if x == xs[3] || (x != xs[0] && up) {
                        1
                    } else {
                        -1
                    };
                    let offset = 1e-6 * line.0 - 4e-6 * line.1;
                    points.push(RunPoint {
                        pass,
                        axes_m: [x, line.0, line.1],
                        approach: [dir, 1, 1],
                        deviation_m: [g(x) + offset + 0.5 * reversal * dir as f64, 0.0, 0.0],
                        sigma_m: [1e-8; 3],
                    });
                }
            }
        }
        let (curves, notes) = axis_curves(&points, 0).unwrap();
        assert_eq!(curves.targets, vec![0.33, 0.52]);
        assert!(
            notes.iter().any(|n| n.contains("0.1000 m left out")),
            "{notes:?}"
        );
        let e = evaluate(&curves).unwrap();
        let b = e.figures().bidirectional.clone().unwrap();
        assert!((b.reversal - reversal).abs() < 1e-13, "{}", b.reversal);
        let want_m = g(0.52) - g(0.33);
        assert!(
            (b.mean_error - want_m).abs() < 1e-13,
            "{} vs {want_m}",
            b.mean_error
        );
        assert_eq!((curves.up.len(), curves.down.len()), (2, 2));
    }

    fn homing(station: &str, pass: usize, approach: i8) -> PointMeasurement {
        PointMeasurement {
            station: station.into(),
            station_index: 0,
            point: 0,
            pass,
            target: "t0".into(),
            nominal_m: [0.0; 3],
            axes: AxisMap::new(),
            approach: AXES.iter().map(|a| (*a, approach)).collect(),
            beam_segment: 0,
            length_m: 0.0,
            sigma_m: 1e-7,
            path_sigma: None,
            samples: 10,
            settled_from_s: 0.0,
            settled_to_s: 1.0,
        }
    }

    /// The run's first homing, before any axis moved, is the odd one out of its station; a
    /// station homed alike in every pass keeps every pass.
    #[test]
    fn a_pass_homed_from_rest_is_named() {
        let ms = [
            homing("s1", 0, 0),
            homing("s1", 1, -1),
            homing("s1", 2, -1),
            homing("s2", 0, -1),
            homing("s2", 1, -1),
        ];
        let odd = homed_otherwise(&ms);
        assert_eq!(
            odd.into_iter().collect::<Vec<_>>(),
            vec![("s1".to_string(), "t0".to_string(), 0, 0)]
        );
        // Two passes, one homing each: the one before the axes moved is the odd one.
        let two = [homing("s1", 0, 0), homing("s1", 1, -1)];
        assert_eq!(
            homed_otherwise(&two)
                .into_iter()
                .map(|h| h.3)
                .collect::<Vec<_>>(),
            vec![0]
        );
    }
}
