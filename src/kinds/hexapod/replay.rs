//! `geocal replay` of a hexapod recording: its sequencer against a hexapod and a pose sensor
//! that hand out what was recorded.

use std::collections::VecDeque;
use std::sync::Arc;

use async_trait::async_trait;
use geocal_drivers::{
    DeviceError, Hexapod, HexapodState, LegReading, PlatformPose, PoseReading, PoseSensor,
};

use super::config as hx;
use crate::run::replay::{
    config_from_header, device_id, ended, replay_runtime, sequence_end, stream, ReplayClock,
    SequenceEnd,
};
use crate::session::kind_messages::{hexapod_legs_topic, LegSample, PlatformPoseSample};
use crate::session::messages::RunEvent;
use crate::session::reader::Session;
use crate::session::recorder::RecorderHandle;

/// Re-run this kind's sequencer against `session` into `handle` (`geocal replay`).
pub fn replay(session: &Session, handle: RecorderHandle) -> anyhow::Result<SequenceEnd> {
    let clock = Arc::new(ReplayClock::default());
    let first_event_ns = session.events.first().map_or(0, |e| e.log_time_ns);
    let runtime = replay_runtime()?;
    let end = {
        let id = device_id(session, "hexapod")?;
        let config: hx::HexapodConfig = config_from_header(
            session,
            serde_json::json!({
                "machine": {"name": session.header.machine.name,
                            "base_hinges_m": [], "platform_hinges_m": []},
                "devices": {
                    "hexapod": {"id": id, "driver": "sim", "encoder_noise_m": 1.0,
                                "speed_m_s": 1.0, "angular_speed_rad_s": 1.0,
                                "reading_period_s": 1.0},
                },
            }),
        )?;
        let plan = crate::kinds::hexapod::plan::HexapodPlan::from_config(&config);
        let sensor = session
            .header
            .devices
            .iter()
            .find(|d| d.kind == "pose_sensor")
            .map(|d| d.id.clone());
        let arrivals: VecDeque<u64> = session
            .events
            .iter()
            .filter(|e| matches!(e.msg, RunEvent::PoseBegin { .. }))
            .map(|e| e.log_time_ns)
            .collect();
        let pose_topic = super::solve::measured_pose_topic(session, &id, sensor.as_deref())?;
        let pose_sensor = match sensor {
            Some(sid) => Some(Box::new(ReplayPoseSensor {
                clock: clock.clone(),
                poses: stream(session, &pose_topic)?,
                id: sid,
            }) as Box<dyn PoseSensor>),
            None => None,
        };
        let devices = crate::kinds::hexapod::sequence::HexapodDevices {
            hexapod: Box::new(ReplayHexapod {
                clock: clock.clone(),
                arrivals,
                legs: stream(session, &hexapod_legs_topic(&id))?,
                moving: false,
                id,
            }),
            pose_sensor,
        };
        // The run's start: the header's time is not in `Session`; the first event is the
        // first arrival, and nothing this kind records counts from the start.
        clock.set_fixed(first_event_ns);
        handle.session(
            &crate::run::replay::replay_header(&session.header),
            first_event_ns,
        );
        let sequencer = crate::kinds::hexapod::sequence::HexapodSequencer::new(
            &plan,
            devices,
            handle,
            clock.clone(),
        );
        runtime
            .block_on(sequencer.run(&mut |_: u64, _: u64| {}))
            .map(|_| ())
            .map_err(|e| {
                let device = match &e {
                    crate::sequencer::SequencerError::Device(d) => Some(d),
                    _ => None,
                };
                sequence_end(device, e.to_string())
            })
    };
    Ok(end)
}

/// The hexapod of a recording: arrives at each pose when the recording began measuring there.
struct ReplayHexapod {
    id: String,
    clock: Arc<ReplayClock>,
    arrivals: VecDeque<u64>,
    legs: VecDeque<(u64, LegSample)>,
    moving: bool,
}

#[async_trait]
impl Hexapod for ReplayHexapod {
    fn id(&self) -> &str {
        &self.id
    }
    async fn start_move(&mut self, _pose: &PlatformPose) -> Result<(), DeviceError> {
        self.moving = true;
        Ok(())
    }
    async fn state(&mut self) -> Result<HexapodState, DeviceError> {
        if !self.moving {
            return Ok(HexapodState::Idle);
        }
        let t = self.arrivals.pop_front().ok_or_else(|| ended(&self.id))?;
        self.clock.set_fixed(t);
        self.moving = false;
        Ok(HexapodState::Idle)
    }
    async fn read_legs(&mut self) -> Result<LegReading, DeviceError> {
        let (t, s) = self.legs.pop_front().ok_or_else(|| ended(&self.id))?;
        self.clock.set_fixed(t);
        Ok(LegReading {
            t_s: s.t_s,
            lengths_m: s.lengths_m,
        })
    }
}

struct ReplayPoseSensor {
    id: String,
    clock: Arc<ReplayClock>,
    poses: VecDeque<(u64, PlatformPoseSample)>,
}

#[async_trait]
impl PoseSensor for ReplayPoseSensor {
    fn id(&self) -> &str {
        &self.id
    }
    async fn measure(&mut self) -> Result<PoseReading, DeviceError> {
        let (t, s) = self.poses.pop_front().ok_or_else(|| ended(&self.id))?;
        self.clock.set_fixed(t);
        Ok(PoseReading {
            t_s: s.t_s,
            pose: PlatformPose {
                translation_m: s.translation_m,
                rotation_vector_rad: s.rotation_vector_rad,
            },
        })
    }
}
