//! The simulated hexapod behind the Modbus hexapod emulator (`HexapodSource`): a go command
//! moves the world's platform, the encoders read the world's legs; the world follows `HilTime`.

use std::sync::{Arc, MutexGuard};

use geocal_drivers::modbus_hexapod::HexapodSource;
use geocal_drivers::PlatformPose;

use super::sim::{HexapodWorld, SharedHexapodWorld};
use crate::clock::VirtualClock;
use crate::sim::hil::HilTime;

/// The world's hexapod as the Modbus emulator drives it. The emulator runs in real time, so
/// every call first brings the world's clock (`clock`, the one the world was built with) up
/// to the run's `HilTime`.
pub struct WorldHexapodSource {
    world: SharedHexapodWorld,
    clock: Arc<VirtualClock>,
    time: Arc<HilTime>,
    /// The platform was at rest at the last look (and no command came since).
    settled: bool,
}

impl WorldHexapodSource {
    pub fn new(world: SharedHexapodWorld, clock: Arc<VirtualClock>, time: Arc<HilTime>) -> Self {
        Self {
            world,
            clock,
            time,
            settled: true,
        }
    }

    fn world(&self) -> MutexGuard<'_, HexapodWorld> {
        // A poisoned world only means a panic elsewhere; the emulator keeps serving.
        let w = self.world.lock().unwrap_or_else(|e| e.into_inner());
        self.clock.advance_to(self.time.elapsed_s());
        w
    }
}

impl HexapodSource for WorldHexapodSource {
    /// `t_s` is the emulator's own elapsed time; the world follows the shared `HilTime`.
    fn command(&mut self, pose: PlatformPose, _t_s: f64) {
        // A pose whose design leg lengths have no nearby true pose: the platform stays put,
        // as a controller refusing the move would (the run then sees it never arrive).
        if let Err(why) = self.world().start_move(pose) {
            tracing::warn!("hexapod emulator: {why}");
        }
        self.settled = false;
    }

    /// The world's `idle()` moves its clock on while the platform moves (a poll costs
    /// virtual time); here that clock must not run ahead of wall time, so while it is ahead
    /// the platform is still moving and the world is not asked.
    fn in_position(&mut self, _t_s: f64) -> bool {
        let settled = {
            let mut w = self.world();
            if !self.settled && self.clock.elapsed_s() > self.time.elapsed_s() {
                return false;
            }
            w.idle()
        };
        self.settled = settled;
        settled
    }

    fn legs(&mut self, _t_s: f64) -> [f64; 6] {
        self.world().read_legs().lengths_m
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Mutex;

    use super::*;
    use crate::kinds::hexapod::config::HexapodConfig;

    #[test]
    fn a_go_moves_the_world_platform_and_the_legs_follow() {
        let text = include_str!("../../../config/hexapod.toml")
            .replace("speed_m_s = 0.01", "speed_m_s = 2.0")
            .replace("angular_speed_rad_s = 0.05", "angular_speed_rad_s = 20.0");
        let config =
            HexapodConfig::parse(&text, std::path::Path::new("hexapod.toml")).expect("config");
        let clock = Arc::new(VirtualClock::new(0));
        let world = Arc::new(Mutex::new(HexapodWorld::new(&config, clock.clone())));
        let time = Arc::new(HilTime::new(0));
        let mut source = WorldHexapodSource::new(world.clone(), clock, time);
        assert!(source.in_position(0.0));
        let home = source.legs(0.0);
        let target = PlatformPose {
            translation_m: [0.05, -0.03, -0.68],
            rotation_vector_rad: [0.1, 0.0, -0.05],
        };
        source.command(target, 0.0);
        assert!(!source.in_position(0.0), "62 mm at 2 m/s take 31 ms");
        std::thread::sleep(std::time::Duration::from_millis(60));
        assert!(source.in_position(0.0));
        let moved = source.legs(0.0);
        // The platform moved: legs change by millimetres (a 50 mm, 0.1 rad move) ...
        let largest = (0..6)
            .map(|i| (moved[i] - home[i]).abs())
            .fold(0.0, f64::max);
        assert!(largest > 1e-3, "{largest}");
        // ... and the emulator reads what the world's own encoders read (5 σ of two
        // readings of 1 µm noise): the same platform, not a copy.
        let direct = world.lock().expect("world").read_legs().lengths_m;
        for i in 0..6 {
            let d = moved[i] - direct[i];
            assert!(d.abs() < 5.0 * 2f64.sqrt() * 1e-6, "leg {i}: {d}");
        }
    }
}
