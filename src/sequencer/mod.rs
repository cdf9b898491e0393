//! The run sequencer: executes a plan on devices seen only through their traits, turns the
//! rotary table the tracer stands on, waits for stillstand, homes, and records every raw sample
//! and every step to the session.

use std::collections::BTreeMap;
use std::sync::Arc;

use geocal_drivers::{
    AxisPositions, DeviceError, Environment, Machine, MachineState, Operator, RotaryState,
    RotaryTable, Tracer, TracerReading,
};

use crate::clock::Clock;
use crate::extract::{Stillstand, StillstandDetector};
use crate::plan::{Plan, PlanRotation, PlanTarget, AXES};
use crate::session::messages::{EnvSample, RotaryStateSample, RunEvent, TracerSample};
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
    #[error("rotary table {table} not in position at {commanded_rad} rad within {waited_s:.0} s of device time")]
    NoInPosition {
        table: String,
        commanded_rad: f64,
        waited_s: f64,
    },
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

pub struct Sequencer<'a> {
    plan: &'a Plan,
    devices: Devices,
    recorder: RecorderHandle,
    clock: Arc<dyn Clock>,
    approach: BTreeMap<String, i8>,
    position: Option<[f64; 3]>,
    last_sample: Option<TracerReading>,
    next_env_poll_s: f64,
    /// The tracer stands on the rotary table (placed there by the operator).
    on_table: bool,
    /// Clock reading at the start of the run: `/rotary/<id>/state` times count from here.
    start_ns: u64,
    summary: RunSummary,
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
            approach: AXES.iter().map(|a| (a.to_string(), 0)).collect(),
            position: None,
            last_sample: None,
            next_env_poll_s: 0.0,
            on_table: false,
            start_ns,
            summary: RunSummary::default(),
        }
    }

    /// Run the whole plan: every station, every pass, every point.
    pub async fn run(mut self, progress: Progress<'_>) -> Result<RunSummary, SequencerError> {
        let plan = self.plan;
        let total =
            (plan.stations.len() * plan.targets.len() * plan.passes.len() * plan.points.len())
                as u64;
        let mut mounted: Option<&PlanTarget> = None;
        let mut done = 0;
        for (station_index, station) in plan.stations.iter().enumerate() {
            self.event(RunEvent::StationBegin {
                station: station.id.clone(),
                station_index,
                hint_m: station.hint_m,
            });
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
            for target in &plan.targets {
                if mounted != Some(target) {
                    self.devices
                        .operator
                        .mount_target(&target.id, target.offset_m)
                        .await?;
                    mounted = Some(target);
                }
                for (pass, &direction) in plan.passes.iter().enumerate() {
                    for point in plan.pass_order(direction) {
                        self.move_to(point).await?;
                        if point == 0 {
                            self.home(&station.id).await?;
                        }
                        self.measure(&station.id, target, point, pass).await?;
                        done += 1;
                        progress(done, total);
                    }
                }
            }
            self.event(RunEvent::StationEnd {
                station: station.id.clone(),
            });
        }
        self.poll_environment().await?;
        Ok(self.summary)
    }

    fn event(&mut self, event: RunEvent) {
        if matches!(event, RunEvent::Fault { .. }) {
            self.summary.faults += 1;
        }
        self.recorder.event(&event, self.clock.now_ns());
    }

    /// Pull one sample from the tracer and record it; poll the environment now and then.
    async fn sample(&mut self) -> Result<TracerReading, SequencerError> {
        let reading = self.devices.tracer.next_sample().await?;
        let sample = TracerSample {
            seq: reading.seq,
            t_s: reading.t_s,
            length_m: reading.length_m,
            signal: reading.signal,
            tracking: reading.tracking,
            beam_segment: reading.beam_segment,
        };
        self.recorder
            .tracer(self.devices.tracer.id(), &sample, self.clock.now_ns());
        self.summary.samples += 1;
        self.last_sample = Some(reading);
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
        for reading in env.poll().await? {
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

    /// Command the move to a plan point and keep recording until the machine reports arrival.
    async fn move_to(&mut self, point: usize) -> Result<(), SequencerError> {
        let target = self.plan.points[point].axes_m;
        if self.position == Some(target) {
            return Ok(());
        }
        if let Some(from) = self.position {
            for (k, axis) in AXES.iter().enumerate() {
                let delta = target[k] - from[k];
                if delta != 0.0 {
                    self.approach.insert(axis.to_string(), delta.signum() as i8);
                }
            }
        }
        let command: AxisPositions = AXES.iter().map(|a| a.to_string()).zip(target).collect();
        self.devices.machine.start_move(&command).await?;
        let started_s = self.sample().await?.t_s;
        loop {
            if let MachineState::Idle { .. } = self.devices.machine.state().await? {
                break;
            }
            let t_s = self.sample().await?.t_s;
            if t_s - started_s > MAX_MOVE_S {
                return Err(SequencerError::NoArrival {
                    point,
                    waited_s: t_s - started_s,
                });
            }
        }
        self.position = Some(target);
        Ok(())
    }

    /// Command the table to a station's angle (a `rotation` event), then keep recording the
    /// tracer and the table's state until the table reports in position.
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
        });
        if let Some(table) = self.devices.rotary.as_mut() {
            table.start_rotation(rotation.commanded_rad).await?;
        }
        let started_s = self.sample().await?.t_s;
        loop {
            let state = match self.devices.rotary.as_mut() {
                Some(table) => table.state().await?,
                None => RotaryState::Moving,
            };
            let encoder_rad = match state {
                RotaryState::InPosition { encoder_rad } => Some(encoder_rad),
                RotaryState::Moving => None,
            };
            let now_ns = self.clock.now_ns();
            let sample = RotaryStateSample {
                t_s: now_ns.saturating_sub(self.start_ns) as f64 * 1e-9,
                commanded_rad: rotation.commanded_rad,
                encoder_rad,
                in_position: encoder_rad.is_some(),
            };
            self.recorder.rotary(&table_id, &sample, now_ns);
            if encoder_rad.is_some() {
                return Ok(());
            }
            let t_s = self.sample().await?.t_s;
            if t_s - started_s > MAX_ROTATION_S {
                return Err(SequencerError::NoInPosition {
                    table: table_id,
                    commanded_rad: rotation.commanded_rad,
                    waited_s: t_s - started_s,
                });
            }
        }
    }

    /// Record for at least `min_dwell_s` and until the readings settle; after max_dwell_s
    /// give up with a `fault` event. Returns whether stillstand was reached.
    async fn dwell(&mut self, point: usize, min_dwell_s: f64) -> Result<bool, SequencerError> {
        let plan = self.plan;
        let mut detector =
            StillstandDetector::new(plan.stillstand_window_s, plan.stillstand_tolerance_m);
        let begin_s = self.last_sample.map_or(0.0, |s| s.t_s);
        loop {
            let sample = self.sample().await?;
            let settled = matches!(
                detector.push(sample.t_s, sample.length_m),
                Stillstand::Settled { .. }
            );
            let elapsed_s = sample.t_s - begin_s;
            if settled && elapsed_s >= min_dwell_s {
                return Ok(true);
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
                return Ok(false);
            }
        }
    }

    /// Zero the counter at point 0 once at rest there: every pass is relative to point 0.
    /// A homing after the beam was interrupted starts a new beam segment: say so.
    async fn home(&mut self, station: &str) -> Result<(), SequencerError> {
        self.dwell(0, 0.0).await?;
        let before = self.last_sample.map(|s| s.beam_segment);
        self.devices.tracer.home().await?;
        let after = self.sample().await?.beam_segment;
        if before.is_some_and(|b| b != after) {
            self.event(RunEvent::Rehome {
                station: station.to_string(),
                beam_segment: after,
            });
        }
        Ok(())
    }

    /// The dwell at a point: point_begin, at least dwell_s and until settled, point_end.
    async fn measure(
        &mut self,
        station: &str,
        target: &PlanTarget,
        point: usize,
        pass: usize,
    ) -> Result<(), SequencerError> {
        let p = &self.plan.points[point];
        self.event(RunEvent::PointBegin {
            station: station.to_string(),
            point,
            pass,
            target: target.id.clone(),
            nominal_m: self.plan.nominal_m(point, target),
            axes: AXES.iter().map(|a| a.to_string()).zip(p.axes_m).collect(),
            approach: self.approach.clone(),
        });
        self.dwell(point, self.plan.dwell_s).await?;
        self.event(RunEvent::PointEnd {
            station: station.to_string(),
            point,
            pass,
        });
        self.summary.points_measured += 1;
        Ok(())
    }
}
