//! geocal-drivers: the device traits the sequencer sees, the real protocol drivers (hpi3d,
//! grbl, probe, modbus_table) and their device emulators. Nothing here depends on the core.

pub mod grbl;
pub mod hpi3d;
pub mod linuxcnc;
pub mod modbus;
pub mod modbus_hexapod;
pub mod modbus_table;
pub mod probe;
pub mod serial;
pub mod traits;

pub use traits::ControllerTrim;
pub use traits::{
    AxisPositions, DeviceError, EnvReading, Environment, LinkFault, Machine, MachineState,
    Operator, Probe, ProbeReading, RotaryState, RotaryTable, Tracer, TracerReading,
};
pub use traits::{Hexapod, HexapodState, LegReading, PlatformPose, PoseReading, PoseSensor};
