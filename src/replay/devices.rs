//! Replay drivers: the device traits fed from one recording through a shared cursor (the
//! number of tracer samples delivered), and the clock that follows the recorded log times.

use std::collections::VecDeque;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use async_trait::async_trait;
use geocal_drivers::{
    AxisPositions, DeviceError, EnvReading, Environment, LinkFault, Machine, MachineState,
    Operator, Probe, ProbeReading, RotaryState, RotaryTable, Tracer, TracerReading,
};

use super::recording::{Arrival, Recording};
use crate::plan::Plan;
use crate::run::replay::ClockState;
pub use crate::run::replay::ReplayClock;
use crate::session::messages::RunEvent;
use crate::session::recorder::RecorderHandle;

/// What every replay device shares: the recording and how far the replay has got.
pub struct ReplayState {
    recording: Recording,
    plan: Plan,
    /// Tracer samples delivered so far.
    cursor: usize,
    /// Pace delivery by the wall clock (`--realtime`), from this instant and log time.
    realtime: Option<(Instant, u64)>,
    clock: Arc<ReplayClock>,
    /// Recorded device faults still to raise again, per device, in order.
    tracer_faults: VecDeque<(usize, DeviceError)>,
    machine_faults: VecDeque<(usize, DeviceError)>,
    env_faults: VecDeque<(usize, DeviceError)>,
    table_faults: VecDeque<(usize, DeviceError)>,
    /// Recorded link faults (recovered inside the drivers) still to report, per device.
    tracer_links: VecDeque<(usize, LinkFault)>,
    machine_links: VecDeque<(usize, LinkFault)>,
    table_links: VecDeque<(usize, LinkFault)>,
    /// Recorded environment samples handed out so far.
    env_next: usize,
    /// Where the current move or rotation ends (cursor), and the encoder angle in position.
    machine_arrival: Option<(Arrival, AxisPositions)>,
    table_arrival: Option<(Arrival, f64)>,
    /// A rotation through its overshoot angle: after the overshoot, the recorded in-position
    /// states are searched from this cursor for the station's own angle.
    table_second_leg: Option<(usize, f64)>,
    /// Cursor values at which the sequencer homed the tracer.
    pub homings: Vec<usize>,
    /// The replay's decisions in order (moves and where they end, homings): shown when the
    /// replay diverges, so that the divergence can be traced to a decision.
    pub trail: Vec<String>,
    /// The recorder of the replayed session: the tracer waits while its queue is long.
    pub recorder: Option<RecorderHandle>,
}

/// Decisions the trail keeps at least (a diverged replay shows its last few).
const TRAIL_KEPT: usize = 64;

/// Messages the replayed session's recorder may hold queued before the replay tracer waits
/// for it (at full speed the sequencer outruns the writer: the queue would hold the run).
const RECORDER_BACKLOG: u64 = 8192;

pub type SharedReplay = Arc<Mutex<ReplayState>>;

fn lock<'a>(
    shared: &'a SharedReplay,
    device: &str,
) -> Result<MutexGuard<'a, ReplayState>, DeviceError> {
    shared.lock().map_err(|_| DeviceError::Disconnected {
        device: device.to_string(),
        message: "replay state poisoned by an earlier panic".into(),
    })
}

impl ReplayClock {
    /// Follow the recording with `k` samples delivered.
    pub fn at_cursor(&self, recording: &mut Recording, k: usize) {
        let base_ns = k
            .checked_sub(1)
            .and_then(|i| recording.samples.get(i))
            .map_or(recording.earliest_ns, |s| s.log_time_ns);
        let limit_ns = recording
            .samples
            .get(k)
            .map_or(u64::MAX, |s| s.log_time_ns.saturating_sub(1))
            .max(base_ns);
        let mut c = self.state.lock().unwrap_or_else(|e| e.into_inner());
        *c = ClockState {
            base_ns,
            limit_ns,
            strict: recording.later_at(k),
            calls: 0,
        };
    }
}

