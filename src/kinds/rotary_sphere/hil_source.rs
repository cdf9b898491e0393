//! The `rotary_sphere` world's table behind the Modbus table emulator (`TableSource`): a go
//! command turns the sphere world's table; motion and settling follow the emulator's clock.
//!
//! The sphere world counts its own (virtual) time per query and per probe reading, so the
//! timing of the table under emulation is the emulator's wall time with the world's speed and
//! settle time (`KinematicTable`); the angle the probe sees is set at the command.

use geocal_drivers::modbus_table::{KinematicTable, TableSource};

use super::sim::SharedSphereWorld;

pub struct SphereTableSource {
    world: SharedSphereWorld,
    table: KinematicTable,
}

impl SphereTableSource {
    /// Starts at 0 rad, as the sphere world does.
    pub fn new(world: SharedSphereWorld, speed_rad_s: f64, settle_s: f64) -> Self {
        Self {
            world,
            table: KinematicTable::new(0.0, speed_rad_s, settle_s),
        }
    }
}

impl TableSource for SphereTableSource {
    fn command(&mut self, target_rad: f64, t_s: f64) {
        // A poisoned world only means a panic elsewhere; the emulator keeps serving.
        let mut world = self.world.lock().unwrap_or_else(|e| e.into_inner());
        world.start_rotation(target_rad);
        self.table.command(target_rad, t_s);
    }

    fn angle(&mut self, t_s: f64) -> (f64, bool) {
        self.table.angle(t_s)
    }
}

#[cfg(test)]
mod tests {
    use std::sync::{Arc, Mutex};

    use super::*;
    use crate::clock::VirtualClock;
    use crate::kinds::rotary_sphere::config::RotarySphereConfig;
    use crate::kinds::rotary_sphere::plan::SpherePlan;
    use crate::kinds::rotary_sphere::sim::SphereWorld;

    #[test]
    fn go_turns_the_sphere_world_and_settles_after_the_motion() {
        let path =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rotary-sphere.toml");
        let config = RotarySphereConfig::load(&path).expect("config");
        let plan = SpherePlan::from_config(&config.plan);
        let world = Arc::new(Mutex::new(
            SphereWorld::new(&config, &plan, Arc::new(VirtualClock::new(0))).expect("world"),
        ));
        world.lock().expect("world").mount_sphere(0);
        let before = world.lock().expect("world").true_centre().expect("centre");
        let mut source = SphereTableSource::new(world.clone(), 0.5, 1.0);
        // At rest at 0 rad once the power-on settling is over.
        assert_eq!(source.angle(5.0), (0.0, true));
        source.command(1.0, 10.0);
        // 1 rad at 0.5 rad/s, then 1 s of settling.
        let (mid, moving_done) = source.angle(11.0);
        assert!((mid - 0.5).abs() < 1e-12 && !moving_done);
        assert_eq!(source.angle(12.5), (1.0, false));
        assert_eq!(source.angle(13.0), (1.0, true));
        // The probe sees the sphere at the commanded angle.
        let after = world.lock().expect("world").true_centre().expect("centre");
        let turned = before.xy().angle(&after.xy());
        assert!((turned - 1.0).abs() < 1e-3, "{turned}");
    }
}
