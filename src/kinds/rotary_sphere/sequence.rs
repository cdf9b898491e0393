//! The `rotary_sphere` step runner: for each height, for each commanded angle, turn the table
//! and wait in position, then probe every point of the sphere; records every raw reading.
//!
//! As published (ref3), points are probed by a probing arm, not by the machine: the arm (an
//! operator or its controller, `ProbeArm`) brings the probe to the approach start of each
//! nominal point; the probe (`Probe`) reports how far beyond the nominal surface it met the
//! sphere. Timeouts and protocol errors are retried (`DEVICE_RETRIES`) with a `fault` event,
//! as the core sequencer does; other device errors end the run (the session is kept).

use std::sync::Arc;

use async_trait::async_trait;
use geocal_drivers::{DeviceError, Probe, RotaryState, RotaryTable};

use crate::clock::Clock;
use crate::kinds::rotary_sphere::plan::SpherePlan;
use crate::session::messages::{ProbeSample, RotaryStateSample, RunEvent};
use crate::session::recorder::RecorderHandle;

/// Whoever moves the probe and the sphere: mounts the sphere at a height, brings the probe to
/// the start of an approach (a measuring arm's operator; the simulated world).
#[async_trait]
pub trait ProbeArm: Send {
    /// Put the sphere on its stand at height `height_index` (nominal centre at angle 0).
    async fn mount_sphere(
        &mut self,
        height_index: usize,
        nominal_m: [f64; 3],
    ) -> Result<(), DeviceError>;
    /// Bring the probe to `start_m`, ready to travel along −`direction`.
    async fn approach(&mut self, start_m: [f64; 3], direction: [f64; 3])
        -> Result<(), DeviceError>;
}

pub struct SphereDevices {
    pub table: Box<dyn RotaryTable>,
    pub probe: Box<dyn Probe>,
    pub arm: Box<dyn ProbeArm>,
}

#[derive(Debug, thiserror::Error)]
pub enum SphereRunError {
    #[error(transparent)]
    Device(#[from] DeviceError),
    #[error("rotary table {table} not in position at {commanded_rad} rad within {waited_s:.0} s")]
    NoInPosition {
        table: String,
        commanded_rad: f64,
        waited_s: f64,
    },
    #[error(transparent)]
    Cancelled(#[from] crate::sequencer::control::Cancelled),
}

#[derive(Debug, Default, Clone, PartialEq)]
pub struct SphereRunSummary {
    pub spheres: u64,
    pub points: u64,
    pub readings: u64,
    pub faults: u64,
}

pub struct SphereSequencer<'a> {
    plan: &'a SpherePlan,
    devices: SphereDevices,
    recorder: RecorderHandle,
    clock: Arc<dyn Clock>,
    start_ns: u64,
    summary: SphereRunSummary,
    /// The first sphere (height, angle index) to measure: spheres before it in plan order
    /// were finished by an interrupted run.
    first_sphere: (usize, usize),
}

impl<'a> SphereSequencer<'a> {
    pub fn new(
        plan: &'a SpherePlan,
        devices: SphereDevices,
        recorder: RecorderHandle,
        clock: Arc<dyn Clock>,
    ) -> Self {
        let start_ns = clock.now_ns();
        Self {
            plan,
            devices,
            recorder,
            clock,
            start_ns,
            summary: SphereRunSummary::default(),
            first_sphere: (0, 0),
        }
    }

    /// Continue an interrupted run at sphere (height, angle index).
    pub fn resume_at(mut self, first_sphere: (usize, usize)) -> Self {
        self.first_sphere = first_sphere;
        self
    }

    /// Run the whole plan; `progress(done, total)` after every probed point.
    pub async fn run(
        mut self,
        progress: &mut dyn FnMut(u64, u64),
    ) -> Result<SphereRunSummary, SphereRunError> {
        let plan = self.plan;
        let total = plan.total_points();
        let (first_height, first_angle) = self.first_sphere;
        let mut done = (first_height * plan.angles_rad.len() + first_angle) as u64
            * plan.directions.len() as u64;
        for (h, height) in plan.heights.iter().enumerate().skip(first_height) {
            self.devices
                .arm
                .mount_sphere(h, height.sphere_m.into())
                .await?;
            for (a, &commanded_rad) in plan.angles_rad.iter().enumerate() {
                if (h, a) < self.first_sphere {
                    continue;
                }
                self.rotate(commanded_rad).await?;
                self.event(RunEvent::SphereBegin {
                    height_index: h,
                    angle_index: a,
                    commanded_rad,
                });
                for k in 0..plan.directions.len() {
                    self.probe_point(h, a, k).await?;
                    done += 1;
                    progress(done, total);
                    crate::sequencer::control::cancellation_point().await;
                }
                self.event(RunEvent::SphereEnd {
                    height_index: h,
                    angle_index: a,
                });
                self.summary.spheres += 1;
            }
        }
        Ok(self.summary)
    }

