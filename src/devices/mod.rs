//! Builds the run's devices as trait objects from the configuration, plus the clock that
//! stamps them and, for simulated and emulated runs, the world behind them:
//! - every device `sim`: the simulated drivers in virtual time (the tracer stream advances
//!   the clock, so runs take seconds whatever the dwell times);
//! - protocol drivers (`hpi3d`, `grbl`, `linuxcnc`) without `[hil]`: the real devices at their
//!   ports (LinuxCNC at its linuxcncrsh host and port),
//!   stamped by the system clock;
//! - `[hil] emulate = true`: geocal hosts the HPI-3D and GRBL emulators on ptys (and the
//!   Modbus table emulator, `rotary_table.rs`) backed by the simulated world and connects the
//!   real drivers to them; the world follows wall time.

pub mod held;
pub mod hosting;
pub mod operator;
pub mod rotary_table;

use std::sync::{Arc, Mutex};

use anyhow::Context;
use geocal_drivers::grbl::{GrblConfig, GrblMachine};
use geocal_drivers::hpi3d::{Hpi3dConfig, Hpi3dTracer};
use geocal_drivers::linuxcnc::{LinuxCncConfig, LinuxCncMachine};
use geocal_drivers::{Environment, Machine, Operator, RotaryTable, Tracer};

use crate::clock::{Clock, SystemClock, VirtualClock};
use crate::config::{Config, DriverKind};
use crate::plan::Plan;
use crate::sequencer::Devices;
use crate::sim::devices::{
    SharedWorld, SimEnvironment, SimMachine, SimOperator, SimRotaryTable, SimTracer,
};
use crate::sim::hil::{HilOperator, HilTime};
use crate::sim::world::SimWorld;

pub struct BuiltDevices {
    pub devices: Devices,
    pub clock: Arc<dyn Clock>,
    /// The simulated world, when the run is simulated or emulated (for exporting the truth).
    pub world: Option<SharedWorld>,
    /// The emulators of an emulated run; dropping them stops them.
    pub emulators: Emulators,
}

/// Device emulators hosted by this process (`[hil] emulate = true`; `src/devices/hosting.rs`).
#[derive(Default)]
pub struct Emulators {
    pub hosted: Option<crate::devices::hosting::Hosted>,
}

/// Build the devices; must run inside the tokio runtime that will run the sequencer (the
/// drivers' reader tasks and the emulators are spawned on it).
/// A real run's operator comes from `operator` when given (the daemon's prompts), else from
/// the console.
pub async fn build(
    config: &Config,
    plan: &Plan,
    epoch_ns: u64,
    operator: Option<&crate::sequencer::control::OperatorSource>,
    holder: Option<&held::DeviceHolder>,
) -> anyhow::Result<BuiltDevices> {
    let mut built = if config.emulated() {
        build_emulated(config, plan, epoch_ns).await?
    } else if all_simulated(config) {
        build_simulated(config, plan, epoch_ns)?
    } else {
        return build_real(config, epoch_ns, operator, holder).await;
    };
    let operator_config = config.operator.clone().unwrap_or_default();
    if operator_config.rehearse {
        let ask = real_operator(config, operator)?;
        let act = std::mem::replace(&mut built.devices.operator, Box::new(NoOperator));
        built.devices.operator = Box::new(crate::devices::operator::Rehearsal { ask, act });
    }
    Ok(built)
}

/// Every device is simulated in this process.
fn all_simulated(config: &Config) -> bool {
    config.devices.tracer.driver == DriverKind::Sim
        && matches!(
            config.devices.machine.driver,
            DriverKind::Sim | DriverKind::Passive
        )
        && config
            .devices
            .rotary_table
            .as_ref()
            .is_none_or(|t| t.driver == DriverKind::Sim)
}

/// The run talks to devices outside this process (neither simulated nor emulated here).
pub fn uses_real_devices(config: &Config) -> bool {
    !config.emulated() && !all_simulated(config)
}

