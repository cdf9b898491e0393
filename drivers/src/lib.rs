//! geocal-drivers: the device traits the sequencer sees, and (later) the real protocol
//! drivers and device emulators. Nothing here depends on the geocal core.

pub mod traits;

pub use traits::{
    AxisPositions, DeviceError, EnvReading, Environment, Machine, MachineState, Operator,
    RotaryState, RotaryTable, Tracer, TracerReading,
};