    fn event(&mut self, event: RunEvent) {
        if matches!(event, RunEvent::Fault { .. }) {
            self.summary.faults += 1;
        }
        self.recorder.event(&event, self.clock.now_ns());
    }

    /// Record a failed device call as a `fault` event; Ok if it may be retried.
    fn retry_or_fail(
        &mut self,
        error: DeviceError,
        attempt: &mut u32,
    ) -> Result<(), SphereRunError> {
        if let Some((event, retry)) = crate::sequencer::kind_faults::retry_decision(&error, attempt)
        {
            self.event(event);
            return if retry { Ok(()) } else { Err(error.into()) };
        }
        match &error {
            DeviceError::Rejected { device, .. }
            | DeviceError::Disconnected { device, .. }
            | DeviceError::Alarm { device, .. } => {
                // Not retried, but on the record before the run ends.
                let (device, message) = (device.clone(), error.to_string());
                self.event(RunEvent::Fault {
                    device,
                    code: "failed".into(),
                    message,
                });
            }
            _ => {}
        }
        Err(error.into())
    }

    /// Faults the table's driver recovered from by itself (e.g. a Modbus reconnect after a
    /// timeout), as `fault` events.
    fn record_table_link_faults(&mut self) {
        let device = self.devices.table.id().to_string();
        for fault in self.devices.table.take_link_faults() {
            self.event(RunEvent::Fault {
                device: device.clone(),
                code: fault.code,
                message: fault.message,
            });
        }
    }

    /// Turn the table to `commanded_rad` (a `rotation` event) and record its state until it
    /// reports in position.
    async fn rotate(&mut self, commanded_rad: f64) -> Result<(), SphereRunError> {
        let table = self.devices.table.id().to_string();
        self.event(RunEvent::Rotation {
            table: table.clone(),
            commanded_rad,
            via_rad: None,
        });
        let mut attempt = 0;
        while let Err(e) = self.devices.table.start_rotation(commanded_rad).await {
            self.record_table_link_faults();
            self.retry_or_fail(e, &mut attempt)?;
        }
        self.record_table_link_faults();
        let started_ns = self.clock.now_ns();
        let pause = std::time::Duration::from_secs_f64(self.plan.poll_interval_s);
        loop {
            let mut attempt = 0;
            let state = loop {
                match self.devices.table.state().await {
                    Ok(s) => break s,
                    Err(e) => {
                        self.record_table_link_faults();
                        self.retry_or_fail(e, &mut attempt)?
                    }
                }
            };
            self.record_table_link_faults();
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
            self.recorder.rotary(&table, &sample, now_ns);
            if encoder_rad.is_some() {
                return Ok(());
            }
            let waited_s = now_ns.saturating_sub(started_ns) as f64 * 1e-9;
            if waited_s > self.plan.in_position_timeout_s {
                return Err(SphereRunError::NoInPosition {
                    table,
                    commanded_rad,
                    waited_s,
                });
            }
            if !pause.is_zero() {
                tokio::time::sleep(pause).await;
            }
        }
    }

    /// One point: approach, `readings_per_point` readings, each recorded.
    async fn probe_point(&mut self, h: usize, a: usize, k: usize) -> Result<(), SphereRunError> {
        let (nominal, direction) = self.plan.nominal_point(h, a, k);
        let start = self.plan.approach_start(&nominal, &direction);
        self.event(RunEvent::ProbePointBegin {
            height_index: h,
            angle_index: a,
            point: k,
            nominal_m: nominal.into(),
            direction: direction.into(),
        });
        for _ in 0..self.plan.readings_per_point {
            let mut attempt = 0;
            while let Err(e) = self
                .devices
                .arm
                .approach(start.into(), direction.into())
                .await
            {
                self.retry_or_fail(e, &mut attempt)?;
            }
            let mut attempt = 0;
            let reading = loop {
                match self.devices.probe.read().await {
                    Ok(r) => break r,
                    Err(e) => self.retry_or_fail(e, &mut attempt)?,
                }
            };
            self.summary.readings += 1;
            let sample = ProbeSample {
                seq: self.summary.readings,
                t_s: reading.t_s,
                value_m: Some(reading.value_m),
            };
            self.recorder
                .probe(self.devices.probe.id(), &sample, self.clock.now_ns());
        }
        self.event(RunEvent::ProbePointEnd {
            height_index: h,
            angle_index: a,
            point: k,
        });
        // A probed point is on disk before the arm moves on (merged when points come fast).
        self.recorder.checkpoint();
        self.summary.points += 1;
        Ok(())
    }
}
