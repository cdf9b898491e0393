//! geocal: geometric calibration of machine tools, CMMs, rotary tables and hexapods.
//! See ../README.md and docs/ for the architecture; each module's top comment says what it owns.

pub mod allocator;
pub mod clock;
pub mod compensate;
pub mod config;
pub mod console;
pub mod devices;
pub mod diagnose;
pub mod document;
pub mod evaluate;
pub mod export;
pub mod extract;
pub mod history;
pub mod kinds;
pub mod method;
pub mod model;
pub mod monitor;
pub mod parallel;
pub mod plan;
pub mod progress;
pub mod progress_sink;
pub mod replay;
pub mod report;
pub mod run;
pub mod sequencer;
pub mod serve;
pub mod session;
pub mod sim;
pub mod solve;
