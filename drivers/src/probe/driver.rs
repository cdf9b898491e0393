//! ASCII probe driver: owns the port and the timing (request, reply timeout, stale replies)
//! and implements `Probe` on top of the sans-I/O codec.

use std::collections::VecDeque;
use std::time::Duration;

use async_trait::async_trait;
use serde::{Deserialize, Serialize};
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::time::Instant;

use super::codec::{Framed, LineFramer, ProbeProtocol, ProbeReply, MAX_REPLY_BYTES};
use crate::traits::{DeviceError, Probe, ProbeReading};

/// How a request/response displacement sensor is reached and read. Defaults describe a
/// Keyence-style `M0` -> `M0,+00.1234` (mm) exchange.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProbeConfig {
    #[serde(default = "default_id")]
    pub id: String,
    /// Serial device path.
    pub port: String,
    #[serde(default = "default_baud")]
    pub baud: u32,
    /// Request sent for one reading, terminator included.
    #[serde(default = "default_command")]
    pub command: String,
    /// Regex a value reply matches; captures the number (group `value`, else group 1).
    #[serde(default = "default_value_pattern")]
    pub value_pattern: String,
    /// Regex an error reply matches; may capture a code (group `code`, else group 1).
    #[serde(default = "default_error_pattern")]
    pub error_pattern: Option<String>,
    /// Metres per device unit (1e-3 for a sensor that answers in mm).
    #[serde(default = "default_scale_to_m")]
    pub scale_to_m: f64,
    /// Longest wait for a reply, seconds.
    #[serde(default = "default_timeout_s")]
    pub timeout_s: f64,
}

fn default_id() -> String {
    "probe".into()
}
fn default_baud() -> u32 {
    9600
}
fn default_command() -> String {
    "M0\r".into()
}
fn default_value_pattern() -> String {
    r"^M0,(?P<value>[+-]?\d+(?:\.\d+)?)$".into()
}
fn default_error_pattern() -> Option<String> {
    Some(r"^ER,\w+,(?P<code>\d+)$".into())
}
fn default_scale_to_m() -> f64 {
    1e-3
}
fn default_timeout_s() -> f64 {
    0.5
}

impl Default for ProbeConfig {
    fn default() -> Self {
        Self {
            id: default_id(),
            port: String::new(),
            baud: default_baud(),
            command: default_command(),
            value_pattern: default_value_pattern(),
            error_pattern: default_error_pattern(),
            scale_to_m: default_scale_to_m(),
            timeout_s: default_timeout_s(),
        }
    }
}

impl ProbeConfig {
    /// The codec this config describes.
    pub fn protocol(&self) -> Result<ProbeProtocol, DeviceError> {
        ProbeProtocol::new(
            &self.command,
            &self.value_pattern,
            self.error_pattern.as_deref(),
            self.scale_to_m,
        )
        .map_err(|e| DeviceError::Protocol {
            device: self.id.clone(),
            message: e.to_string(),
        })
    }
}

/// A displacement sensor read by an ASCII request/response exchange.
pub struct AsciiProbe<S> {
    cfg: ProbeConfig,
    protocol: ProbeProtocol,
    io: S,
    framer: LineFramer,
    lines: VecDeque<String>,
    t0: Instant,
    stale_replies: u64,
}

impl AsciiProbe<tokio_serial::SerialStream> {
    /// Open the serial port named in the config.
    pub fn open(cfg: ProbeConfig) -> Result<Self, DeviceError> {
        let port = crate::serial::open_8n1(&cfg.id, &cfg.port, cfg.baud)?;
        Self::from_stream(port, cfg)
    }
}

impl<S: AsyncRead + AsyncWrite + Unpin + Send> AsciiProbe<S> {
    /// Read a sensor over any byte stream.
    pub fn from_stream(io: S, cfg: ProbeConfig) -> Result<Self, DeviceError> {
        crate::serial::check_seconds(&cfg.id, "timeout_s", cfg.timeout_s)?;
        Ok(Self {
            protocol: cfg.protocol()?,
            cfg,
            io,
            framer: LineFramer::new(MAX_REPLY_BYTES),
            lines: VecDeque::new(),
            t0: Instant::now(),
            stale_replies: 0,
        })
    }

