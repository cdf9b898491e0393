//! The run sequencer: executes a plan on devices seen only through their traits, turns the
//! rotary table the tracer stands on, waits for stillstand, homes, and records every raw sample
//! and every step to the session.
//!
//! Real devices misbehave: a timeout or protocol error is retried (`DEVICE_RETRIES` times)
//! and recorded as a `fault` event; lost frames (gaps in the tracer's `seq`) are recorded as
//! `fault` events; a beam break stops the pass, waits for the beam, re-homes at point 0 (a new
//! beam segment: `rehome` event) and repeats the pass from the first point whose window the
//! break touched. Every sample is recorded throughout. A machine alarm is recorded, unlocked
//! and the move commanded again; faults the drivers recovered from by themselves (CRC
//! failures, reconnects) are recorded as `fault` events too.

pub mod control;
pub(crate) mod kind_faults;
pub mod passive;

use std::sync::Arc;

use tokio_util::sync::CancellationToken;

use geocal_drivers::{
    AxisPositions, DeviceError, Environment, Machine, MachineState, Operator, RotaryState,
    RotaryTable, Tracer, TracerReading,
};

use crate::clock::Clock;
use crate::extract::{Stillstand, StillstandDetector};
use crate::plan::{Plan, PlanRotation, PlanTarget, AXES};
use crate::session::messages::{
    AxisMap, EnvSample, MachineStateSample, Name, RotaryStateSample, RunEvent, TracerSample,
};
use crate::session::recorder::RecorderHandle;

/// The devices of a run, as trait objects built from the configuration.
pub struct Devices {
    pub tracer: Box<dyn Tracer>,
    pub environment: Option<Box<dyn Environment>>,
    pub machine: Box<dyn Machine>,
    pub operator: Box<dyn Operator>,
    /// The rotary table the tracer stands on (plans with table stations).
    pub rotary: Option<Box<dyn RotaryTable>>,
}

#[derive(Debug, thiserror::Error)]
pub enum SequencerError {
    #[error(transparent)]
    Device(#[from] DeviceError),
    #[error("machine did not arrive at point {point} within {waited_s:.0} s of device time")]
    NoArrival { point: usize, waited_s: f64 },
    #[error(
        "station {station} is on rotary table `{table}`, but the run has no rotary table device"
    )]
    NoTable { station: String, table: String },
    #[error("station {station} is on rotary table `{table}`, but the run's table is `{device}`")]
    WrongTable {
        station: String,
        table: String,
        device: String,
    },
    #[error("beam still broken after {waited_s:.0} s of device time at station {station}")]
    NoBeam { station: String, waited_s: f64 },
    #[error("beam broken {breaks} times in one pass at station {station}; giving up")]
    TooManyBeamBreaks { station: String, breaks: u32 },
    #[error("rotary table {table} not in position at {commanded_rad} rad within {waited_s:.0} s of device time")]
    NoInPosition {
        table: String,
        commanded_rad: f64,
        waited_s: f64,
    },
    #[error(transparent)]
    Cancelled(#[from] crate::sequencer::control::Cancelled),
}

/// Where a resumed run continues (`geocal run --resume`, src/run/resume.rs): the first
/// unfinished point in plan order, and what the interrupted run left behind.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ResumeAt {
    /// Plan indices of the station and target, the pass, and the position in the pass order
    /// of the first unfinished point. A station index past the last means nothing is left.
    pub station: usize,
    pub target: usize,
    pub pass: usize,
    pub order_index: usize,
    /// The interrupted run recorded this station's `station_begin` already.
    pub station_begun: bool,
    /// Points the interrupted run finished (for the progress count).
    pub done: u64,
    /// Added to every recorded `beam_segment`, so the continuation's segments follow the
    /// interrupted run's: its lengths are relative to a new homing.
    pub segment_offset: u32,
    /// Where the machine was last commanded, and the approach signs then.
    pub commanded: Option<[f64; 3]>,
    pub approach: AxisMap<i8>,
}

/// Called after each finished point with (done, total).
pub type Progress<'a> = &'a mut dyn FnMut(u64, u64);

