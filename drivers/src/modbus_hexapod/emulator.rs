//! Modbus hexapod emulator: the controller's registers on the shared Modbus register server
//! (loopback TCP or a pty, RTU), values from a `HexapodSource`, with seeded fault injection.

use std::io;
use std::net::SocketAddr;

use tokio_modbus::ExceptionCode;

use super::map::HexapodRegisterMap;
use crate::modbus::server::{
    ModbusFaults, RegisterBank, RegisterDevice, RegisterServer, ServerStats,
};
use crate::modbus::RegisterKind;
use crate::traits::PlatformPose;

/// The machine behind the emulated controller: told each commanded pose, asked whether it is
/// in position and what its leg encoders read. Times are seconds since the emulator started.
pub trait HexapodSource: Send {
    /// A go command for `pose` was accepted at `t_s`.
    fn command(&mut self, pose: PlatformPose, t_s: f64);
    /// Whether the platform is at rest at the commanded pose at `t_s`.
    fn in_position(&mut self, t_s: f64) -> bool;
    /// The six leg encoders at `t_s` (one sample each, taken when the registers are read),
    /// metres.
    fn legs(&mut self, t_s: f64) -> [f64; 6];
}

struct HexapodDevice {
    map: HexapodRegisterMap,
    source: Box<dyn HexapodSource>,
    last_target: Option<PlatformPose>,
}

impl RegisterDevice for HexapodDevice {
    fn registers(&self) -> Vec<(RegisterKind, u16, u16)> {
        let m = &self.map;
        vec![
            (
                RegisterKind::Holding,
                m.pose_target.address,
                m.pose_target.block_words(),
            ),
            (m.legs.kind, m.legs.address, m.legs.block_words()),
        ]
    }

    fn writable(&self, a: u16) -> bool {
        let p = &self.map.pose_target;
        (u32::from(p.address)..u32::from(p.address) + u32::from(p.block_words()))
            .contains(&u32::from(a))
    }

    fn refresh(&mut self, _bank: &mut RegisterBank, t_s: f64) -> bool {
        self.source.in_position(t_s)
    }

    /// The encoders are sampled when their registers are read (one sample per read).
    fn before_read(
        &mut self,
        bank: &mut RegisterBank,
        kind: RegisterKind,
        address: u16,
        count: u16,
        t_s: f64,
    ) {
        let l = &self.map.legs;
        let (a, b) = (u32::from(address), u32::from(address) + u32::from(count));
        let (la, lb) = (
            u32::from(l.address),
            u32::from(l.address) + u32::from(l.block_words()),
        );
        if kind != l.kind || b <= la || lb <= a {
            return;
        }
        // Out of the register's range: the counter shows 0.
        let words = l
            .encode(&self.source.legs(t_s))
            .unwrap_or_else(|_| vec![0; usize::from(l.block_words())]);
        bank.put(l.kind, l.address, &words);
    }

    fn go(&mut self, bank: &mut RegisterBank, t_s: f64) -> Result<(), ExceptionCode> {
        let p = &self.map.pose_target;
        let words = bank.read(RegisterKind::Holding, p.address, p.block_words())?;
        let pose = p.decode(&words).ok_or(ExceptionCode::ServerDeviceFailure)?;
        self.last_target = Some(pose);
        self.source.command(pose, t_s);
        Ok(())
    }
}

/// A running emulated hexapod controller; stops when dropped.
pub struct ModbusHexapodEmulator {
    server: RegisterServer<HexapodDevice>,
}

fn device(map: &HexapodRegisterMap, source: Box<dyn HexapodSource>) -> io::Result<HexapodDevice> {
    map.validate()
        .map_err(|m| io::Error::new(io::ErrorKind::InvalidInput, m))?;
    Ok(HexapodDevice {
        map: map.clone(),
        source,
        last_target: None,
    })
}

impl ModbusHexapodEmulator {
    /// Serve Modbus TCP on 127.0.0.1 at a free port (see `addr()`).
    pub async fn start_tcp(
        map: &HexapodRegisterMap,
        faults: ModbusFaults,
        source: Box<dyn HexapodSource>,
    ) -> io::Result<Self> {
        let server =
            RegisterServer::start_tcp(device(map, source)?, map.handshake(), faults).await?;
        Ok(Self { server })
    }

    /// Serve Modbus RTU on a serial stream (the master side of a pty pair).
    pub fn start_rtu(
        map: &HexapodRegisterMap,
        faults: ModbusFaults,
        source: Box<dyn HexapodSource>,
        serial: tokio_serial::SerialStream,
    ) -> io::Result<Self> {
        let server =
            RegisterServer::start_rtu(device(map, source)?, map.handshake(), faults, serial)?;
        Ok(Self { server })
    }

    /// The TCP address served (None for RTU).
    pub fn addr(&self) -> Option<SocketAddr> {
        self.server.addr()
    }

    pub fn stats(&self) -> ServerStats {
        self.server.stats()
    }

    /// The last commanded pose as the controller decoded it from its registers.
    pub fn last_target(&self) -> Option<PlatformPose> {
        self.server.with_device(|d| d.last_target)
    }

    /// Set or clear the fault bit now (with the configured fault code).
    pub fn set_fault(&self, on: bool) {
        self.server.set_fault(on);
    }
}
