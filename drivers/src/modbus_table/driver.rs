//! Modbus rotary-table driver (TCP or RTU via tokio-modbus): the table's config, and the
//! `RotaryTable` over the shared Modbus client (timeouts, reconnect, ack handshake).

use std::net::SocketAddr;

use async_trait::async_trait;
use serde::{Deserialize, Serialize};
use tokio::time::Instant;

use super::map::RegisterMap;
use crate::modbus::client::{ModbusClient, ModbusTiming};
pub use crate::modbus::client::{ModbusStats as ModbusTableStats, ModbusTransport};
use crate::serial::check_seconds;
use crate::traits::{DeviceError, LinkFault, RotaryState, RotaryTable};

/// A Modbus rotary table's config: transport, timing and register map.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModbusTableConfig {
    #[serde(default = "default_id")]
    pub id: String,
    /// Needed by `ModbusTable::connect`; the explicit constructors take it as arguments.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub transport: Option<ModbusTransport>,
    /// Longest wait for one reply (and for a TCP connect), seconds.
    #[serde(default = "default_timeout_s")]
    pub timeout_s: f64,
    /// Extra attempts after a timeout or transport error (each after a reconnect).
    #[serde(default = "default_retries")]
    pub retries: u32,
    /// Longest wait for the acknowledge of a go command, seconds.
    #[serde(default = "default_ack_timeout_s")]
    pub ack_timeout_s: f64,
    /// Minimum time between two status polls; `state()` returns the last state in between.
    #[serde(default = "default_poll_interval_s")]
    pub poll_interval_s: f64,
    pub map: RegisterMap,
}

fn default_id() -> String {
    "rotary".into()
}
pub(crate) fn default_timeout_s() -> f64 {
    0.5
}
pub(crate) fn default_retries() -> u32 {
    2
}
pub(crate) fn default_ack_timeout_s() -> f64 {
    2.0
}
pub(crate) fn default_poll_interval_s() -> f64 {
    0.05
}

/// Timing settings every Modbus driver config has; checked the same way.
pub(crate) fn check_timing(id: &str, t: &ModbusTiming) -> Result<(), DeviceError> {
    check_seconds(id, "timeout_s", t.timeout_s)?;
    check_seconds(id, "ack_timeout_s", t.ack_timeout_s)?;
    check_seconds(id, "poll_interval_s", t.poll_interval_s)?;
    if t.timeout_s <= 0.0 {
        return Err(DeviceError::Protocol {
            device: id.to_string(),
            message: "timeout_s must be positive".into(),
        });
    }
    Ok(())
}

impl ModbusTableConfig {
    /// A config with default timing around `map`.
    pub fn new(map: RegisterMap) -> Self {
        Self {
            id: default_id(),
            transport: None,
            timeout_s: default_timeout_s(),
            retries: default_retries(),
            ack_timeout_s: default_ack_timeout_s(),
            poll_interval_s: default_poll_interval_s(),
            map,
        }
    }

    pub fn timing(&self) -> ModbusTiming {
        ModbusTiming {
            timeout_s: self.timeout_s,
            retries: self.retries,
            ack_timeout_s: self.ack_timeout_s,
            poll_interval_s: self.poll_interval_s,
        }
    }

    /// Reject values the driver cannot work with.
    pub fn validate(&self) -> Result<(), DeviceError> {
        check_timing(&self.id, &self.timing())?;
        self.map
            .validate()
            .map_err(|m| self.bad(format!("register map: {m}")))
    }

    fn bad(&self, message: String) -> DeviceError {
        DeviceError::Protocol {
            device: self.id.clone(),
            message,
        }
    }
}

/// A rotary table driven over Modbus with a configured register map.
pub struct ModbusTable {
    cfg: ModbusTableConfig,
    client: ModbusClient,
    last_poll: Option<Instant>,
    last_state: Option<RotaryState>,
}

impl ModbusTable {
    /// Connect as the config's `transport` says.
    pub async fn connect(cfg: ModbusTableConfig) -> Result<Self, DeviceError> {
        match cfg.transport.clone() {
            Some(transport) => Self::start(transport, cfg).await,
            None => Err(cfg.bad("no transport configured".into())),
        }
    }

    /// Modbus TCP to `address`.
    pub async fn connect_tcp(
        address: SocketAddr,
        cfg: ModbusTableConfig,
    ) -> Result<Self, DeviceError> {
        Self::start(ModbusTransport::Tcp { address }, cfg).await
    }

    /// Modbus RTU on the serial port `port` at `baud` (8N1).
    pub async fn open_rtu(
        port: &str,
        baud: u32,
        cfg: ModbusTableConfig,
    ) -> Result<Self, DeviceError> {
        Self::start(
            ModbusTransport::Rtu {
                port: port.to_string(),
                baud,
            },
            cfg,
        )
        .await
    }

