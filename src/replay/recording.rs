//! A recorded session laid out for replay: the tracer samples in order (held whole, or streamed
//! from a clean file: `stream::Samples`), every other message placed between them (`after`),
//! and the machine arrivals and device faults the recording implies.
//!
//! Placement: a message recorded at log time T comes after every tracer sample logged at or
//! before T. The recorder stamps samples and events with one clock in call order, so this is
//! the order in which the sequencer saw them (a simulated run stamps events with the time of
//! the sample before them; a live run with a later time).

use std::collections::BTreeSet;
use std::path::Path;

use geocal_drivers::{AxisPositions, DeviceError, LinkFault};

use crate::extract::{Stillstand, StillstandDetector};
use crate::plan::Plan;
use crate::session::messages::{
    AxisMap, EnvSample, MachineStateSample, RotaryStateSample, RunEvent, TracerSample,
};
use crate::session::reader::{Completeness, Session, Stamped};

use super::stream::{choose_tracer, Mark, MarkedEvents, Samples, TimeMarks};

/// A recorded message and its place among the tracer samples.
#[derive(Debug, Clone, PartialEq)]
pub struct Placed<T> {
    /// Number of tracer samples recorded before it.
    pub after: usize,
    pub log_time_ns: u64,
    pub msg: T,
}

/// Where the recording shows a machine move ending.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Arrival {
    /// The machine reports arrival once this many samples have been delivered.
    At(usize),
    /// The recording ends before the move does.
    Never,
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum RecordingError {
    #[error("the session has no tracer stream (/tracer/<id>/range) to replay")]
    NoTracer,
    #[error("the session has {0} tracer streams and its header names none of them as a tracer")]
    AmbiguousTracer(usize),
}

#[derive(Debug)]
pub struct Recording {
    pub tracer_id: String,
    pub machine_id: String,
    pub env_id: Option<String>,
    pub table_id: Option<String>,
    /// The tracer samples: held whole, or streamed from the file as the replay goes.
    pub samples: Samples,
    pub events: Vec<Placed<RunEvent>>,
    /// Per event: the seq of the tracer sample before it.
    pub event_seqs: Vec<Option<u64>>,
    pub env: Vec<Placed<EnvSample>>,
    pub rotary: Vec<Placed<RotaryStateSample>>,
    /// The machine's recorded arrivals (`/machine/<id>/state` polls that reported it at
    /// rest); empty in recordings made before the sequencer wrote them.
    pub arrivals: Vec<Placed<MachineStateSample>>,
    /// Cursors k after which some recorded message carries a later log time than sample k-1
    /// (a wall-clock recording) rather than the same one (a virtual clock).
    later_at: BTreeSet<usize>,
    /// The first tracer sample's log time.
    pub first_sample_ns: Option<u64>,
    /// The earliest log time in the recording.
    pub earliest_ns: u64,
    /// The clock reading at which the recorded run started (rotary state times count from it).
    pub start_ns: u64,
    pub completeness: Completeness,
}

fn device_id(session: &Session, kind: &str) -> Option<String> {
    session
        .header
        .devices
        .iter()
        .find(|d| d.kind == kind)
        .map(|d| d.id.clone())
}

/// The recorded streams of the other devices a replay follows (each sorted by log time).
struct OtherDevices {
    machine_id: String,
    env_id: Option<String>,
    table_id: Option<String>,
    env: Vec<Stamped<EnvSample>>,
    rotary: Vec<Stamped<RotaryStateSample>>,
    arrivals: Vec<Stamped<MachineStateSample>>,
}

impl OtherDevices {
    fn of(session: &Session) -> OtherDevices {
        let env_id = device_id(session, "environment")
            .filter(|id| session.env.contains_key(id))
            .or_else(|| session.env.keys().next().cloned());
        let env = env_id
            .as_ref()
            .and_then(|id| session.env.get(id))
            .cloned()
            .unwrap_or_default();
        let table_id =
            device_id(session, "rotary_table").or_else(|| session.rotary.keys().next().cloned());
        let rotary = table_id
            .as_ref()
            .and_then(|id| session.rotary.get(id))
            .cloned()
            .unwrap_or_default();
        let machine_id = device_id(session, "machine").unwrap_or_else(|| "machine".into());
        let arrivals = session
            .machines
            .get(&machine_id)
            .map(|v| {
                v.iter()
                    .filter(|e| e.msg.state == "Idle")
                    .cloned()
                    .collect()
            })
            .unwrap_or_default();
        OtherDevices {
            machine_id,
            env_id,
            table_id,
            env,
            rotary,
            arrivals,
        }
    }