impl ReplayState {
    pub fn new(
        mut recording: Recording,
        plan: Plan,
        realtime: bool,
    ) -> (SharedReplay, Arc<ReplayClock>) {
        let clock = Arc::new(ReplayClock::default());
        clock.at_cursor(&mut recording, 0);
        let queue = |id: &str| recording.device_faults(id).into_iter().collect();
        let tracer_faults = queue(&recording.tracer_id);
        let machine_faults = queue(&recording.machine_id);
        let env_faults = recording.env_id.as_deref().map(queue).unwrap_or_default();
        let table_faults = recording.table_id.as_deref().map(queue).unwrap_or_default();
        let links = |id: &str| recording.link_faults(id).into_iter().collect();
        let tracer_links = links(&recording.tracer_id);
        let machine_links = links(&recording.machine_id);
        let table_links = recording.table_id.as_deref().map(links).unwrap_or_default();
        let first_ns = recording.first_sample_ns.unwrap_or(0);
        let state = ReplayState {
            realtime: realtime.then(|| (Instant::now(), first_ns)),
            recording,
            plan,
            cursor: 0,
            clock: clock.clone(),
            tracer_faults,
            machine_faults,
            env_faults,
            table_faults,
            tracer_links,
            machine_links,
            table_links,
            env_next: 0,
            machine_arrival: None,
            table_arrival: None,
            table_second_leg: None,
            homings: Vec::new(),
            trail: Vec::new(),
            recorder: None,
        };
        (Arc::new(Mutex::new(state)), clock)
    }

    pub fn recording(&self) -> &Recording {
        &self.recording
    }

    pub fn recording_mut(&mut self) -> &mut Recording {
        &mut self.recording
    }

    pub fn cursor(&self) -> usize {
        self.cursor
    }

    /// The recorded run's events around the cursor, one line each (link faults left out):
    /// the last `before` placed at or before it and the next `after`, what the recording did
    /// where the replay stopped.
    pub fn recorded_events_near(&self, before: usize, after: usize) -> Vec<String> {
        let events: Vec<_> = (self.recording.events.iter())
            .zip(&self.recording.event_seqs)
            .filter(|(e, _)| {
                !matches!(&e.msg, RunEvent::Fault { code, .. }
                    if ["crc", "resync", "frames_lost"].contains(&code.as_str()))
            })
            .collect();
        let split = events.partition_point(|(e, _)| e.after <= self.cursor);
        events[split.saturating_sub(before)..(split + after).min(events.len())]
            .iter()
            .map(|(e, seq_before)| {
                let seq = seq_before.map_or(String::new(), |seq| format!(" (seq {seq})"));
                let text = serde_json::to_string(&e.msg).unwrap_or_default();
                format!("after sample {}{seq}: {}", e.after, shorten(&text, 160))
            })
            .collect()
    }

    /// A decision for the trail, which keeps the last `TRAIL_KEPT` or more.
    fn note(&mut self, decision: String) {
        if self.trail.len() >= 2 * TRAIL_KEPT {
            self.trail.drain(..TRAIL_KEPT);
        }
        self.trail.push(decision);
    }

    /// The next recorded fault of a device, if the replay has reached it.
    fn due(queue: &mut VecDeque<(usize, DeviceError)>, cursor: usize) -> Option<DeviceError> {
        if queue.front().is_some_and(|(after, _)| *after <= cursor) {
            queue.pop_front().map(|(_, e)| e)
        } else {
            None
        }
    }

    /// The recorded link faults of a device the replay has reached.
    fn due_links(queue: &mut VecDeque<(usize, LinkFault)>, cursor: usize) -> Vec<LinkFault> {
        let n = queue.partition_point(|(after, _)| *after <= cursor);
        queue.drain(..n).map(|(_, f)| f).collect()
    }

    fn end_of_stream(&self) -> DeviceError {
        DeviceError::EndOfStream {
            device: self.recording.tracer_id.clone(),
        }
    }
}

pub struct ReplayTracer {
    pub id: String,
    pub shared: SharedReplay,
}

