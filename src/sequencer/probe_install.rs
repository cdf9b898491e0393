//! Sequencer of plan kind `probe_install`: for every posture (A, B), move the 5-axis CMM to
//! each sphere point, record its reported position and every raw probe reading.
//!
//! Events: `posture_begin` / `posture_end` around a posture, `probe_begin` / `probe_end` around
//! the readings of one point; `/machine/pose` at every arrival; `/probe/<id>/reading` for every
//! reading (null when out of range, with a `fault` event). Timeouts and protocol errors are
//! retried with `fault` events; a gap in the probe's counter would show as `frames_lost`.

use std::sync::Arc;

use geocal_drivers::{AxisPositions, DeviceError, Machine, MachineState, Probe};

use super::kind_faults::{retried, EventLog};
use super::{Progress, RunSummary, SequencerError};
use crate::clock::Clock;
use crate::plan::probe_install::{ProbeInstallPlan, CMM_AXES};
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
            seq: 0,
            summary: RunSummary::default(),
        }
    }

    pub async fn run(mut self, progress: Progress<'_>) -> Result<RunSummary, SequencerError> {
        let plan = self.plan;
        let total = plan.points.len() as u64;
        let mut current: Option<usize> = None;
        for (done, p) in plan.points.iter().enumerate() {
            if current != Some(p.posture) {
                if let Some(prev) = current {
                    self.log.event(RunEvent::PostureEnd { posture: prev });
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
                axes: commanded,
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
        }
        if let Some(prev) = current {
            self.log.event(RunEvent::PostureEnd { posture: prev });
        }
        self.summary.faults = self.log.faults;
        Ok(self.summary)
    }

    /// Command a move, wait for Idle, record the commanded and reported positions.
    async fn move_to(&mut self, commanded: &AxisPositions) -> Result<(), SequencerError> {
        retried!(self.log, self.devices.machine.start_move(commanded));
        let mut queries = 0;
        let reported = loop {
            if let MachineState::Idle { position } =
                retried!(self.log, self.devices.machine.state())
            {
                break position;
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

    /// One raw reading, recorded whatever it is; out of range is a null value and a fault.
    async fn read_probe(&mut self) -> Result<(), SequencerError> {
        let id = self.devices.probe.id().to_string();
        let mut attempt = 0;
        let value_m = loop {
            match self.devices.probe.read().await {
                Ok(r) => break Some(r.value_m),
                Err(DeviceError::Rejected { message, .. }) if message.contains("out of range") => {
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
