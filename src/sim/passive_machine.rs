//! The simulated machine of a passive run: it executes the exported NC program (src/plan/nc.rs)
//! by itself in virtual time, with unplanned stops and dwell jitter from `[sim.passive]`.

use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::Arc;

use async_trait::async_trait;
use geocal_drivers::{DeviceError, Operator, Tracer, TracerReading};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::devices::SharedWorld;
use super::world::SimWorld;
pub use crate::config::sim::{SimPassiveConfig, UnplannedStop};
use crate::plan::nc::NcBlock;

enum State {
    Ready,
    /// Moving; then pause for the given seconds and go on to the target.
    Moving(Option<(f64, [f64; 3])>),
    Paused {
        until_s: f64,
        target: [f64; 3],
    },
    Dwelling {
        until_s: f64,
    },
    /// At M0, waiting for the operator.
    WaitRelease,
}

/// Executes the program's blocks as virtual time passes.
pub struct ProgramRunner {
    blocks: Vec<NcBlock>,
    next: usize,
    moves: usize,
    state: State,
    config: SimPassiveConfig,
    /// Operator actions so far (each releases one M0), and M0s passed.
    releases: Arc<AtomicU32>,
    passed: u32,
    rng: ChaCha8Rng,
}

impl ProgramRunner {
    pub fn new(
        blocks: Vec<NcBlock>,
        config: SimPassiveConfig,
        releases: Arc<AtomicU32>,
        seed: u64,
    ) -> Self {
        Self {
            blocks,
            next: 0,
            moves: 0,
            state: State::Ready,
            config,
            releases,
            passed: 0,
            rng: ChaCha8Rng::seed_from_u64(seed ^ 0x5041_5353_4956_4500),
        }
    }

    /// Run the program up to the world's present.
    pub fn advance(&mut self, world: &mut SimWorld) {
        loop {
            let now = world.now_s();
            match self.state {
                State::Moving(pause) => {
                    if world.machine_idle_at().is_none() {
                        return;
                    }
                    self.state = match pause {
                        Some((duration_s, target)) => State::Paused {
                            until_s: now + duration_s,
                            target,
                        },
                        None => State::Ready,
                    };
                }
                State::Paused { until_s, target } => {
                    if now < until_s {
                        return;
                    }
                    world.start_move(target);
                    self.state = State::Moving(None);
                }
                State::Dwelling { until_s } => {
                    if now < until_s {
                        return;
                    }
                    self.state = State::Ready;
                }
                State::WaitRelease => {
                    if self.releases.load(Ordering::Relaxed) <= self.passed {
                        return;
                    }
                    self.passed += 1;
                    self.state = State::Ready;
                }
                State::Ready => {
                    let Some(block) = self.blocks.get(self.next) else {
                        return;
                    };
                    self.next += 1;
                    self.state = match block {
                        NcBlock::Stop { .. } => State::WaitRelease,
                        NcBlock::Dwell { s } => {
                            let j = self.config.dwell_jitter_s.abs();
                            let jitter = if j > 0.0 {
                                self.rng.random_range(-j..=j)
                            } else {
                                0.0
                            };
                            State::Dwelling {
                                until_s: now + (s + jitter).max(0.0),
                            }
                        }
                        NcBlock::Move { axes_m, .. } => {
                            let index = self.moves;
                            self.moves += 1;
                            let stop = self
                                .config
                                .unplanned_stops
                                .iter()
                                .find(|s| s.move_index == index);
                            match stop {
                                Some(stop) => {
                                    let (from, _) = world.hil_machine_axes();
                                    let f = stop.fraction.clamp(0.0, 1.0);
                                    let mid = std::array::from_fn(|k| {
                                        from[k] + (axes_m[k] - from[k]) * f
                                    });
                                    world.start_move(mid);
                                    State::Moving(Some((stop.duration_s, *axes_m)))
                                }
                                None => {
                                    world.start_move(*axes_m);
                                    State::Moving(None)
                                }
                            }
                        }
                    };
                }
            }
        }
    }
}

/// The simulated tracer and operator of a passive run: the tracer drives the machine's
/// program, the operator releases its M0 stops.
pub fn tracer_and_operator(
    config: &crate::config::Config,
    plan: &crate::plan::Plan,
    world: SharedWorld,
) -> (Box<dyn Tracer>, Box<dyn Operator>) {
    let releases = Arc::new(AtomicU32::new(0));
    let sim = config.sim.as_ref();
    let runner = ProgramRunner::new(
        crate::plan::nc::program(config, plan),
        sim.and_then(|s| s.passive.clone()).unwrap_or_default(),
        releases.clone(),
        sim.map_or(0, |s| s.seed),
    );
    let tracer = Box::new(PassiveSimTracer {
        id: config.devices.tracer.id.clone(),
        world: world.clone(),
        runner,
    });
    let operator = Box::new(PassiveSimOperator { world, releases });
    (tracer, operator)
}

/// The simulated tracer of a passive run: before each sample the machine's program runs up
/// to the present (the world has no other clock-driven actor).
pub struct PassiveSimTracer {
    pub id: String,
    pub world: SharedWorld,
    pub runner: ProgramRunner,
}

fn poisoned(device: &str) -> DeviceError {
    DeviceError::Disconnected {
        device: device.to_string(),
        message: "simulated world poisoned by an earlier panic".into(),
    }
}

#[async_trait]
impl Tracer for PassiveSimTracer {
    fn id(&self) -> &str {
        &self.id
    }
    async fn next_sample(&mut self) -> Result<TracerReading, DeviceError> {
        let mut world = self.world.lock().map_err(|_| poisoned(&self.id))?;
        self.runner.advance(&mut world);
        Ok(world.next_tracer_sample())
    }
    async fn home(&mut self) -> Result<(), DeviceError> {
        self.world
            .lock()
            .map_err(|_| poisoned(&self.id))?
            .home_tracer();
        Ok(())
    }
}

/// The operator of a passive simulated run: each action also presses cycle start at the
/// program's M0.
pub struct PassiveSimOperator {
    pub world: SharedWorld,
    pub releases: Arc<AtomicU32>,
}

#[async_trait]
impl Operator for PassiveSimOperator {
    async fn place_station(
        &mut self,
        index: usize,
        _id: &str,
        _hint_m: Option<[f64; 3]>,
    ) -> Result<(), DeviceError> {
        self.world
            .lock()
            .map_err(|_| poisoned("operator"))?
            .place_station(index);
        self.releases.fetch_add(1, Ordering::Relaxed);
        Ok(())
    }
    async fn mount_target(&mut self, _target: &str, offset_m: [f64; 3]) -> Result<(), DeviceError> {
        self.world
            .lock()
            .map_err(|_| poisoned("operator"))?
            .mount_target(offset_m);
        self.releases.fetch_add(1, Ordering::Relaxed);
        Ok(())
    }
}
