//! Point extraction: pairs `point_begin`/`point_end` events, takes the tracer samples inside
//! each window, finds their settled stretch and reduces it to one length with its sigma.

use std::collections::BTreeMap;

use serde::Serialize;

use super::stillstand::{Stillstand, StillstandDetector};
pub use crate::config::noise::NoiseModel;
use crate::session::messages::{RunEvent, SessionHeader, TracerSample};
use crate::session::reader::{Session, Stamped};
pub use crate::solve::multilateration::PathSigma;

#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ExtractOptions {
    pub window_s: f64,
    pub tolerance_m: f64,
}

impl Default for ExtractOptions {
    fn default() -> Self {
        Self {
            window_s: 0.5,
            tolerance_m: 2e-6,
        }
    }
}

impl ExtractOptions {
    /// The stillstand settings the plan recorded (`plan.stillstand`), else the defaults.
    pub fn from_header(header: &SessionHeader) -> ExtractOptions {
        let defaults = ExtractOptions::default();
        let stillstand = &header.plan["stillstand"];
        ExtractOptions {
            window_s: stillstand["window_s"].as_f64().unwrap_or(defaults.window_s),
            tolerance_m: stillstand["tolerance_m"]
                .as_f64()
                .unwrap_or(defaults.tolerance_m),
        }
    }
}

/// One settled dwell: the mean relative length at a point, seen from one station.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PointMeasurement {
    pub station: String,
    pub station_index: usize,
    pub point: usize,
    pub pass: usize,
    pub target: String,
    pub nominal_m: [f64; 3],
    pub axes: BTreeMap<String, f64>,
    pub approach: BTreeMap<String, i8>,
    pub beam_segment: u32,
    pub length_m: f64,
    /// σ of the mean length. With a declared noise model this is its value for a beam of
    /// zero length (`path_sigma.at_zero_beam_m`): the beam |station − target| is known only
    /// once the geometry is solved, which then adds `path_sigma.per_beam_m` per metre.
    pub sigma_m: f64,
    /// The declared noise model's σ of this mean as a function of the beam length; None when
    /// no model is declared (then `sigma_m` is the samples' own scatter).
    pub path_sigma: Option<PathSigma>,
    pub samples: usize,
    /// Device time of the settled stretch.
    pub settled_from_s: f64,
    pub settled_to_s: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DroppedWindow {
    pub station: String,
    pub point: usize,
    pub pass: usize,
    pub reason: String,
}

#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct Extraction {
    pub measurements: Vec<PointMeasurement>,
    pub dropped: Vec<DroppedWindow>,
    /// Windows a beam break cut short: the sequencer re-homed (`rehome`) and repeated them.
    pub repeated: Vec<DroppedWindow>,
    /// Station ids in order of their `station_begin`.
    pub stations: Vec<StationSeen>,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct StationSeen {
    pub id: String,
    pub hint_m: Option<[f64; 3]>,
}

#[derive(Debug, thiserror::Error)]
pub enum ExtractError {
    #[error("session has no tracer stream (/tracer/<id>/range)")]
    NoTracer,
    #[error(
        "session has {0} tracer streams; point extraction handles one tracer at a time, name it"
    )]
    SeveralTracers(usize),
    #[error("session has no tracer `{0}`")]
    UnknownTracer(String),
}

/// Why a window is dropped when messages it may hold were in a damaged chunk.
pub const DAMAGED_CHUNK: &str = "samples lost in a damaged chunk";

struct OpenWindow {
    log_time_ns: u64,
    station: String,
    point: usize,
    pass: usize,
    target: String,
    nominal_m: [f64; 3],
    axes: BTreeMap<String, f64>,
    approach: BTreeMap<String, i8>,
}