    async fn start(
        transport: ModbusTransport,
        cfg: ModbusTableConfig,
    ) -> Result<Self, DeviceError> {
        cfg.validate()?;
        let client =
            ModbusClient::connect(&cfg.id, transport, cfg.map.unit_id, cfg.timing()).await?;
        Ok(Self {
            cfg,
            client,
            last_poll: None,
            last_state: None,
        })
    }

    pub fn config(&self) -> &ModbusTableConfig {
        &self.cfg
    }

    pub fn stats(&self) -> ModbusTableStats {
        self.client.stats()
    }

    async fn read_angle(&mut self, actual: bool) -> Result<f64, DeviceError> {
        let (a, name) = if actual {
            (self.cfg.map.actual.clone(), "actual angle")
        } else {
            (self.cfg.map.target.clone(), "target angle")
        };
        let words = self.client.read(a.kind, a.address, a.words(), name).await?;
        a.decode_rad(&words).ok_or_else(|| {
            self.client
                .protocol(format!("cannot decode {name} from {words:?}"))
        })
    }

    /// Read the encoder angle, radians.
    pub async fn read_encoder_rad(&mut self) -> Result<f64, DeviceError> {
        self.read_angle(true).await
    }

    /// Read the commanded (target) angle back from the table, radians.
    pub async fn read_target_rad(&mut self) -> Result<f64, DeviceError> {
        self.read_angle(false).await
    }
}

#[async_trait]
impl RotaryTable for ModbusTable {
    fn id(&self) -> &str {
        &self.cfg.id
    }

    async fn start_rotation(&mut self, commanded_rad: f64) -> Result<(), DeviceError> {
        let map = self.cfg.map.clone();
        let words = map
            .target
            .encode_rad(commanded_rad)
            .map_err(|m| self.client.rejected(format!("target: {m}")))?;
        self.last_state = None;
        self.last_poll = None;
        self.client
            .write(map.target.address, words, "target angle")
            .await?;
        self.client.go(&map.handshake()).await
    }

    async fn state(&mut self) -> Result<RotaryState, DeviceError> {
        if let (Some(t), Some(s)) = (self.last_poll, self.last_state) {
            if t.elapsed().as_secs_f64() < self.cfg.poll_interval_s {
                return Ok(s);
            }
        }
        let hs = self.cfg.map.handshake();
        let status = self.client.read_status(&hs).await?;
        let state = if hs.status.in_position(status) && !hs.status.moving(status) {
            RotaryState::InPosition {
                encoder_rad: self.read_encoder_rad().await?,
            }
        } else {
            RotaryState::Moving
        };
        self.last_poll = Some(Instant::now());
        self.last_state = Some(state);
        Ok(state)
    }

    /// Connections reopened (after a timeout or a transport error) since the last call.
    fn take_link_faults(&mut self) -> Vec<LinkFault> {
        self.client.take_link_faults()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Deserialize)]
    struct Doc {
        rotary: ModbusTableConfig,
    }

    /// The TOML example in docs/protocols/modbus-table.md parses and validates.
    #[test]
    fn documented_config_parses() {
        let doc = include_str!("../../../docs/protocols/modbus-table.md");
        let start = doc.find("```toml\n").expect("toml block") + 8;
        let len = doc[start..].find("```").expect("block end");
        let cfg = toml::from_str::<Doc>(&doc[start..start + len])
            .expect("documented config parses")
            .rotary;
        cfg.validate().expect("documented config validates");
        assert_eq!(
            cfg.transport,
            Some(ModbusTransport::Tcp {
                address: "192.168.0.20:502".parse().expect("addr")
            })
        );
        let c = &cfg.map.target;
        assert!((c.scale_counts_per_rad() - 1000.0 * 180.0 / std::f64::consts::PI).abs() < 1e-3);
        let bad = doc[start..start + len].replace("timeout_s = 0.5", "timeout_s = 0.5\ntimout = 1");
        assert!(toml::from_str::<Doc>(&bad).is_err());
    }

    #[test]
    fn bad_timing_rejected() {
        let doc = include_str!("../../../docs/protocols/modbus-table.md");
        let start = doc.find("```toml\n").expect("toml block") + 8;
        let len = doc[start..].find("```").expect("block end");
        let mut cfg = toml::from_str::<Doc>(&doc[start..start + len])
            .expect("parses")
            .rotary;
        cfg.timeout_s = 0.0;
        assert!(cfg.validate().is_err());
        cfg.timeout_s = f64::NAN;
        assert!(cfg.validate().is_err());
    }
}
