//! geocal: geometric calibration of machine tools, CMMs, rotary tables and hexapods.
//! See ../README.md and docs/ for the architecture; each module's top comment says what it owns.

pub mod session;
pub mod model;
pub mod solve;
pub mod sim;
