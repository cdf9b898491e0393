//! The simulated world: a seeded truth machine, instruments with their noise models, and
//! simulated drivers behind the same traits as real ones.

pub mod bump;
pub mod compensation;
pub mod devices;
pub mod effects;
pub mod hil;
pub mod linuxcnc;
pub mod pace;
pub mod passive_machine;
pub mod rotary;
pub mod table_source;
pub mod truth;
pub mod world;
