//! LinuxCNC over linuxcncrsh, its TCP text interface: codec (sans-I/O) and driver (`Machine`).
//! See docs/linuxcnc.md.

pub mod codec;
pub mod driver;

pub use codec::ProgramStatus;
pub use driver::{
    tcp_connector, ControllerStatus, HomePolicy, LinuxCncConfig, LinuxCncMachine, MoveMode,
    Passwords, StreamConnector, ALARM_ESTOP, ALARM_MACHINE_OFF,
};
