//! The window pairing shared by the whole-session and the streaming extraction: run events in
//! log-time order open and close dwell windows, and each closed window's tracer samples are
//! reduced to one settled length. The caller decides what a measured window becomes.

use std::collections::BTreeMap;

use super::points::{DroppedWindow, ExtractOptions, NoiseModel, StationSeen, DAMAGED_CHUNK};
use super::stillstand::{Stillstand, StillstandDetector};
use crate::session::messages::{AxisMap, Name, RunEvent, TracerSample};
use crate::session::reader::Stamped;

/// A `point_begin` whose `point_end` has not come yet.
pub(crate) struct OpenWindow {
    pub(crate) log_time_ns: u64,
    pub(crate) station: Name,
    pub(crate) point: usize,
    pub(crate) pass: usize,
    pub(crate) target: Name,
    pub(crate) nominal_m: [f64; 3],
    pub(crate) axes: AxisMap<f64>,
    pub(crate) approach: AxisMap<i8>,
}

/// A closed window whose samples settled.
pub(crate) struct Measured {
    pub(crate) window: OpenWindow,
    pub(crate) station_index: usize,
    pub(crate) settled: Settled,
}

pub(crate) struct Settled {
    pub(crate) mean_m: f64,
    pub(crate) sigma_m: f64,
    pub(crate) count: usize,
    pub(crate) from_s: f64,
    pub(crate) to_s: f64,
    pub(crate) beam_segment: u32,
}

/// A streamed extraction's state once its session began: the one tracer, its declared noise
/// and the pairing (`M` as in `Pairing`).
pub(crate) struct StreamStart<M> {
    pub(crate) tracer_id: String,
    pub(crate) noise: Option<NoiseModel>,
    pub(crate) pairing: Pairing<M>,
}

impl<M> StreamStart<M> {
    /// The start of a stream of a session with exactly one tracer (None otherwise), with the
    /// header's noise model and stillstand settings; room for one measurement per two events.
    pub(crate) fn of_header(
        header: &crate::session::messages::SessionHeader,
        tracers: &[String],
        run_events: usize,
    ) -> Option<Self> {
        let [tracer_id] = tracers else {
            return None;
        };
        let noise = NoiseModel::from_header(header, tracer_id);
        let mut pairing = Pairing::new(noise, ExtractOptions::from_header(header));
        // A window takes two events (point_begin, point_end): no regrowth of the lengths.
        pairing.measurements.reserve(run_events / 2);
        Some(StreamStart {
            tracer_id: tracer_id.clone(),
            noise,
            pairing,
        })
    }
}

/// Event-by-event state of the extraction; `M` is what a measured window becomes.
pub(crate) struct Pairing<M> {
    noise: Option<NoiseModel>,
    previous_ns: u64,
    open: Option<OpenWindow>,
    station_index: BTreeMap<String, usize>,
    pub(crate) stations: Vec<StationSeen>,
    pub(crate) measurements: Vec<M>,
    pub(crate) dropped: Vec<DroppedWindow>,
    pub(crate) repeated: Vec<DroppedWindow>,
    /// Reset for every window: its queues keep their room instead of growing anew.
    detector: StillstandDetector,
}

impl<M> Pairing<M> {
    pub(crate) fn new(noise: Option<NoiseModel>, options: ExtractOptions) -> Self {
        Pairing {
            noise,
            previous_ns: 0,
            open: None,
            station_index: BTreeMap::new(),
            stations: Vec::new(),
            measurements: Vec::new(),
            dropped: Vec::new(),
            repeated: Vec::new(),
            detector: StillstandDetector::new(options.window_s, options.tolerance_m),
        }
    }

    /// The log time of the open window's `point_begin`: no earlier sample is needed any more.
    pub(crate) fn open_since_ns(&self) -> Option<u64> {
        self.open.as_ref().map(|w| w.log_time_ns)
    }

    fn index_of(&mut self, id: &str, hint: Option<[f64; 3]>) -> usize {
        if let Some(&index) = self.station_index.get(id) {
            return index;
        }
        let next = self.station_index.len();
        let stations = &mut self.stations;
        *self.station_index.entry(id.to_string()).or_insert_with(|| {
            stations.push(StationSeen {
                id: id.to_string(),
                hint_m: hint,
            });
            next
        })
    }

