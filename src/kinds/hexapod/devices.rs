//! The devices of a `hexapod` run from config: the simulated hexapod, the Modbus driver of a
//! real controller or of the hosted emulator (`[hil]`), and the pose sensor (sim or given).

use std::sync::{Arc, Mutex};

use anyhow::Context;
use async_trait::async_trait;
use geocal_drivers::modbus::ModbusTransport;
use geocal_drivers::modbus_hexapod::{ModbusHexapod, ModbusHexapodConfig, ModbusHexapodEmulator};
use geocal_drivers::serial::PtySlave;
use geocal_drivers::{
    DeviceError, Hexapod, HexapodState, LegReading, LinkFault, PlatformPose, PoseReading,
    PoseSensor,
};

use crate::clock::{Clock, SystemClock, VirtualClock};
use crate::kinds::hexapod::config::{HexapodConfig, HexapodDriver, PoseSensorDriver};
use crate::kinds::hexapod::hil_source::WorldHexapodSource;
use crate::kinds::hexapod::sequence::HexapodDevices;
use crate::kinds::hexapod::sim::{HexapodWorld, SharedHexapodWorld, SimHexapod, SimPoseSensor};
use crate::sim::hil::HilTime;

/// The Modbus hexapod emulator this run hosts, and where it listens.
pub struct HostedHexapod {
    pub emulator: ModbusHexapodEmulator,
    /// `127.0.0.1:PORT` (TCP) or the pty path (RTU).
    pub endpoint: String,
    /// The host end of the RTU pty, kept open while the driver reopens it by path.
    pub pty: Option<PtySlave>,
}

/// A run's devices, its log clock, the simulated world (if any) and the hosted emulator.
pub struct Built {
    pub devices: HexapodDevices,
    pub clock: Arc<dyn Clock>,
    pub world: Option<SharedHexapodWorld>,
    pub hosted: Option<HostedHexapod>,
}

/// The last pose the hexapod accepted, shared with the `given` pose sensor.
type LastCommand = Arc<Mutex<Option<PlatformPose>>>;

/// A hexapod that remembers the last pose it accepted (for the `given` pose sensor).
struct RememberCommand {
    inner: Box<dyn Hexapod>,
    last: LastCommand,
}

#[async_trait]
impl Hexapod for RememberCommand {
    fn id(&self) -> &str {
        self.inner.id()
    }
    async fn start_move(&mut self, pose: &PlatformPose) -> Result<(), DeviceError> {
        self.inner.start_move(pose).await?;
        *self.last.lock().unwrap_or_else(|e| e.into_inner()) = Some(*pose);
        Ok(())
    }
    async fn state(&mut self) -> Result<HexapodState, DeviceError> {
        self.inner.state().await
    }
    async fn read_legs(&mut self) -> Result<LegReading, DeviceError> {
        self.inner.read_legs().await
    }
    fn take_link_faults(&mut self) -> Vec<LinkFault> {
        self.inner.take_link_faults()
    }
}

/// Pose sensor `given`: the commanded pose, taken as exact (no instrument).
pub struct GivenPoseSensor {
    id: String,
    last: LastCommand,
    clock: Arc<dyn Clock>,
    start_ns: u64,
}

#[async_trait]
impl PoseSensor for GivenPoseSensor {
    fn id(&self) -> &str {
        &self.id
    }
    async fn measure(&mut self) -> Result<PoseReading, DeviceError> {
        let last = *self.last.lock().unwrap_or_else(|e| e.into_inner());
        let pose = last.ok_or_else(|| DeviceError::Rejected {
            device: self.id.clone(),
            message: "no pose commanded yet: a given pose is the commanded one".into(),
        })?;
        Ok(PoseReading {
            t_s: self.clock.now_ns().saturating_sub(self.start_ns) as f64 * 1e-9,
            pose,
        })
    }
}

/// The driver's settings with the hexapod's id (validation guarantees them for Modbus kinds).
fn modbus_config(config: &HexapodConfig) -> anyhow::Result<ModbusHexapodConfig> {
    let h = &config.devices.hexapod;
    let mut cfg = h.modbus.clone().with_context(|| {
        format!(
            "devices.hexapod.driver = \"{}\" needs [devices.hexapod.modbus]",
            h.driver.as_str()
        )
    })?;
    cfg.id = h.id.clone();
    Ok(cfg)
}

/// Host the Modbus hexapod emulator (TCP on 127.0.0.1 at an ephemeral port, RTU on a pty),
/// backed by the world's hexapod; values follow `time`.
pub async fn host_emulator(
    config: &HexapodConfig,
    source: WorldHexapodSource,
) -> anyhow::Result<HostedHexapod> {
    let cfg = modbus_config(config)?;
    let faults = config
        .hil
        .as_ref()
        .map(|h| h.hexapod_faults.clone())
        .unwrap_or_default();
    match config.devices.hexapod.driver {
        HexapodDriver::ModbusRtu => {
            let (master, slave) = geocal_drivers::serial::pty_pair()
                .context("creating a pty for the Modbus RTU hexapod emulator")?;
            let endpoint = slave
                .path()
                .context("the Modbus RTU emulator's pty has no path")?
                .to_string();
            let emulator =
                ModbusHexapodEmulator::start_rtu(&cfg.map, faults, Box::new(source), master)
                    .context("starting the Modbus RTU hexapod emulator")?;
            Ok(HostedHexapod {
                emulator,
                endpoint,
                pty: Some(slave),
            })
        }
        _ => {
            let emulator = ModbusHexapodEmulator::start_tcp(&cfg.map, faults, Box::new(source))
                .await
                .context("starting the Modbus TCP hexapod emulator on 127.0.0.1")?;
            let addr = emulator
                .addr()
                .context("the Modbus TCP hexapod emulator has no address")?;
            Ok(HostedHexapod {
                emulator,
                endpoint: addr.to_string(),
                pty: None,
            })
        }
    }
}