#[derive(Debug, Default, Clone, PartialEq)]
pub struct RunSummary {
    pub points_measured: u64,
    pub samples: u64,
    pub env_samples: u64,
    pub faults: u64,
}

/// How long device time may pass during one move before it counts as lost.
const MAX_MOVE_S: f64 = 600.0;
/// How long device time may pass during one rotation before it counts as lost.
const MAX_ROTATION_S: f64 = 600.0;
/// How often (device time) the environment is polled.
const ENV_POLL_S: f64 = 0.5;
/// Retries of a device call that timed out or hit a protocol error, before the run fails.
const DEVICE_RETRIES: u32 = 5;
/// How long device time may pass waiting for a broken beam to return.
const MAX_BEAM_WAIT_S: f64 = 600.0;
/// Beam breaks tolerated within one pass before the run fails.
const MAX_BEAM_BREAKS: u32 = 10;
/// Machine alarms tolerated during one move before the run fails.
pub(crate) const MAX_ALARMS: u32 = 3;

/// How a step ended: done, or cut short by a beam break (the pass must be repeated from it).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Step {
    Done,
    BeamBroken,
}

/// How a dwell ended.
enum DwellEnd {
    Settled,
    Unsettled,
    BeamBroken,
}

pub struct Sequencer<'a> {
    plan: &'a Plan,
    devices: Devices,
    recorder: RecorderHandle,
    clock: Arc<dyn Clock>,
    approach: AxisMap<i8>,
    /// Where the machine was last sent (for the approach directions).
    commanded: Option<[f64; 3]>,
    /// Where the machine reported arrival; None while moving or unknown.
    position: Option<[f64; 3]>,
    last_sample: Option<TracerReading>,
    /// The station being measured (for `rehome` events).
    station: String,
    next_env_poll_s: f64,
    /// The tracer stands on the rotary table (placed there by the operator).
    on_table: bool,
    /// Clock reading at the start of the run: `/rotary/<id>/state` times count from here.
    start_ns: u64,
    summary: RunSummary,
    resume: Option<ResumeAt>,
    /// Passive mode (src/sequencer/passive.rs): the hint tolerance for matching stops.
    passive: Option<f64>,
    /// Added to recorded beam segments (see `ResumeAt::segment_offset`).
    segment_offset: u32,
    /// Cancels the run (the daemon's cancel, Ctrl-C): it stops at once, then `finish`es.
    cancel: CancellationToken,
}

impl<'a> Sequencer<'a> {
    pub fn new(
        plan: &'a Plan,
        devices: Devices,
        recorder: RecorderHandle,
        clock: Arc<dyn Clock>,
    ) -> Self {
        let start_ns = clock.now_ns();
        Self {
            plan,
            devices,
            recorder,
            clock,
            approach: AXES.iter().map(|a| (*a, 0)).collect(),
            commanded: None,
            position: None,
            last_sample: None,
            station: String::new(),
            next_env_poll_s: 0.0,
            on_table: false,
            start_ns,
            summary: RunSummary::default(),
            resume: None,
            passive: None,
            segment_offset: 0,
            cancel: CancellationToken::new(),
        }
    }

    /// Stop the run as soon as `cancel` is cancelled (the machine's controller is still left
    /// as found).
    pub fn cancelled_by(mut self, cancel: CancellationToken) -> Self {
        self.cancel = cancel;
        self
    }

    /// Passive mode: the machine runs its NC program; stops are matched to the plan's points
    /// with a station-hint tolerance of `hint_tolerance_m`.
    pub fn passive(mut self, hint_tolerance_m: f64) -> Self {
        self.passive = Some(hint_tolerance_m);
        self
    }

    /// Continue an interrupted run at `at` instead of starting from the beginning.
    pub fn resume_at(mut self, at: ResumeAt) -> Self {
        self.segment_offset = at.segment_offset;
        self.commanded = at.commanded;
        for (axis, sign) in &at.approach {
            self.approach.insert(axis.as_str(), *sign);
        }
        self.resume = Some(at);
        self
    }

