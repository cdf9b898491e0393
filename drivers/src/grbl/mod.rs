//! GRBL-style G-code streaming over serial: codec (sans-I/O), driver (`Machine`) and a
//! pty emulator of the controller for hardware-in-the-loop tests. See docs/protocols/grbl.md.

pub mod codec;
pub mod driver;
pub mod emulator;

pub use driver::{GrblConfig, GrblMachine};
pub use emulator::{
    GrblEmulator, GrblEmulatorConfig, GrblEmulatorStats, GrblFaults, KinematicSink, MachineSink,
};
