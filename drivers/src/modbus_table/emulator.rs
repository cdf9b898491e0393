//! Modbus rotary-table emulator: the table's registers on the shared Modbus register server
//! (loopback TCP or a pty, RTU), values from a `TableSource`, with seeded fault injection.

use std::io;
use std::net::SocketAddr;

use serde::{Deserialize, Serialize};
use tokio_modbus::ExceptionCode;

use super::map::{RegisterKind, RegisterMap};
pub use crate::modbus::server::ModbusFaults as ModbusTableFaults;
use crate::modbus::server::{RegisterBank, RegisterDevice, RegisterServer};

/// The table behind the emulated controller: told the commanded angle, asked the encoder
/// angle. Times are seconds since the emulator started; angles are radians.
pub trait TableSource: Send {
    /// A go command for `target_rad` was accepted at `t_s`.
    fn command(&mut self, target_rad: f64, t_s: f64);
    /// Encoder angle at `t_s`, and whether the table is settled in position.
    fn angle(&mut self, t_s: f64) -> (f64, bool);
}

/// Constant-speed rotation, then in position after a settle time.
#[derive(Debug, Clone)]
pub struct KinematicTable {
    pub speed_rad_s: f64,
    pub settle_s: f64,
    from_rad: f64,
    to_rad: f64,
    t0_s: f64,
    duration_s: f64,
}

impl KinematicTable {
    pub fn new(start_rad: f64, speed_rad_s: f64, settle_s: f64) -> Self {
        Self {
            speed_rad_s,
            settle_s,
            from_rad: start_rad,
            to_rad: start_rad,
            t0_s: 0.0,
            duration_s: 0.0,
        }
    }
}

impl TableSource for KinematicTable {
    fn command(&mut self, target_rad: f64, t_s: f64) {
        let (here, _) = self.angle(t_s);
        self.from_rad = here;
        self.to_rad = target_rad;
        self.t0_s = t_s;
        self.duration_s = if self.speed_rad_s > 0.0 {
            (target_rad - here).abs() / self.speed_rad_s
        } else {
            0.0
        };
    }

    fn angle(&mut self, t_s: f64) -> (f64, bool) {
        let dt = t_s - self.t0_s;
        if dt >= self.duration_s {
            return (self.to_rad, dt >= self.duration_s + self.settle_s);
        }
        let f = (dt / self.duration_s).max(0.0);
        (self.from_rad + f * (self.to_rad - self.from_rad), false)
    }
}

/// The emulator's register map and faults.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModbusTableEmulatorConfig {
    pub map: RegisterMap,
    #[serde(default)]
    pub faults: ModbusTableFaults,
}

/// What the emulator saw and did.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ModbusTableEmulatorStats {
    pub connections: u64,
    pub requests: u64,
    pub dropped: u64,
    pub exceptions: u64,
    pub go_commands: u64,
    /// Last commanded target, radians.
    pub last_target_rad: Option<f64>,
}

/// The table's part of the register server: target and actual angle registers.
struct TableDevice {
    map: RegisterMap,
    source: Box<dyn TableSource>,
    last_target_rad: Option<f64>,
}

impl RegisterDevice for TableDevice {
    fn registers(&self) -> Vec<(RegisterKind, u16, u16)> {
        let m = &self.map;
        vec![
            (m.target.kind, m.target.address, m.target.words()),
            (m.actual.kind, m.actual.address, m.actual.words()),
        ]
    }

    fn writable(&self, a: u16) -> bool {
        let t = &self.map.target;
        (t.address..t.address + t.words()).contains(&a)
    }

    fn refresh(&mut self, bank: &mut RegisterBank, t_s: f64) -> bool {
        let (angle, in_pos) = self.source.angle(t_s);
        let actual = &self.map.actual;
        let words = actual
            .encode_rad(angle)
            .unwrap_or_else(|_| actual.encode_counts(0));
        bank.put(actual.kind, actual.address, &words);
        in_pos
    }

    fn go(&mut self, bank: &mut RegisterBank, t_s: f64) -> Result<(), ExceptionCode> {
        let target = &self.map.target;
        let tw = bank.read(RegisterKind::Holding, target.address, target.words())?;
        let target_rad = target
            .decode_rad(&tw)
            .ok_or(ExceptionCode::ServerDeviceFailure)?;
        self.last_target_rad = Some(target_rad);
        self.source.command(target_rad, t_s);
        Ok(())
    }
}

/// A running emulator; stops when dropped.
pub struct ModbusTableEmulator {
    server: RegisterServer<TableDevice>,
}

impl ModbusTableEmulator {
    fn parts(
        cfg: ModbusTableEmulatorConfig,
        source: Box<dyn TableSource>,
    ) -> io::Result<(TableDevice, crate::modbus::Handshake, ModbusTableFaults)> {
        cfg.map
            .validate()
            .map_err(|m| io::Error::new(io::ErrorKind::InvalidInput, m))?;
        let hs = cfg.map.handshake();
        let device = TableDevice {
            map: cfg.map,
            source,
            last_target_rad: None,
        };
        Ok((device, hs, cfg.faults))
    }

    /// Serve Modbus TCP on 127.0.0.1 at a free port (see `addr()`).
    pub async fn start_tcp(
        cfg: ModbusTableEmulatorConfig,
        source: Box<dyn TableSource>,
    ) -> io::Result<Self> {
        let (device, hs, faults) = Self::parts(cfg, source)?;
        let server = RegisterServer::start_tcp(device, hs, faults).await?;
        Ok(Self { server })
    }

    /// Serve Modbus RTU on a serial stream (the master side of a pty pair). The server
    /// answers every unit id's frames that match the map's; an undecodable frame ends it.
    pub fn start_rtu(
        cfg: ModbusTableEmulatorConfig,
        source: Box<dyn TableSource>,
        serial: tokio_serial::SerialStream,
    ) -> io::Result<Self> {
        let (device, hs, faults) = Self::parts(cfg, source)?;
        let server = RegisterServer::start_rtu(device, hs, faults, serial)?;
        Ok(Self { server })
    }

    /// The TCP address served (None for RTU).
    pub fn addr(&self) -> Option<SocketAddr> {
        self.server.addr()
    }

    pub fn stats(&self) -> ModbusTableEmulatorStats {
        let s = self.server.stats();
        ModbusTableEmulatorStats {
            connections: s.connections,
            requests: s.requests,
            dropped: s.dropped,
            exceptions: s.exceptions,
            go_commands: s.go_commands,
            last_target_rad: self.server.with_device(|d| d.last_target_rad),
        }
    }

    /// Set or clear the fault bit now (with the configured fault code).
    pub fn set_fault(&self, on: bool) {
        self.server.set_fault(on);
    }
}
