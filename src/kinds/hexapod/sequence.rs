//! Sequencer of plan kind `hexapod`: command the platform to each pose, measure the pose, read
//! the six leg encoders; every reading recorded.
//!
//! Events: `pose_begin` / `pose_end` around the measurements at one pose (after arrival);
//! `/hexapod/<id>/pose` for each measured pose and `/hexapod/<id>/legs` for each encoder
//! reading. Timeouts and protocol errors are retried with `fault` events; faults the driver
//! recovered from itself (`reconnect`) are `fault` events too. A checkpoint follows every
//! `pose_end`: a resumed run keeps the finished poses and measures the unfinished one again.

use std::sync::Arc;

use geocal_drivers::{Hexapod, HexapodState, PlatformPose, PoseSensor};

use crate::clock::Clock;
use crate::kinds::hexapod::plan::{HexapodPlan, POSE_AXES};
use crate::sequencer::kind_faults::{retried, EventLog};
use crate::sequencer::{Progress, RunSummary, SequencerError};
use crate::session::kind_messages::{
    hexapod_legs_topic, hexapod_pose_topic, to_value, LegSample, PlatformPoseSample, SCHEMA_LEGS,
    SCHEMA_PLATFORM_POSE,
};
use crate::session::messages::RunEvent;
use crate::session::recorder::RecorderHandle;

const MAX_STATE_QUERIES: u64 = 1_000_000;

pub struct HexapodDevices {
    pub hexapod: Box<dyn Hexapod>,
    pub pose_sensor: Option<Box<dyn PoseSensor>>,
}

pub struct HexapodSequencer<'a> {
    plan: &'a HexapodPlan,
    devices: HexapodDevices,
    log: EventLog,
    summary: RunSummary,
    /// Wall-time pause between two state queries of a moving hexapod (0 for the simulated
    /// one, whose queries cost virtual time).
    poll_interval_s: f64,
    /// The first pose to measure: poses before it were finished by an interrupted run.
    first_pose: usize,
}

impl<'a> HexapodSequencer<'a> {
    pub fn new(
        plan: &'a HexapodPlan,
        devices: HexapodDevices,
        recorder: RecorderHandle,
        clock: Arc<dyn Clock>,
    ) -> Self {
        Self {
            plan,
            devices,
            log: EventLog::new(recorder, clock),
            summary: RunSummary::default(),
            poll_interval_s: 0.0,
            first_pose: 0,
        }
    }

    /// Continue an interrupted run at `pose` (measured again in full).
    pub fn resume_at(mut self, pose: usize) -> Self {
        self.first_pose = pose;
        self
    }

    /// Pause `s` seconds of wall time between state queries (a real controller's driver).
    pub fn with_poll_interval(mut self, s: f64) -> Self {
        self.poll_interval_s = if s.is_finite() { s.max(0.0) } else { 0.0 };
        self
    }

    pub async fn run(mut self, progress: Progress<'_>) -> Result<RunSummary, SequencerError> {
        let plan = self.plan;
        let total = plan.poses.len() as u64;
        let id = self.devices.hexapod.id().to_string();
        for (pose, p) in plan.poses.iter().enumerate().skip(self.first_pose) {
            let command = PlatformPose {
                translation_m: p.translation_m,
                rotation_vector_rad: p.rotation_vector_rad,
            };
            retried!(self.log, self.devices.hexapod.start_move(&command));
            self.link_faults();
            let mut queries = 0;
            while retried!(self.log, self.devices.hexapod.state()) != HexapodState::Idle {
                self.link_faults();
                queries += 1;
                if queries > MAX_STATE_QUERIES {
                    return Err(SequencerError::NoArrival {
                        point: pose,
                        waited_s: self.log.elapsed_s(),
                    });
                }
                if self.poll_interval_s > 0.0 {
                    tokio::time::sleep(std::time::Duration::from_secs_f64(self.poll_interval_s))
                        .await;
                }
            }
            self.link_faults();
            self.log.event(RunEvent::PoseBegin {
                pose,
                axes: POSE_AXES
                    .iter()
                    .map(|a| a.to_string())
                    .zip(p.axes())
                    .collect(),
            });
            if let Some(sensor) = self.devices.pose_sensor.as_mut() {
                let reading = retried!(self.log, sensor.measure());
                let sample = PlatformPoseSample {
                    t_s: reading.t_s,
                    rotation_vector_rad: reading.pose.rotation_vector_rad,
                    translation_m: reading.pose.translation_m,
                };
                self.log.recorder.json(
                    &hexapod_pose_topic(&id),
                    SCHEMA_PLATFORM_POSE,
                    to_value(&sample),
                    self.log.clock.now_ns(),
                );
            }
            let readings = if pose == 0 {
                plan.reference_readings
            } else {
                plan.readings_per_pose
            };
            for _ in 0..readings {
                let r = retried!(self.log, self.devices.hexapod.read_legs());
                self.link_faults();
                let sample = LegSample {
                    t_s: r.t_s,
                    lengths_m: r.lengths_m,
                };
                self.log.recorder.json(
                    &hexapod_legs_topic(&id),
                    SCHEMA_LEGS,
                    to_value(&sample),
                    self.log.clock.now_ns(),
                );
                self.summary.samples += 1;
            }
            self.log.event(RunEvent::PoseEnd { pose });
            // A finished pose is on disk before the platform moves on: a resume keeps it.
            self.log.recorder.checkpoint();
            self.summary.points_measured += 1;
            progress(pose as u64 + 1, total);
            crate::sequencer::control::cancellation_point().await;
        }
        self.summary.faults = self.log.faults;
        Ok(self.summary)
    }

    /// Record what the hexapod's driver recovered from by itself (Modbus reconnects).
    fn link_faults(&mut self) {
        let id = self.devices.hexapod.id().to_string();
        for f in self.devices.hexapod.take_link_faults() {
            self.log.fault(&id, &f.code, f.message);
        }
    }
}