    /// Run the whole plan: every station, every pass, every point. Done, failed or
    /// cancelled, the machine is then asked to leave its controller as the run found it
    /// (`finish`); a failure to is a `fault` event, not a failed run.
    pub async fn run(mut self, progress: Progress<'_>) -> Result<RunSummary, SequencerError> {
        let cancel = self.cancel.clone();
        let passive = self.passive.take();
        let result = tokio::select! {
            biased;
            _ = cancel.cancelled() => Err(SequencerError::Cancelled(control::Cancelled)),
            result = async {
                match passive {
                    Some(hint_tolerance_m) => self.run_passive(hint_tolerance_m, progress).await,
                    None => self.run_plan(progress).await,
                }
            } => result,
        };
        if let Err(e) = self.devices.machine.finish().await {
            tracing::warn!("leaving the machine's controller as found: {e}");
            self.event(RunEvent::Fault {
                device: self.devices.machine.id().to_string(),
                code: "finish".into(),
                message: format!("leaving the controller as the run found it: {e}"),
            });
        }
        result
    }

    async fn run_plan(&mut self, progress: Progress<'_>) -> Result<RunSummary, SequencerError> {
        let plan = self.plan;
        let total =
            (plan.stations.len() * plan.targets.len() * plan.passes.len() * plan.points.len())
                as u64;
        let mut mounted: Option<&PlanTarget> = None;
        let resume = self.resume.take();
        let mut done = resume.as_ref().map_or(0, |r| r.done);
        for (station_index, station) in plan.stations.iter().enumerate() {
            if resume.as_ref().is_some_and(|r| station_index < r.station) {
                continue;
            }
            // The station the interrupted run stopped in (targets and passes before the
            // resume point are skipped).
            let resumed = resume.as_ref().filter(|r| r.station == station_index);
            self.station = station.id.clone();
            if !resumed.is_some_and(|r| r.station_begun) {
                self.event(RunEvent::StationBegin {
                    station: station.id.as_str().into(),
                    station_index,
                    hint_m: station.hint_m,
                });
            }
            // The operator places the tracer, once onto the table for all its table stations;
            // from then on the table turns it from station to station.
            if !(station.rotation.is_some() && self.on_table) {
                self.devices
                    .operator
                    .place_station(station_index, &station.id, station.hint_m)
                    .await?;
                self.on_table = station.rotation.is_some();
            }
            if let Some(rotation) = &station.rotation {
                self.rotate(&station.id, rotation).await?;
            }
            for (target_index, target) in plan.targets.iter().enumerate() {
                if resumed.is_some_and(|r| target_index < r.target) {
                    continue;
                }
                if mounted != Some(target) {
                    self.devices
                        .operator
                        .mount_target(&target.id, target.offset_m)
                        .await?;
                    mounted = Some(target);
                }
                for (pass, &direction) in plan.passes.iter().enumerate() {
                    let resumed = resumed.filter(|r| r.target == target_index);
                    if resumed.is_some_and(|r| pass < r.pass) {
                        continue;
                    }
                    let order = plan.pass_order(direction);
                    let mut next = 0;
                    if let Some(r) = resumed.filter(|r| r.pass == pass) {
                        // Home at point 0 again (a new beam segment), then go on.
                        next = r.order_index;
                        let point = order.get(next).copied().unwrap_or(0);
                        self.rehome_after_resume(&station.id, point, pass).await?;
                    }
                    let mut breaks = 0;
                    while let Some(&point) = order.get(next) {
                        match self.visit(&station.id, target, point, pass).await? {
                            Step::Done => {
                                next += 1;
                                done += 1;
                                progress(done, total);
                                control::cancellation_point().await;
                            }
                            Step::BeamBroken => {
                                breaks += 1;
                                if breaks > MAX_BEAM_BREAKS {
                                    return Err(SequencerError::TooManyBeamBreaks {
                                        station: station.id.clone(),
                                        breaks,
                                    });
                                }
                                self.recover_beam(&station.id, point, pass).await?;
                            }
                        }
                    }
                }
            }
            self.event(RunEvent::StationEnd {
                station: station.id.as_str().into(),
            });
        }
        self.poll_environment().await?;
        Ok(self.summary.clone())
    }

