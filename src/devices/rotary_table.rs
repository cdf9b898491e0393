//! The rotary table's protocol drivers from config (`modbus_tcp`, `modbus_rtu`): connecting
//! to a real table, and hosting the Modbus table emulator backed by the simulated world.

use std::sync::Arc;

use anyhow::Context;
use geocal_drivers::modbus_table::{
    ModbusTable, ModbusTableConfig, ModbusTableEmulator, ModbusTableEmulatorConfig,
    ModbusTableFaults, ModbusTransport, TableSource,
};
use geocal_drivers::serial::PtySlave;
use geocal_drivers::RotaryTable;

use crate::config::{DriverKind, RotaryTableConfig};
use crate::sim::devices::SharedWorld;
use crate::sim::hil::HilTime;
use crate::sim::table_source::WorldTableSource;

/// The driver's settings with the table's id (validation guarantees them for Modbus kinds).
fn modbus_config(table: &RotaryTableConfig) -> anyhow::Result<ModbusTableConfig> {
    let mut cfg = table.modbus.clone().with_context(|| {
        format!(
            "devices.rotary_table.driver = \"{}\" needs [devices.rotary_table.modbus]",
            table.driver.as_str()
        )
    })?;
    cfg.id = table.id.clone();
    Ok(cfg)
}

/// Connect the Modbus driver of a real table at its configured transport (or lend the
/// connection `holder` keeps).
pub async fn connect_real(
    table: &RotaryTableConfig,
    holder: Option<&crate::devices::held::DeviceHolder>,
) -> anyhow::Result<Box<dyn RotaryTable>> {
    let cfg = modbus_config(table)?;
    let at = match &cfg.transport {
        Some(ModbusTransport::Tcp { address }) => format!("Modbus TCP {address}"),
        Some(ModbusTransport::Rtu { port, baud }) => format!("Modbus RTU {port} at {baud} Bd"),
        None => String::from("(no transport configured)"),
    };
    let driver = crate::devices::held::lend_or_open(holder, &table.id, &cfg.clone(), || async {
        ModbusTable::connect(cfg)
            .await
            .with_context(|| format!("connecting rotary table {} over {at}", table.id))
    })
    .await?;
    Ok(driver)
}

/// A Modbus table emulator hosted by this process, and where it listens.
pub struct HostedTable {
    pub emulator: ModbusTableEmulator,
    /// `127.0.0.1:PORT` (TCP) or the pty path (RTU).
    pub endpoint: String,
    /// The host end of the RTU pty, kept open so that the pty stays usable while the driver
    /// reopens it by path.
    pub pty: Option<PtySlave>,
    pub driver: DriverKind,
}

/// Host the Modbus table emulator of `table` (TCP on 127.0.0.1 at an ephemeral port, RTU
/// on a pty), backed by the world's table; values follow `time`.
pub async fn host_emulator(
    table: &RotaryTableConfig,
    faults: &ModbusTableFaults,
    world: SharedWorld,
    time: Arc<HilTime>,
) -> anyhow::Result<HostedTable> {
    host_emulator_with(table, faults, Box::new(WorldTableSource::new(world, time))).await
}

/// Host the Modbus table emulator of `table` backed by any `source` (e.g. the `rotary_sphere`
/// world's table).
pub async fn host_emulator_with(
    table: &RotaryTableConfig,
    faults: &ModbusTableFaults,
    source: Box<dyn TableSource>,
) -> anyhow::Result<HostedTable> {
    let cfg = modbus_config(table)?;
    let emu_cfg = ModbusTableEmulatorConfig {
        map: cfg.map.clone(),
        faults: faults.clone(),
    };
    match table.driver {
        DriverKind::ModbusTcp => {
            let emulator = ModbusTableEmulator::start_tcp(emu_cfg, source)
                .await
                .context("starting the Modbus TCP table emulator on 127.0.0.1")?;
            let addr = emulator
                .addr()
                .context("the Modbus TCP table emulator has no address")?;
            Ok(HostedTable {
                emulator,
                endpoint: addr.to_string(),
                pty: None,
                driver: table.driver,
            })
        }
        DriverKind::ModbusRtu => {
            let (master, slave) = geocal_drivers::serial::pty_pair()
                .context("creating a pty for the Modbus RTU table emulator")?;
            let path = slave
                .path()
                .context("the Modbus RTU emulator's pty has no path")?
                .to_string();
            let emulator = ModbusTableEmulator::start_rtu(emu_cfg, source, master)
                .context("starting the Modbus RTU table emulator")?;
            Ok(HostedTable {
                emulator,
                endpoint: path,
                pty: Some(slave),
                driver: table.driver,
            })
        }
        kind => anyhow::bail!(
            "devices.rotary_table.driver = \"{}\" has no emulator",
            kind.as_str()
        ),
    }
}

