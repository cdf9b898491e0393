//! What the diagnosis and the effects' fit read of a session beside the solve's lengths: the
//! extraction with its names and maps, each measurement's raw settled samples and arrival
//! time, the environment log and the header (`SettledSession`; `SettledDwells` keeps the
//! solve's compact lengths instead of the names and maps). From a whole session, or straight
//! from a streamed session file (`WindowStream`), which holds only the open dwell window's
//! tracer samples and each measured window's settled (t, length) pairs.

use std::collections::{BTreeMap, HashMap};

use super::lengths::{length_measurement, LengthMeasurement, Lengths, TargetNames};
use super::pairing::{Measured, StreamStart};
use super::points::{point_measurement, ExtractError, PointMeasurement, StationSeen};
use super::{extract_points, ExtractOptions, Extraction, NoiseModel};
use crate::session::messages::{AxisMap, EnvSample, RunEvent, SessionHeader, TracerSample};
use crate::session::reader::{DamagedChunk, Session, SessionSink, Stamped, Streamed};

/// The raw samples of one settled dwell window (what its mean length averages).
#[derive(Debug, Clone, PartialEq)]
pub struct RawWindow {
    /// Device time of the first sample after `point_begin`: the machine has just arrived.
    pub arrival_s: f64,
    /// (t_s, length_m) of the settled stretch (at least 2); empty when read with
    /// `WindowSamples::ArrivalOnly`.
    pub samples: Vec<(f64, f64)>,
}

/// What a settled window keeps of its raw samples.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WindowSamples {
    /// Every sample of the settled stretch (what the settling test fits).
    Kept,
    /// The arrival alone (the zeroing's time), `RawWindow::samples` left empty: what the
    /// effects' fit of the calibration reads.
    ArrivalOnly,
}

/// A session reduced to its settled windows: everything the diagnosis's observations and the
/// effects' fit are built from, without the tracer stream.
#[derive(Debug, Clone, PartialEq)]
pub struct SettledSession {
    pub header: SessionHeader,
    /// Key: id from the topic `/env/<id>` (as `Session::env`).
    pub env: BTreeMap<String, Vec<Stamped<EnvSample>>>,
    /// Chunks of the file that could not be read (as `Session::damaged`).
    pub damaged: Vec<DamagedChunk>,
    /// The session's only tracer.
    pub tracer_id: String,
    /// The tracer's declared noise model.
    pub noise: Option<NoiseModel>,
    /// `extract_points` of the tracer with the header's stillstand settings.
    pub extraction: Extraction,
    /// Per measurement: its raw settled window (None when the session's events do not
    /// locate it, or it holds fewer than 2 samples).
    pub windows: Vec<Option<RawWindow>>,
    /// The stations that stood on a rotary table: (station, commanded table angle of its last
    /// `rotation` event), in the session's order; empty without a table.
    pub rotations: Vec<(String, f64)>,
}

/// What the diagnosis reads of a dwell beside its length (`LengthMeasurement`): the approach
/// signs and commanded axes of its `point_begin` and its settled stretch.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Dwell {
    /// Sign of the last move of x, y, z before the dwell (0 for an axis not named).
    pub approach: [i8; 3],
    /// Commanded x, y, z (0 for an axis not named).
    pub axes_m: [f64; 3],
    /// Device time of the settled stretch.
    pub settled_from_s: f64,
    pub settled_to_s: f64,
}

impl Dwell {
    fn of(m: &PointMeasurement) -> Dwell {
        Dwell {
            approach: xyz(&m.approach),
            axes_m: xyz(&m.axes),
            settled_from_s: m.settled_from_s,
            settled_to_s: m.settled_to_s,
        }
    }
}

/// A streamed measured window in the compact form (`WindowStream::compact`).
pub struct DwellMeasurement {
    length: LengthMeasurement,
    dwell: Dwell,
}

/// Per axis x, y, z: its entry of a `point_begin`'s map, 0 for an axis not named.
fn xyz<T: Copy + Default>(map: &AxisMap<T>) -> [T; 3] {
    XYZ.map(|a| map.get(a).copied().unwrap_or_default())
}

const XYZ: [&str; 3] = ["x", "y", "z"];

