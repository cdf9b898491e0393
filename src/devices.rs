//! Builds the run's devices as trait objects from the configuration, plus the clock that
//! stamps them and, for simulated and emulated runs, the world behind them:
//! - every device `sim`: the simulated drivers in virtual time (the tracer stream advances
//!   the clock, so runs take seconds whatever the dwell times);
//! - protocol drivers (`hpi3d`, `grbl`) without `[hil]`: the real devices at their ports,
//!   stamped by the system clock;
//! - `[hil] emulate = true`: geocal hosts the HPI-3D and GRBL emulators on ptys backed by the
//!   simulated world and connects the real drivers to them; the world follows wall time.

use std::sync::{Arc, Mutex};

use anyhow::Context;
use geocal_drivers::grbl::{GrblConfig, GrblEmulator, GrblEmulatorConfig, GrblMachine};
use geocal_drivers::hpi3d::{EmulatorConfig, Hpi3dConfig, Hpi3dEmulator, Hpi3dTracer};
use geocal_drivers::{Environment, Machine, Operator, RotaryTable, Tracer};

use crate::clock::{Clock, SystemClock, VirtualClock};
use crate::config::{Config, DriverKind};
use crate::extract::NoiseModel;
use crate::plan::Plan;
use crate::sequencer::Devices;
use crate::sim::devices::{
    SharedWorld, SimEnvironment, SimMachine, SimOperator, SimRotaryTable, SimTracer,
};
use crate::sim::hil::{HilOperator, HilTime, WorldMachineSink, WorldTracerSource};
use crate::sim::world::SimWorld;

pub struct BuiltDevices {
    pub devices: Devices,
    pub clock: Arc<dyn Clock>,
    /// The simulated world, when the run is simulated or emulated (for exporting the truth).
    pub world: Option<SharedWorld>,
    /// The emulators of an emulated run; dropping them stops them.
    pub emulators: Emulators,
}

/// Device emulators hosted by this process (`[hil] emulate = true`).
#[derive(Default)]
pub struct Emulators {
    pub tracer: Option<Hpi3dEmulator>,
    pub machine: Option<GrblEmulator>,
}

/// Build the devices; must run inside the tokio runtime that will run the sequencer (the
/// drivers' reader tasks and the emulators are spawned on it).
pub async fn build(config: &Config, plan: &Plan, epoch_ns: u64) -> anyhow::Result<BuiltDevices> {
    let all_sim = config.devices.tracer.driver == DriverKind::Sim
        && matches!(
            config.devices.machine.driver,
            DriverKind::Sim | DriverKind::Passive
        );
    if config.emulated() {
        build_emulated(config, plan, epoch_ns).await
    } else if all_sim {
        build_simulated(config, plan, epoch_ns)
    } else {
        build_real(config, plan, epoch_ns).await
    }
}

fn hpi3d_config(config: &Config) -> Hpi3dConfig {
    let tracer = &config.devices.tracer;
    let mut c = tracer.hpi3d.clone().unwrap_or_default();
    c.id = tracer.id.clone();
    // The Environment handle reads the meteo stream only if it is asked for.
    c.meteo = config
        .devices
        .environment
        .as_ref()
        .is_some_and(|e| e.driver == DriverKind::Hpi3d);
    c
}

fn grbl_config(config: &Config) -> GrblConfig {
    let machine = &config.devices.machine;
    let mut c = machine.grbl.clone().unwrap_or_default();
    c.id = machine.id.clone();
    c.feed_m_s = machine.feed_m_s;
    c
}

pub(crate) fn sim_environment(
    config: &Config,
    world: &SharedWorld,
) -> Option<Box<dyn Environment>> {
    let env = config.devices.environment.as_ref()?;
    Some(Box::new(SimEnvironment {
        id: env.id.clone(),
        world: world.clone(),
    }))
}

fn sim_rotary(config: &Config, world: &Option<SharedWorld>) -> Option<Box<dyn RotaryTable>> {
    let table = config.devices.rotary_table.as_ref()?;
    let world = world.as_ref()?;
    Some(Box::new(SimRotaryTable {
        id: table.id.clone(),
        world: world.clone(),
    }))
}