#[async_trait]
impl Tracer for ReplayTracer {
    fn id(&self) -> &str {
        &self.id
    }

    async fn next_sample(&mut self) -> Result<TracerReading, DeviceError> {
        let recorder = lock(&self.shared, &self.id)?
            .recorder
            .clone()
            .filter(|r| r.queued() > RECORDER_BACKLOG);
        if let Some(recorder) = recorder {
            // The recorded times come from the replay clock: waiting changes nothing recorded.
            while recorder.queued() > RECORDER_BACKLOG / 2 {
                tokio::time::sleep(Duration::from_millis(1)).await;
            }
        }
        let (reading, wait) = {
            let mut s = lock(&self.shared, &self.id)?;
            let cursor = s.cursor;
            if let Some(e) = ReplayState::due(&mut s.tracer_faults, cursor) {
                return Err(e);
            }
            let Some(sample) = s.recording.samples.get(cursor) else {
                return Err(s.end_of_stream());
            };
            s.cursor += 1;
            let s = &mut *s;
            s.clock.at_cursor(&mut s.recording, s.cursor);
            // The devices look back at most to the sample before the cursor.
            s.recording.samples.release_before(cursor);
            let wait = s.realtime.map(|(start, first_ns)| {
                let due = start + Duration::from_nanos(sample.log_time_ns.saturating_sub(first_ns));
                due.saturating_duration_since(Instant::now())
            });
            let m = sample.msg;
            let reading = TracerReading {
                seq: m.seq,
                t_s: m.t_s,
                length_m: m.length_m,
                signal: m.signal,
                tracking: m.tracking,
                beam_segment: m.beam_segment,
            };
            (reading, wait)
        };
        if let Some(wait) = wait.filter(|w| !w.is_zero()) {
            tokio::time::sleep(wait).await;
        }
        Ok(reading)
    }

    /// The recorded samples already show the homing where it happened: nothing to zero here.
    async fn home(&mut self) -> Result<(), DeviceError> {
        let mut s = lock(&self.shared, &self.id)?;
        let cursor = s.cursor;
        if let Some(e) = ReplayState::due(&mut s.tracer_faults, cursor) {
            return Err(e);
        }
        s.homings.push(cursor);
        s.note(format!("after sample {cursor}: tracer homed"));
        Ok(())
    }

    fn take_link_faults(&mut self) -> Vec<LinkFault> {
        take_links(&self.shared, |s| &mut s.tracer_links)
    }
}

/// The due link faults from one of the state's queues (none if the state is poisoned).
fn take_links(
    shared: &SharedReplay,
    queue: impl FnOnce(&mut ReplayState) -> &mut VecDeque<(usize, LinkFault)>,
) -> Vec<LinkFault> {
    let mut s = shared.lock().unwrap_or_else(|e| e.into_inner());
    let cursor = s.cursor;
    ReplayState::due_links(queue(&mut s), cursor)
}

pub struct ReplayEnvironment {
    pub id: String,
    pub shared: SharedReplay,
}

#[async_trait]
impl Environment for ReplayEnvironment {
    fn id(&self) -> &str {
        &self.id
    }

    /// The recorded samples up to the replay's cursor (all that remain once the stream ended).
    async fn poll(&mut self) -> Result<Vec<EnvReading>, DeviceError> {
        let mut s = lock(&self.shared, &self.id)?;
        let cursor = s.cursor;
        if let Some(e) = ReplayState::due(&mut s.env_faults, cursor) {
            return Err(e);
        }
        let all_delivered = cursor >= s.recording.samples.len();
        let mut out = Vec::new();
        while let Some(e) = s.recording.env.get(s.env_next) {
            if e.after > cursor && !all_delivered {
                break;
            }
            out.push(EnvReading {
                t_s: e.msg.t_s,
                air_temp_k: e.msg.air_temp_k,
                pressure_pa: e.msg.pressure_pa,
                humidity_pct: e.msg.humidity_pct,
                material_temp_k: e.msg.material_temp_k.clone(),
            });
            s.env_next += 1;
        }
        Ok(out)
    }
}