/// A session reduced to its settled windows in the compact form of the solve's lengths
/// (`SettledSession` without the per-window names and maps): what the diagnosis holds.
#[derive(Debug, Clone, PartialEq)]
pub struct SettledDwells {
    pub header: SessionHeader,
    /// Key: id from the topic `/env/<id>` (as `Session::env`).
    pub env: BTreeMap<String, Vec<Stamped<EnvSample>>>,
    /// Chunks of the file that could not be read (as `Session::damaged`).
    pub damaged: Vec<DamagedChunk>,
    pub tracer_id: String,
    pub noise: Option<NoiseModel>,
    /// The solve's lengths (`Lengths::of_extraction` of the session's extraction).
    pub lengths: Lengths,
    /// Per measurement: the rest of its dwell.
    pub dwells: Vec<Dwell>,
    /// Per measurement: its raw settled window, as `SettledSession::windows`.
    pub windows: Vec<Option<RawWindow>>,
    pub rotations: Vec<(String, f64)>,
}

impl SettledDwells {
    /// The compact form of a settled session (a whole read's).
    pub fn of_settled(settled: SettledSession) -> SettledDwells {
        SettledDwells {
            lengths: Lengths::of_extraction(&settled.extraction),
            dwells: settled
                .extraction
                .measurements
                .iter()
                .map(Dwell::of)
                .collect(),
            header: settled.header,
            env: settled.env,
            damaged: settled.damaged,
            tracer_id: settled.tracer_id,
            noise: settled.noise,
            windows: settled.windows,
            rotations: settled.rotations,
        }
    }

    /// The same windows with their raw samples let go (`WindowSamples::ArrivalOnly`).
    pub fn without_window_samples(mut self) -> SettledDwells {
        for window in self.windows.iter_mut().flatten() {
            window.samples = Vec::new();
        }
        self
    }
}

/// Streams the session at `path` to its `SettledDwells` (raw samples as `keep` says) when its
/// kind passes `accept_kind`; None as `stream_settled`.
pub fn stream_dwells(
    path: &std::path::Path,
    accept_kind: fn(&str) -> bool,
    keep: WindowSamples,
) -> Option<SettledDwells> {
    let mut sink = WindowStream::compact(accept_kind, keep);
    let streamed = crate::session::reader::stream_session(path, &mut sink)?;
    sink.finish_compact(streamed)
}

/// What a streamed measured window becomes (`WindowStream`'s measurements).
pub(crate) trait WindowRecord: Sized {
    fn of_measured(m: Measured, noise: Option<NoiseModel>, targets: &mut TargetNames) -> Self;
    /// The settled stretch (device seconds).
    fn settled_s(&self) -> (f64, f64);
    fn station_index(&self) -> usize;
    fn point_pass(&self) -> (usize, usize);
}

impl WindowRecord for PointMeasurement {
    fn of_measured(m: Measured, noise: Option<NoiseModel>, _: &mut TargetNames) -> Self {
        point_measurement(m, noise)
    }
    fn settled_s(&self) -> (f64, f64) {
        (self.settled_from_s, self.settled_to_s)
    }
    fn station_index(&self) -> usize {
        self.station_index
    }
    fn point_pass(&self) -> (usize, usize) {
        (self.point, self.pass)
    }
}

impl WindowRecord for DwellMeasurement {
    fn of_measured(m: Measured, noise: Option<NoiseModel>, targets: &mut TargetNames) -> Self {
        let dwell = Dwell {
            approach: xyz(&m.window.approach),
            axes_m: xyz(&m.window.axes),
            settled_from_s: m.settled.from_s,
            settled_to_s: m.settled.to_s,
        };
        DwellMeasurement {
            length: length_measurement(m, noise, targets),
            dwell,
        }
    }
    fn settled_s(&self) -> (f64, f64) {
        (self.dwell.settled_from_s, self.dwell.settled_to_s)
    }
    fn station_index(&self) -> usize {
        self.length.station_index
    }
    fn point_pass(&self) -> (usize, usize) {
        (self.length.point, self.length.pass)
    }
}

/// The `rotation` events of a session, each with the station it happened in.
#[derive(Debug, Clone, Default)]
struct Rotations {
    current: Option<String>,
    found: Vec<(String, f64)>,
}

impl Rotations {
    fn event(&mut self, event: &RunEvent) {
        match event {
            RunEvent::StationBegin { station, .. } => self.current = Some(station.to_string()),
            RunEvent::StationEnd { .. } => self.current = None,
            RunEvent::Rotation { commanded_rad, .. } => {
                if let Some(station) = &self.current {
                    // A repeated rotation within a station (a retry) replaces the earlier one.
                    if self.found.last().is_some_and(|(s, _)| s == station) {
                        self.found.pop();
                    }
                    self.found.push((station.clone(), *commanded_rad));
                }
            }
            _ => {}
        }
    }
}

