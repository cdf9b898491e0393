//! Line-oriented ASCII readout of displacement probes (request, pattern, scale): codec
//! (sans-I/O), driver (`Probe`) and a pty emulator. See docs/protocols/probe-ascii.md.

pub mod codec;
pub mod driver;
pub mod emulator;

pub use driver::{AsciiProbe, ProbeConfig};
pub use emulator::{
    ProbeEmulator, ProbeEmulatorConfig, ProbeEmulatorStats, ProbeFaults, ProbeSource,
};
