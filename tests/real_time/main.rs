//! The tests that spend most of their time waiting on real time — LinuxCNC's runs and the
//! daemon's jobs — in one binary. Cargo runs test binaries one after another; in one binary
//! these waits overlap. LinuxCNC's scenarios run one at a time in their own test
//! (`controller`, first in name order, so it starts at once) while the daemon's tests run on
//! the other test thread beside it.

#[path = "../common/mod.rs"]
mod common;

mod controller;
mod daemon;
