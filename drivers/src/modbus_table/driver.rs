//! Modbus rotary-table driver (TCP or RTU via tokio-modbus): owns the connection and the
//! timing (per-call timeouts, reconnect and retry, ack handshake, rate-limited polling).

use std::borrow::Cow;
use std::net::SocketAddr;
use std::time::Duration;

use async_trait::async_trait;
use serde::{Deserialize, Serialize};
use tokio::time::Instant;
use tokio_modbus::client::{Client as _, Context};
use tokio_modbus::{ExceptionCode, Request, Response, Slave};

use super::map::{RegisterKind, RegisterMap};
use crate::serial::check_seconds;
use crate::traits::{DeviceError, LinkFault, RotaryState, RotaryTable};

/// Where the table is reached.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum ModbusTransport {
    /// Modbus TCP, e.g. `address = "192.168.0.20:502"`.
    Tcp { address: SocketAddr },
    /// Modbus RTU on a serial port (8N1).
    Rtu {
        port: String,
        #[serde(default = "default_baud")]
        baud: u32,
    },
}

fn default_baud() -> u32 {
    19_200
}

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
fn default_timeout_s() -> f64 {
    0.5
}
fn default_retries() -> u32 {
    2
}
fn default_ack_timeout_s() -> f64 {
    2.0
}
fn default_poll_interval_s() -> f64 {
    0.05
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

    /// Reject values the driver cannot work with.
    pub fn validate(&self) -> Result<(), DeviceError> {
        check_seconds(&self.id, "timeout_s", self.timeout_s)?;
        check_seconds(&self.id, "ack_timeout_s", self.ack_timeout_s)?;
        check_seconds(&self.id, "poll_interval_s", self.poll_interval_s)?;
        if self.timeout_s <= 0.0 {
            return Err(self.bad("timeout_s must be positive".into()));
        }
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

/// Counters of what happened on the link, for diagnosis and tests.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ModbusTableStats {
    pub requests: u64,
    pub timeouts: u64,
    pub reconnects: u64,
    pub exceptions: u64,
    pub status_polls: u64,
}

#[derive(Debug, Clone)]
enum Link {
    Tcp(SocketAddr),
    Rtu { port: String, baud: u32 },
}

/// A rotary table driven over Modbus with a configured register map.
pub struct ModbusTable {
    cfg: ModbusTableConfig,
    link: Link,
    ctx: Option<Context>,
    last_poll: Option<Instant>,
    last_state: Option<RotaryState>,
    stats: ModbusTableStats,
    /// Reconnects already reported by `take_link_faults`.
    reported_reconnects: u64,
    /// Why the last connection was dropped.
    last_drop: String,
}

impl ModbusTable {
    /// Connect as the config's `transport` says.
    pub async fn connect(cfg: ModbusTableConfig) -> Result<Self, DeviceError> {
        match cfg.transport.clone() {
            Some(ModbusTransport::Tcp { address }) => Self::connect_tcp(address, cfg).await,
            Some(ModbusTransport::Rtu { port, baud }) => Self::open_rtu(&port, baud, cfg).await,
            None => Err(cfg.bad("no transport configured".into())),
        }
    }

    /// Modbus TCP to `address`.
    pub async fn connect_tcp(
        address: SocketAddr,
        cfg: ModbusTableConfig,
    ) -> Result<Self, DeviceError> {
        Self::start(Link::Tcp(address), cfg).await
    }

    /// Modbus RTU on the serial port `port` at `baud` (8N1).
    pub async fn open_rtu(
        port: &str,
        baud: u32,
        cfg: ModbusTableConfig,
    ) -> Result<Self, DeviceError> {
        Self::start(
            Link::Rtu {
                port: port.to_string(),
                baud,
            },
            cfg,
        )
        .await
    }

    async fn start(link: Link, cfg: ModbusTableConfig) -> Result<Self, DeviceError> {
        cfg.validate()?;
        let mut table = Self {
            cfg,
            link,
            ctx: None,
            last_poll: None,
            last_state: None,
            stats: ModbusTableStats::default(),
            reported_reconnects: 0,
            last_drop: String::new(),
        };
        let ctx = open_link(
            table.link.clone(),
            table.cfg.map.unit_id,
            table.cfg.timeout_s,
        )
        .await
        .map_err(|message| DeviceError::Disconnected {
            device: table.cfg.id.clone(),
            message,
        })?;
        table.ctx = Some(ctx);
        Ok(table)
    }

    pub fn config(&self) -> &ModbusTableConfig {
        &self.cfg
    }

    pub fn stats(&self) -> ModbusTableStats {
        self.stats
    }

    fn timeout(&self) -> Duration {
        Duration::from_secs_f64(self.cfg.timeout_s)
    }

    /// One request with timeout, reconnect and retry. Exceptions are not retried (except
    /// "server device busy"); they come back as `Rejected` naming the exception and `what`.
    async fn call(&mut self, what: &str, req: Request<'static>) -> Result<Response, DeviceError> {
        let mut last_err = String::new();
        let mut all_timeouts = true;
        for _attempt in 0..=self.cfg.retries {
            if self.ctx.is_none() {
                self.stats.reconnects += 1;
                match open_link(self.link.clone(), self.cfg.map.unit_id, self.cfg.timeout_s).await {
                    Ok(c) => self.ctx = Some(c),
                    Err(e) => {
                        all_timeouts = false;
                        last_err = e;
                        continue;
                    }
                }
            }
            let timeout = self.timeout();
            let Some(ctx) = self.ctx.as_mut() else {
                continue;
            };
            self.stats.requests += 1;
            match tokio::time::timeout(timeout, ctx.call(req.clone())).await {
                Ok(Ok(Ok(resp))) => return Ok(resp),
                Ok(Ok(Err(exc))) => {
                    self.stats.exceptions += 1;
                    if exc == ExceptionCode::ServerDeviceBusy {
                        all_timeouts = false;
                        last_err = format!("device busy while {what}");
                        tokio::time::sleep(Duration::from_secs_f64(self.cfg.poll_interval_s)).await;
                        continue;
                    }
                    return Err(DeviceError::Rejected {
                        device: self.cfg.id.clone(),
                        message: format!(
                            "Modbus exception {exc:?} (code {}, {exc}) while {what}",
                            u8::from(exc)
                        ),
                    });
                }
                Ok(Err(e)) => {
                    // Transport or framing error: the context may be desynchronised.
                    all_timeouts = false;
                    last_err = format!("{e} while {what}");
                    self.last_drop.clone_from(&last_err);
                    self.ctx = None;
                }
                Err(_) => {
                    // A late reply would be taken for the next request's: reconnect.
                    self.stats.timeouts += 1;
                    last_err = format!("no reply while {what}");
                    self.last_drop.clone_from(&last_err);
                    self.ctx = None;
                }
            }
        }
        if all_timeouts {
            Err(DeviceError::Timeout {
                device: self.cfg.id.clone(),
                what: format!("{what} ({} attempts)", self.cfg.retries + 1),
                after_s: self.cfg.timeout_s,
            })
        } else {
            Err(DeviceError::Disconnected {
                device: self.cfg.id.clone(),
                message: last_err,
            })
        }
    }

    fn protocol(&self, message: String) -> DeviceError {
        DeviceError::Protocol {
            device: self.cfg.id.clone(),
            message,
        }
    }

    /// Read `count` words of `kind` at `address`.
    async fn read(
        &mut self,
        kind: RegisterKind,
        address: u16,
        count: u16,
        name: &str,
    ) -> Result<Vec<u16>, DeviceError> {
        let what = format!(
            "reading {} register {address} ({name}, {count} word{})",
            kind.name(),
            if count == 1 { "" } else { "s" }
        );
        let req = match kind {
            RegisterKind::Holding => Request::ReadHoldingRegisters(address, count),
            RegisterKind::Input => Request::ReadInputRegisters(address, count),
        };
        let words = match self.call(&what, req).await? {
            Response::ReadHoldingRegisters(w) | Response::ReadInputRegisters(w) => w,
            other => return Err(self.protocol(format!("unexpected reply {other:?} while {what}"))),
        };
        if words.len() < usize::from(count) {
            return Err(self.protocol(format!(
                "{} words instead of {count} while {what}",
                words.len()
            )));
        }
        Ok(words[..usize::from(count)].to_vec())
    }

    /// Write holding registers (function 0x06 for one word, 0x10 for more).
    async fn write(
        &mut self,
        address: u16,
        words: Vec<u16>,
        name: &str,
    ) -> Result<(), DeviceError> {
        let what = format!("writing holding register {address} ({name}, {words:?})");
        let req = if let [w] = words[..] {
            Request::WriteSingleRegister(address, w)
        } else {
            Request::WriteMultipleRegisters(address, Cow::Owned(words))
        };
        match self.call(&what, req).await? {
            Response::WriteSingleRegister(..) | Response::WriteMultipleRegisters(..) => Ok(()),
            other => Err(self.protocol(format!("unexpected reply {other:?} while {what}"))),
        }
    }

    async fn read_status(&mut self) -> Result<u16, DeviceError> {
        let s = self.cfg.map.status.clone();
        self.stats.status_polls += 1;
        let w = self.read(s.kind, s.address, 1, "status").await?;
        let word = w.first().copied().unwrap_or(0);
        if s.fault(word) {
            return Err(self.fault_error(word).await);
        }
        Ok(word)
    }

    async fn fault_error(&mut self, status: u16) -> DeviceError {
        let code = match self.cfg.map.fault_code {
            Some(r) => match self.read(r.kind, r.address, 1, "fault code").await {
                Ok(w) => format!(", fault code {}", w.first().copied().unwrap_or(0)),
                Err(e) => format!(", fault code unreadable: {e}"),
            },
            None => String::new(),
        };
        DeviceError::Rejected {
            device: self.cfg.id.clone(),
            message: format!("table reports a fault (status word {status:#06x}){code}"),
        }
    }

    /// Read the encoder angle, radians.
    pub async fn read_encoder_rad(&mut self) -> Result<f64, DeviceError> {
        let a = self.cfg.map.actual.clone();
        let words = self
            .read(a.kind, a.address, a.words(), "actual angle")
            .await?;
        a.decode_rad(&words)
            .ok_or_else(|| self.protocol(format!("cannot decode actual angle from {words:?}")))
    }

    /// Read the commanded (target) angle back from the table, radians.
    pub async fn read_target_rad(&mut self) -> Result<f64, DeviceError> {
        let a = self.cfg.map.target.clone();
        let words = self
            .read(a.kind, a.address, a.words(), "target angle")
            .await?;
        a.decode_rad(&words)
            .ok_or_else(|| self.protocol(format!("cannot decode target angle from {words:?}")))
    }

    async fn wait_ack(&mut self) -> Result<(), DeviceError> {
        let deadline = Instant::now() + Duration::from_secs_f64(self.cfg.ack_timeout_s);
        let ack = self.cfg.map.ack_register();
        let in_status = self.cfg.map.ack.register.is_none();
        loop {
            let status = self.read_status().await?;
            let word = if in_status {
                status
            } else {
                let w = self.read(ack.kind, ack.address, 1, "acknowledge").await?;
                w.first().copied().unwrap_or(0)
            };
            if self.cfg.map.acknowledged(word) {
                return Ok(());
            }
            if Instant::now() >= deadline {
                return Err(DeviceError::Timeout {
                    device: self.cfg.id.clone(),
                    what: format!(
                        "acknowledge of the go command ({} register {})",
                        ack.kind.name(),
                        ack.address
                    ),
                    after_s: self.cfg.ack_timeout_s,
                });
            }
            tokio::time::sleep(Duration::from_secs_f64(self.cfg.poll_interval_s.max(0.002))).await;
        }
    }
}

/// Open a fresh client context on `link` (no `&self` across the await: `Context` is not
/// `Sync`).
async fn open_link(link: Link, unit_id: u8, timeout_s: f64) -> Result<Context, String> {
    let slave = Slave(unit_id);
    match &link {
        Link::Tcp(addr) => {
            match tokio::time::timeout(
                Duration::from_secs_f64(timeout_s),
                tokio_modbus::client::tcp::connect_slave(*addr, slave),
            )
            .await
            {
                Ok(Ok(ctx)) => Ok(ctx),
                Ok(Err(e)) => Err(format!("cannot connect to {addr}: {e}")),
                Err(_) => Err(format!(
                    "connecting to {addr} timed out after {} s",
                    timeout_s
                )),
            }
        }
        Link::Rtu { port, baud } => {
            let serial =
                crate::serial::open_8n1("modbus", port, *baud).map_err(|e| e.to_string())?;
            Ok(tokio_modbus::client::rtu::attach_slave(serial, slave))
        }
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
            .map_err(|m| DeviceError::Rejected {
                device: self.cfg.id.clone(),
                message: format!("target: {m}"),
            })?;
        self.last_state = None;
        self.last_poll = None;
        self.write(map.target.address, words, "target angle")
            .await?;
        self.write(
            map.command.address,
            vec![map.command.go_value],
            "go command",
        )
        .await?;
        self.wait_ack().await?;
        if let Some(clear) = map.command.clear_value {
            self.write(map.command.address, vec![clear], "clear command")
                .await?;
        }
        Ok(())
    }

    async fn state(&mut self) -> Result<RotaryState, DeviceError> {
        if let (Some(t), Some(s)) = (self.last_poll, self.last_state) {
            if t.elapsed().as_secs_f64() < self.cfg.poll_interval_s {
                return Ok(s);
            }
        }
        let status = self.read_status().await?;
        let st = &self.cfg.map.status;
        let state = if st.in_position(status) && !st.moving(status) {
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
        let new = self
            .stats
            .reconnects
            .saturating_sub(self.reported_reconnects);
        self.reported_reconnects = self.stats.reconnects;
        if new == 0 {
            return Vec::new();
        }
        vec![LinkFault {
            code: "reconnect".into(),
            message: format!(
                "reopened the Modbus connection {new} time(s) (last dropped: {})",
                self.last_drop
            ),
        }]
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
