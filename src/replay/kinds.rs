//! `geocal replay` of the plan kinds rotary_sphere, probe_install and hexapod: their own
//! sequencers re-run against the recording through replay devices, recorded anew and compared.
//!
//! Every device hands out its recorded stream in order and sets the replay clock to the
//! recorded log time of what it hands out (a machine's or hexapod's arrival: the recorded
//! arrival), so the replayed events and samples carry the recorded log times and the method
//! sees the same windows. Recorded `out_of_range` probe readings are raised again; other
//! recorded device faults (retries) are not (these kinds run on simulated devices so far).

use std::collections::VecDeque;
use std::path::Path;
use std::sync::Arc;

use anyhow::Context;
use async_trait::async_trait;
use geocal_drivers::{
    AxisPositions, DeviceError, Hexapod, HexapodState, LegReading, Machine, MachineState,
    PlatformPose, PoseReading, PoseSensor, Probe, ProbeReading, RotaryState, RotaryTable,
};

use super::compare::{compare_windows, event_counts, Window};
use super::devices::ReplayClock;
use super::{
    write_comparison, Comparison, Outcome, ReplayOptions, ReplayOutput, COMPARISON_FORMAT,
};
use crate::kinds::hexapod::config as hx;
use crate::kinds::probe_install::config as pi;
use crate::kinds::rotary_sphere::config as rs;
use crate::sequencer::SequencerError;
use crate::session::kind_messages::{
    hexapod_legs_topic, hexapod_pose_topic, LegSample, MachinePoseSample, PlatformPoseSample,
    TOPIC_MACHINE_POSE,
};
use crate::session::messages::RunEvent;
use crate::session::reader::{read_session, Session};
use crate::session::recorder::{Recorder, RecorderOptions};

/// The kinds replayed here.
pub fn replays(kind: &str) -> bool {
    kind == pi::KIND || kind == hx::KIND || kind == rs::KIND
}

fn device_id(session: &Session, kind: &str) -> anyhow::Result<String> {
    session
        .header
        .devices
        .iter()
        .find(|d| d.kind == kind)
        .map(|d| d.id.clone())
        .ok_or_else(|| anyhow::anyhow!("session header: no device of kind `{kind}`"))
}

/// A topic's recorded JSON messages parsed, with their log times.
fn stream<T: serde::de::DeserializeOwned>(
    session: &Session,
    topic: &str,
) -> anyhow::Result<VecDeque<(u64, T)>> {
    session
        .topics
        .get(topic)
        .map(Vec::as_slice)
        .unwrap_or(&[])
        .iter()
        .map(|m| {
            T::deserialize(&m.msg)
                .map(|v| (m.log_time_ns, v))
                .with_context(|| format!("message on {topic} at log time {} ns", m.log_time_ns))
        })
        .collect()
}