    /// Every log time of these streams, sorted, without repeats.
    fn log_times(&self) -> Vec<u64> {
        let mut times: Vec<u64> = (self.env.iter().map(|e| e.log_time_ns))
            .chain(self.rotary.iter().map(|e| e.log_time_ns))
            .chain(self.arrivals.iter().map(|e| e.log_time_ns))
            .collect();
        times.sort_unstable();
        times.dedup();
        times
    }
}

/// A recorded run event with its mark among the tracer samples.
struct MarkedEvent {
    event: Stamped<RunEvent>,
    mark: Mark,
}

/// The replay's view of the recording, whatever holds its samples.
struct Parts {
    tracer_id: String,
    samples: Samples,
    first_sample_ns: Option<u64>,
    events: Vec<MarkedEvent>,
    others: OtherDevices,
    completeness: Completeness,
}

/// Marks every log time among `samples`, as `stream::TimeMarks` does for a streamed file.
pub(crate) fn mark_in(samples: &[Stamped<TracerSample>], log_time_ns: u64) -> Mark {
    let before = samples.partition_point(|s| s.log_time_ns < log_time_ns);
    let at_or_before = samples.partition_point(|s| s.log_time_ns <= log_time_ns);
    let last = at_or_before.checked_sub(1).map(|i| &samples[i]);
    Mark {
        before,
        at_or_before,
        first_seq_from: samples.get(before).map(|s| s.msg.seq),
        last_seq_to: last.map(|s| s.msg.seq),
        later: last.is_none_or(|s| log_time_ns > s.log_time_ns),
    }
}

impl Recording {
    /// The recording of a session read whole.
    pub fn new(session: &Session) -> Result<Recording, RecordingError> {
        let tracer_id =
            choose_tracer(&session.header, session.tracers.keys()).map_err(|n| match n {
                0 => RecordingError::NoTracer,
                n => RecordingError::AmbiguousTracer(n),
            })?;
        let samples = session.tracers.get(&tracer_id).cloned().unwrap_or_default();
        let events = session
            .events
            .iter()
            .map(|e| MarkedEvent {
                event: e.clone(),
                mark: mark_in(&samples, e.log_time_ns),
            })
            .collect();
        let mark = |t: u64| mark_in(&samples, t);
        let parts = Parts {
            tracer_id,
            first_sample_ns: samples.first().map(|s| s.log_time_ns),
            events,
            others: OtherDevices::of(session),
            completeness: session.completeness.clone(),
            samples: Samples::whole(Vec::new()),
        };
        let mut recording = Recording::assemble(parts, &mark);
        recording.samples = Samples::whole(samples);
        Ok(recording)
    }

    /// The recording of a clean session file, streamed: its tracer samples are read by a
    /// thread as the replay reaches them and never held whole. `marked` and `rest` are the
    /// file's first streamed read (`stream::EventMarks::read`). None when the file does not
    /// stream (read it whole).
    pub fn streamed(path: &Path, marked: &MarkedEvents, rest: &Session) -> Option<Recording> {
        let others = OtherDevices::of(rest);
        let times = others.log_times();
        let marks = if times.is_empty() {
            Vec::new()
        } else {
            TimeMarks::read(path, &marked.tracer_id, &times)?
        };
        let mark = |t: u64| {
            times
                .binary_search(&t)
                .ok()
                .and_then(|k| marks.get(k))
                .copied()
                .unwrap_or_default()
        };
        let events = marked
            .events
            .iter()
            .zip(&marked.marks)
            .map(|(event, mark)| MarkedEvent {
                event: event.clone(),
                mark: *mark,
            })
            .collect();
        let samples = Samples::streamed(path, &marked.tracer_id, marked.samples).ok()?;
        let parts = Parts {
            tracer_id: marked.tracer_id.clone(),
            samples,
            first_sample_ns: marked.first_log_ns,
            events,
            others,
            completeness: rest.completeness.clone(),
        };
        Some(Recording::assemble(parts, &mark))
    }

