//! `geocal replay` of a probe_install recording: its sequencer against a CMM and a probe that
//! hand out what was recorded.

use std::collections::VecDeque;
use std::sync::Arc;

use async_trait::async_trait;
use geocal_drivers::{AxisPositions, DeviceError, Machine, MachineState};

use super::config as pi;
use crate::run::replay::{
    config_from_header, device_id, ended, replay_runtime, sequence_end, stream, ReplayClock,
    ReplayLaserProbe, SequenceEnd,
};
use crate::session::kind_messages::{MachinePoseSample, TOPIC_MACHINE_POSE};
use crate::session::messages::RunEvent;
use crate::session::reader::Session;
use crate::session::recorder::RecorderHandle;

/// Re-run this kind's sequencer against `session` into `handle` (`geocal replay`).
pub fn replay(session: &Session, handle: RecorderHandle) -> anyhow::Result<SequenceEnd> {
    let clock = Arc::new(ReplayClock::default());
    let first_event_ns = session.events.first().map_or(0, |e| e.log_time_ns);
    let runtime = replay_runtime()?;
    let end = {
        let probe_id = device_id(session, "probe")?;
        let machine_id = device_id(session, "machine")?;
        let config: pi::ProbeInstallConfig = config_from_header(
            session,
            serde_json::json!({
                "machine": {"name": session.header.machine.name,
                            "travel_m": session.header.machine.travel_m},
                "devices": {
                    "machine": {"id": machine_id, "driver": "sim", "feed_m_s": 1.0,
                                "rotary_speed_rad_s": 1.0},
                    "probe": {"id": probe_id, "driver": "sim", "noise_m": 1.0,
                              "range_m": [-1.0, 1.0], "reading_period_s": 1.0},
                },
            }),
        )?;
        let plan = crate::kinds::probe_install::plan::ProbeInstallPlan::from_config(&config);
        let recorded = session
            .probes
            .get(&probe_id)
            .map(Vec::as_slice)
            .unwrap_or(&[]);
        // The run's start: a reading's log time less its `t_s` (seconds since the start).
        let start_ns = recorded.first().map_or(first_event_ns, |s| {
            s.log_time_ns
                .saturating_sub((s.msg.t_s * 1e9).round() as u64)
        });
        let out_of_range = session
            .events
            .iter()
            .filter_map(|e| match &e.msg {
                RunEvent::Fault {
                    device,
                    code,
                    message,
                } if code == "out_of_range" && *device == probe_id => Some(message.clone()),
                _ => None,
            })
            .collect();
        let devices = crate::kinds::probe_install::sequence::ProbeInstallDevices {
            machine: Box::new(ReplayCmm {
                id: machine_id,
                clock: clock.clone(),
                poses: stream(session, TOPIC_MACHINE_POSE)?,
                arrival: None,
            }),
            probe: Box::new(ReplayLaserProbe {
                id: probe_id,
                clock: clock.clone(),
                readings: recorded
                    .iter()
                    .map(|s| (s.log_time_ns, s.msg.t_s, s.msg.value_m))
                    .collect(),
                out_of_range,
            }),
        };
        clock.set_fixed(start_ns);
        handle.session(
            &crate::run::replay::replay_header(&session.header),
            start_ns,
        );
        let sequencer = crate::kinds::probe_install::sequence::ProbeInstallSequencer::new(
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

/// The CMM of a probe_install recording: each move arrives where `/machine/pose` recorded.
struct ReplayCmm {
    id: String,
    clock: Arc<ReplayClock>,
    poses: VecDeque<(u64, MachinePoseSample)>,
    arrival: Option<(u64, AxisPositions)>,
}

#[async_trait]
impl Machine for ReplayCmm {
    fn id(&self) -> &str {
        &self.id
    }
    async fn start_move(&mut self, target: &AxisPositions) -> Result<(), DeviceError> {
        let (t, pose) = self.poses.pop_front().ok_or_else(|| ended(&self.id))?;
        if &pose.commanded != target {
            return Err(DeviceError::Rejected {
                device: self.id.clone(),
                message: format!(
                    "the replay diverged: commanded {target:?}, the recording moved to {:?}",
                    pose.commanded
                ),
            });
        }
        self.arrival = Some((t, pose.reported));
        Ok(())
    }
    async fn state(&mut self) -> Result<MachineState, DeviceError> {
        let (t, position) = self.arrival.take().ok_or_else(|| ended(&self.id))?;
        self.clock.set_fixed(t);
        Ok(MachineState::Idle { position })
    }
}