    /// One event, in log-time order. `samples` (sorted by log time) must hold every sample of
    /// the selected tracer from the open window's begin up to at least this event's log time;
    /// `lost(from, to)` says whether messages in that span may be lost in a damaged chunk.
    pub(crate) fn event(
        &mut self,
        event: &Stamped<RunEvent>,
        samples: &[Stamped<TracerSample>],
        lost: &impl Fn(u64, u64) -> bool,
        make: &mut impl FnMut(Measured) -> M,
    ) {
        if matches!(event.msg, RunEvent::PointBegin { .. }) {
            return self.event_owned(event.clone(), samples, lost, make);
        }
        let since_ns = std::mem::replace(&mut self.previous_ns, event.log_time_ns);
        let reason = |w: &OpenWindow, to_ns: u64, otherwise: &'static str| {
            if lost(w.log_time_ns, to_ns) {
                DAMAGED_CHUNK
            } else {
                otherwise
            }
        };
        match &event.msg {
            RunEvent::StationBegin {
                station, hint_m, ..
            } => {
                self.index_of(station, *hint_m);
            }
            RunEvent::Rehome { .. } => {
                if let Some(w) = self.open.take() {
                    self.repeated
                        .push(dropped(&w, "beam broken: repeated after re-homing"));
                }
            }
            RunEvent::Resume { .. } => {
                if let Some(w) = self.open.take() {
                    self.repeated
                        .push(dropped(&w, "run interrupted: repeated after resume"));
                }
            }
            RunEvent::UnplannedStop { .. } => {
                if let Some(w) = self.open.take() {
                    self.repeated
                        .push(dropped(&w, "not the planned stop (unplanned_stop)"));
                }
            }
            RunEvent::PointEnd {
                station,
                point,
                pass,
            } => {
                let Some(w) = self.open.take() else {
                    // Its point_begin was in a damaged chunk.
                    if lost(since_ns, event.log_time_ns) {
                        self.dropped.push(DroppedWindow {
                            station: station.to_string(),
                            point: *point,
                            pass: *pass,
                            reason: DAMAGED_CHUNK.into(),
                        });
                    }
                    return;
                };
                let why = reason(
                    &w,
                    event.log_time_ns,
                    "point_end does not match its point_begin",
                );
                if (&w.station, w.point, w.pass) != (station, *point, *pass) || why == DAMAGED_CHUNK
                {
                    self.dropped.push(dropped(&w, why));
                    return;
                }
                let station_index = self.index_of(&w.station, None);
                let window = in_window(samples, w.log_time_ns, event.log_time_ns);
                match settle(window, self.noise, &mut self.detector) {
                    Ok(settled) => {
                        let measured = make(Measured {
                            window: w,
                            station_index,
                            settled,
                        });
                        self.measurements.push(measured);
                    }
                    Err(reason) => self.dropped.push(dropped(&w, reason)),
                }
            }
            _ => {}
        }
    }

    /// As `event`, taking the event: a `point_begin`'s names and maps move into the open
    /// window instead of being copied.
    pub(crate) fn event_owned(
        &mut self,
        event: Stamped<RunEvent>,
        samples: &[Stamped<TracerSample>],
        lost: &impl Fn(u64, u64) -> bool,
        make: &mut impl FnMut(Measured) -> M,
    ) {
        let Stamped {
            log_time_ns,
            publish_time_ns,
            msg,
        } = event;
        match msg {
            RunEvent::PointBegin {
                station,
                point,
                pass,
                target,
                nominal_m,
                axes,
                approach,
            } => {
                self.previous_ns = log_time_ns;
                let window = OpenWindow {
                    log_time_ns,
                    station,
                    point,
                    pass,
                    target,
                    nominal_m,
                    axes,
                    approach,
                };
                self.open_window(window, lost);
            }
            msg => {
                let event = Stamped {
                    log_time_ns,
                    publish_time_ns,
                    msg,
                };
                self.event(&event, samples, lost, make);
            }
        }
    }

    /// A `point_begin` opens `window`; a window still open never closed.
    fn open_window(&mut self, window: OpenWindow, lost: &impl Fn(u64, u64) -> bool) {
        if let Some(w) = self.open.take() {
            let why = if lost(w.log_time_ns, window.log_time_ns) {
                DAMAGED_CHUNK
            } else {
                "point_begin without point_end"
            };
            self.dropped.push(dropped(&w, why));
        }
        self.open = Some(window);
    }

    /// The session is over: a window still open never closed.
    pub(crate) fn finish(&mut self, lost: &impl Fn(u64, u64) -> bool) {
        if let Some(w) = self.open.take() {
            let why = if lost(w.log_time_ns, u64::MAX) {
                DAMAGED_CHUNK
            } else {
                "no point_end (session cut short?)"
            };
            self.dropped.push(dropped(&w, why));
        }
    }
}

fn dropped(w: &OpenWindow, reason: &str) -> DroppedWindow {
    DroppedWindow {
        station: w.station.to_string(),
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

/// The last settled stretch of a dwell window, averaged.
fn settle(
    window: &[Stamped<TracerSample>],
    noise: Option<NoiseModel>,
    detector: &mut StillstandDetector,
) -> Result<Settled, &'static str> {
    let first = window.first().ok_or("no tracer samples in the window")?;
    let beam_segment = first.msg.beam_segment;
    if window
        .iter()
        .any(|s| !s.msg.tracking || s.msg.beam_segment != beam_segment)
    {
        return Err("beam broken inside the window");
    }
    detector.reset();
    let mut stretch: Option<(f64, f64)> = None;
    for s in window {
        if let Stillstand::Settled { since_s } = detector.push(s.msg.t_s, s.msg.length_m) {
            stretch = Some((since_s, s.msg.t_s));
        }
    }
    let (from_s, to_s) = stretch.ok_or("never settled inside the window")?;
    let settled = || {
        window
            .iter()
            .filter(move |s| s.msg.t_s >= from_s && s.msg.t_s <= to_s)
            .map(|s| s.msg.length_m)
    };
    let count = settled().count();
    if count < 2 {
        return Err("settled stretch holds fewer than 2 samples");
    }
    let mean_m = settled().sum::<f64>() / count as f64;
    let sigma_m = match noise {
        Some(model) => model.mean_sigma(count).at_zero_beam_m,
        None => {
            let var = settled().map(|v| (v - mean_m).powi(2)).sum::<f64>() / (count - 1) as f64;
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