    fn event(&mut self, event: RunEvent) {
        if matches!(event, RunEvent::Fault { .. }) {
            self.summary.faults += 1;
        }
        self.recorder.event(&event, self.clock.now_ns());
    }

    /// Record a failed device call as a `fault` event; Ok if it may be retried (a timeout
    /// or a protocol error, at most `DEVICE_RETRIES` times), else the error.
    fn retry_or_fail(
        &mut self,
        error: DeviceError,
        attempt: &mut u32,
    ) -> Result<(), SequencerError> {
        match kind_faults::retry_decision(&error, attempt) {
            Some((event, retry)) => {
                self.event(event);
                if retry {
                    Ok(())
                } else {
                    Err(error.into())
                }
            }
            None => Err(error.into()),
        }
    }

    /// The tracer's next reading, retried on timeouts; a gap in `seq` is a `fault` event.
    async fn next_reading(&mut self) -> Result<TracerReading, SequencerError> {
        let mut attempt = 0;
        let reading = loop {
            match self.devices.tracer.next_sample().await {
                Ok(r) => break r,
                Err(e) => self.retry_or_fail(e, &mut attempt)?,
            }
        };
        if let Some(last) = self.last_sample {
            if reading.seq > last.seq + 1 {
                let lost = reading.seq - last.seq - 1;
                self.event(RunEvent::Fault {
                    device: self.devices.tracer.id().to_string(),
                    code: "frames_lost".into(),
                    message: format!(
                        "{lost} frame(s) lost between seq {} and {} (dropped or failed CRC)",
                        last.seq, reading.seq
                    ),
                });
            }
        }
        Ok(reading)
    }

    /// Home the tracer, retried on timeouts.
    async fn home_tracer(&mut self) -> Result<(), SequencerError> {
        let mut attempt = 0;
        loop {
            match self.devices.tracer.home().await {
                Ok(()) => return Ok(()),
                Err(e) => self.retry_or_fail(e, &mut attempt)?,
            }
        }
    }

    /// Start a machine move, retried on timeouts (the move is absolute: a resend after a
    /// lost `ok` is harmless); an alarm is cleared and the move commanded again.
    async fn start_move(&mut self, command: &AxisPositions) -> Result<(), SequencerError> {
        let (mut attempt, mut alarms) = (0, 0);
        loop {
            match self.devices.machine.start_move(command).await {
                Ok(()) => return Ok(()),
                Err(e @ DeviceError::Alarm { .. }) => self.clear_alarm(e, &mut alarms).await?,
                Err(e) => self.retry_or_fail(e, &mut attempt)?,
            }
        }
    }

    /// The machine's state during the move to `command`, retried on timeouts; an alarm
    /// (the move was aborted) is cleared and the move commanded again.
    async fn machine_state(
        &mut self,
        command: &AxisPositions,
        alarms: &mut u32,
    ) -> Result<MachineState, SequencerError> {
        let mut attempt = 0;
        loop {
            match self.devices.machine.state().await {
                Ok(s) => return Ok(s),
                Err(e @ DeviceError::Alarm { .. }) => {
                    self.clear_alarm(e, alarms).await?;
                    self.start_move(command).await?;
                    return Ok(MachineState::Moving);
                }
                Err(e) => self.retry_or_fail(e, &mut attempt)?,
            }
        }
    }

    /// A machine alarm: `fault {code: "alarm"}`, then unlock (retried on timeouts). The
    /// caller commands the interrupted move again; the point is measured after it.
    async fn clear_alarm(
        &mut self,
        error: DeviceError,
        alarms: &mut u32,
    ) -> Result<(), SequencerError> {
        *alarms += 1;
        let device = self.devices.machine.id().to_string();
        self.event(RunEvent::Fault {
            device,
            code: "alarm".into(),
            message: format!(
                "{error}: unlock asked (the move is commanded again once the alarm is cleared)"
            ),
        });
        if *alarms > MAX_ALARMS {
            return Err(error.into());
        }
        let mut attempt = 0;
        loop {
            match self.devices.machine.unlock().await {
                Ok(()) => return Ok(()),
                Err(e) => self.retry_or_fail(e, &mut attempt)?,
            }
        }
    }

