//! Modbus hexapod driver (TCP or RTU): writes the pose block, runs the go/ack handshake, polls
//! the in-position bit and reads the six leg encoders, over the shared Modbus client.

use std::net::SocketAddr;

use async_trait::async_trait;
use serde::{Deserialize, Serialize};
use tokio::time::Instant;

use super::map::HexapodRegisterMap;
use crate::modbus::client::{ModbusClient, ModbusStats, ModbusTiming, ModbusTransport};
use crate::modbus_table::driver::{
    check_timing, default_ack_timeout_s, default_poll_interval_s, default_retries,
    default_timeout_s,
};
use crate::traits::{DeviceError, Hexapod, HexapodState, LegReading, LinkFault, PlatformPose};

/// A Modbus hexapod's config: transport, timing (as the Modbus table's) and register map.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModbusHexapodConfig {
    #[serde(default = "default_id")]
    pub id: String,
    /// Needed by `ModbusHexapod::connect`; may be left out when the run hosts the emulator.
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
    pub map: HexapodRegisterMap,
}

fn default_id() -> String {
    "hexapod".into()
}

impl ModbusHexapodConfig {
    /// A config with default timing around `map`.
    pub fn new(map: HexapodRegisterMap) -> Self {
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

    /// Reject values the driver cannot work with; the message names the setting.
    pub fn validate(&self) -> Result<(), DeviceError> {
        check_timing(&self.id, &self.timing())?;
        self.map.validate().map_err(|m| DeviceError::Protocol {
            device: self.id.clone(),
            message: format!("register map: {m}"),
        })
    }
}

/// A hexapod controller driven over Modbus with a configured register map.
pub struct ModbusHexapod {
    cfg: ModbusHexapodConfig,
    client: ModbusClient,
    opened: Instant,
    last_poll: Option<Instant>,
    last_state: Option<HexapodState>,
}

impl ModbusHexapod {
    /// Connect as the config's `transport` says.
    pub async fn connect(cfg: ModbusHexapodConfig) -> Result<Self, DeviceError> {
        let Some(transport) = cfg.transport.clone() else {
            return Err(DeviceError::Protocol {
                device: cfg.id.clone(),
                message: "no transport configured".into(),
            });
        };
        cfg.validate()?;
        let client =
            ModbusClient::connect(&cfg.id, transport, cfg.map.unit_id, cfg.timing()).await?;
        Ok(Self {
            cfg,
            client,
            opened: Instant::now(),
            last_poll: None,
            last_state: None,
        })
    }

    /// Modbus TCP to `address`.
    pub async fn connect_tcp(
        address: SocketAddr,
        mut cfg: ModbusHexapodConfig,
    ) -> Result<Self, DeviceError> {
        cfg.transport = Some(ModbusTransport::Tcp { address });
        Self::connect(cfg).await
    }

    pub fn config(&self) -> &ModbusHexapodConfig {
        &self.cfg
    }

    pub fn stats(&self) -> ModbusStats {
        self.client.stats()
    }

    /// Read the commanded pose back from the controller.
    pub async fn read_target(&mut self) -> Result<PlatformPose, DeviceError> {
        let p = self.cfg.map.pose_target.clone();
        let words = self
            .client
            .read(
                crate::modbus::RegisterKind::Holding,
                p.address,
                p.block_words(),
                "pose target",
            )
            .await?;
        p.decode(&words).ok_or_else(|| {
            self.client
                .protocol(format!("cannot decode the pose from {words:?}"))
        })
    }
}

#[async_trait]
impl Hexapod for ModbusHexapod {
    fn id(&self) -> &str {
        &self.cfg.id
    }

    async fn start_move(&mut self, pose: &PlatformPose) -> Result<(), DeviceError> {
        let map = self.cfg.map.clone();
        let words = map
            .pose_target
            .encode(pose)
            .map_err(|m| self.client.rejected(format!("pose target: {m}")))?;
        self.last_state = None;
        self.last_poll = None;
        // One write for the whole block: the controller never sees half a pose.
        self.client
            .write(map.pose_target.address, words, "pose target")
            .await?;
        self.client.go(&map.handshake()).await
    }

    async fn state(&mut self) -> Result<HexapodState, DeviceError> {
        if let (Some(t), Some(s)) = (self.last_poll, self.last_state) {
            if t.elapsed().as_secs_f64() < self.cfg.poll_interval_s {
                return Ok(s);
            }
        }
        let hs = self.cfg.map.handshake();
        let status = self.client.read_status(&hs).await?;
        let state = if hs.status.in_position(status) && !hs.status.moving(status) {
            HexapodState::Idle
        } else {
            HexapodState::Moving
        };
        self.last_poll = Some(Instant::now());
        self.last_state = Some(state);
        Ok(state)
    }

    /// All six legs in one read (one instant); `t_s` is the midpoint of request and reply.
    async fn read_legs(&mut self) -> Result<LegReading, DeviceError> {
        let l = self.cfg.map.legs.clone();
        let asked_s = self.opened.elapsed().as_secs_f64();
        let words = self
            .client
            .read(l.kind, l.address, l.block_words(), "leg encoders")
            .await?;
        let t_s = 0.5 * (asked_s + self.opened.elapsed().as_secs_f64());
        let lengths_m = l.decode(&words).ok_or_else(|| {
            self.client
                .protocol(format!("cannot decode the leg lengths from {words:?}"))
        })?;
        Ok(LegReading { t_s, lengths_m })
    }

    fn take_link_faults(&mut self) -> Vec<LinkFault> {
        self.client.take_link_faults()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::modbus::RegisterKind;

    /// The `[devices.hexapod.modbus]` block of docs/hexapod.md.
    fn documented() -> String {
        let doc = include_str!("../../../docs/hexapod.md");
        let start = doc
            .find("```toml\n[devices.hexapod.modbus]")
            .expect("toml block")
            + 8;
        let len = doc[start..].find("```").expect("block end");
        doc[start..start + len].to_string()
    }

    fn parse(text: &str) -> Result<ModbusHexapodConfig, String> {
        let table: toml::Table = text.parse().map_err(|e| format!("{e}"))?;
        table["devices"]["hexapod"]["modbus"]
            .clone()
            .try_into()
            .map_err(|e: toml::de::Error| e.to_string())
    }

    #[test]
    fn documented_config_parses_and_validates() {
        let cfg = parse(&documented()).expect("documented config parses");
        cfg.validate().expect("documented config validates");
        assert_eq!(
            cfg.transport,
            Some(ModbusTransport::Tcp {
                address: "192.168.0.30:502".parse().expect("addr")
            })
        );
        assert_eq!(cfg.map.legs.kind, RegisterKind::Input);
        assert_eq!(cfg.map.pose_target.block_words(), 12);
        let bad = documented().replace("retries = 2", "retries = 2\nretry = 1");
        assert!(parse(&bad).is_err());
        let mut c = cfg.clone();
        c.poll_interval_s = -1.0;
        assert!(c.validate().is_err());
    }
}
