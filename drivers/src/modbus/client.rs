//! The client side of a Modbus device (TCP or RTU via tokio-modbus): owns the connection and
//! the timing (per-call timeouts, reconnect and retry, status and go/ack handshake).

use std::borrow::Cow;
use std::net::SocketAddr;
use std::time::Duration;

use serde::{Deserialize, Serialize};
use tokio::time::Instant;
use tokio_modbus::client::{Client as _, Context};
use tokio_modbus::{ExceptionCode, Request, Response, Slave};

use super::registers::{Handshake, RegisterKind};
use crate::traits::{DeviceError, LinkFault};

/// Where the device is reached.
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

pub(crate) fn default_baud() -> u32 {
    19_200
}

impl ModbusTransport {
    /// For messages: "Modbus TCP 1.2.3.4:502" / "Modbus RTU /dev/ttyUSB1 at 19200 Bd".
    pub fn describe(&self) -> String {
        match self {
            ModbusTransport::Tcp { address } => format!("Modbus TCP {address}"),
            ModbusTransport::Rtu { port, baud } => format!("Modbus RTU {port} at {baud} Bd"),
        }
    }
}

/// The timing settings of a Modbus driver (validated by its config).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ModbusTiming {
    /// Longest wait for one reply (and for a TCP connect), seconds.
    pub timeout_s: f64,
    /// Extra attempts after a timeout or transport error (each after a reconnect).
    pub retries: u32,
    /// Longest wait for the acknowledge of a go command, seconds.
    pub ack_timeout_s: f64,
    /// Minimum time between two status polls, seconds.
    pub poll_interval_s: f64,
}

/// Counters of what happened on the link, for diagnosis and tests.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ModbusStats {
    pub requests: u64,
    pub timeouts: u64,
    pub reconnects: u64,
    pub exceptions: u64,
    pub status_polls: u64,
}

/// One Modbus connection with geocal's timing rules: every request under a timeout; after a
/// timeout or transport error the connection is dropped (a late reply would desynchronise
/// it) and reopened by the next attempt.
pub struct ModbusClient {
    id: String,
    transport: ModbusTransport,
    unit_id: u8,
    timing: ModbusTiming,
    ctx: Option<Context>,
    stats: ModbusStats,
    /// Reconnects already reported by `take_link_faults`.
    reported_reconnects: u64,
    /// Why the last connection was dropped.
    last_drop: String,
}

impl ModbusClient {
    /// Connect to `transport` as device `id` (the name in errors).
    pub async fn connect(
        id: &str,
        transport: ModbusTransport,
        unit_id: u8,
        timing: ModbusTiming,
    ) -> Result<Self, DeviceError> {
        let mut client = Self {
            id: id.to_string(),
            transport,
            unit_id,
            timing,
            ctx: None,
            stats: ModbusStats::default(),
            reported_reconnects: 0,
            last_drop: String::new(),
        };
        let ctx = open_link(client.transport.clone(), unit_id, timing.timeout_s)
            .await
            .map_err(|message| DeviceError::Disconnected {
                device: client.id.clone(),
                message,
            })?;
        client.ctx = Some(ctx);
        Ok(client)
    }

    pub fn id(&self) -> &str {
        &self.id
    }

    pub fn stats(&self) -> ModbusStats {
        self.stats
    }

    pub fn timing(&self) -> ModbusTiming {
        self.timing
    }

    /// A `Protocol` error of this device.
    pub fn protocol(&self, message: String) -> DeviceError {
        DeviceError::Protocol {
            device: self.id.clone(),
            message,
        }
    }

    /// A `Rejected` error of this device.
    pub fn rejected(&self, message: String) -> DeviceError {
        DeviceError::Rejected {
            device: self.id.clone(),
            message,
        }
    }