fn build_simulated(config: &Config, plan: &Plan, epoch_ns: u64) -> anyhow::Result<BuiltDevices> {
    let clock = Arc::new(VirtualClock::new(epoch_ns));
    let world: SharedWorld = Arc::new(Mutex::new(SimWorld::new(config, plan, clock.clone())?));
    let world_opt = Some(world.clone());
    if config.devices.machine.driver == DriverKind::Passive {
        return Ok(crate::sim::passive_machine::build(
            config, plan, world, clock,
        ));
    }
    Ok(BuiltDevices {
        devices: Devices {
            tracer: paced(
                config,
                Box::new(SimTracer {
                    id: config.devices.tracer.id.clone(),
                    world: world.clone(),
                }),
            ),
            environment: sim_environment(config, &world),
            machine: Box::new(SimMachine {
                id: config.devices.machine.id.clone(),
                world: world.clone(),
            }),
            operator: Box::new(SimOperator {
                world: world.clone(),
            }),
            rotary: sim_rotary(config, &world_opt),
        },
        clock,
        world: world_opt,
        emulators: Emulators::default(),
    })
}

/// The simulated tracer held back to `[sim] pace` times wall time, if set.
pub(crate) fn paced(config: &Config, tracer: Box<dyn Tracer>) -> Box<dyn Tracer> {
    match config.sim.as_ref().and_then(|s| s.pace) {
        Some(pace) => Box::new(crate::sim::pace::PacedTracer::new(tracer, pace)),
        None => tracer,
    }
}

/// The HPI-3D tracer and, if configured, its meteo stream as the environment.
fn hpi3d_devices(
    config: &Config,
    tracer: Hpi3dTracer,
) -> (Box<dyn Tracer>, Option<Box<dyn Environment>>) {
    let env = config
        .devices
        .environment
        .as_ref()
        .filter(|e| e.driver == DriverKind::Hpi3d)
        .map(|_| Box::new(tracer.environment()) as Box<dyn Environment>);
    (Box::new(tracer), env)
}

async fn build_emulated(
    config: &Config,
    plan: &Plan,
    epoch_ns: u64,
) -> anyhow::Result<BuiltDevices> {
    let (sim, hil) = match (&config.sim, &config.hil) {
        (Some(sim), Some(hil)) => (sim, hil),
        _ => anyhow::bail!("[hil] emulate = true needs [sim] (config validation checks this)"),
    };
    let time = Arc::new(HilTime::new(epoch_ns));
    let world_clock = Arc::new(VirtualClock::new(epoch_ns));
    let world: SharedWorld = Arc::new(Mutex::new(SimWorld::new(config, plan, world_clock)?));

    // The tracer: the HPI-3D emulator on a pty, the real driver on its other end.
    let tracer_cfg = &config.devices.tracer;
    let meteo_period_s = config
        .devices
        .environment
        .as_ref()
        .map_or(1.0, |e| 1.0 / e.sample_rate_hz);
    let source = WorldTracerSource::new(
        world.clone(),
        time.clone(),
        NoiseModel {
            noise_m: tracer_cfg.noise_m,
            noise_ppm: tracer_cfg.noise_ppm,
        },
        sim.seed,
    );
    let (tracer_emulator, tracer_port) = Hpi3dEmulator::spawn_pty(
        EmulatorConfig {
            rate_hz: tracer_cfg.sample_rate_hz,
            meteo_period_s,
            faults: hil.tracer_faults.clone(),
        },
        Box::new(source),
    )
    .context("starting the HPI-3D emulator on a pty")?;
    let mut hpi3d = hpi3d_config(config);
    if let Some(path) = tracer_emulator.slave_path() {
        hpi3d.port = path.display().to_string();
    }
    tracing::info!("HPI-3D emulator on {}", hpi3d.port);
    let tracer = Hpi3dTracer::from_io(tracer_port, hpi3d)
        .await
        .context("connecting the HPI-3D driver to its emulator")?;
    let (tracer, hpi3d_env) = hpi3d_devices(config, tracer);
    let environment = match hpi3d_env {
        Some(env) => Some(env),
        None => sim_environment(config, &world),
    };

    // The machine: the GRBL emulator on a pty, or the simulated machine.
    let mut machine_emulator = None;
    let machine: Box<dyn Machine> = match config.devices.machine.driver {
        DriverKind::Grbl => {
            let travel = |k: usize| {
                config
                    .machine
                    .travel_m
                    .get(crate::plan::AXES[k])
                    .copied()
                    .unwrap_or([-1.0, 1.0])
            };
            let mut emulator = GrblEmulator::spawn_pty(
                GrblEmulatorConfig {
                    travel_min_m: std::array::from_fn(|k| travel(k)[0]),
                    travel_max_m: std::array::from_fn(|k| travel(k)[1]),
                    faults: hil.machine_faults.clone(),
                    ..GrblEmulatorConfig::default()
                },
                Box::new(WorldMachineSink::new(world.clone(), time.clone())),
            )
            .context("starting the GRBL emulator on a pty")?;
            let port = emulator
                .take_slave()
                .context("the GRBL emulator's pty has no slave end")?;
            let mut grbl = grbl_config(config);
            grbl.port = emulator.slave_path().unwrap_or_default().to_string();
            tracing::info!("GRBL emulator on {}", grbl.port);
            machine_emulator = Some(emulator);
            Box::new(GrblMachine::from_stream(port, grbl)?)
        }
        _ => Box::new(SimMachine {
            id: config.devices.machine.id.clone(),
            world: world.clone(),
        }),
    };
    let world_opt = Some(world.clone());
    Ok(BuiltDevices {
        devices: Devices {
            tracer,
            environment,
            machine,
            operator: Box::new(HilOperator {
                world: world.clone(),
                time: time.clone(),
            }) as Box<dyn Operator>,
            rotary: sim_rotary(config, &world_opt),
        },
        clock: time,
        world: world_opt,
        emulators: Emulators {
            tracer: Some(tracer_emulator),
            machine: machine_emulator,
        },
    })
}