    fn assemble(parts: Parts, mark: &dyn Fn(u64) -> Mark) -> Recording {
        let Parts {
            tracer_id,
            samples,
            first_sample_ns,
            events: marked_events,
            others,
            completeness,
        } = parts;
        let mut later_at = BTreeSet::new();
        let mut earliest = first_sample_ns.unwrap_or(0);
        let mut place = |log_time_ns: u64, m: Mark| {
            if m.later {
                later_at.insert(m.at_or_before);
            }
            earliest = earliest.min(log_time_ns);
            m.at_or_before
        };
        let mut events = Vec::with_capacity(marked_events.len());
        let mut event_seqs = Vec::with_capacity(marked_events.len());
        for MarkedEvent { event, mark } in marked_events {
            events.push(Placed {
                after: place(event.log_time_ns, mark),
                log_time_ns: event.log_time_ns,
                msg: event.msg,
            });
            event_seqs.push(mark.last_seq_to);
        }
        let mut placed = |t: u64| place(t, mark(t));
        let env: Vec<_> = (others.env.into_iter())
            .map(|e| Placed {
                after: placed(e.log_time_ns),
                log_time_ns: e.log_time_ns,
                msg: e.msg,
            })
            .collect();
        let rotary: Vec<_> = (others.rotary.into_iter())
            .map(|e| Placed {
                after: placed(e.log_time_ns),
                log_time_ns: e.log_time_ns,
                msg: e.msg,
            })
            .collect();
        let arrivals: Vec<_> = (others.arrivals.into_iter())
            .map(|e| Placed {
                after: placed(e.log_time_ns),
                log_time_ns: e.log_time_ns,
                msg: e.msg,
            })
            .collect();
        // Rotary state times count from the run's start: recover it from the first one.
        let start_ns = rotary
            .first()
            .map(|r| {
                r.log_time_ns
                    .saturating_sub((r.msg.t_s.max(0.0) * 1e9).round() as u64)
            })
            .unwrap_or(earliest);
        Recording {
            tracer_id,
            machine_id: others.machine_id,
            env_id: others.env_id,
            table_id: others.table_id,
            samples,
            events,
            event_seqs,
            env,
            rotary,
            arrivals,
            later_at,
            first_sample_ns,
            earliest_ns: earliest,
            start_ns,
            completeness,
        }
    }

    /// Whether the messages recorded after sample k-1 carry later log times than it.
    pub fn later_at(&self, k: usize) -> bool {
        k > self.samples.len() || self.later_at.contains(&k)
    }

    /// Where the recording shows the move the sequencer starts with `start_cursor` samples
    /// delivered, to `target`, ending: at the next `point_begin` (which must be at the target),
    /// at a `beam_break` fault (the move ended with the beam broken), or, for a move to the
    /// homing point, where the sequencer's homing dwell must begin to end where the recording
    /// homed. An error when the recording's next point lies elsewhere.
    pub fn arrival(
        &mut self,
        plan: &Plan,
        machine_id: &str,
        start_cursor: usize,
        target: &AxisPositions,
    ) -> Result<Arrival, DeviceError> {
        self.arrival_explained(plan, machine_id, start_cursor, target)
            .map(|(arrival, _)| arrival)
    }

    /// `arrival`, with what in the recording decided it (for the replay's trail).
    pub fn arrival_explained(
        &mut self,
        plan: &Plan,
        machine_id: &str,
        start_cursor: usize,
        target: &AxisPositions,
    ) -> Result<(Arrival, &'static str), DeviceError> {
        let inferred = self.inferred_arrival(plan, machine_id, start_cursor, target)?;
        if self.arrivals.is_empty() {
            return Ok(inferred);
        }
        // The move ends at the poll that reported the machine at rest; the events have still
        // checked that the move is the recorded one.
        Ok(
            match self.arrivals.iter().find(|a| a.after > start_cursor) {
                Some(recorded) => (Arrival::At(recorded.after), "the recorded arrival"),
                None => (Arrival::Never, "the recording ends first"),
            },
        )
    }

