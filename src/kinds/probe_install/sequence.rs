//! Sequencer of plan kind `probe_install`: for every posture (A, B), move the 5-axis CMM to
//! each sphere point, record its reported position and every raw probe reading.
//!
//! Events: `posture_begin` / `posture_end` around a posture, `probe_begin` / `probe_end` around
//! the readings of one point; `/machine/pose` at every arrival; `/probe/<id>/reading` for every
//! reading (null when out of range or refused by the sensor, with a `fault` event). Timeouts and
//! protocol errors are retried, alarms cleared, and link faults drained, all as `fault` events.
//! A checkpoint follows every `posture_end`: a resumed run keeps the finished postures and
//! measures the unfinished one again.

use std::sync::Arc;

use geocal_drivers::{AxisPositions, DeviceError, Machine, MachineState, Probe};

use crate::clock::Clock;
use crate::kinds::probe_install::plan::{ProbeInstallPlan, CMM_AXES};
use crate::sequencer::kind_faults::EventLog;
use crate::sequencer::{Progress, RunSummary, SequencerError};
use crate::session::kind_messages::{
    to_value, MachinePoseSample, SCHEMA_MACHINE_POSE, TOPIC_MACHINE_POSE,
};
use crate::session::messages::{ProbeSample, RunEvent};
use crate::session::recorder::RecorderHandle;

/// State queries before a move counts as lost.
const MAX_STATE_QUERIES: u64 = 1_000_000;

pub struct ProbeInstallDevices {
    pub machine: Box<dyn Machine>,
    pub probe: Box<dyn Probe>,
}

pub struct ProbeInstallSequencer<'a> {
    plan: &'a ProbeInstallPlan,
    devices: ProbeInstallDevices,
    log: EventLog,
    seq: u64,
    summary: RunSummary,
    /// The first posture to measure: postures before it were finished by an interrupted run.
    first_posture: usize,
}

impl<'a> ProbeInstallSequencer<'a> {
    pub fn new(
        plan: &'a ProbeInstallPlan,
        devices: ProbeInstallDevices,
        recorder: RecorderHandle,
        clock: Arc<dyn Clock>,
    ) -> Self {
        Self {
            plan,
            devices,
            log: EventLog::new(recorder, clock),
            // Readings are counted from 1 (docs/session-format.md), as the other kinds do.
            seq: 1,
            summary: RunSummary::default(),
            first_posture: 0,
        }
    }

    /// Continue an interrupted run at `posture` (measured again in full); the readings go on
    /// counting at `next_seq`, so that `seq` stays unique in the continued session.
    pub fn resume_at(mut self, posture: usize, next_seq: u64) -> Self {
        self.first_posture = posture;
        self.seq = next_seq;
        self
    }

    pub async fn run(mut self, progress: Progress<'_>) -> Result<RunSummary, SequencerError> {
        let plan = self.plan;
        let total = plan.points.len() as u64;
        let mut current: Option<usize> = None;
        let first = self.first_posture;
        for (done, p) in plan.points.iter().enumerate() {
            if p.posture < first {
                continue;
            }
            if current != Some(p.posture) {
                if let Some(prev) = current {
                    self.end_posture(prev);
                }
                let [a_rad, b_rad] = plan.postures_rad[p.posture];
                self.log.event(RunEvent::PostureBegin {
                    posture: p.posture,
                    a_rad,
                    b_rad,
                });
                current = Some(p.posture);
            }
            let commanded: AxisPositions =
                CMM_AXES.iter().map(|a| a.to_string()).zip(p.axes).collect();
            self.move_to(&commanded).await?;
            self.log.event(RunEvent::ProbeBegin {
                posture: p.posture,
                point: p.point,
                axes: commanded
                    .iter()
                    .map(|(name, value)| (name.as_str(), *value))
                    .collect(),
            });
            for _ in 0..plan.readings_per_point {
                self.read_probe().await?;
            }
            self.log.event(RunEvent::ProbeEnd {
                posture: p.posture,
                point: p.point,
            });
            self.summary.points_measured += 1;
            progress(done as u64 + 1, total);
            crate::sequencer::control::cancellation_point().await;
        }
        if let Some(prev) = current {
            self.end_posture(prev);
        }
        self.summary.faults = self.log.faults;
        Ok(self.summary)
    }

    /// A finished posture is on disk before the machine moves on: a resume keeps it.
    fn end_posture(&mut self, posture: usize) {
        self.log.event(RunEvent::PostureEnd { posture });
        self.log.recorder.checkpoint();
    }