impl SettledSession {
    /// From a session read whole. The errors are `extract_points`'s (no tracer, several).
    pub fn of_session(session: &Session) -> Result<SettledSession, ExtractError> {
        let tracer_id = match session.tracers.keys().next() {
            Some(id) if session.tracers.len() == 1 => Some(id.clone()),
            _ => None,
        };
        let noise = tracer_id
            .as_deref()
            .and_then(|id| NoiseModel::from_header(&session.header, id));
        let options = ExtractOptions::from_header(&session.header);
        let extraction = extract_points(session, tracer_id.as_deref(), noise, &options)?;
        // extract_points has named the problem unless there is exactly one tracer.
        let tracer_id = tracer_id.ok_or(ExtractError::NoTracer)?;
        let windows = raw_windows(session, &tracer_id, &extraction.measurements);
        let mut rotations = Rotations::default();
        for e in &session.events {
            rotations.event(&e.msg);
        }
        Ok(SettledSession {
            rotations: rotations.found,
            header: session.header.clone(),
            env: session.env.clone(),
            damaged: session.damaged.clone(),
            tracer_id,
            noise,
            extraction,
            windows,
        })
    }
}

/// Streams the session at `path` to its `SettledSession` when its kind passes `accept_kind`.
/// None whenever the stream could differ from the whole read (`stream_session`, and
/// `WindowStream`'s own refusals): the caller then reads the session whole.
pub fn stream_settled(
    path: &std::path::Path,
    accept_kind: fn(&str) -> bool,
) -> Option<SettledSession> {
    let mut sink = WindowStream::new(accept_kind);
    let streamed = crate::session::reader::stream_session(path, &mut sink)?;
    sink.finish(streamed)
}

/// The raw settled samples of each measurement and the arrival time before them: the last
/// `point_begin` of its (station, point, pass) (a repeat after a re-homing replaces the first).
fn raw_windows(
    session: &Session,
    tracer_id: &str,
    measurements: &[PointMeasurement],
) -> Vec<Option<RawWindow>> {
    let Some(samples) = session.tracers.get(tracer_id) else {
        return vec![None; measurements.len()];
    };
    let mut begins: BTreeMap<(&str, usize, usize), u64> = BTreeMap::new();
    for e in &session.events {
        if let RunEvent::PointBegin {
            station,
            point,
            pass,
            ..
        } = &e.msg
        {
            begins.insert((station.as_str(), *point, *pass), e.log_time_ns);
        }
    }
    measurements
        .iter()
        .map(|m| {
            let begin = *begins.get(&(m.station.as_str(), m.point, m.pass))?;
            let mut window = WindowCollector::new(begin, m.settled_s(), WindowSamples::Kept);
            let from = samples.partition_point(|s| s.log_time_ns < begin);
            for s in &samples[from..] {
                if !window.push(&s.msg) {
                    break;
                }
            }
            window.finish()
        })
        .collect()
}

/// One measurement's raw window, gathered sample by sample from its `point_begin` on: the
/// first sample is the arrival, then the samples up to the first one past the settled
/// stretch's end, of which those inside the stretch are kept.
#[derive(Debug, Clone)]
struct WindowCollector {
    begin_ns: u64,
    from_s: f64,
    to_s: f64,
    arrival_s: Option<f64>,
    keep: WindowSamples,
    /// Samples inside the settled stretch (kept or not).
    settled: usize,
    samples: Vec<(f64, f64)>,
    done: bool,
}

impl WindowCollector {
    fn new(begin_ns: u64, (from_s, to_s): (f64, f64), keep: WindowSamples) -> Self {
        WindowCollector {
            begin_ns,
            from_s,
            to_s,
            arrival_s: None,
            keep,
            settled: 0,
            samples: Vec::new(),
            done: false,
        }
    }

    /// The next sample (log-time order, at or after `begin_ns`). False: the window is complete.
    fn push(&mut self, s: &TracerSample) -> bool {
        if self.done {
            return false;
        }
        self.arrival_s.get_or_insert(s.t_s);
        if s.t_s <= self.to_s {
            if s.t_s >= self.from_s {
                self.settled += 1;
                if self.keep == WindowSamples::Kept {
                    self.samples.push((s.t_s, s.length_m));
                }
            }
        } else {
            self.done = true;
        }
        !self.done
    }

    /// A later `point_begin` of the same (station, point, pass): the window starts again there.
    fn restart(&mut self, begin_ns: u64) {
        self.begin_ns = begin_ns;
        self.arrival_s = None;
        self.settled = 0;
        self.samples.clear();
        self.done = false;
    }

    /// Feeds the samples of `held` (sorted by log time) from `begin_ns` on.
    fn push_from_begin(&mut self, held: &[Stamped<TracerSample>]) {
        let from = held.partition_point(|s| s.log_time_ns < self.begin_ns);
        for s in &held[from..] {
            if !self.push(&s.msg) {
                break;
            }
        }
    }