    /// Record what the drivers detected and recovered from by themselves (frames failed
    /// their CRC, links lost and reopened) as `fault` events.
    fn record_link_faults(&mut self) {
        let d = &mut self.devices;
        let mut found: Vec<(String, geocal_drivers::LinkFault)> = Vec::new();
        let id = d.tracer.id().to_string();
        found.extend(
            d.tracer
                .take_link_faults()
                .into_iter()
                .map(|f| (id.clone(), f)),
        );
        let id = d.machine.id().to_string();
        found.extend(
            d.machine
                .take_link_faults()
                .into_iter()
                .map(|f| (id.clone(), f)),
        );
        if let Some(table) = d.rotary.as_mut() {
            let id = table.id().to_string();
            found.extend(
                table
                    .take_link_faults()
                    .into_iter()
                    .map(|f| (id.clone(), f)),
            );
        }
        for (device, fault) in found {
            self.event(RunEvent::Fault {
                device,
                code: fault.code,
                message: fault.message,
            });
        }
    }

    /// Start a table rotation, retried on timeouts (the angle is absolute: a resend is
    /// harmless; the Modbus driver reconnects after a timeout).
    async fn start_rotation(&mut self, commanded_rad: f64) -> Result<(), SequencerError> {
        let mut attempt = 0;
        while let Some(table) = self.devices.rotary.as_mut() {
            match table.start_rotation(commanded_rad).await {
                Ok(()) => break,
                Err(e) => self.retry_or_fail(e, &mut attempt)?,
            }
        }
        Ok(())
    }

    /// The table's state, retried on timeouts.
    async fn table_state(&mut self) -> Result<RotaryState, SequencerError> {
        let mut attempt = 0;
        while let Some(table) = self.devices.rotary.as_mut() {
            match table.state().await {
                Ok(s) => return Ok(s),
                Err(e) => self.retry_or_fail(e, &mut attempt)?,
            }
        }
        Ok(RotaryState::Moving)
    }

    /// Pull one sample from the tracer and record it; poll the environment now and then.
    async fn sample(&mut self) -> Result<TracerReading, SequencerError> {
        let reading = self.next_reading().await?;
        let sample = TracerSample {
            seq: reading.seq,
            t_s: reading.t_s,
            length_m: reading.length_m,
            signal: reading.signal,
            tracking: reading.tracking,
            beam_segment: reading.beam_segment + self.segment_offset,
        };
        self.recorder
            .tracer(self.devices.tracer.id(), &sample, self.clock.now_ns());
        self.summary.samples += 1;
        self.record_link_faults();
        let before = self.last_sample.replace(reading);
        // A homing after the beam was interrupted starts a new beam segment: say so, at the
        // first sample of the new segment (a driver may still hold samples from before).
        if before.is_some_and(|b| b.beam_segment != reading.beam_segment) {
            self.event(RunEvent::Rehome {
                station: self.station.as_str().into(),
                beam_segment: reading.beam_segment + self.segment_offset,
            });
        }
        if reading.t_s >= self.next_env_poll_s {
            self.next_env_poll_s = reading.t_s + ENV_POLL_S;
            self.poll_environment().await?;
        }
        Ok(reading)
    }

    async fn poll_environment(&mut self) -> Result<(), SequencerError> {
        let Some(env) = self.devices.environment.as_mut() else {
            return Ok(());
        };
        let id = env.id().to_string();
        let readings = match env.poll().await {
            Ok(r) => r,
            Err(e) => {
                // Environment data are auxiliary: a failed poll is recorded, not retried.
                self.event(RunEvent::Fault {
                    device: id,
                    code: "poll".into(),
                    message: e.to_string(),
                });
                return Ok(());
            }
        };
        for reading in readings {
            let sample = EnvSample {
                t_s: reading.t_s,
                air_temp_k: reading.air_temp_k,
                pressure_pa: reading.pressure_pa,
                humidity_pct: reading.humidity_pct,
                material_temp_k: reading.material_temp_k,
            };
            self.recorder.env(&id, &sample, self.clock.now_ns());
            self.summary.env_samples += 1;
        }
        Ok(())
    }

