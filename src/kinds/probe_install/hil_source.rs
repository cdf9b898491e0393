//! The `probe_install` world behind the emulators of a `[hil]` run, in wall time (`HilTime`):
//! the 5-axis CMM for the GRBL emulator (`MachineSink`), the laser for the probe's (`ProbeSource`).

use std::sync::{Arc, MutexGuard};

use geocal_drivers::grbl::MachineSink;
use geocal_drivers::probe::ProbeSource;

use super::sim::{ProbeInstallWorld, SharedProbeWorld};
use crate::sim::hil::HilTime;

/// Lock the world and bring its clock up to now; a poisoned world only means a panic
/// elsewhere, so the emulators keep serving.
fn world_now<'a>(world: &'a SharedProbeWorld, time: &HilTime) -> MutexGuard<'a, ProbeInstallWorld> {
    let w = world.lock().unwrap_or_else(|e| e.into_inner());
    w.advance_to(time.elapsed_s());
    w
}

/// The world's CMM (X, Y, Z, A, B) as the GRBL emulator drives it: a move turns into the
/// world's own motion (its feed and rotary speed), positions come from the world.
pub struct WorldCmmSink {
    world: SharedProbeWorld,
    time: Arc<HilTime>,
}

impl WorldCmmSink {
    pub fn new(world: SharedProbeWorld, time: Arc<HilTime>) -> Self {
        Self { world, time }
    }
}

impl MachineSink for WorldCmmSink {
    fn commanded(&mut self, axes_m: [f64; 3], feed_m_s: f64, t_s: f64) {
        let rotary = self.rotary_position(t_s);
        self.commanded_rotary(axes_m, &rotary, feed_m_s, t_s);
    }

    fn position(&mut self, _t_s: f64) -> ([f64; 3], bool) {
        let (axes, moving) = world_now(&self.world, &self.time).axes_now();
        ([axes[0], axes[1], axes[2]], moving)
    }

    fn rotary_axes(&self) -> usize {
        2
    }

    /// `t_s` is the emulator's own time; the world follows the shared `HilTime`. The wire's
    /// feed is GRBL's combined feed; the world moves at its configured speeds instead.
    fn commanded_rotary(&mut self, axes_m: [f64; 3], rotary_rad: &[f64], _feed: f64, _t_s: f64) {
        let mut w = world_now(&self.world, &self.time);
        let (here, _) = w.axes_now();
        let a = rotary_rad.first().copied().unwrap_or(here[3]);
        let b = rotary_rad.get(1).copied().unwrap_or(here[4]);
        // The emulator checked the soft limits already (error:15); the world's own travel
        // check can only agree, so a refusal leaves the axes where they are.
        if let Err(e) = w.start_move([axes_m[0], axes_m[1], axes_m[2], a, b]) {
            tracing::warn!("emulated CMM refused a move: {e}");
        }
    }

    fn rotary_position(&mut self, _t_s: f64) -> Vec<f64> {
        let (axes, _) = world_now(&self.world, &self.time).axes_now();
        vec![axes[3], axes[4]]
    }
}

/// The world's laser probe as the ASCII emulator reads it: the true beam on the true sphere
/// at the axes' position now, plus the probe's noise; None (the sensor's error reply) when out
/// of range.
pub struct WorldLaserSource {
    world: SharedProbeWorld,
    time: Arc<HilTime>,
}

impl WorldLaserSource {
    pub fn new(world: SharedProbeWorld, time: Arc<HilTime>) -> Self {
        Self { world, time }
    }
}

impl ProbeSource for WorldLaserSource {
    fn value_m(&mut self, _t_s: f64) -> Option<f64> {
        world_now(&self.world, &self.time).reading_now()
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Mutex;

    use super::*;
    use crate::clock::VirtualClock;
    use crate::kinds::probe_install::config::ProbeInstallConfig;
    use crate::kinds::probe_install::plan::ProbeInstallPlan;

    #[test]
    fn a_commanded_move_takes_wall_time_and_the_probe_reads_the_sphere_there() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/config/probe-install.toml");
        let mut config = ProbeInstallConfig::load(std::path::Path::new(path)).expect("example");
        config.devices.machine.feed_m_s = 10.0;
        config.devices.machine.rotary_speed_rad_s = 100.0;
        let plan = ProbeInstallPlan::from_config(&config);
        let world = Arc::new(Mutex::new(ProbeInstallWorld::new(
            &config,
            Arc::new(VirtualClock::new(0)),
        )));
        let time = Arc::new(HilTime::new(0));
        let mut sink = WorldCmmSink::new(world.clone(), time.clone());
        let mut probe = WorldLaserSource::new(world, time);
        assert_eq!(sink.rotary_axes(), 2);
        let p = &plan.points[plan.points.len() - 1];
        sink.commanded_rotary(
            [p.axes[0], p.axes[1], p.axes[2]],
            &[p.axes[3], p.axes[4]],
            0.0,
            0.0,
        );
        let (_, moving) = sink.position(0.0);
        assert!(moving, "a move of 90° at 100 rad/s takes 16 ms");
        std::thread::sleep(std::time::Duration::from_millis(40));
        let (xyz, moving) = sink.position(0.0);
        assert!(!moving);
        assert_eq!(xyz, [p.axes[0], p.axes[1], p.axes[2]]);
        assert_eq!(sink.rotary_position(0.0), vec![p.axes[3], p.axes[4]]);
        // The nominal reading plus the mis-installation (about 1 mm) stays in the ±8 mm range.
        let v = probe.value_m(0.0).expect("in range");
        assert!((v - p.nominal_reading_m).abs() < 5e-3, "{v}");
    }
}