    pub fn config(&self) -> &ProbeConfig {
        &self.cfg
    }

    /// Lines that arrived outside a request (late replies after a timeout), discarded.
    pub fn stale_replies(&self) -> u64 {
        self.stale_replies
    }

    fn disconnected(&self, message: String) -> DeviceError {
        DeviceError::Disconnected {
            device: self.cfg.id.clone(),
            message,
        }
    }

    fn take_bytes(&mut self, bytes: &[u8]) {
        for f in self.framer.push(bytes) {
            if let Framed::Line(l) = f {
                self.lines.push_back(l);
            }
        }
    }

    /// Drop what arrived since the last request: a late reply must not be taken for the
    /// answer to the next one.
    async fn drain(&mut self) -> Result<(), DeviceError> {
        let mut buf = [0u8; 128];
        loop {
            match tokio::time::timeout(Duration::ZERO, self.io.read(&mut buf)).await {
                Err(_) => break,
                Ok(Ok(0)) => return Err(self.disconnected("port closed by the device".into())),
                Ok(Ok(n)) => self.take_bytes(&buf[..n]),
                Ok(Err(e)) => return Err(self.disconnected(format!("read failed: {e}"))),
            }
        }
        self.stale_replies += self.lines.len() as u64;
        self.lines.clear();
        self.framer.clear();
        Ok(())
    }
}

#[async_trait]
impl<S: AsyncRead + AsyncWrite + Unpin + Send> Probe for AsciiProbe<S> {
    fn id(&self) -> &str {
        &self.cfg.id
    }

    async fn read(&mut self) -> Result<ProbeReading, DeviceError> {
        self.drain().await?;
        let sent = Instant::now();
        let request = self.protocol.request().to_vec();
        let w = async {
            self.io.write_all(&request).await?;
            self.io.flush().await
        }
        .await;
        w.map_err(|e| self.disconnected(format!("write failed: {e}")))?;
        let deadline = sent + Duration::from_secs_f64(self.cfg.timeout_s.max(0.0));
        let mut buf = [0u8; 128];
        let line = loop {
            if let Some(l) = self.lines.pop_front() {
                break l;
            }
            match tokio::time::timeout_at(deadline, self.io.read(&mut buf)).await {
                Err(_) => {
                    return Err(DeviceError::Timeout {
                        device: self.cfg.id.clone(),
                        what: format!("reply to `{}`", self.protocol.command_shown()),
                        after_s: self.cfg.timeout_s,
                    })
                }
                Ok(Ok(0)) => return Err(self.disconnected("port closed by the device".into())),
                Ok(Ok(n)) => self.take_bytes(&buf[..n]),
                Ok(Err(e)) => return Err(self.disconnected(format!("read failed: {e}"))),
            }
        };
        let received = Instant::now();
        match self.protocol.parse_line(&line) {
            ProbeReply::Value { value_m, .. } => {
                // The sensor stamps nothing: the midpoint of request and reply is the best
                // estimate of when it measured.
                let mid = sent + (received - sent) / 2;
                Ok(ProbeReading {
                    t_s: (mid - self.t0).as_secs_f64(),
                    value_m,
                })
            }
            ProbeReply::Error { code, line } => Err(DeviceError::Rejected {
                device: self.cfg.id.clone(),
                message: format!(
                    "error reply `{line}` (code {code}) to `{}`",
                    self.protocol.command_shown()
                ),
            }),
            ProbeReply::Unrecognised(line) => Err(DeviceError::Protocol {
                device: self.cfg.id.clone(),
                message: format!(
                    "unrecognised reply {line:?} to `{}`",
                    self.protocol.command_shown()
                ),
            }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn config_defaults_and_unknown_keys() {
        let c: ProbeConfig = serde_json::from_str(r#"{"port": "/dev/ttyS0"}"#).expect("config");
        assert_eq!(c.command, "M0\r");
        assert!(c.protocol().is_ok());
        assert!(serde_json::from_str::<ProbeConfig>(r#"{"port": "p", "scale": 1}"#).is_err());
        let bad = ProbeConfig {
            value_pattern: "no group".into(),
            ..ProbeConfig::default()
        };
        assert!(AsciiProbe::from_stream(tokio::io::empty(), bad).is_err());
    }
}