/// Connect the Modbus driver to a hosted emulator (its configured transport is ignored).
pub async fn connect_hosted(
    table: &RotaryTableConfig,
    hosted: &HostedTable,
) -> anyhow::Result<Box<dyn RotaryTable>> {
    let mut cfg = modbus_config(table)?;
    cfg.transport = Some(match hosted.driver {
        DriverKind::ModbusRtu => ModbusTransport::Rtu {
            port: hosted.endpoint.clone(),
            baud: match &cfg.transport {
                Some(ModbusTransport::Rtu { baud, .. }) => *baud,
                _ => 115_200,
            },
        },
        _ => ModbusTransport::Tcp {
            address: hosted
                .endpoint
                .parse()
                .context("the table emulator's TCP address")?,
        },
    });
    tracing::info!(
        "Modbus table emulator ({}) on {}",
        hosted.driver.as_str(),
        hosted.endpoint
    );
    let driver = ModbusTable::connect(cfg)
        .await
        .with_context(|| format!("connecting the table driver to {}", hosted.endpoint))?;
    Ok(Box::new(driver))
}

#[cfg(test)]
mod tests {
    use std::sync::Mutex;

    use geocal_drivers::RotaryState;

    use super::*;
    use crate::clock::VirtualClock;
    use crate::config::Config;
    use crate::plan::Plan;
    use crate::sim::world::SimWorld;

    /// The rotary example with its table on `driver` (emulated) and a fast simulated table.
    fn emulated(driver: &str) -> Config {
        let text = include_str!("../../config/rotary-tracer.toml")
            .replace(
                "id = \"c\"\ndriver = \"sim\"",
                &format!("id = \"c\"\ndriver = \"{driver}\""),
            )
            .replace(
                "id = \"tracer0\"\ndriver = \"sim\"",
                "id = \"tracer0\"\ndriver = \"hpi3d\"",
            )
            .replace(
                "axis_tilt_rad = 1e-4 }",
                "axis_tilt_rad = 1e-4, speed_rad_s = 50.0, settle_s = 0.01 }",
            );
        let text = format!(
            "{text}
[devices.rotary_table.modbus]
timeout_s = 0.5
[devices.rotary_table.modbus.map]
target = {{ address = 100, counts_per_rad = 1e7 }}
actual = {{ address = 200, kind = \"input\", counts_per_rad = 1e7 }}
status = {{ address = 300, kind = \"input\", in_position_bit = 0, fault_bit = 2 }}
command = {{ address = 110, go_value = 1, clear_value = 0 }}
ack = {{ bit = 3 }}
[hil]
emulate = true
"
        );
        Config::parse(&text, std::path::Path::new("table.toml")).expect("config")
    }

    async fn turn_over(driver: &str) {
        let config = emulated(driver);
        let plan = Plan::from_config(&config);
        let world = Arc::new(Mutex::new(
            SimWorld::new(&config, &plan, Arc::new(VirtualClock::new(0))).expect("world"),
        ));
        let table = config.devices.rotary_table.as_ref().expect("table");
        let time = Arc::new(HilTime::new(0));
        let hosted = host_emulator(table, &Default::default(), world.clone(), time)
            .await
            .expect("emulator");
        let mut driver = connect_hosted(table, &hosted).await.expect("driver");
        driver.start_rotation(1.25).await.expect("go");
        let mut polls = 0;
        let encoder = loop {
            polls += 1;
            assert!(polls < 500, "never in position");
            match driver.state().await.expect("state") {
                RotaryState::InPosition { encoder_rad } => break encoder_rad,
                RotaryState::Moving => {
                    tokio::time::sleep(std::time::Duration::from_millis(5)).await
                }
            }
        };
        assert!((encoder - 1.25).abs() < 1e-7, "{encoder}");
        assert!(polls > 1, "the table moved for a while");
        // The world's table turned to the command.
        let w = world.lock().expect("world");
        assert_eq!(w.table_in_position(), Some(1.25));
        assert_eq!(hosted.emulator.stats().go_commands, 1);
    }

    #[tokio::test]
    async fn emulated_modbus_tcp_table_turns_the_world() {
        turn_over("modbus_tcp").await;
    }

    #[tokio::test]
    async fn emulated_modbus_rtu_table_on_a_pty_turns_the_world() {
        turn_over("modbus_rtu").await;
    }
}
