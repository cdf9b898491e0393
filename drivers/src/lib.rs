//! geocal-drivers: the device traits the sequencer sees, the real protocol drivers (`hpi3d`)
//! and their device emulators. Nothing here depends on the geocal core.

pub mod hpi3d;
pub mod traits;

pub use traits::{
    AxisPositions, DeviceError, EnvReading, Environment, Machine, MachineState, Operator, Tracer,
    TracerReading,
};