    /// The arrival of a recording without recorded arrivals, inferred from the events.
    fn inferred_arrival(
        &mut self,
        plan: &Plan,
        machine_id: &str,
        start_cursor: usize,
        target: &AxisPositions,
    ) -> Result<(Arrival, &'static str), DeviceError> {
        let home = plan.points.first().map(|p| p.axes_m);
        let to_home = home.is_some_and(|h| same_axes(target, &h));
        let next = self.events.iter().position(|e| e.after > start_cursor);
        for k in next.into_iter().flat_map(|k| k..self.events.len()) {
            let event = &self.events[k];
            match &event.msg {
                RunEvent::PointBegin {
                    point,
                    axes,
                    pass,
                    station,
                    ..
                } => {
                    if !axes_match(target, axes) {
                        return Err(DeviceError::Rejected {
                            device: machine_id.to_string(),
                            message: format!(
                                "replay: the sequencer commanded a move to {} after sample {}, \
                                 but the recording's next point is point {point} (pass {pass}, \
                                 station {station}) at {} (log time {} ns)",
                                show_axes(target),
                                start_cursor,
                                show_axes(axes),
                                event.log_time_ns
                            ),
                        });
                    }
                    return Ok(if to_home && *point == 0 {
                        let marked = event.after;
                        self.homing_arrival(plan, start_cursor + 1, marked)
                    } else {
                        (Arrival::At(event.after), "the next point_begin")
                    });
                }
                RunEvent::Fault { code, .. } if code == "beam_break" => {
                    return Ok((Arrival::At(event.after), "a beam_break fault"))
                }
                RunEvent::Rehome { .. } if to_home => {
                    let marked = event.after;
                    return Ok(self.homing_arrival(plan, start_cursor + 1, marked));
                }
                RunEvent::StationBegin { station, .. } | RunEvent::StationEnd { station } => {
                    return Err(DeviceError::Rejected {
                        device: machine_id.to_string(),
                        message: format!(
                            "replay: the sequencer commanded a move to {} after sample {}, but \
                             the recording goes on to station {station}'s begin or end first \
                             (log time {} ns)",
                            show_axes(target),
                            start_cursor,
                            event.log_time_ns
                        ),
                    });
                }
                _ => {}
            }
        }
        Ok((Arrival::Never, "the recording ends first"))
    }

    /// The arrival for a homing whose first sample after zeroing was sample `marked - 1`:
    /// the latest arrival (not before `lo`) from which the sequencer's homing dwell (stillstand
    /// with no minimum dwell, or `max_dwell_s`) ends exactly at the sample before that.
    fn homing_arrival(&mut self, plan: &Plan, lo: usize, marked: usize) -> (Arrival, &'static str) {
        if !self.arrivals.is_empty() {
            // Recorded, not inferred (see `arrival_explained`).
            return (Arrival::At(lo), "recorded");
        }
        let Some(end) = marked.checked_sub(2) else {
            return (Arrival::At(lo), "a homing at the recording's start");
        };
        let end_s = self.samples.get(end).map_or(0.0, |s| s.msg.t_s);
        let mut a = end;
        while a >= lo.max(1) {
            if dwell_end(&mut self.samples, plan, a, end) == Some(end) {
                return (Arrival::At(a), "the recorded homing reproduced");
            }
            // A dwell ends by max_dwell_s: earlier arrivals cannot end this late.
            let begin_s = self
                .samples
                .get(a - 1)
                .map_or(f64::NEG_INFINITY, |s| s.msg.t_s);
            if end_s - begin_s > plan.max_dwell_s + plan.stillstand_window_s {
                break;
            }
            a -= 1;
        }
        tracing::warn!(
            "replay: no arrival reproduces the recorded homing before sample {marked}; \
             reporting arrival at once"
        );
        (
            Arrival::At(lo),
            "no arrival reproduces the recorded homing: at once",
        )
    }

    /// Recorded device faults of `device` that the replayed device raises again (the
    /// sequencer retries them and records each as it did): timeouts and protocol errors.
    pub fn device_faults(&self, device: &str) -> Vec<(usize, DeviceError)> {
        self.events
            .iter()
            .filter_map(|e| match &e.msg {
                RunEvent::Fault {
                    device: d,
                    code,
                    message,
                } if d == device => replayed_error(device, code, message).map(|err| (e.after, err)),
                _ => None,
            })
            .collect()
    }
}

/// Where the sequencer's homing dwell from an arrival after sample `a - 1` ends (stillstand
/// with no minimum dwell, or `max_dwell_s`), if by sample `end`.
fn dwell_end(samples: &mut Samples, plan: &Plan, a: usize, end: usize) -> Option<usize> {
    let begin_s = samples.get(a.checked_sub(1)?)?.msg.t_s;
    let mut detector =
        StillstandDetector::new(plan.stillstand_window_s, plan.stillstand_tolerance_m);
    for j in a..=end {
        let s = samples.get(j)?;
        if !s.msg.tracking {
            return None;
        }
        let settled = matches!(
            detector.push(s.msg.t_s, s.msg.length_m),
            Stillstand::Settled { .. }
        );
        if settled || s.msg.t_s - begin_s >= plan.max_dwell_s {
            return Some(j);
        }
    }
    None
}