pub struct ReplayMachine {
    pub id: String,
    pub shared: SharedReplay,
}

#[async_trait]
impl Machine for ReplayMachine {
    fn id(&self) -> &str {
        &self.id
    }

    async fn start_move(&mut self, target: &AxisPositions) -> Result<(), DeviceError> {
        let mut s = lock(&self.shared, &self.id)?;
        let cursor = s.cursor;
        if let Some(e) = ReplayState::due(&mut s.machine_faults, cursor) {
            return Err(e);
        }
        let st = &mut *s;
        let (arrival, why) = st
            .recording
            .arrival_explained(&st.plan, &self.id, cursor, target)?;
        let ends = match arrival {
            Arrival::At(at) => format!("arrives after sample {at}"),
            Arrival::Never => "never arrives".to_string(),
        };
        s.note(format!(
            "after sample {cursor}: move to {}: {ends} ({why})",
            crate::replay::recording::show_axes(target)
        ));
        s.machine_arrival = Some((arrival, target.clone()));
        Ok(())
    }

    async fn state(&mut self) -> Result<MachineState, DeviceError> {
        let mut s = lock(&self.shared, &self.id)?;
        let cursor = s.cursor;
        if let Some(e) = ReplayState::due(&mut s.machine_faults, cursor) {
            return Err(e);
        }
        Ok(match &s.machine_arrival {
            Some((Arrival::At(at), position)) if cursor >= *at => MachineState::Idle {
                position: position.clone(),
            },
            _ => MachineState::Moving,
        })
    }

    fn take_link_faults(&mut self) -> Vec<LinkFault> {
        take_links(&self.shared, |s| &mut s.machine_links)
    }
}

/// Places stations as the recording did: the sequencer's next station must be the recording's.
pub struct ReplayOperator {
    pub shared: SharedReplay,
}

#[async_trait]
impl Operator for ReplayOperator {
    async fn place_station(
        &mut self,
        _index: usize,
        id: &str,
        _hint_m: Option<[f64; 3]>,
    ) -> Result<(), DeviceError> {
        let s = lock(&self.shared, "operator")?;
        let cursor = s.cursor;
        let next = s.recording.events.iter().find_map(|e| match &e.msg {
            RunEvent::StationBegin { station, .. } if e.after >= cursor => Some(station),
            _ => None,
        });
        match next {
            Some(station) if station == id => Ok(()),
            Some(station) => Err(DeviceError::Rejected {
                device: "operator".into(),
                message: format!(
                    "replay: the sequencer placed the tracer at station {id} after sample \
                     {cursor}, but the recording's next station is {station}"
                ),
            }),
            None => Err(s.end_of_stream()),
        }
    }

    async fn mount_target(
        &mut self,
        _target: &str,
        _offset_m: [f64; 3],
    ) -> Result<(), DeviceError> {
        Ok(())
    }
}

pub struct ReplayRotaryTable {
    pub id: String,
    pub shared: SharedReplay,
}

#[async_trait]
impl RotaryTable for ReplayRotaryTable {
    fn id(&self) -> &str {
        &self.id
    }

