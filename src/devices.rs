//! Builds the run's devices as trait objects from the configuration (real drivers join in a
//! later issue), plus the clock that stamps them and, for simulated runs, the world behind them.

use std::sync::{Arc, Mutex};

use crate::clock::{Clock, VirtualClock};
use crate::config::{Config, DriverKind};
use crate::plan::Plan;
use crate::sequencer::Devices;
use crate::sim::devices::{
    SharedWorld, SimEnvironment, SimMachine, SimOperator, SimRotaryTable, SimTracer,
};
use crate::sim::world::{SimError, SimWorld};

pub struct BuiltDevices {
    pub devices: Devices,
    pub clock: Arc<dyn Clock>,
    /// The simulated world, when the run is simulated (for exporting the truth).
    pub world: Option<SharedWorld>,
}

pub fn build(config: &Config, plan: &Plan, epoch_ns: u64) -> Result<BuiltDevices, SimError> {
    // Every driver is `sim` until the protocol drivers land; the match keeps the seam visible.
    match config.devices.tracer.driver {
        DriverKind::Sim => {}
    }
    let clock = Arc::new(VirtualClock::new(epoch_ns));
    let world: SharedWorld = Arc::new(Mutex::new(SimWorld::new(config, plan, clock.clone())?));
    let environment = config.devices.environment.as_ref().map(|env| {
        Box::new(SimEnvironment {
            id: env.id.clone(),
            world: world.clone(),
        }) as Box<dyn geocal_drivers::Environment>
    });
    let rotary = config.devices.rotary_table.as_ref().map(|table| {
        Box::new(SimRotaryTable {
            id: table.id.clone(),
            world: world.clone(),
        }) as Box<dyn geocal_drivers::RotaryTable>
    });
    Ok(BuiltDevices {
        devices: Devices {
            tracer: Box::new(SimTracer {
                id: config.devices.tracer.id.clone(),
                world: world.clone(),
            }),
            environment,
            machine: Box::new(SimMachine {
                id: config.devices.machine.id.clone(),
                world: world.clone(),
            }),
            operator: Box::new(SimOperator {
                world: world.clone(),
            }),
            rotary,
        },
        clock,
        world: Some(world),
    })
}