/// Fault codes a driver detects and recovers from by itself (`LinkFault`): replayed through
/// `take_link_faults`, so the sequencer records them again where it did.
const LINK_FAULT_CODES: [&str; 4] = ["crc", "resync", "disconnect", "reconnect"];

impl Recording {
    /// Recorded link faults of `device`, each with the cursor after which it was recorded.
    pub fn link_faults(&self, device: &str) -> Vec<(usize, LinkFault)> {
        self.events
            .iter()
            .filter_map(|e| match &e.msg {
                RunEvent::Fault {
                    device: d,
                    code,
                    message,
                } if d == device && LINK_FAULT_CODES.contains(&code.as_str()) => Some((
                    e.after,
                    LinkFault {
                        code: code.clone(),
                        message: message.clone(),
                    },
                )),
                _ => None,
            })
            .collect()
    }
}

/// The device error behind a recorded `fault` event, rebuilt so that the sequencer records
/// the same message again; None for faults the sequencer itself derives (beam breaks, ...).
fn replayed_error(device: &str, code: &str, message: &str) -> Option<DeviceError> {
    // The sequencer appends " (retry n of N)" or " (giving up after N retries)".
    let text = message
        .rfind(" (retry ")
        .or_else(|| message.rfind(" (giving up"))
        .map_or(message, |i| &message[..i]);
    let body = text
        .strip_prefix(device)
        .and_then(|t| t.strip_prefix(": "))
        .unwrap_or(text);
    match code {
        "timeout" => {
            let parsed = body.strip_prefix("timed out after ").and_then(|rest| {
                let (after, what) = rest.split_once(" s waiting for ")?;
                Some((after.parse::<f64>().ok()?, what.to_string()))
            });
            let (after_s, what) = parsed.unwrap_or((0.0, format!("(replayed) {body}")));
            Some(DeviceError::Timeout {
                device: device.to_string(),
                what,
                after_s,
            })
        }
        "protocol" => Some(DeviceError::Protocol {
            device: device.to_string(),
            message: body
                .strip_prefix("protocol error: ")
                .unwrap_or(body)
                .to_string(),
        }),
        // A failed environment poll is recorded with the error's own text.
        "poll" => Some(DeviceError::Rejected {
            device: device.to_string(),
            message: body.to_string(),
        }),
        _ => None,
    }
}

/// Commanded and recorded axis positions agree (1 nm: the plan is rebuilt from its JSON).
const AXIS_MATCH_M: f64 = 1e-9;

fn axes_match(a: &AxisPositions, b: &AxisMap<f64>) -> bool {
    a.len() == b.len()
        && a.iter()
            .all(|(k, v)| b.get(k).is_some_and(|w| (v - w).abs() <= AXIS_MATCH_M))
}

fn same_axes(a: &AxisPositions, h: &[f64; 3]) -> bool {
    crate::plan::AXES
        .iter()
        .zip(h)
        .all(|(name, v)| a.get(*name).is_some_and(|w| (v - w).abs() <= AXIS_MATCH_M))
}

