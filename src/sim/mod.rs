//! The simulated world: a seeded truth machine, instruments with their noise models, and
//! simulated drivers behind the same traits as real ones.

pub mod devices;
pub mod effects;
pub mod hexapod;
pub mod hil;
pub mod probe_install;
pub mod rotary;
pub mod truth;
pub mod world;