    /// One point of a pass: move there, home at point 0, measure.
    async fn visit(
        &mut self,
        station: &str,
        target: &PlanTarget,
        point: usize,
        pass: usize,
    ) -> Result<Step, SequencerError> {
        if self.move_to(point).await? == Step::BeamBroken {
            return Ok(Step::BeamBroken);
        }
        if point == 0 && self.home().await? == Step::BeamBroken {
            return Ok(Step::BeamBroken);
        }
        self.measure(station, target, point, pass).await
    }

    /// After a beam break at (or on the way to) `point`: a `fault` event, wait for the beam,
    /// go to point 0 and re-home there (a new beam segment: `rehome` event). The caller then
    /// repeats the pass from `point`. A break during the recovery starts it over.
    async fn recover_beam(
        &mut self,
        station: &str,
        point: usize,
        pass: usize,
    ) -> Result<(), SequencerError> {
        self.event(RunEvent::Fault {
            device: self.devices.tracer.id().to_string(),
            code: "beam_break".into(),
            message: format!(
                "beam broken at point {point} of pass {pass}: waiting for the beam, re-homing \
                 at point 0, repeating the pass from point {point}"
            ),
        });
        let segment = self.last_sample.map_or(0, |s| s.beam_segment);
        for _ in 0..=MAX_BEAM_BREAKS {
            self.wait_for_beam(station).await?;
            if self.move_to(0).await? == Step::BeamBroken {
                continue;
            }
            if self.home().await? == Step::Done && self.wait_for_segment(station, segment).await? {
                return Ok(());
            }
        }
        Err(SequencerError::TooManyBeamBreaks {
            station: station.to_string(),
            breaks: MAX_BEAM_BREAKS,
        })
    }

    /// A resumed run continues mid-pass: go to point 0 and home there, so the lengths of the
    /// rest of the pass are relative to point 0 again (a `rehome` event with the new segment).
    async fn rehome_after_resume(
        &mut self,
        station: &str,
        point: usize,
        pass: usize,
    ) -> Result<(), SequencerError> {
        let mut step = self.move_to(0).await?;
        if step == Step::Done {
            step = self.home().await?;
        }
        if step == Step::BeamBroken {
            self.recover_beam(station, point, pass).await?;
        }
        let segment = self.last_sample.map_or(0, |s| s.beam_segment) + self.segment_offset;
        self.event(RunEvent::Rehome {
            station: Name::from(station),
            beam_segment: segment,
        });
        Ok(())
    }

    /// After a re-homing, keep recording until the samples show the new beam segment (the
    /// `rehome` event then precedes the repeated windows). False if the beam broke again.
    async fn wait_for_segment(&mut self, station: &str, old: u32) -> Result<bool, SequencerError> {
        let begin_s = self.last_sample.map_or(0.0, |s| s.t_s);
        loop {
            let sample = self.sample().await?;
            if !sample.tracking {
                return Ok(false);
            }
            if sample.beam_segment != old {
                return Ok(true);
            }
            if sample.t_s - begin_s > MAX_BEAM_WAIT_S {
                return Err(SequencerError::NoBeam {
                    station: station.to_string(),
                    waited_s: sample.t_s - begin_s,
                });
            }
        }
    }

    /// Keep recording until the tracer tracks again.
    async fn wait_for_beam(&mut self, station: &str) -> Result<(), SequencerError> {
        let begin_s = self.last_sample.map_or(0.0, |s| s.t_s);
        loop {
            let sample = self.sample().await?;
            if sample.tracking {
                return Ok(());
            }
            if sample.t_s - begin_s > MAX_BEAM_WAIT_S {
                return Err(SequencerError::NoBeam {
                    station: station.to_string(),
                    waited_s: sample.t_s - begin_s,
                });
            }
        }
    }