    fn finish(mut self) -> Option<RawWindow> {
        let arrival_s = self.arrival_s?;
        // Held to the end of the diagnosis: no room left from the gathering's growth.
        self.samples.shrink_to_fit();
        (self.settled >= 2).then_some(RawWindow {
            arrival_s,
            samples: self.samples,
        })
    }
}

/// The `SettledSession` of a streamed session file (`session::reader::stream_session`) with
/// exactly one tracer, as `SettledSession::of_session` gives it of the whole read (or its
/// compact `SettledDwells`, `WindowStream::compact`). It declines a session whose kind
/// `accept_kind` refuses or with another number of tracers, and stops at a `data_lost` event
/// (a repaired copy: its windows need the whole session's lost spans).
pub struct WindowStream<M = PointMeasurement> {
    accept_kind: fn(&str) -> bool,
    started: Option<StreamStart<M>>,
    /// Samples of the tracer from the open window's begin (or the current batch) on.
    samples: Vec<Stamped<TracerSample>>,
    /// Per measurement: its raw window being gathered.
    windows: Vec<WindowCollector>,
    /// Measurements whose window still takes samples.
    gathering: Vec<usize>,
    /// Measurements by (station index, point, pass): a later `point_begin` restarts their
    /// windows.
    by_key: HashMap<(usize, usize, usize), Vec<usize>>,
    /// The most tracer samples held at once, the gathered windows' pairs aside (tests).
    pub peak_samples: usize,
    rotations: Rotations,
    targets: TargetNames,
    keep: WindowSamples,
}

impl WindowStream<PointMeasurement> {
    /// For sessions whose plan kind passes `accept_kind`.
    pub fn new(accept_kind: fn(&str) -> bool) -> Self {
        WindowStream::with_kind(accept_kind)
    }

    /// The settled session, with the header, environment and damage of the streamed read's
    /// session; None when the stream never began.
    pub fn finish(self, streamed: Streamed) -> Option<SettledSession> {
        let (started, windows, rotations) = self.into_parts()?;
        let pairing = started.pairing;
        let session = streamed.session;
        Some(SettledSession {
            rotations,
            header: session.header,
            env: session.env,
            damaged: session.damaged,
            tracer_id: started.tracer_id,
            noise: started.noise,
            extraction: Extraction {
                measurements: pairing.measurements,
                dropped: pairing.dropped,
                repeated: pairing.repeated,
                stations: pairing.stations,
            },
            windows,
        })
    }
}

impl WindowStream<DwellMeasurement> {
    /// The compact form: each measured window kept as the solve's length and its few extras,
    /// its raw samples as `keep` says.
    pub fn compact(accept_kind: fn(&str) -> bool, keep: WindowSamples) -> Self {
        WindowStream {
            keep,
            ..WindowStream::with_kind(accept_kind)
        }
    }

    /// As `finish`, compact.
    pub fn finish_compact(mut self, streamed: Streamed) -> Option<SettledDwells> {
        let targets = std::mem::take(&mut self.targets.names);
        let (started, windows, rotations) = self.into_parts()?;
        let pairing = started.pairing;
        let (measurements, dwells) = pairing
            .measurements
            .into_iter()
            .map(|m| (m.length, m.dwell))
            .unzip();
        let session = streamed.session;
        Some(SettledDwells {
            rotations,
            header: session.header,
            env: session.env,
            damaged: session.damaged,
            tracer_id: started.tracer_id,
            noise: started.noise,
            lengths: Lengths {
                measurements,
                targets,
                dropped: pairing.dropped,
                repeated: pairing.repeated,
                stations: pairing.stations,
            },
            dwells,
            windows,
        })
    }
}

type StreamParts<M> = (StreamStart<M>, Vec<Option<RawWindow>>, Vec<(String, f64)>);

/// The gathering shared by both forms (a trait: its bound is crate-private).
trait Gathering<M>: Sized {
    fn with_kind(accept_kind: fn(&str) -> bool) -> Self;
    fn into_parts(self) -> Option<StreamParts<M>>;
    fn restart_windows(&mut self, station: &str, point: usize, pass: usize, begin_ns: u64);
}

impl<M: WindowRecord> Gathering<M> for WindowStream<M> {
    fn with_kind(accept_kind: fn(&str) -> bool) -> Self {
        WindowStream {
            accept_kind,
            started: None,
            samples: Vec::new(),
            windows: Vec::new(),
            gathering: Vec::new(),
            by_key: HashMap::new(),
            peak_samples: 0,
            rotations: Rotations::default(),
            targets: TargetNames::default(),
            keep: WindowSamples::Kept,
        }
    }