/// The operator who answers a real run's prompts: the daemon's when given, else the console's.
fn real_operator(
    config: &Config,
    operator: Option<&crate::sequencer::control::OperatorSource>,
) -> anyhow::Result<Box<dyn Operator>> {
    Ok(match operator {
        Some(source) => source(),
        None => Box::new(crate::devices::operator::ConsoleOperator::stdin(
            &config.operator.clone().unwrap_or_default(),
        )?),
    })
}

/// A placeholder while an operator is being wrapped.
struct NoOperator;

#[async_trait::async_trait]
impl Operator for NoOperator {
    async fn place_station(
        &mut self,
        _index: usize,
        _id: &str,
        _hint_m: Option<[f64; 3]>,
    ) -> Result<(), geocal_drivers::DeviceError> {
        Ok(())
    }

    async fn mount_target(
        &mut self,
        _target: &str,
        _offset_m: [f64; 3],
    ) -> Result<(), geocal_drivers::DeviceError> {
        Ok(())
    }
}

fn hpi3d_config(config: &Config) -> Hpi3dConfig {
    let tracer = &config.devices.tracer;
    let mut c = tracer.hpi3d.clone().unwrap_or_default();
    c.id = tracer.id.clone();
    // The samples are timed on the stream's grid, so the driver needs its rate.
    c.stream_rate_hz = tracer.sample_rate_hz;
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

/// The LinuxCNC driver's settings: `[devices.machine.linuxcnc]` with the machine's id and feed.
pub fn linuxcnc_config(config: &Config) -> LinuxCncConfig {
    let machine = &config.devices.machine;
    let mut c = machine.linuxcnc.clone().unwrap_or_default();
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
        // geocal gets a machine it cannot command; the program drives it.
        let (tracer, operator) =
            crate::sim::passive_machine::tracer_and_operator(config, plan, world.clone());
        return Ok(BuiltDevices {
            devices: Devices {
                tracer: paced(config, tracer),
                environment: sim_environment(config, &world),
                machine: Box::new(crate::sequencer::passive::PassiveMachine {
                    id: config.devices.machine.id.clone(),
                }),
                operator,
                rotary: None,
            },
            clock,
            world: world_opt,
            emulators: Default::default(),
        });
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

    let mut hosted = crate::devices::hosting::host(config, sim, hil, &world, &time).await?;

    // The tracer: the real driver on the other end of the HPI-3D emulator's pty.
    let mut hpi3d = hpi3d_config(config);
    hpi3d.port = hosted.tracer_path.clone();
    tracing::info!("HPI-3D emulator on {}", hpi3d.port);
    let tracer_port = hosted
        .tracer_port
        .take()
        .context("the HPI-3D emulator's pty has no host end")?;
    let tracer = Hpi3dTracer::from_io(tracer_port, hpi3d)
        .await
        .context("connecting the HPI-3D driver to its emulator")?;
    let (tracer, hpi3d_env) = hpi3d_devices(config, tracer);
    let environment = match hpi3d_env {
        Some(env) => Some(env),
        None => sim_environment(config, &world),
    };

    // The machine: the GRBL driver opens the emulator's link path (and reopens it after
    // an injected disconnect), or the simulated machine.
    let machine: Box<dyn Machine> = match (&hosted.machine_path, &hosted.linuxcnc) {
        (_, Some(linuxcnc)) => {
            // geocal started this LinuxCNC (in E-stop, unhomed): the driver powers it on and
            // homes the joints where they stand, as the INI geocal wrote allows (the driver
            // reads its joint count from that INI).
            let mut cfg = linuxcnc_config(config);
            cfg.home = geocal_drivers::linuxcnc::HomePolicy::Allow;
            cfg.power_on = true;
            let driver = LinuxCncMachine::connect_with(cfg, linuxcnc.stream_connector())
                .await
                .context("connecting the LinuxCNC driver to the LinuxCNC geocal started")?;
            // Each point's trims go into the session (`controller_trims` events).
            Box::new(crate::sim::linuxcnc::host::TrimReportingMachine {
                inner: Box::new(driver),
                latest: linuxcnc.trims_handle(),
            })
        }
        (Some(path), None) => {
            let mut grbl = grbl_config(config);
            grbl.port = path.clone();
            tracing::info!("GRBL emulator on {}", grbl.port);
            Box::new(GrblMachine::open(grbl).context("opening the GRBL emulator's pty")?)
        }
        (None, None) => Box::new(SimMachine {
            id: config.devices.machine.id.clone(),
            world: world.clone(),
        }),
    };
    let world_opt = Some(world.clone());
    // The rotary table: the Modbus driver to its emulator, or the simulated table.
    let rotary = match (config.devices.rotary_table.as_ref(), hosted.table.as_ref()) {
        (Some(table), Some(emulator)) => {
            Some(crate::devices::rotary_table::connect_hosted(table, emulator).await?)
        }
        _ => sim_rotary(config, &world_opt),
    };
    Ok(BuiltDevices {
        devices: Devices {
            tracer,
            environment,
            machine,
            operator: Box::new(HilOperator {
                world: world.clone(),
                time: time.clone(),
            }) as Box<dyn Operator>,
            rotary,
        },
        clock: time,
        world: world_opt,
        emulators: Emulators {
            hosted: Some(hosted),
        },
    })
}

async fn build_real(
    config: &Config,
    _epoch_ns: u64,
    operator: Option<&crate::sequencer::control::OperatorSource>,
    holder: Option<&held::DeviceHolder>,
) -> anyhow::Result<BuiltDevices> {
    // First, so that a run without a console fails before it touches a device.
    let operator = real_operator(config, operator)?;
    let (tracer, environment) = match config.devices.tracer.driver {
        DriverKind::Hpi3d => {
            let cfg = hpi3d_config(config);
            let port = cfg.port.clone();
            let tracer = held::lend_or_open(holder, &cfg.id.clone(), &cfg.clone(), || async {
                Hpi3dTracer::open(cfg)
                    .await
                    .with_context(|| format!("opening the HPI-3D at {port}"))
            })
            .await?;
            let environment = config
                .devices
                .environment
                .as_ref()
                .filter(|e| e.driver == DriverKind::Hpi3d)
                .map(|_| Box::new(tracer.environment()) as Box<dyn Environment>);
            (tracer as Box<dyn Tracer>, environment)
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
            held::lend_or_open(holder, &cfg.id.clone(), &cfg.clone(), || async {
                GrblMachine::open(cfg).with_context(|| format!("opening GRBL at {port}"))
            })
            .await?
        }
        DriverKind::Linuxcnc => {
            let cfg = linuxcnc_config(config);
            let at = format!("{}:{}", cfg.host, cfg.port);
            held::lend_or_open(holder, &cfg.id.clone(), &cfg.clone(), || async {
                LinuxCncMachine::connect(cfg)
                    .await
                    .with_context(|| format!("connecting to LinuxCNC (linuxcncrsh) at {at}"))
            })
            .await?
        }
        DriverKind::Passive => Box::new(crate::sequencer::passive::PassiveMachine {
            id: config.devices.machine.id.clone(),
        }),
        kind => anyhow::bail!(
            "devices.machine.driver = \"{}\" in a real run: expected \"grbl\" or \"linuxcnc\"",
            kind.as_str()
        ),
    };
    let rotary = match config.devices.rotary_table.as_ref() {
        Some(table) if table.driver != DriverKind::Sim => {
            crate::devices::rotary_table::connect_real(table, holder)
                .await
                .map(Some)
        }
        Some(table) => Err(anyhow::anyhow!(
            "devices.rotary_table.driver = \"{}\" in a real run: expected \"modbus_tcp\" or \"modbus_rtu\"",
            table.driver.as_str()
        )),
        None => Ok(None),
    };
    let mut machine = machine;
    let rotary = match rotary {
        Ok(rotary) => rotary,
        Err(e) => {
            // The machine was prepared for the run (its mode): leave it as found.
            if let Err(f) = machine.finish().await {
                tracing::warn!("leaving the machine's controller as found: {f}");
            }
            return Err(e);
        }
    };
    Ok(BuiltDevices {
        devices: Devices {
            tracer,
            environment,
            machine,
            operator,
            rotary,
        },
        clock: Arc::new(SystemClock),
        world: None,
        emulators: Emulators::default(),
    })
}
