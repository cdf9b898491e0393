//! Simulated drivers: the device traits implemented on the shared simulated world.

use std::sync::{Arc, Mutex, MutexGuard};

use async_trait::async_trait;
use geocal_drivers::{
    AxisPositions, DeviceError, EnvReading, Environment, Machine, MachineState, Operator,
    RotaryState, RotaryTable, Tracer, TracerReading,
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

/// The rotary table of the simulated world; the tracer on it turns with it.
pub struct SimRotaryTable {
    pub id: String,
    pub world: SharedWorld,
}

#[async_trait]
impl RotaryTable for SimRotaryTable {
    fn id(&self) -> &str {
        &self.id
    }
    async fn start_rotation(&mut self, commanded_rad: f64) -> Result<(), DeviceError> {
        if !commanded_rad.is_finite() {
            return Err(DeviceError::Rejected {
                device: self.id.clone(),
                message: format!("commanded angle {commanded_rad} rad is not finite"),
            });
        }
        if lock(&self.world, &self.id)?.start_rotation(commanded_rad) {
            Ok(())
        } else {
            Err(DeviceError::Disconnected {
                device: self.id.clone(),
                message: "the simulated world has no rotary table (no [plan.rotary])".into(),
            })
        }
    }
    async fn state(&mut self) -> Result<RotaryState, DeviceError> {
        let world = lock(&self.world, &self.id)?;
        if !world.has_table() {
            return Err(DeviceError::Disconnected {
                device: self.id.clone(),
                message: "the simulated world has no rotary table (no [plan.rotary])".into(),
            });
        }
        Ok(match world.table_in_position() {
            Some(encoder_rad) => RotaryState::InPosition { encoder_rad },
            None => RotaryState::Moving,
        })
    }
}