    /// Command the move to a plan point and keep recording until the machine reports arrival.
    async fn move_to(&mut self, point: usize) -> Result<Step, SequencerError> {
        let target = self.plan.points[point].axes_m;
        if self.position == Some(target) {
            return Ok(Step::Done);
        }
        let command: AxisPositions = AXES.iter().map(|a| a.to_string()).zip(target).collect();
        self.position = None;
        self.start_move(&command).await?;
        self.note_command(target);
        let first = self.sample().await?;
        let started_s = first.t_s;
        let mut tracking = first.tracking;
        let mut alarms = 0;
        loop {
            if let MachineState::Idle { position } =
                self.machine_state(&command, &mut alarms).await?
            {
                self.record_arrival(&position, &command);
                break;
            }
            let sample = self.sample().await?;
            tracking &= sample.tracking;
            if sample.t_s - started_s > MAX_MOVE_S {
                return Err(SequencerError::NoArrival {
                    point,
                    waited_s: sample.t_s - started_s,
                });
            }
        }
        self.position = Some(target);
        Ok(if tracking {
            Step::Done
        } else {
            Step::BeamBroken
        })
    }

    /// The status poll that reported the machine at rest: where the move ended among the
    /// samples, so that a replay need not infer it.
    /// (An axis the controller does not report is given as commanded.)
    fn record_arrival(&mut self, position: &AxisPositions, commanded: &AxisPositions) {
        let now_ns = self.clock.now_ns();
        let axis = |a: &str| {
            position
                .get(a)
                .or_else(|| commanded.get(a))
                .copied()
                .unwrap_or_default()
        };
        let sample = MachineStateSample {
            t_s: now_ns.saturating_sub(self.start_ns) as f64 * 1e-9,
            state: "Idle".into(),
            position_m: [axis("x"), axis("y"), axis("z")],
            frame: "machine".into(),
            feed_m_s: None,
        };
        self.recorder
            .machine_state(self.devices.machine.id(), &sample, now_ns);
    }

    /// The machine was sent to `target`: update the approach signs of the axes that move.
    fn note_command(&mut self, target: [f64; 3]) {
        if let Some(from) = self.commanded {
            for (k, axis) in AXES.iter().enumerate() {
                let delta = target[k] - from[k];
                if delta != 0.0 {
                    self.approach.insert(*axis, delta.signum() as i8);
                }
            }
        }
        self.commanded = Some(target);
    }

    /// The `point_begin` event of a plan point.
    fn point_begin_event(
        &self,
        station: &str,
        target: &PlanTarget,
        point: usize,
        pass: usize,
    ) -> RunEvent {
        RunEvent::PointBegin {
            station: Name::from(station),
            point,
            pass,
            target: target.id.as_str().into(),
            nominal_m: self.plan.nominal_m(point, target),
            axes: AXES
                .iter()
                .copied()
                .zip(self.plan.points[point].axes_m)
                .collect(),
            approach: self.approach.clone(),
        }
    }

    /// Command the table to a station's angle (a `rotation` event), through its overshoot
    /// angle if the plan gives one, recording the tracer and the table's state meanwhile.
    async fn rotate(
        &mut self,
        station: &str,
        rotation: &PlanRotation,
    ) -> Result<(), SequencerError> {
        let Some(table_id) = self.devices.rotary.as_ref().map(|t| t.id().to_string()) else {
            return Err(SequencerError::NoTable {
                station: station.to_string(),
                table: rotation.table.clone(),
            });
        };
        if table_id != rotation.table {
            return Err(SequencerError::WrongTable {
                station: station.to_string(),
                table: rotation.table.clone(),
                device: table_id,
            });
        }
        self.event(RunEvent::Rotation {
            table: table_id.clone(),
            commanded_rad: rotation.commanded_rad,
            via_rad: rotation.via_rad,
        });
        for commanded_rad in rotation.via_rad.into_iter().chain([rotation.commanded_rad]) {
            self.turn_table(&table_id, commanded_rad).await?;
        }
        Ok(())
    }