fn ended(device: &str) -> DeviceError {
    DeviceError::EndOfStream {
        device: device.to_string(),
    }
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

/// The laser probe of a probe_install recording: every raw reading, out-of-range ones again
/// as the driver's out-of-range rejection.
struct ReplayLaserProbe {
    id: String,
    clock: Arc<ReplayClock>,
    /// Log time, recorded `t_s` and value (None: out of range) of every reading.
    readings: VecDeque<(u64, f64, Option<f64>)>,
    /// The recorded `out_of_range` fault messages, one per null reading, in order.
    out_of_range: VecDeque<String>,
}

#[async_trait]
impl Probe for ReplayLaserProbe {
    fn id(&self) -> &str {
        &self.id
    }
    async fn read(&mut self) -> Result<ProbeReading, DeviceError> {
        let (t, t_s, value) = self.readings.pop_front().ok_or_else(|| ended(&self.id))?;
        self.clock.set_fixed(t);
        match value {
            Some(value_m) => Ok(ProbeReading { t_s, value_m }),
            None => Err(DeviceError::Rejected {
                device: self.id.clone(),
                message: self
                    .out_of_range
                    .pop_front()
                    .unwrap_or_else(|| "out of range".into()),
            }),
        }
    }
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

/// A kind's configuration with the recorded plan: only `plan` matters to expanding it, the
/// rest is taken from the header or is a placeholder.
fn config_from_header<T: serde::de::DeserializeOwned>(
    session: &Session,
    mut rest: serde_json::Value,
) -> anyhow::Result<T> {
    rest["kind"] = session.header.kind.clone().into();
    rest["plan"] = session.header.plan.clone();
    serde_path_to_error::deserialize(rest).map_err(|e| {
        anyhow::anyhow!(
            "the session header cannot be replayed: key `{}`: {}",
            e.path(),
            e.inner()
        )
    })
}

/// Windows of a kind (`probe_begin`..`probe_end`, `probe_point_begin`..`probe_point_end` or
/// `pose_begin`..`pose_end`) and the readings inside, as `Window`s (station: the posture, the
/// sphere or `pose`).
fn kind_windows(session: &Session) -> Vec<Window> {
    let probe: Vec<(u64, Option<u64>)> = session
        .probes
        .values()
        .flatten()
        .map(|s| (s.log_time_ns, Some(s.msg.seq)))
        .collect();
    let legs: Vec<(u64, Option<u64>)> = session
        .topics
        .iter()
        .filter(|(t, _)| t.starts_with("/hexapod/") && t.ends_with("/legs"))
        .flat_map(|(_, v)| v.iter().map(|m| (m.log_time_ns, None)))
        .collect();
    let mut out = Vec::new();
    let mut open: Option<u64> = None;
    for e in &session.events {
        let (station, point, samples) = match &e.msg {
            RunEvent::ProbeBegin { .. }
            | RunEvent::PoseBegin { .. }
            | RunEvent::ProbePointBegin { .. } => {
                open = Some(e.log_time_ns);
                continue;
            }
            RunEvent::ProbeEnd { posture, point } => (format!("posture {posture}"), *point, &probe),
            RunEvent::PoseEnd { pose } => ("pose".to_string(), *pose, &legs),
            RunEvent::ProbePointEnd {
                height_index,
                angle_index,
                point,
            } => (
                format!("height {height_index} angle {angle_index}"),
                *point,
                &probe,
            ),
            _ => continue,
        };
        let Some(begin) = open.take() else { continue };
        let inside: Vec<&(u64, Option<u64>)> = samples
            .iter()
            .filter(|(t, _)| *t >= begin && *t <= e.log_time_ns)
            .collect();
        out.push(Window {
            station,
            point,
            pass: 0,
            target: String::new(),
            samples: inside.len(),
            first_seq: inside.first().and_then(|s| s.1),
            last_seq: inside.last().and_then(|s| s.1),
        });
    }
    out
}

fn readings(session: &Session) -> usize {
    session.probes.values().map(Vec::len).sum::<usize>()
        + session
            .topics
            .iter()
            .filter(|(t, _)| t.starts_with("/hexapod/") && t.ends_with("/legs"))
            .map(|(_, v)| v.len())
            .sum::<usize>()
}

/// Replay a probe_install or hexapod recording (`replays(kind)`).
pub fn replay(
    session: &Session,
    session_path: &Path,
    options: &ReplayOptions,
) -> anyhow::Result<ReplayOutput> {
    std::fs::create_dir_all(&options.out_dir)
        .with_context(|| format!("creating output directory {}", options.out_dir.display()))?;
    let out_path = options.out_dir.join("session.mcap");
    if super::same_file(session_path, &out_path) {
        anyhow::bail!(
            "the replay would overwrite its recording {}: choose another --out",
            session_path.display()
        );
    }
    let clock = Arc::new(ReplayClock::default());
    let first_event_ns = session.events.first().map_or(0, |e| e.log_time_ns);
    let recorder = Recorder::create(&out_path, RecorderOptions::default())
        .with_context(|| format!("creating {}", out_path.display()))?;
    let handle = recorder.handle();
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    let sequencer_end = |e: SequencerError| match e {
        SequencerError::Device(DeviceError::EndOfStream { device }) => {
            (Some(device), String::new())
        }
        e => (None, e.to_string()),
    };
    let ended: Result<(), (Option<String>, String)> = if session.header.kind == rs::KIND {
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
        handle.session(&super::replay_header(&session.header), start_ns);
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
    } else if session.header.kind == pi::KIND {
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
        handle.session(&super::replay_header(&session.header), start_ns);
        let sequencer = crate::kinds::probe_install::sequence::ProbeInstallSequencer::new(
            &plan,
            devices,
            handle,
            clock.clone(),
        );
        runtime
            .block_on(sequencer.run(&mut |_: u64, _: u64| {}))
            .map(|_| ())
            .map_err(sequencer_end)
    } else {
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
        let pose_sensor = match sensor {
            Some(sid) => Some(Box::new(ReplayPoseSensor {
                clock: clock.clone(),
                poses: stream(session, &hexapod_pose_topic(&id))?,
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
        handle.session(&super::replay_header(&session.header), first_event_ns);
        let sequencer = crate::kinds::hexapod::sequence::HexapodSequencer::new(
            &plan,
            devices,
            handle,
            clock.clone(),
        );
        runtime
            .block_on(sequencer.run(&mut |_: u64, _: u64| {}))
            .map(|_| ())
            .map_err(sequencer_end)
    };
    recorder
        .finish()
        .context("finishing the replayed session file")?;
    let replayed =
        read_session(&out_path).with_context(|| format!("reading back {}", out_path.display()))?;
    let (outcome, message) = match &ended {
        Ok(()) => (
            Outcome::Completed,
            "the sequencer completed the plan".to_string(),
        ),
        Err((Some(device), _)) => (
            Outcome::RecordingEnded,
            format!("the recording of {device} ends before the plan is done: replayed up to there"),
        ),
        Err((None, e)) => (Outcome::Diverged, format!("the replay stopped: {e}")),
    };
    let (results, results_error, results_path) =
        super::compare_results(session, &replayed, options)?;
    let comparison = Comparison {
        format: COMPARISON_FORMAT,
        recording: session_path.display().to_string(),
        replay: out_path.display().to_string(),
        outcome,
        message,
        truncation: match &session.completeness {
            crate::session::reader::Completeness::Complete => None,
            crate::session::reader::Completeness::Truncated { reason, .. } => Some(reason.clone()),
        },
        samples_recorded: readings(session),
        samples_replayed: readings(&replayed),
        windows: compare_windows(&kind_windows(session), &kind_windows(&replayed)),
        events_recorded: event_counts(session),
        events_replayed: event_counts(&replayed),
        trail: Vec::new(),
        recorded_nearby: Vec::new(),
        results,
        results_error,
    };
    write_comparison(options, out_path, results_path, comparison)
}