    /// In position where the recording shows the table in position after this rotation's
    /// `rotation` event, at the recorded encoder angle.
    async fn start_rotation(&mut self, commanded_rad: f64) -> Result<(), DeviceError> {
        let mut s = lock(&self.shared, &self.id)?;
        let cursor = s.cursor;
        if let Some(e) = ReplayState::due(&mut s.table_faults, cursor) {
            return Err(e);
        }
        let leg = match s.table_second_leg.take() {
            Some((from, target_rad)) => Some((from, target_rad, None)),
            None => s.recording.events.iter().find_map(|e| match &e.msg {
                RunEvent::Rotation {
                    table,
                    commanded_rad: c,
                    via_rad,
                } if e.after >= cursor && table == &self.id => match via_rad {
                    Some(via) => Some((e.after + 1, *via, Some(*c))),
                    None => Some((e.after + 1, *c, None)),
                },
                _ => None,
            }),
        };
        let Some((search_from, recorded_rad, then_rad)) = leg else {
            return Err(s.end_of_stream());
        };
        if (recorded_rad - commanded_rad).abs() > 1e-12 {
            return Err(DeviceError::Rejected {
                device: self.id.clone(),
                message: format!(
                    "replay: the sequencer commanded {commanded_rad} rad after sample {cursor}, \
                     but the recording's next rotation is to {recorded_rad} rad"
                ),
            });
        }
        let arrival = s
            .recording
            .rotary
            .iter()
            .find(|r| {
                r.after >= search_from
                    && r.msg.in_position
                    && (r.msg.commanded_rad - recorded_rad).abs() <= 1e-12
            })
            .map_or((Arrival::Never, commanded_rad), |r| {
                (
                    Arrival::At(r.after),
                    r.msg.encoder_rad.unwrap_or(commanded_rad),
                )
            });
        if let (Some(target_rad), Arrival::At(at)) = (then_rad, arrival.0) {
            s.table_second_leg = Some((at, target_rad));
        }
        s.table_arrival = Some(arrival);
        Ok(())
    }

    async fn state(&mut self) -> Result<RotaryState, DeviceError> {
        let mut s = lock(&self.shared, &self.id)?;
        let cursor = s.cursor;
        if let Some(e) = ReplayState::due(&mut s.table_faults, cursor) {
            return Err(e);
        }
        Ok(match s.table_arrival {
            Some((Arrival::At(at), encoder_rad)) if s.cursor >= at => {
                RotaryState::InPosition { encoder_rad }
            }
            _ => RotaryState::Moving,
        })
    }
    fn take_link_faults(&mut self) -> Vec<LinkFault> {
        take_links(&self.shared, |s| &mut s.table_links)
    }
}

/// A probe replayed from a session's `/probe/<id>/reading` stream: the recorded readings in
/// order, then `EndOfStream` (no plan kind drives a probe yet, so it needs no shared cursor).
pub struct ReplayProbe {
    id: String,
    readings: VecDeque<ProbeReading>,
}

impl ReplayProbe {
    /// The probe `id` of `session`; None if the session has no such stream.
    pub fn from_session(session: &crate::session::reader::Session, id: &str) -> Option<Self> {
        let readings = session.probes.get(id)?;
        Some(ReplayProbe {
            id: id.to_string(),
            // Out-of-range readings (null) carry no value to hand out again.
            readings: readings
                .iter()
                .filter_map(|r| {
                    Some(ProbeReading {
                        t_s: r.msg.t_s,
                        value_m: r.msg.value_m?,
                    })
                })
                .collect(),
        })
    }
}

#[async_trait]
impl Probe for ReplayProbe {
    fn id(&self) -> &str {
        &self.id
    }

    async fn read(&mut self) -> Result<ProbeReading, DeviceError> {
        self.readings
            .pop_front()
            .ok_or_else(|| DeviceError::EndOfStream {
                device: self.id.clone(),
            })
    }
}

