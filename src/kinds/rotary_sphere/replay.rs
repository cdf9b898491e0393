//! `geocal replay` of a rotary_sphere recording: the sphere sequencer against a table, a probe
//! and an arm that hand out what was recorded.

use std::collections::VecDeque;
use std::sync::Arc;

use async_trait::async_trait;
use geocal_drivers::{DeviceError, RotaryState, RotaryTable};

use super::config as rs;
use crate::run::replay::{
    device_id, ended, replay_runtime, ReplayClock, ReplayLaserProbe, SequenceEnd,
};
use crate::session::messages::RunEvent;
use crate::session::reader::Session;
use crate::session::recorder::RecorderHandle;

/// Re-run this kind's sequencer against `session` into `handle` (`geocal replay`).
pub fn replay(session: &Session, handle: RecorderHandle) -> anyhow::Result<SequenceEnd> {
    let clock = Arc::new(ReplayClock::default());
    let first_event_ns = session.events.first().map_or(0, |e| e.log_time_ns);
    let runtime = replay_runtime()?;
    let end = {
        let plan_config: rs::SpherePlanConfig =
            serde_path_to_error::deserialize(session.header.plan.clone()).map_err(|e| {
                anyhow::anyhow!(
                    "the session header cannot be replayed: key `plan.{}`: {}",
                    e.path(),
                    e.inner()
                )
            })?;
        let mut plan = crate::kinds::rotary_sphere::plan::SpherePlan::from_config(&plan_config);
        // The recorded table states come at full speed: waiting between polls adds nothing.
        plan.poll_interval_s = 0.0;
        let probe_id = device_id(session, "probe")?;
        let table_id = plan.table.clone();
        let states: VecDeque<_> = session
            .rotary
            .get(&table_id)
            .map(Vec::as_slice)
            .unwrap_or(&[])
            .iter()
            .map(|s| (s.log_time_ns, s.msg))
            .collect();
        // The run's start: a table state's log time less its `t_s` (seconds since the start).
        let start_ns = states.front().map_or(first_event_ns, |(t, s)| {
            t.saturating_sub((s.t_s * 1e9).round() as u64)
        });
        // Each height's mount ends where its first `rotation` event was recorded.
        let mut mounts = VecDeque::new();
        let mut last_rotation = start_ns;
        for e in &session.events {
            match &e.msg {
                RunEvent::Rotation { .. } => last_rotation = e.log_time_ns,
                RunEvent::SphereBegin { angle_index: 0, .. } => mounts.push_back(last_rotation),
                _ => {}
            }
        }
        let devices = crate::kinds::rotary_sphere::sequence::SphereDevices {
            table: Box::new(ReplaySphereTable {
                id: table_id,
                clock: clock.clone(),
                states,
            }),
            probe: Box::new(ReplayLaserProbe {
                clock: clock.clone(),
                readings: session
                    .probes
                    .get(&probe_id)
                    .map(Vec::as_slice)
                    .unwrap_or(&[])
                    .iter()
                    .map(|s| (s.log_time_ns, s.msg.t_s, s.msg.value_m))
                    .collect(),
                out_of_range: VecDeque::new(),
                id: probe_id,
            }),
            arm: Box::new(ReplayArm {
                clock: clock.clone(),
                mounts,
            }),
        };
        clock.set_fixed(start_ns);
        handle.session(
            &crate::run::replay::replay_header(&session.header),
            start_ns,
        );
        let sequencer = crate::kinds::rotary_sphere::sequence::SphereSequencer::new(
            &plan,
            devices,
            handle,
            clock.clone(),
        );
        runtime
            .block_on(sequencer.run(&mut |_: u64, _: u64| {}))
            .map(|_| ())
            .map_err(|e| match e {
                crate::kinds::rotary_sphere::sequence::SphereRunError::Device(
                    DeviceError::EndOfStream { device },
                ) => (Some(device), String::new()),
                e => (None, e.to_string()),
            })
    };
    Ok(end)
}

/// The rotary table of a rotary_sphere recording: each poll returns the next recorded
/// `/rotary/<id>/state` (moving or in position at the recorded encoder angle).
struct ReplaySphereTable {
    id: String,
    clock: Arc<ReplayClock>,
    states: VecDeque<(u64, crate::session::messages::RotaryStateSample)>,
}

#[async_trait]
impl RotaryTable for ReplaySphereTable {
    fn id(&self) -> &str {
        &self.id
    }
    async fn start_rotation(&mut self, commanded_rad: f64) -> Result<(), DeviceError> {
        match self.states.front() {
            Some((_, s)) if (s.commanded_rad - commanded_rad).abs() > 1e-12 => {
                Err(DeviceError::Rejected {
                    device: self.id.clone(),
                    message: format!(
                        "the replay diverged: commanded {commanded_rad} rad, the recording \
                         turned to {} rad",
                        s.commanded_rad
                    ),
                })
            }
            Some(_) => Ok(()),
            None => Err(ended(&self.id)),
        }
    }
    async fn state(&mut self) -> Result<RotaryState, DeviceError> {
        let (t, s) = self.states.pop_front().ok_or_else(|| ended(&self.id))?;
        self.clock.set_fixed(t);
        Ok(match s.encoder_rad {
            Some(encoder_rad) if s.in_position => RotaryState::InPosition { encoder_rad },
            _ => RotaryState::Moving,
        })
    }
}

/// The probing arm of a rotary_sphere recording: mounting the sphere at a height takes until
/// the recorded `rotation` event that follows it; approaches take no recorded time.
struct ReplayArm {
    clock: Arc<ReplayClock>,
    mounts: VecDeque<u64>,
}

#[async_trait]
impl crate::kinds::rotary_sphere::sequence::ProbeArm for ReplayArm {
    async fn mount_sphere(&mut self, _h: usize, _nominal_m: [f64; 3]) -> Result<(), DeviceError> {
        let t = self.mounts.pop_front().ok_or_else(|| ended("arm"))?;
        self.clock.set_fixed(t);
        Ok(())
    }
    async fn approach(&mut self, _start: [f64; 3], _dir: [f64; 3]) -> Result<(), DeviceError> {
        Ok(())
    }
}