/// Connect the Modbus driver at `transport` (the configured one, or the hosted emulator's),
/// or lend the connection `holder` keeps.
async fn connect(
    mut cfg: ModbusHexapodConfig,
    transport: ModbusTransport,
    holder: Option<&crate::devices::held::DeviceHolder>,
) -> anyhow::Result<Box<dyn Hexapod>> {
    let at = transport.describe();
    cfg.transport = Some(transport);
    let id = cfg.id.clone();
    let context = format!("connecting hexapod {id} over {at}");
    let driver = crate::devices::held::lend_or_open(holder, &id, &cfg.clone(), || async {
        ModbusHexapod::connect(cfg).await.context(context)
    })
    .await?;
    tracing::info!("hexapod {id} over {at}");
    Ok(driver)
}

/// Build the run's devices. Must run inside the tokio runtime that will serve the emulator.
pub async fn build(
    config: &HexapodConfig,
    epoch_ns: u64,
    holder: Option<&crate::devices::held::DeviceHolder>,
) -> anyhow::Result<Built> {
    let h = &config.devices.hexapod;
    let virtual_clock = Arc::new(VirtualClock::new(epoch_ns));
    let world: Option<SharedHexapodWorld> = config
        .sim
        .as_ref()
        .map(|_| Arc::new(Mutex::new(HexapodWorld::new(config, virtual_clock.clone()))));
    let mut hosted = None;
    let (hexapod, clock): (Box<dyn Hexapod>, Arc<dyn Clock>) = match (h.driver, &world) {
        (HexapodDriver::Sim, Some(w)) => (
            Box::new(SimHexapod {
                id: h.id.clone(),
                world: w.clone(),
            }),
            virtual_clock.clone(),
        ),
        (HexapodDriver::Sim, None) => {
            anyhow::bail!("devices.hexapod.driver = \"sim\" needs [sim] (validation checks this)")
        }
        (_, Some(w)) if config.emulated() => {
            // The emulator runs in real time: the world and the log follow wall time.
            let time = Arc::new(HilTime::new(epoch_ns));
            let source = WorldHexapodSource::new(w.clone(), virtual_clock.clone(), time.clone());
            let host = host_emulator(config, source).await?;
            let cfg = modbus_config(config)?;
            let transport = match h.driver {
                HexapodDriver::ModbusRtu => ModbusTransport::Rtu {
                    port: host.endpoint.clone(),
                    baud: match &cfg.transport {
                        Some(ModbusTransport::Rtu { baud, .. }) => *baud,
                        _ => 115_200,
                    },
                },
                _ => ModbusTransport::Tcp {
                    address: host
                        .endpoint
                        .parse()
                        .context("the hexapod emulator's TCP address")?,
                },
            };
            tracing::info!("Modbus hexapod emulator on {}", host.endpoint);
            hosted = Some(host);
            (connect(cfg, transport, None).await?, time as Arc<dyn Clock>)
        }
        (_, _) => {
            let cfg = modbus_config(config)?;
            let transport = cfg
                .transport
                .clone()
                .context("devices.hexapod.modbus.transport is needed for a real hexapod")?;
            (
                connect(cfg, transport, holder).await?,
                Arc::new(SystemClock),
            )
        }
    };
    let last: LastCommand = Arc::new(Mutex::new(None));
    let (hexapod, pose_sensor): (Box<dyn Hexapod>, Option<Box<dyn PoseSensor>>) =
        match &config.devices.pose_sensor {
            None => (hexapod, None),
            Some(s) if s.driver == PoseSensorDriver::Given => (
                Box::new(RememberCommand {
                    inner: hexapod,
                    last: last.clone(),
                }),
                Some(Box::new(GivenPoseSensor {
                    id: s.id.clone(),
                    last,
                    clock: clock.clone(),
                    start_ns: clock.now_ns(),
                })),
            ),
            Some(s) => match &world {
                Some(w) => (
                    hexapod,
                    Some(Box::new(SimPoseSensor {
                        id: s.id.clone(),
                        world: w.clone(),
                    })),
                ),
                None => anyhow::bail!(
                    "devices.pose_sensor.driver = \"sim\" needs [sim] (validation checks this)"
                ),
            },
        };
    Ok(Built {
        devices: HexapodDevices {
            hexapod,
            pose_sensor,
        },
        clock,
        world,
        hosted,
    })
}