/// Extract every dwell window of the session's tracer (`tracer_id`, or the only one).
pub fn extract_points(
    session: &Session,
    tracer_id: Option<&str>,
    noise: Option<NoiseModel>,
    options: &ExtractOptions,
) -> Result<Extraction, ExtractError> {
    let samples = select_tracer(session, tracer_id)?;
    // Messages of a damaged chunk are lost: a window they may have touched is never half-used.
    let damaged = |from_ns: u64, to_ns: u64| session.lost_between(from_ns, to_ns);
    let reason = |w: &OpenWindow, to_ns: u64, otherwise: &'static str| {
        if damaged(w.log_time_ns, to_ns) {
            DAMAGED_CHUNK
        } else {
            otherwise
        }
    };
    let mut previous_ns = 0;
    let mut out = Extraction::default();
    let mut station_index: BTreeMap<String, usize> = BTreeMap::new();
    let mut open: Option<OpenWindow> = None;

    let mut index_of = |out: &mut Extraction, id: &str, hint: Option<[f64; 3]>| -> usize {
        let next = station_index.len();
        *station_index.entry(id.to_string()).or_insert_with(|| {
            out.stations.push(StationSeen {
                id: id.to_string(),
                hint_m: hint,
            });
            next
        })
    };

    for event in &session.events {
        let since_ns = std::mem::replace(&mut previous_ns, event.log_time_ns);
        match &event.msg {
            RunEvent::StationBegin {
                station, hint_m, ..
            } => {
                index_of(&mut out, station, *hint_m);
            }
            RunEvent::PointBegin {
                station,
                point,
                pass,
                target,
                nominal_m,
                axes,
                approach,
            } => {
                if let Some(w) = open.take() {
                    let why = reason(&w, event.log_time_ns, "point_begin without point_end");
                    out.dropped.push(dropped(&w, why));
                }
                open = Some(OpenWindow {
                    log_time_ns: event.log_time_ns,
                    station: station.clone(),
                    point: *point,
                    pass: *pass,
                    target: target.clone(),
                    nominal_m: *nominal_m,
                    axes: axes.clone(),
                    approach: approach.clone(),
                });
            }
            RunEvent::Rehome { .. } => {
                if let Some(w) = open.take() {
                    out.repeated
                        .push(dropped(&w, "beam broken: repeated after re-homing"));
                }
            }
            RunEvent::Resume { .. } => {
                if let Some(w) = open.take() {
                    out.repeated
                        .push(dropped(&w, "run interrupted: repeated after resume"));
                }
            }
            RunEvent::UnplannedStop { .. } => {
                if let Some(w) = open.take() {
                    out.repeated
                        .push(dropped(&w, "not the planned stop (unplanned_stop)"));
                }
            }
            RunEvent::PointEnd {
                station,
                point,
                pass,
            } => {
                let Some(w) = open.take() else {
                    // Its point_begin was in a damaged chunk.
                    if damaged(since_ns, event.log_time_ns) {
                        out.dropped.push(DroppedWindow {
                            station: station.clone(),
                            point: *point,
                            pass: *pass,
                            reason: DAMAGED_CHUNK.into(),
                        });
                    }
                    continue;
                };
                let why = reason(
                    &w,
                    event.log_time_ns,
                    "point_end does not match its point_begin",
                );
                if (&w.station, w.point, w.pass) != (station, *point, *pass) || why == DAMAGED_CHUNK
                {
                    out.dropped.push(dropped(&w, why));
                    continue;
                }
                let index = index_of(&mut out, &w.station, None);
                let window = in_window(samples, w.log_time_ns, event.log_time_ns);
                match settle(window, noise, options) {
                    Ok(settled) => out.measurements.push(PointMeasurement {
                        station: w.station,
                        station_index: index,
                        point: w.point,
                        pass: w.pass,
                        target: w.target,
                        nominal_m: w.nominal_m,
                        axes: w.axes,
                        approach: w.approach,
                        beam_segment: settled.beam_segment,
                        length_m: settled.mean_m,
                        sigma_m: settled.sigma_m,
                        path_sigma: noise.map(|n| n.mean_sigma(settled.count)),
                        samples: settled.count,
                        settled_from_s: settled.from_s,
                        settled_to_s: settled.to_s,
                    }),
                    Err(reason) => out.dropped.push(dropped(&w, reason)),
                }
            }
            _ => {}
        }
    }
    if let Some(w) = open.take() {
        let why = reason(&w, u64::MAX, "no point_end (session cut short?)");
        out.dropped.push(dropped(&w, why));
    }
    Ok(out)
}

fn select_tracer<'a>(
    session: &'a Session,
    tracer_id: Option<&str>,
) -> Result<&'a [Stamped<TracerSample>], ExtractError> {
    match tracer_id {
        Some(id) => session
            .tracers
            .get(id)
            .map(Vec::as_slice)
            .ok_or_else(|| ExtractError::UnknownTracer(id.to_string())),
        None => match session.tracers.len() {
            0 => Err(ExtractError::NoTracer),
            1 => Ok(session
                .tracers
                .values()
                .next()
                .map(Vec::as_slice)
                .unwrap_or(&[])),
            n => Err(ExtractError::SeveralTracers(n)),
        },
    }
}

fn dropped(w: &OpenWindow, reason: &str) -> DroppedWindow {
    DroppedWindow {
        station: w.station.clone(),
        point: w.point,
        pass: w.pass,
        reason: reason.to_string(),
    }
}

/// Samples with begin <= log_time <= end (the slice is sorted by log_time).
fn in_window(
    samples: &[Stamped<TracerSample>],
    begin_ns: u64,
    end_ns: u64,
) -> &[Stamped<TracerSample>] {
    let from = samples.partition_point(|s| s.log_time_ns < begin_ns);
    let to = samples.partition_point(|s| s.log_time_ns <= end_ns);
    &samples[from..to.max(from)]
}

struct Settled {
    mean_m: f64,
    sigma_m: f64,
    count: usize,
    from_s: f64,
    to_s: f64,
    beam_segment: u32,
}

/// The last settled stretch of a dwell window, averaged.
fn settle(
    window: &[Stamped<TracerSample>],
    noise: Option<NoiseModel>,
    options: &ExtractOptions,
) -> Result<Settled, &'static str> {
    let first = window.first().ok_or("no tracer samples in the window")?;
    let beam_segment = first.msg.beam_segment;
    if window
        .iter()
        .any(|s| !s.msg.tracking || s.msg.beam_segment != beam_segment)
    {
        return Err("beam broken inside the window");
    }
    let mut detector = StillstandDetector::new(options.window_s, options.tolerance_m);
    let mut stretch: Option<(f64, f64)> = None;
    for s in window {
        if let Stillstand::Settled { since_s } = detector.push(s.msg.t_s, s.msg.length_m) {
            stretch = Some((since_s, s.msg.t_s));
        }
    }
    let (from_s, to_s) = stretch.ok_or("never settled inside the window")?;
    let settled: Vec<f64> = window
        .iter()
        .filter(|s| s.msg.t_s >= from_s && s.msg.t_s <= to_s)
        .map(|s| s.msg.length_m)
        .collect();
    let count = settled.len();
    if count < 2 {
        return Err("settled stretch holds fewer than 2 samples");
    }
    let mean_m = settled.iter().sum::<f64>() / count as f64;
    let sigma_m = match noise {
        Some(model) => model.mean_sigma(count).at_zero_beam_m,
        None => {
            let var =
                settled.iter().map(|v| (v - mean_m).powi(2)).sum::<f64>() / (count - 1) as f64;
            var.sqrt().max(1e-12) / (count as f64).sqrt()
        }
    };
    Ok(Settled {
        mean_m,
        sigma_m,
        count,
        from_s,
        to_s,
        beam_segment,
    })
}
