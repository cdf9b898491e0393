//! The simulated world's rotary table behind the Modbus table emulator (`TableSource`): a go
//! command turns the world's table (and the tracer on it), the encoder reads the world's.

use std::sync::Arc;

use geocal_drivers::modbus_table::TableSource;

use super::devices::SharedWorld;
use super::hil::HilTime;

/// The world's table as the Modbus emulator drives it; the world follows `HilTime`.
pub struct WorldTableSource {
    world: SharedWorld,
    time: Arc<HilTime>,
}

impl WorldTableSource {
    pub fn new(world: SharedWorld, time: Arc<HilTime>) -> Self {
        Self { world, time }
    }
}

impl TableSource for WorldTableSource {
    /// `t_s` is the emulator's own elapsed time; the world follows the shared `HilTime`.
    fn command(&mut self, target_rad: f64, _t_s: f64) {
        // A world without a table (no [plan.rotary]) ignores it; its encoder then reads 0.
        let _ = self.time.world(&self.world).start_rotation(target_rad);
    }

    fn angle(&mut self, _t_s: f64) -> (f64, bool) {
        self.time
            .world(&self.world)
            .hil_table_encoder()
            .unwrap_or((0.0, true))
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Mutex;

    use super::*;
    use crate::clock::VirtualClock;
    use crate::config::Config;
    use crate::plan::Plan;
    use crate::sim::world::SimWorld;

    #[test]
    fn go_turns_the_world_table_and_settles_at_the_command() {
        let text = include_str!("../../config/rotary-tracer.toml").replace(
            "axis_tilt_rad = 1e-4 }",
            "axis_tilt_rad = 1e-4, speed_rad_s = 50.0, settle_s = 0.01 }",
        );
        let config =
            Config::parse(&text, std::path::Path::new("rotary-tracer.toml")).expect("config");
        let plan = Plan::from_config(&config);
        let clock = Arc::new(VirtualClock::new(0));
        let world = Arc::new(Mutex::new(
            SimWorld::new(&config, &plan, clock).expect("world"),
        ));
        let time = Arc::new(HilTime::new(0));
        let mut source = WorldTableSource::new(world, time);
        assert_eq!(source.angle(0.0), (0.0, true));
        source.command(0.5, 0.0);
        let (during, in_position) = source.angle(0.0);
        assert!(!in_position && during < 0.5);
        // 2 * 0.5 / 50 s of motion and 10 ms of settling, in wall time.
        std::thread::sleep(std::time::Duration::from_millis(60));
        assert_eq!(source.angle(0.0), (0.5, true));
    }
}