    /// Command a move, wait for Idle, record the commanded and reported positions. Timeouts
    /// and protocol errors are retried (the move is absolute: a resend after a lost `ok` is
    /// harmless); an alarm is recorded, cleared (`unlock`) and the move commanded again.
    async fn move_to(&mut self, commanded: &AxisPositions) -> Result<(), SequencerError> {
        let mut alarms = 0;
        self.start_move(commanded, &mut alarms).await?;
        let pause = std::time::Duration::from_secs_f64(self.plan.poll_interval_s.max(0.0));
        let mut queries = 0;
        let reported = loop {
            let mut attempt = 0;
            let state = loop {
                match self.devices.machine.state().await {
                    Ok(s) => break s,
                    Err(e @ DeviceError::Alarm { .. }) => {
                        self.clear_alarm(e, &mut alarms).await?;
                        self.start_move(commanded, &mut alarms).await?;
                        break MachineState::Moving;
                    }
                    Err(e) => self.log.retry_or_fail(e, &mut attempt)?,
                }
            };
            self.drain_link_faults();
            if let MachineState::Idle { position } = state {
                break position;
            }
            if !pause.is_zero() {
                tokio::time::sleep(pause).await;
            }
            queries += 1;
            if queries > MAX_STATE_QUERIES {
                return Err(SequencerError::NoArrival {
                    point: self.summary.points_measured as usize,
                    waited_s: self.log.elapsed_s(),
                });
            }
        };
        let sample = MachinePoseSample {
            t_s: self.log.elapsed_s(),
            commanded: commanded.clone(),
            reported,
        };
        self.log.recorder.json(
            TOPIC_MACHINE_POSE,
            SCHEMA_MACHINE_POSE,
            to_value(&sample),
            self.log.clock.now_ns(),
        );
        Ok(())
    }

    async fn start_move(
        &mut self,
        commanded: &AxisPositions,
        alarms: &mut u32,
    ) -> Result<(), SequencerError> {
        let mut attempt = 0;
        loop {
            match self.devices.machine.start_move(commanded).await {
                Ok(()) => break,
                Err(e @ DeviceError::Alarm { .. }) => self.clear_alarm(e, alarms).await?,
                Err(e) => self.log.retry_or_fail(e, &mut attempt)?,
            }
        }
        self.drain_link_faults();
        Ok(())
    }

    /// A machine alarm: `fault {code: "alarm"}`, then unlock (retried); at most
    /// `MAX_ALARMS` per move.
    async fn clear_alarm(
        &mut self,
        error: DeviceError,
        alarms: &mut u32,
    ) -> Result<(), SequencerError> {
        *alarms += 1;
        let id = self.devices.machine.id().to_string();
        self.log.fault(
            &id,
            "alarm",
            format!(
                "{error}: unlock asked (the move is commanded again once the alarm is cleared)"
            ),
        );
        if *alarms > crate::sequencer::MAX_ALARMS {
            return Err(error.into());
        }
        let mut attempt = 0;
        loop {
            match self.devices.machine.unlock().await {
                Ok(()) => return Ok(()),
                Err(e) => self.log.retry_or_fail(e, &mut attempt)?,
            }
        }
    }

    /// Faults the machine driver recovered from by itself (lost port and reconnect), as
    /// `fault` events.
    fn drain_link_faults(&mut self) {
        let id = self.devices.machine.id().to_string();
        for f in self.devices.machine.take_link_faults() {
            self.log.fault(&id, &f.code, f.message);
        }
    }

    /// One raw reading, recorded whatever it is; out of range is a null value and a fault.
    async fn read_probe(&mut self) -> Result<(), SequencerError> {
        let id = self.devices.probe.id().to_string();
        let mut attempt = 0;
        let value_m = loop {
            match self.devices.probe.read().await {
                Ok(r) => break Some(r.value_m),
                // The sensor answered that it has no valid reading: the simulated probe says
                // "out of range", a real one sends its error reply (`ER,M0,01`).
                Err(DeviceError::Rejected { message, .. }) => {
                    self.log.fault(&id, "out_of_range", message);
                    break None;
                }
                Err(e) => self.log.retry_or_fail(e, &mut attempt)?,
            }
        };
        let sample = ProbeSample {
            seq: self.seq,
            t_s: self.log.elapsed_s(),
            value_m,
        };
        self.seq += 1;
        self.log
            .recorder
            .probe(&id, &sample, self.log.clock.now_ns());
        self.summary.samples += 1;
        Ok(())
    }
}
