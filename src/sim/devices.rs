//! Simulated drivers: the device traits implemented on the shared simulated world.

use std::sync::{Arc, Mutex, MutexGuard};

use async_trait::async_trait;
use geocal_drivers::{
    AxisPositions, DeviceError, EnvReading, Environment, Machine, MachineState, Operator, Tracer,
    TracerReading,
};

use super::world::SimWorld;

pub type SharedWorld = Arc<Mutex<SimWorld>>;

fn lock<'a>(world: &'a SharedWorld, device: &str) -> Result<MutexGuard<'a, SimWorld>, DeviceError> {
    world.lock().map_err(|_| DeviceError::Disconnected {
        device: device.to_string(),
        message: "simulated world poisoned by an earlier panic".into(),
    })
}

pub struct SimTracer {
    pub id: String,
    pub world: SharedWorld,
}

#[async_trait]
impl Tracer for SimTracer {
    fn id(&self) -> &str {
        &self.id
    }
    async fn next_sample(&mut self) -> Result<TracerReading, DeviceError> {
        Ok(lock(&self.world, &self.id)?.next_tracer_sample())
    }
    async fn home(&mut self) -> Result<(), DeviceError> {
        lock(&self.world, &self.id)?.home_tracer();
        Ok(())
    }
}

pub struct SimEnvironment {
    pub id: String,
    pub world: SharedWorld,
}

#[async_trait]
impl Environment for SimEnvironment {
    fn id(&self) -> &str {
        &self.id
    }
    async fn poll(&mut self) -> Result<Vec<EnvReading>, DeviceError> {
        Ok(lock(&self.world, &self.id)?.env_samples_until_now())
    }
}

pub struct SimMachine {
    pub id: String,
    pub world: SharedWorld,
}

#[async_trait]
impl Machine for SimMachine {
    fn id(&self) -> &str {
        &self.id
    }
    async fn start_move(&mut self, target: &AxisPositions) -> Result<(), DeviceError> {
        let mut axes = [0.0; 3];
        for (k, name) in crate::plan::AXES.iter().enumerate() {
            axes[k] = *target.get(*name).ok_or_else(|| DeviceError::Rejected {
                device: self.id.clone(),
                message: format!("move without axis `{name}`"),
            })?;
        }
        lock(&self.world, &self.id)?.start_move(axes);
        Ok(())
    }
    async fn state(&mut self) -> Result<MachineState, DeviceError> {
        let world = lock(&self.world, &self.id)?;
        Ok(match world.machine_idle_at() {
            None => MachineState::Moving,
            Some(at) => MachineState::Idle {
                position: crate::plan::AXES
                    .iter()
                    .zip(at)
                    .map(|(name, v)| (name.to_string(), v))
                    .collect(),
            },
        })
    }
}

/// The operator of the simulated world: moving the tracer takes `relocation_s`.
pub struct SimOperator {
    pub world: SharedWorld,
}

#[async_trait]
impl Operator for SimOperator {
    async fn place_station(
        &mut self,
        index: usize,
        _id: &str,
        _hint_m: Option<[f64; 3]>,
    ) -> Result<(), DeviceError> {
        lock(&self.world, "operator")?.place_station(index);
        Ok(())
    }
    async fn mount_target(&mut self, _target: &str, offset_m: [f64; 3]) -> Result<(), DeviceError> {
        lock(&self.world, "operator")?.mount_target(offset_m);
        Ok(())
    }
}
