//! Hardware-in-the-loop: the simulated world behind the device emulators of `geocal_drivers`
//! (`TracerSource` for the HPI-3D, `MachineSink` for GRBL) and the operator of an emulated
//! run. The emulators run in real time, so here the world's clock follows wall time
//! (`HilTime`) instead of being advanced by the tracer stream.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Instant;

use async_trait::async_trait;
use geocal_drivers::grbl::MachineSink;
use geocal_drivers::hpi3d::{MeteoSensorReading, SourceReading, TracerSource};
use geocal_drivers::{DeviceError, Operator};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

use super::devices::SharedWorld;
use super::world::SimWorld;
use crate::clock::Clock;
use crate::extract::NoiseModel;

/// Wall time since the run started, plus the virtual time the world skipped (an operator's
/// relocation of the tracer is not waited for). The world's clock, the session's log times
/// and both emulators' values all follow it. Strictly increasing in nanoseconds, so that no
/// two records of the session share a log time.
pub struct HilTime {
    start: Instant,
    epoch_ns: u64,
    skipped_ns: AtomicU64,
    last_ns: AtomicU64,
}

impl HilTime {
    pub fn new(epoch_ns: u64) -> Self {
        Self {
            start: Instant::now(),
            epoch_ns,
            skipped_ns: AtomicU64::new(0),
            last_ns: AtomicU64::new(0),
        }
    }

    fn elapsed_ns(&self) -> u64 {
        let wall = u64::try_from(self.start.elapsed().as_nanos()).unwrap_or(u64::MAX);
        let t = wall.saturating_add(self.skipped_ns.load(Ordering::Relaxed));
        let prev = self.last_ns.fetch_max(t, Ordering::Relaxed);
        if prev >= t {
            // Same nanosecond as the last reading (or a skip raced it): step past it.
            self.last_ns.fetch_add(1, Ordering::Relaxed) + 1
        } else {
            t
        }
    }

    /// Seconds of world time since the run started.
    pub fn elapsed_s(&self) -> f64 {
        self.elapsed_ns() as f64 * 1e-9
    }

    /// The world jumped ahead by `s` seconds (virtual time nobody waits for).
    fn skip(&self, s: f64) {
        if s.is_finite() && s > 0.0 {
            self.skipped_ns
                .fetch_add((s * 1e9).round() as u64, Ordering::Relaxed);
        }
    }

    /// Lock the world and bring its clock up to now.
    pub(crate) fn world<'a>(&self, world: &'a SharedWorld) -> std::sync::MutexGuard<'a, SimWorld> {
        // A poisoned world only means a panic elsewhere; the emulators keep serving.
        let w = world.lock().unwrap_or_else(|e| e.into_inner());
        w.clock.advance_to(self.elapsed_s());
        w
    }
}

impl Clock for HilTime {
    fn now_ns(&self) -> u64 {
        self.epoch_ns + self.elapsed_ns()
    }
}

/// The world as the HPI-3D emulator sees it: the true distance plus the tracer's noise.
pub struct WorldTracerSource {
    world: SharedWorld,
    time: Arc<HilTime>,
    noise: NoiseModel,
    rng: ChaCha8Rng,
    last_noise_m: f64,
    /// Noise of the sample the emulator zeroed its counter on, carried by every later
    /// sample so that it cancels: homing is exact, as in the virtual-time simulation.
    home_noise_m: f64,
}

impl WorldTracerSource {
    pub fn new(world: SharedWorld, time: Arc<HilTime>, noise: NoiseModel, seed: u64) -> Self {
        Self {
            world,
            time,
            noise,
            rng: ChaCha8Rng::seed_from_u64(seed ^ 0x4849_4c5f_5452_4143),
            last_noise_m: 0.0,
            home_noise_m: 0.0,
        }
    }
}

impl TracerSource for WorldTracerSource {
    /// `t_s` is the emulator's own elapsed time; the world follows the shared `HilTime`,
    /// which differs from it only by the moment the emulator was spawned.
    fn sample(&mut self, _t_s: f64) -> SourceReading {
        let distance_m = self.time.world(&self.world).hil_distance_m();
        let sigma = self.noise.sample_sigma_m(distance_m);
        let noise = Normal::new(0.0, sigma).map_or(0.0, |n| n.sample(&mut self.rng));
        self.last_noise_m = noise;
        SourceReading {
            length_m: distance_m + noise + self.home_noise_m,
            beam_ok: true,
            signal: 0.9,
        }
    }

    fn home(&mut self, _t_s: f64) {
        // The emulator took its origin from the sample just drawn.
        self.home_noise_m += self.last_noise_m;
        self.time.world(&self.world).home_tracer();
    }

    fn meteo(&mut self, _t_s: f64) -> Vec<MeteoSensorReading> {
        let env = {
            let w = self.time.world(&self.world);
            w.env_at(w.now_s())
        };
        let air = MeteoSensorReading {
            sensor: 0,
            temperature_k: env.air_temp_k,
            humidity_pct: env.humidity_pct,
            pressure_pa: env.pressure_pa,
        };
        let material = env
            .material_temp_k
            .iter()
            .enumerate()
            .map(|(k, &t)| MeteoSensorReading {
                sensor: u8::try_from(k + 1).unwrap_or(u8::MAX),
                temperature_k: t,
                humidity_pct: env.humidity_pct,
                pressure_pa: env.pressure_pa,
            });
        std::iter::once(air).chain(material).collect()
    }
}

/// The world's machine as the GRBL emulator drives it (the world's motion profile and feed).
pub struct WorldMachineSink {
    world: SharedWorld,
    time: Arc<HilTime>,
}

impl WorldMachineSink {
    pub fn new(world: SharedWorld, time: Arc<HilTime>) -> Self {
        Self { world, time }
    }
}

impl MachineSink for WorldMachineSink {
    fn commanded(&mut self, axes_m: [f64; 3], _feed_m_s: f64, _t_s: f64) {
        self.time.world(&self.world).start_move(axes_m);
    }

    fn position(&mut self, _t_s: f64) -> ([f64; 3], bool) {
        self.time.world(&self.world).hil_machine_axes()
    }
}

/// The operator of an emulated run: places the tracer in the world at once; the relocation
/// time the world accounts for is skipped, not waited for.
pub struct HilOperator {
    pub world: SharedWorld,
    pub time: Arc<HilTime>,
}

#[async_trait]
impl Operator for HilOperator {
    async fn place_station(
        &mut self,
        index: usize,
        _id: &str,
        _hint_m: Option<[f64; 3]>,
    ) -> Result<(), DeviceError> {
        let mut w = self.time.world(&self.world);
        let before = w.now_s();
        w.place_station(index);
        self.time.skip(w.now_s() - before);
        Ok(())
    }

    async fn mount_target(&mut self, _target: &str, offset_m: [f64; 3]) -> Result<(), DeviceError> {
        self.time.world(&self.world).mount_target(offset_m);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hil_time_is_strictly_increasing_and_skips() {
        let t = HilTime::new(1_000);
        let a = t.now_ns();
        let b = t.now_ns();
        assert!(b > a);
        t.skip(10.0);
        assert!(t.elapsed_s() >= 10.0);
        t.skip(f64::NAN);
        assert!(t.elapsed_s() < 11.0);
    }
}
