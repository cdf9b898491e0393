//! Point extraction: pairs `point_begin`/`point_end` events, takes the tracer samples inside
//! each window, finds their settled stretch and reduces it to one length with its sigma.

use serde::Serialize;

use super::pairing::{Measured, Pairing};
pub use crate::config::noise::NoiseModel;
use crate::session::messages::{AxisMap, SessionHeader, TracerSample};
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
    pub axes: AxisMap<f64>,
    pub approach: AxisMap<i8>,
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

/// Extract every dwell window of the session's tracer (`tracer_id`, or the only one).
pub fn extract_points(
    session: &Session,
    tracer_id: Option<&str>,
    noise: Option<NoiseModel>,
    options: &ExtractOptions,
) -> Result<Extraction, ExtractError> {
    let samples = select_tracer(session, tracer_id)?;
    // Messages of a damaged chunk are lost: a window they may have touched is never half-used.
    let lost = |from_ns: u64, to_ns: u64| session.lost_between(from_ns, to_ns);
    let mut pairing = Pairing::new(noise, *options);
    let mut make = |m: Measured| point_measurement(m, noise);
    for event in &session.events {
        pairing.event(event, samples, &lost, &mut make);
    }
    pairing.finish(&lost);
    Ok(Extraction {
        measurements: pairing.measurements,
        dropped: pairing.dropped,
        repeated: pairing.repeated,
        stations: pairing.stations,
    })
}

pub(super) fn point_measurement(m: Measured, noise: Option<NoiseModel>) -> PointMeasurement {
    let (w, settled) = (m.window, m.settled);
    PointMeasurement {
        station: w.station.to_string(),
        station_index: m.station_index,
        point: w.point,
        pass: w.pass,
        target: w.target.to_string(),
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
    }
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
