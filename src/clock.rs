//! Time for log stamps: the host's clock for live runs, the simulated world's virtual clock
//! for simulated runs (which then finish in seconds of wall time).

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{SystemTime, UNIX_EPOCH};

pub trait Clock: Send + Sync {
    /// Nanoseconds since the Unix epoch.
    fn now_ns(&self) -> u64;
}

pub struct SystemClock;

impl Clock for SystemClock {
    fn now_ns(&self) -> u64 {
        system_now_ns()
    }
}

pub fn system_now_ns() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64)
}

/// Virtual time: an epoch plus the simulated seconds elapsed, advanced by the simulation.
#[derive(Debug)]
pub struct VirtualClock {
    epoch_ns: u64,
    elapsed_ns: AtomicU64,
}

impl VirtualClock {
    pub fn new(epoch_ns: u64) -> Self {
        Self {
            epoch_ns,
            elapsed_ns: AtomicU64::new(0),
        }
    }

    pub fn elapsed_s(&self) -> f64 {
        self.elapsed_ns.load(Ordering::Relaxed) as f64 * 1e-9
    }

    /// Move time forward to `t_s` (never backward).
    pub fn advance_to(&self, t_s: f64) {
        let ns = (t_s.max(0.0) * 1e9).round() as u64;
        self.elapsed_ns.fetch_max(ns, Ordering::Relaxed);
    }
}

impl Clock for VirtualClock {
    fn now_ns(&self) -> u64 {
        self.epoch_ns + self.elapsed_ns.load(Ordering::Relaxed)
    }
}