/// `text` cut to at most `max` characters (on a character boundary), marked with "…".
fn shorten(text: &str, max: usize) -> String {
    match text.char_indices().nth(max) {
        Some((cut, _)) => format!("{}…", &text[..cut]),
        None => text.to_string(),
    }
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;

    use super::*;
    use crate::clock::Clock;
    use crate::session::messages::TracerSample;
    use crate::session::reader::testutil::header;
    use crate::session::reader::{Completeness, Session, Stamped};

    fn session(log_times_ns: &[u64]) -> Session {
        let samples = log_times_ns
            .iter()
            .enumerate()
            .map(|(i, &t)| Stamped {
                log_time_ns: t,
                publish_time_ns: t,
                msg: TracerSample {
                    seq: i as u64,
                    t_s: t as f64 * 1e-9,
                    length_m: 0.1,
                    signal: 1.0,
                    tracking: true,
                    beam_segment: 0,
                },
            })
            .collect();
        Session {
            header: header(),
            tracers: BTreeMap::from([("tracer0".to_string(), samples)]),
            env: BTreeMap::new(),
            rotary: BTreeMap::new(),
            machines: BTreeMap::new(),
            probes: BTreeMap::new(),
            topics: BTreeMap::new(),
            events: Vec::new(),
            completeness: Completeness::Complete,
            damaged: Vec::new(),
            lost_before_repair: Vec::new(),
            skipped: 0,
            ignored: 0,
        }
    }

    fn plan() -> Plan {
        Plan {
            targets: Vec::new(),
            points: Vec::new(),
            stations: Vec::new(),
            passes: Vec::new(),
            dwell_s: 0.0,
            max_dwell_s: 1.0,
            stillstand_window_s: 0.1,
            stillstand_tolerance_m: 1e-6,
        }
    }

    async fn drain(realtime: bool, log_times_ns: &[u64]) -> (Vec<u64>, std::time::Duration) {
        let recording = Recording::new(&session(log_times_ns)).expect("recording");
        let (shared, _) = ReplayState::new(recording, plan(), realtime);
        let mut tracer = ReplayTracer {
            id: "tracer0".into(),
            shared,
        };
        let started = Instant::now();
        let mut seqs = Vec::new();
        loop {
            match tracer.next_sample().await {
                Ok(r) => seqs.push(r.seq),
                Err(DeviceError::EndOfStream { device }) => {
                    assert_eq!(device, "tracer0");
                    break;
                }
                Err(e) => panic!("unexpected {e}"),
            }
        }
        (seqs, started.elapsed())
    }

    /// `--realtime` paces the samples by their recorded log times; full speed does not wait.
    #[tokio::test]
    async fn realtime_follows_the_recorded_pace() {
        let times = [1_000_000_000, 1_100_000_000, 1_200_000_000, 1_300_000_000];
        let (seqs, elapsed) = drain(true, &times).await;
        assert_eq!(seqs, vec![0, 1, 2, 3]);
        assert!(elapsed.as_secs_f64() >= 0.3, "{elapsed:?}");
        let (seqs, _) = drain(false, &times).await;
        assert_eq!(seqs, vec![0, 1, 2, 3]);
    }

    #[tokio::test]
    async fn the_probe_replays_its_readings_in_order() {
        use crate::session::messages::ProbeSample;
        let mut s = session(&[]);
        s.probes.insert(
            "p".into(),
            (0..3u64)
                .map(|i| Stamped {
                    log_time_ns: i,
                    publish_time_ns: i,
                    msg: ProbeSample {
                        seq: i + 1,
                        t_s: i as f64,
                        value_m: Some(1e-4 * i as f64),
                    },
                })
                .collect(),
        );
        assert!(ReplayProbe::from_session(&s, "q").is_none());
        let mut probe = ReplayProbe::from_session(&s, "p").expect("probe");
        for i in 0..3 {
            let r = probe.read().await.expect("reading");
            assert_eq!((r.t_s, r.value_m), (i as f64, 1e-4 * i as f64));
        }
        assert!(matches!(
            probe.read().await,
            Err(DeviceError::EndOfStream { .. })
        ));
    }

    /// Virtual-clock recordings keep their stamps; after a sample the clock never runs past
    /// the next one.
    #[test]
    fn the_clock_follows_the_recording() {
        let recording = Recording::new(&session(&[10, 20, 21])).expect("recording");
        let mut recording = recording;
        let clock = ReplayClock::default();
        clock.at_cursor(&mut recording, 1);
        assert_eq!(clock.now_ns(), 10);
        // Nothing recorded between samples 1 and 2: the clock stays below sample 2.
        clock.at_cursor(&mut recording, 2);
        let readings: Vec<u64> = (0..5).map(|_| clock.now_ns()).collect();
        assert!(
            readings.iter().all(|&t| (20..21).contains(&t)),
            "{readings:?}"
        );
        clock.set_fixed(5);
        assert_eq!(clock.now_ns(), 5);
    }
}
