//! LinuxCNC as the controller of a real-controller HIL run: the instance, the simulated
//! carriages following its `joint.N.motor-pos-cmd` (trim included), and the compensation
//! trims it applies (`joint.N.backlash-corr`, the table's value, and `joint.N.backlash-filt`,
//! what its rate limiter let through).

use std::sync::{Arc, Mutex};
use std::time::Duration;

use serde::{Deserialize, Serialize};

use super::{Connector, HalReader, LinuxCnc, MachineSetup};
use crate::sim::world::JointSource;

/// One reading of a joint's compensation as LinuxCNC applies it, metres.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct JointTrim {
    /// `motor-pos-cmd`: the commanded position plus the applied trim.
    pub motor_pos_cmd_m: f64,
    /// `backlash-corr`: the table's value at the position, in the last direction.
    pub table_m: f64,
    /// `backlash-filt`: the trim applied (it follows `table_m` through a rate limiter).
    pub applied_m: f64,
}

/// The latest pin values of all three joints.
pub type Trims = [JointTrim; 3];

const PINS: [&str; 3] = ["motor-pos-cmd", "backlash-corr", "backlash-filt"];

fn pin_names() -> Vec<String> {
    (0..3)
        .flat_map(|k| PINS.iter().map(move |p| format!("joint.{k}.{p}")))
        .collect()
}

type SharedReader = Arc<Mutex<Option<HalReader>>>;

/// The world's carriages as LinuxCNC commands them (mm in HAL, metres here). A failed read
/// (LinuxCNC shutting down) keeps the last positions.
struct LinuxCncJoints {
    reader: SharedReader,
    latest: Arc<Mutex<Trims>>,
}

impl JointSource for LinuxCncJoints {
    fn joints_m(&self) -> [f64; 3] {
        let read = self
            .reader
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .as_mut()
            .map(HalReader::read);
        let mut latest = self.latest.lock().unwrap_or_else(|e| e.into_inner());
        match read {
            Some(Ok(v)) if v.len() == 9 => {
                *latest = std::array::from_fn(|k| JointTrim {
                    motor_pos_cmd_m: v[3 * k] * 1e-3,
                    table_m: v[3 * k + 1] * 1e-3,
                    applied_m: v[3 * k + 2] * 1e-3,
                });
            }
            Some(Err(e)) => tracing::debug!("reading LinuxCNC's joints: {e}"),
            _ => {}
        }
        std::array::from_fn(|k| latest[k].motor_pos_cmd_m)
    }
}

/// A LinuxCNC hosted for a run; dropping it shuts LinuxCNC down and leaves nothing behind.
pub struct HostedLinuxCnc {
    instance: Option<LinuxCnc>,
    reader: SharedReader,
    latest: Arc<Mutex<Trims>>,
    connector: Connector,
}

impl HostedLinuxCnc {
    /// Start LinuxCNC (blocking: waits for the global lock and for linuxcncrsh).
    pub fn start(setup: &MachineSetup, timeout: Duration) -> anyhow::Result<Self> {
        let instance = LinuxCnc::start(setup, timeout)?;
        let reader = instance.hal_reader(pin_names())?;
        let connector = instance.connector()?;
        Ok(Self {
            instance: Some(instance),
            reader: Arc::new(Mutex::new(Some(reader))),
            latest: Arc::new(Mutex::new(Trims::default())),
            connector,
        })
    }

    /// The source the world's carriages follow.
    pub fn joint_source(&self) -> Box<dyn JointSource> {
        Box::new(LinuxCncJoints {
            reader: self.reader.clone(),
            latest: self.latest.clone(),
        })
    }

    /// linuxcncrsh connections inside LinuxCNC's namespace, as the driver opens them.
    pub fn stream_connector(&self) -> geocal_drivers::linuxcnc::StreamConnector {
        let connector = self.connector.clone();
        Arc::new(move || {
            let connector = connector.clone();
            Box::pin(async move { connector.connect_tokio().await })
        })
    }

    /// The pins as last read by the world (at the tracer's rate).
    pub fn trims(&self) -> Trims {
        *self.latest.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// A handle that reads the latest trims after `self` is moved into the hosted devices.
    pub fn trims_handle(&self) -> Arc<Mutex<Trims>> {
        self.latest.clone()
    }

    pub fn instance(&self) -> Option<&LinuxCnc> {
        self.instance.as_ref()
    }

    /// Close the HAL reader, then shut LinuxCNC down and check nothing is left.
    pub fn shutdown(&mut self) -> anyhow::Result<()> {
        if let Some(mut reader) = self.reader.lock().unwrap_or_else(|e| e.into_inner()).take() {
            reader.close();
        }
        match self.instance.take() {
            Some(instance) => instance.shutdown(),
            None => Ok(()),
        }
    }
}

/// The run's machine (the `linuxcnc` driver) with the trims LinuxCNC applies, as the world
/// last read them: at the end of a dwell the carriages stand still, so these are the trims
/// at the point.
pub struct TrimReportingMachine {
    pub inner: Box<dyn geocal_drivers::Machine>,
    pub latest: Arc<Mutex<Trims>>,
}

#[async_trait::async_trait]
impl geocal_drivers::Machine for TrimReportingMachine {
    fn id(&self) -> &str {
        self.inner.id()
    }

    async fn start_move(
        &mut self,
        target: &geocal_drivers::AxisPositions,
    ) -> Result<(), geocal_drivers::DeviceError> {
        self.inner.start_move(target).await
    }

    async fn state(&mut self) -> Result<geocal_drivers::MachineState, geocal_drivers::DeviceError> {
        self.inner.state().await
    }

    async fn unlock(&mut self) -> Result<(), geocal_drivers::DeviceError> {
        self.inner.unlock().await
    }

    async fn finish(&mut self) -> Result<(), geocal_drivers::DeviceError> {
        self.inner.finish().await
    }

    fn take_link_faults(&mut self) -> Vec<geocal_drivers::LinkFault> {
        self.inner.take_link_faults()
    }

    fn controller_trims(&mut self) -> Vec<geocal_drivers::ControllerTrim> {
        let latest = *self.latest.lock().unwrap_or_else(|e| e.into_inner());
        latest
            .iter()
            .enumerate()
            .map(|(joint, t)| geocal_drivers::ControllerTrim {
                joint,
                motor_pos_cmd_m: t.motor_pos_cmd_m,
                table_m: t.table_m,
                applied_m: t.applied_m,
            })
            .collect()
    }
}

impl Drop for HostedLinuxCnc {
    fn drop(&mut self) {
        if let Err(e) = self.shutdown() {
            tracing::warn!("shutting LinuxCNC down: {e:#}");
        }
    }
}
