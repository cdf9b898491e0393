//! The settled lengths as the network solve needs them (`Lengths`: no per-window maps or
//! names), from a whole-session extraction or straight from a streamed session file
//! (`LengthStream`), which keeps only the samples an open dwell window needs.

use std::collections::HashMap;

use super::pairing::{Measured, StreamStart};
use super::points::{DroppedWindow, Extraction, NoiseModel, StationSeen};
use crate::session::messages::{RunEvent, SessionHeader, TracerSample};
use crate::session::reader::{SessionSink, Stamped};
use crate::solve::multilateration::PathSigma;

/// One settled dwell (`PointMeasurement` without its names and maps).
#[derive(Debug, Clone, PartialEq)]
pub struct LengthMeasurement {
    /// Into `Lengths::stations`.
    pub station_index: usize,
    /// Into `Lengths::targets`.
    pub target: usize,
    pub point: usize,
    pub pass: usize,
    pub nominal_m: [f64; 3],
    /// The commanded axes x, y, z of the `point_begin`; None when one is missing.
    pub axes_m: Option<[f64; 3]>,
    pub beam_segment: u32,
    pub length_m: f64,
    pub sigma_m: f64,
    pub path_sigma: Option<PathSigma>,
    pub samples: usize,
}

/// Every dwell window of a session reduced to what the network solve uses; measurement `i`
/// is `Extraction::measurements[i]` of the same session.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Lengths {
    pub measurements: Vec<LengthMeasurement>,
    /// Target ids in order of first appearance.
    pub targets: Vec<String>,
    pub dropped: Vec<DroppedWindow>,
    pub repeated: Vec<DroppedWindow>,
    pub stations: Vec<StationSeen>,
}

impl Lengths {
    pub fn of_extraction(extraction: &Extraction) -> Lengths {
        let mut targets = TargetNames::default();
        let measurements = extraction
            .measurements
            .iter()
            .map(|m| {
                let axis = |name: &str| m.axes.get(name).copied();
                LengthMeasurement {
                    station_index: m.station_index,
                    target: targets.index(&m.target),
                    point: m.point,
                    pass: m.pass,
                    nominal_m: m.nominal_m,
                    axes_m: (|| Some([axis("x")?, axis("y")?, axis("z")?]))(),
                    beam_segment: m.beam_segment,
                    length_m: m.length_m,
                    sigma_m: m.sigma_m,
                    path_sigma: m.path_sigma,
                    samples: m.samples,
                }
            })
            .collect();
        Lengths {
            measurements,
            targets: targets.names,
            dropped: extraction.dropped.clone(),
            repeated: extraction.repeated.clone(),
            stations: extraction.stations.clone(),
        }
    }

    pub fn target(&self, m: &LengthMeasurement) -> &str {
        &self.targets[m.target]
    }

    pub fn station(&self, m: &LengthMeasurement) -> &str {
        &self.stations[m.station_index].id
    }
}

/// Target ids numbered in order of first appearance.
#[derive(Default)]
pub(crate) struct TargetNames {
    pub(crate) names: Vec<String>,
    index: HashMap<String, usize>,
}

impl TargetNames {
    pub(crate) fn index(&mut self, name: &str) -> usize {
        if let Some(&i) = self.index.get(name) {
            return i;
        }
        self.names.push(name.to_owned());
        self.index.insert(name.to_owned(), self.names.len() - 1);
        self.names.len() - 1
    }
}

pub(crate) fn length_measurement(
    m: Measured,
    noise: Option<NoiseModel>,
    targets: &mut TargetNames,
) -> LengthMeasurement {
    let (w, settled) = (m.window, m.settled);
    let axis = |name: &str| w.axes.get(name).copied();
    LengthMeasurement {
        station_index: m.station_index,
        target: targets.index(&w.target),
        point: w.point,
        pass: w.pass,
        nominal_m: w.nominal_m,
        axes_m: (|| Some([axis("x")?, axis("y")?, axis("z")?]))(),
        beam_segment: settled.beam_segment,
        length_m: settled.mean_m,
        sigma_m: settled.sigma_m,
        path_sigma: noise.map(|n| n.mean_sigma(settled.count)),
        samples: settled.count,
    }
}

/// The extraction of a streamed session (`session::reader::stream_session`) of one kind with
/// exactly one tracer, with the stillstand settings and noise model its header declares, as
/// `extract_points` gives them. It declines any other session, and stops at a `data_lost`
/// event (a repaired copy: its windows need the whole session's lost spans).
pub struct LengthStream {
    kind: String,
    started: Option<Started>,
    /// Samples of the tracer from the open window's begin (or the current batch) on.
    samples: Vec<Stamped<TracerSample>>,
    targets: TargetNames,
    /// The most tracer samples held at once (tests: it must not grow with the session).
    pub peak_samples: usize,
}

type Started = StreamStart<LengthMeasurement>;

impl LengthStream {
    /// For sessions of plan kind `kind`.
    pub fn new(kind: &str) -> Self {
        LengthStream {
            kind: kind.to_owned(),
            started: None,
            samples: Vec::new(),
            targets: TargetNames::default(),
            peak_samples: 0,
        }
    }

    /// The extraction, the tracer's id and the declared noise model; None when the stream
    /// never began.
    pub fn finish(self) -> Option<(Lengths, String, Option<NoiseModel>)> {
        let mut started = self.started?;
        started.pairing.finish(&|_, _| false);
        let pairing = started.pairing;
        let lengths = Lengths {
            measurements: pairing.measurements,
            targets: self.targets.names,
            dropped: pairing.dropped,
            repeated: pairing.repeated,
            stations: pairing.stations,
        };
        Some((lengths, started.tracer_id, started.noise))
    }
}

impl SessionSink for LengthStream {
    fn begin(&mut self, header: &SessionHeader, tracers: &[String], run_events: usize) -> bool {
        if header.kind != self.kind {
            return false;
        }
        self.started = Started::of_header(header, tracers, run_events);
        self.started.is_some()
    }

    fn batch(
        &mut self,
        tracers: &mut [Vec<Stamped<TracerSample>>],
        events: &mut Vec<Stamped<RunEvent>>,
    ) -> bool {
        let Some(started) = self.started.as_mut() else {
            return false;
        };
        if let Some(new) = tracers.first_mut() {
            if self.samples.is_empty() {
                std::mem::swap(&mut self.samples, new);
            } else {
                self.samples.append(new);
            }
        }
        self.peak_samples = self.peak_samples.max(self.samples.len());
        let noise = started.noise;
        let targets = &mut self.targets;
        let mut make = |m: Measured| length_measurement(m, noise, targets);
        // A clean file's stream: no message is lost.
        let lost = |_: u64, _: u64| false;
        if events
            .iter()
            .any(|e| matches!(e.msg, RunEvent::DataLost { .. }))
        {
            return false;
        }
        for event in events.drain(..) {
            started
                .pairing
                .event_owned(event, &self.samples, &lost, &mut make);
        }
        // Every later event lies at or after this batch's bound, beyond every sample held:
        // only an open window still needs its samples.
        match started.pairing.open_since_ns() {
            Some(begin_ns) => {
                let stale = self.samples.partition_point(|s| s.log_time_ns < begin_ns);
                self.samples.drain(..stale);
            }
            None => self.samples.clear(),
        }
        true
    }
}