    /// One request with timeout, reconnect and retry. Exceptions are not retried (except
    /// "server device busy"); they come back as `Rejected` naming the exception and `what`.
    pub async fn call(
        &mut self,
        what: &str,
        req: Request<'static>,
    ) -> Result<Response, DeviceError> {
        let mut last_err = String::new();
        let mut all_timeouts = true;
        for _attempt in 0..=self.timing.retries {
            if self.ctx.is_none() {
                self.stats.reconnects += 1;
                match open_link(self.transport.clone(), self.unit_id, self.timing.timeout_s).await {
                    Ok(c) => self.ctx = Some(c),
                    Err(e) => {
                        all_timeouts = false;
                        last_err = e;
                        continue;
                    }
                }
            }
            let timeout = Duration::from_secs_f64(self.timing.timeout_s);
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
                        tokio::time::sleep(Duration::from_secs_f64(self.timing.poll_interval_s))
                            .await;
                        continue;
                    }
                    return Err(self.rejected(format!(
                        "Modbus exception {exc:?} (code {}, {exc}) while {what}",
                        u8::from(exc)
                    )));
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
                device: self.id.clone(),
                what: format!("{what} ({} attempts)", self.timing.retries + 1),
                after_s: self.timing.timeout_s,
            })
        } else {
            Err(DeviceError::Disconnected {
                device: self.id.clone(),
                message: last_err,
            })
        }
    }

    /// Read `count` words of `kind` at `address`.
    pub async fn read(
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
    pub async fn write(
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

    /// Read the status word; a set fault bit is `Rejected` with the fault code if mapped.
    pub async fn read_status(&mut self, hs: &Handshake) -> Result<u16, DeviceError> {
        let s = &hs.status;
        self.stats.status_polls += 1;
        let w = self.read(s.kind, s.address, 1, "status").await?;
        let word = w.first().copied().unwrap_or(0);
        if s.fault(word) {
            let code = match hs.fault_code {
                Some(r) => match self.read(r.kind, r.address, 1, "fault code").await {
                    Ok(w) => format!(", fault code {}", w.first().copied().unwrap_or(0)),
                    Err(e) => format!(", fault code unreadable: {e}"),
                },
                None => String::new(),
            };
            return Err(self.rejected(format!(
                "device reports a fault (status word {word:#06x}){code}"
            )));
        }
        Ok(word)
    }

    /// Write `go_value`, wait for the acknowledge, then write `clear_value` if given (the
    /// target was written before).
    pub async fn go(&mut self, hs: &Handshake) -> Result<(), DeviceError> {
        self.write(hs.command.address, vec![hs.command.go_value], "go command")
            .await?;
        self.wait_ack(hs).await?;
        if let Some(clear) = hs.command.clear_value {
            self.write(hs.command.address, vec![clear], "clear command")
                .await?;
        }
        Ok(())
    }

    async fn wait_ack(&mut self, hs: &Handshake) -> Result<(), DeviceError> {
        let deadline = Instant::now() + Duration::from_secs_f64(self.timing.ack_timeout_s);
        let ack = hs.ack_register();
        let in_status = hs.ack.register.is_none();
        loop {
            let status = self.read_status(hs).await?;
            let word = if in_status {
                status
            } else {
                let w = self.read(ack.kind, ack.address, 1, "acknowledge").await?;
                w.first().copied().unwrap_or(0)
            };
            if hs.acknowledged(word) {
                return Ok(());
            }
            if Instant::now() >= deadline {
                return Err(DeviceError::Timeout {
                    device: self.id.clone(),
                    what: format!(
                        "acknowledge of the go command ({} register {})",
                        ack.kind.name(),
                        ack.address
                    ),
                    after_s: self.timing.ack_timeout_s,
                });
            }
            tokio::time::sleep(Duration::from_secs_f64(
                self.timing.poll_interval_s.max(0.002),
            ))
            .await;
        }
    }

    /// Connections reopened (after a timeout or a transport error) since the last call.
    pub fn take_link_faults(&mut self) -> Vec<LinkFault> {
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

/// Open a fresh client context on `transport` (no `&self` across the await: `Context` is
/// not `Sync`).
async fn open_link(
    transport: ModbusTransport,
    unit_id: u8,
    timeout_s: f64,
) -> Result<Context, String> {
    let slave = Slave(unit_id);
    match &transport {
        ModbusTransport::Tcp { address } => {
            match tokio::time::timeout(
                Duration::from_secs_f64(timeout_s),
                tokio_modbus::client::tcp::connect_slave(*address, slave),
            )
            .await
            {
                Ok(Ok(ctx)) => Ok(ctx),
                Ok(Err(e)) => Err(format!("cannot connect to {address}: {e}")),
                Err(_) => Err(format!(
                    "connecting to {address} timed out after {timeout_s} s"
                )),
            }
        }
        ModbusTransport::Rtu { port, baud } => {
            let serial =
                crate::serial::open_8n1("modbus", port, *baud).map_err(|e| e.to_string())?;
            Ok(tokio_modbus::client::rtu::attach_slave(serial, slave))
        }
    }
}