    /// Turn the table to `commanded_rad`, recording the tracer and the table's state until
    /// the table reports in position.
    async fn turn_table(
        &mut self,
        table_id: &str,
        commanded_rad: f64,
    ) -> Result<(), SequencerError> {
        self.start_rotation(commanded_rad).await?;
        let started_s = self.sample().await?.t_s;
        loop {
            let state = self.table_state().await?;
            let encoder_rad = match state {
                RotaryState::InPosition { encoder_rad } => Some(encoder_rad),
                RotaryState::Moving => None,
            };
            let now_ns = self.clock.now_ns();
            let sample = RotaryStateSample {
                t_s: now_ns.saturating_sub(self.start_ns) as f64 * 1e-9,
                commanded_rad,
                encoder_rad,
                in_position: encoder_rad.is_some(),
            };
            self.recorder.rotary(table_id, &sample, now_ns);
            if encoder_rad.is_some() {
                return Ok(());
            }
            let t_s = self.sample().await?.t_s;
            if t_s - started_s > MAX_ROTATION_S {
                return Err(SequencerError::NoInPosition {
                    table: table_id.to_string(),
                    commanded_rad,
                    waited_s: t_s - started_s,
                });
            }
        }
    }

    /// Record for at least `min_dwell_s` and until the readings settle; after max_dwell_s
    /// give up with a `fault` event. Returns whether stillstand was reached.
    async fn dwell(&mut self, point: usize, min_dwell_s: f64) -> Result<DwellEnd, SequencerError> {
        let plan = self.plan;
        let mut detector =
            StillstandDetector::new(plan.stillstand_window_s, plan.stillstand_tolerance_m);
        let begin_s = self.last_sample.map_or(0.0, |s| s.t_s);
        loop {
            let sample = self.sample().await?;
            if !sample.tracking {
                return Ok(DwellEnd::BeamBroken);
            }
            let settled = matches!(
                detector.push(sample.t_s, sample.length_m),
                Stillstand::Settled { .. }
            );
            let elapsed_s = sample.t_s - begin_s;
            if settled && elapsed_s >= min_dwell_s {
                return Ok(DwellEnd::Settled);
            }
            if elapsed_s >= plan.max_dwell_s {
                let device = self.devices.tracer.id().to_string();
                self.event(RunEvent::Fault {
                    device,
                    code: "unsettled".into(),
                    message: format!(
                        "no stillstand at point {point} within {} s (tolerance {} m over {} s)",
                        plan.max_dwell_s, plan.stillstand_tolerance_m, plan.stillstand_window_s
                    ),
                });
                return Ok(DwellEnd::Unsettled);
            }
        }
    }

    /// Zero the counter at point 0 once at rest there: every pass is relative to point 0.
    /// (A homing after the beam was interrupted starts a new beam segment: `sample` says so.)
    async fn home(&mut self) -> Result<Step, SequencerError> {
        if let DwellEnd::BeamBroken = self.dwell(0, 0.0).await? {
            return Ok(Step::BeamBroken);
        }
        self.home_tracer().await?;
        if !self.sample().await?.tracking {
            return Ok(Step::BeamBroken);
        }
        Ok(Step::Done)
    }

    /// The dwell at a point: point_begin, at least dwell_s and until settled, point_end.
    async fn measure(
        &mut self,
        station: &str,
        target: &PlanTarget,
        point: usize,
        pass: usize,
    ) -> Result<Step, SequencerError> {
        let event = self.point_begin_event(station, target, point, pass);
        self.event(event);
        if let DwellEnd::BeamBroken = self.dwell(point, self.plan.dwell_s).await? {
            // No point_end: the window is abandoned, and repeated after the re-homing.
            return Ok(Step::BeamBroken);
        }
        self.event(RunEvent::PointEnd {
            station: Name::from(station),
            point,
            pass,
        });
        let joints = self.devices.machine.controller_trims();
        if !joints.is_empty() {
            self.event(RunEvent::ControllerTrims {
                station: Name::from(station),
                point,
                pass,
                joints,
            });
        }
        // Checkpoint: the finished point is on disk before the next one starts.
        self.recorder.checkpoint();
        self.summary.points_measured += 1;
        Ok(Step::Done)
    }
}