pub fn show_axes<'a, K: std::fmt::Display + 'a>(
    a: impl IntoIterator<Item = (&'a K, &'a f64)>,
) -> String {
    let parts: Vec<String> = a.into_iter().map(|(k, v)| format!("{k}={v} m")).collect();
    format!("({})", parts.join(", "))
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;

    use super::*;
    use crate::plan::{PlanPoint, AXES};
    use crate::session::reader::testutil::header;

    fn plan() -> Plan {
        Plan {
            targets: Vec::new(),
            points: vec![
                PlanPoint {
                    index: 0,
                    axes_m: [0.0, 0.0, 0.0],
                },
                PlanPoint {
                    index: 1,
                    axes_m: [0.1, 0.0, 0.0],
                },
            ],
            stations: Vec::new(),
            passes: Vec::new(),
            dwell_s: 0.5,
            max_dwell_s: 10.0,
            stillstand_window_s: 0.2,
            stillstand_tolerance_m: 1e-6,
        }
    }

    fn axes(p: [f64; 3]) -> AxisPositions {
        AXES.iter().map(|a| a.to_string()).zip(p).collect()
    }

    fn stamped<T>(t_ns: u64, msg: T) -> Stamped<T> {
        Stamped {
            log_time_ns: t_ns,
            publish_time_ns: t_ns,
            msg,
        }
    }

    /// 100 Hz: a move until sample 30, still from then on; the recording homed after sample
    /// 60 (point_begin of point 0 after the next sample), then went to point 1.
    fn session() -> Session {
        let samples = (0..200u64)
            .map(|i| {
                let length_m = if i < 30 { 1e-3 * i as f64 } else { 0.03 };
                stamped(
                    i * 10_000_000,
                    TracerSample {
                        seq: i,
                        t_s: i as f64 * 0.01,
                        length_m,
                        signal: 1.0,
                        tracking: true,
                        beam_segment: 0,
                    },
                )
            })
            .collect();
        let begin = |point: usize, at: u64| {
            stamped(
                at * 10_000_000 - 10_000_000,
                RunEvent::PointBegin {
                    station: "s1".into(),
                    point,
                    pass: 0,
                    target: "t0".into(),
                    nominal_m: [0.0; 3],
                    axes: axes(plan().points[point].axes_m)
                        .iter()
                        .map(|(name, value)| (name.as_str(), *value))
                        .collect(),
                    approach: AxisMap::new(),
                },
            )
        };
        Session {
            header: header(),
            tracers: BTreeMap::from([("tracer0".to_string(), samples)]),
            env: BTreeMap::new(),
            rotary: BTreeMap::new(),
            machines: BTreeMap::new(),
            probes: BTreeMap::new(),
            topics: BTreeMap::new(),
            events: vec![begin(0, 62), begin(1, 150)],
            completeness: Completeness::Complete,
            damaged: Vec::new(),
            lost_before_repair: Vec::new(),
            skipped: 0,
            ignored: 0,
        }
    }

    /// The homing dwell from the found arrival ends exactly where the recording homed.
    #[test]
    fn the_homing_arrival_reproduces_the_recorded_homing() {
        let mut recording = Recording::new(&session()).expect("recording");
        assert_eq!(recording.events[0].after, 62);
        let arrival = recording
            .arrival(&plan(), "cmm", 0, &axes([0.0; 3]))
            .expect("arrival");
        // A window counts as full once it spans 0.2 s less one sample period (stillstand.rs):
        // 20 samples at 100 Hz, so the dwell that ends at sample 60 begins at sample 41.
        assert_eq!(arrival, Arrival::At(41));
        let next = recording
            .arrival(&plan(), "cmm", 70, &axes([0.1, 0.0, 0.0]))
            .expect("arrival");
        assert_eq!(next, Arrival::At(150));
    }

    #[test]
    fn a_move_the_recording_does_not_hold_is_an_error() {
        let mut recording = Recording::new(&session()).expect("recording");
        let err = recording
            .arrival(&plan(), "cmm", 70, &axes([0.2, 0.0, 0.0]))
            .expect_err("no such move");
        let text = err.to_string();
        assert!(
            text.contains("commanded a move to (x=0.2 m, y=0 m, z=0 m) after sample 70")
                && text.contains("next point is point 1"),
            "{text}"
        );
        // Past the last point the recording holds no arrival: the stream ends first.
        let end = recording
            .arrival(&plan(), "cmm", 160, &axes([0.1, 0.0, 0.0]))
            .expect("no error");
        assert_eq!(end, Arrival::Never);
    }

    #[test]
    fn recorded_faults_come_back_with_their_messages() {
        let e = replayed_error(
            "tracer0",
            "timeout",
            "tracer0: timed out after 0.2 s waiting for a sample (retry 1 of 5)",
        )
        .expect("timeout");
        assert_eq!(
            e.to_string(),
            "tracer0: timed out after 0.2 s waiting for a sample"
        );
        let e = replayed_error(
            "cmm",
            "protocol",
            "cmm: protocol error: error:20 (giving up after 5 retries)",
        )
        .expect("protocol");
        assert_eq!(e.to_string(), "cmm: protocol error: error:20");
        assert!(replayed_error("tracer0", "beam_break", "beam broken").is_none());
        assert!(replayed_error("tracer0", "frames_lost", "3 frames").is_none());
    }
}