    /// The finished pairing, the windows and the rotations; None when the stream never began.
    fn into_parts(self) -> Option<StreamParts<M>> {
        let mut started = self.started?;
        started.pairing.finish(&|_, _| false);
        let mut windows: Vec<Option<RawWindow>> = self
            .windows
            .into_iter()
            .map(WindowCollector::finish)
            .collect();
        // Collected in the collectors' place, which is larger and grew by doubling.
        windows.shrink_to_fit();
        Some((started, windows, self.rotations.found))
    }

    /// A `point_begin` of `station`'s (point, pass) at `begin_ns`: the windows of its earlier
    /// measurements start again there (the whole read takes a measurement's window from its
    /// key's last begin).
    fn restart_windows(&mut self, station: &str, point: usize, pass: usize, begin_ns: u64) {
        let Some(stations) = self.started.as_ref().map(|s| &s.pairing.stations) else {
            return;
        };
        let Some(station) = station_position(stations, station) else {
            return;
        };
        let Some(measured) = self.by_key.get(&(station, point, pass)) else {
            return;
        };
        for &i in measured {
            let window = &mut self.windows[i];
            window.restart(begin_ns);
            window.push_from_begin(&self.samples);
            if !window.done && !self.gathering.contains(&i) {
                self.gathering.push(i);
            }
        }
    }
}

/// A station's index among those seen (the pairing numbers them in order of appearance).
fn station_position(stations: &[StationSeen], id: &str) -> Option<usize> {
    stations.iter().position(|s| s.id == id)
}

impl<M: WindowRecord> SessionSink for WindowStream<M> {
    fn begin(&mut self, header: &SessionHeader, tracers: &[String], run_events: usize) -> bool {
        if !(self.accept_kind)(&header.kind) {
            return false;
        }
        self.started = StreamStart::of_header(header, tracers, run_events);
        self.started.is_some()
    }

    fn batch(
        &mut self,
        tracers: &mut [Vec<Stamped<TracerSample>>],
        events: &mut Vec<Stamped<RunEvent>>,
    ) -> bool {
        if self.started.is_none() {
            return false;
        }
        let fresh = self.samples.len();
        if let Some(new) = tracers.first_mut() {
            self.samples.append(new);
        }
        self.peak_samples = self.peak_samples.max(self.samples.len());
        // The windows still gathering have seen every sample before this batch.
        for &i in &self.gathering {
            let window = &mut self.windows[i];
            for s in &self.samples[fresh..] {
                if !window.push(&s.msg) {
                    break;
                }
            }
        }
        // A clean file's stream: no message is lost.
        let lost = |_: u64, _: u64| false;
        for event in events.iter() {
            self.rotations.event(&event.msg);
            match &event.msg {
                RunEvent::DataLost { .. } => return false,
                RunEvent::PointBegin {
                    station,
                    point,
                    pass,
                    ..
                } => self.restart_windows(station, *point, *pass, event.log_time_ns),
                _ => {}
            }
            let Some(started) = self.started.as_mut() else {
                return false;
            };
            let begin_ns = started.pairing.open_since_ns();
            let noise = started.noise;
            let targets = &mut self.targets;
            let mut make = |m: Measured| M::of_measured(m, noise, targets);
            started
                .pairing
                .event(event, &self.samples, &lost, &mut make);
            // A measured window: its raw samples from its point_begin on (all held: the
            // samples are kept from the open window's begin).
            for i in self.windows.len()..started.pairing.measurements.len() {
                let m = &started.pairing.measurements[i];
                let mut window =
                    WindowCollector::new(begin_ns.unwrap_or(0), m.settled_s(), self.keep);
                window.push_from_begin(&self.samples);
                if !window.done {
                    self.gathering.push(i);
                }
                let (point, pass) = m.point_pass();
                self.by_key
                    .entry((m.station_index(), point, pass))
                    .or_default()
                    .push(i);
                self.windows.push(window);
            }
        }
        let windows = &self.windows;
        self.gathering.retain(|&i| !windows[i].done);
        // Every later event lies at or after this batch's bound, beyond every sample held:
        // only an open window still needs its samples (a measured one has gathered its own).
        match self
            .started
            .as_ref()
            .and_then(|s| s.pairing.open_since_ns())
        {
            Some(begin_ns) => {
                let stale = self.samples.partition_point(|s| s.log_time_ns < begin_ns);
                self.samples.drain(..stale);
            }
            None => self.samples.clear(),
        }
        true
    }
}