/// An operator who is told where to put the tracer; without a console here, it only logs.
struct LoggingOperator;

#[async_trait::async_trait]
impl Operator for LoggingOperator {
    async fn place_station(
        &mut self,
        index: usize,
        id: &str,
        hint_m: Option<[f64; 3]>,
    ) -> Result<(), geocal_drivers::DeviceError> {
        tracing::warn!(index, id, ?hint_m, "place the tracer on station {id}");
        Ok(())
    }
    async fn mount_target(
        &mut self,
        target: &str,
        offset_m: [f64; 3],
    ) -> Result<(), geocal_drivers::DeviceError> {
        tracing::warn!(target, ?offset_m, "mount reflector {target}");
        Ok(())
    }
}

async fn build_real(config: &Config, plan: &Plan, _epoch_ns: u64) -> anyhow::Result<BuiltDevices> {
    let _ = plan;
    let (tracer, environment) = match config.devices.tracer.driver {
        DriverKind::Hpi3d => {
            let cfg = hpi3d_config(config);
            let port = cfg.port.clone();
            let tracer = Hpi3dTracer::open(cfg)
                .await
                .with_context(|| format!("opening the HPI-3D at {port}"))?;
            hpi3d_devices(config, tracer)
        }
        kind => anyhow::bail!(
            "devices.tracer.driver = \"{}\" without [sim] or [hil]: a real run needs \"hpi3d\"",
            kind.as_str()
        ),
    };
    let machine: Box<dyn Machine> = match config.devices.machine.driver {
        DriverKind::Grbl => {
            let cfg = grbl_config(config);
            let port = cfg.port.clone();
            Box::new(GrblMachine::open(cfg).with_context(|| format!("opening GRBL at {port}"))?)
        }
        DriverKind::Passive => Box::new(crate::sequencer::passive::PassiveMachine {
            id: config.devices.machine.id.clone(),
        }),
        kind => anyhow::bail!(
            "devices.machine.driver = \"{}\" in a real run: expected \"grbl\"",
            kind.as_str()
        ),
    };
    Ok(BuiltDevices {
        devices: Devices {
            tracer,
            environment,
            machine,
            operator: Box::new(LoggingOperator),
            rotary: None,
        },
        clock: Arc::new(SystemClock),
        world: None,
        emulators: Emulators::default(),
    })
}
