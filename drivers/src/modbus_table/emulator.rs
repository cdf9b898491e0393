//! Modbus rotary-table emulator: the device side of a register map on loopback TCP (or a
//! pty, RTU), values from a `TableSource`, with seeded fault injection.

use std::collections::BTreeMap;
use std::io;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex, MutexGuard};

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use tokio::net::TcpListener;
use tokio::task::JoinHandle;
use tokio::time::Instant;
use tokio_modbus::server::tcp::{accept_tcp_connection, Server};
use tokio_modbus::{ExceptionCode, Request, Response, SlaveRequest};

use super::map::{RegisterKind, RegisterMap};

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

/// Faults the emulator injects; requests are counted from 1 over all connections.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ModbusTableFaults {
    /// Seed of the generator behind the probabilities.
    pub seed: u64,
    /// Probability that a request gets no answer (the client times out).
    pub drop_probability: f64,
    /// Requests that get no answer (the request is still not executed).
    pub drop_at_requests: Vec<u64>,
    /// Requests answered with exception `exception_code` (once each: a retry is a new request).
    pub exception_at_requests: Vec<u64>,
    /// Modbus exception code, e.g. 2 = IllegalDataAddress, 4 = ServerDeviceFailure.
    pub exception_code: u8,
    /// From this time on (seconds since start) the fault bit is set and `fault_code` shown.
    pub fault_at_s: Option<f64>,
    /// From the go command with this number (from 1) on, the fault bit is set.
    pub fault_at_go: Option<u64>,
    pub fault_code: u16,
    /// At this request the device goes silent for `silence_s` seconds (no answers).
    pub silence_at_request: Option<u64>,
    pub silence_s: f64,
}

impl Default for ModbusTableFaults {
    fn default() -> Self {
        Self {
            seed: 0,
            drop_probability: 0.0,
            drop_at_requests: Vec::new(),
            exception_at_requests: Vec::new(),
            exception_code: 4,
            fault_at_s: None,
            fault_at_go: None,
            fault_code: 1,
            silence_at_request: None,
            silence_s: 0.0,
        }
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

struct Device {
    map: RegisterMap,
    faults: ModbusTableFaults,
    rng: ChaCha8Rng,
    source: Box<dyn TableSource>,
    start: Instant,
    holding: BTreeMap<u16, u16>,
    input: BTreeMap<u16, u16>,
    acked: bool,
    fault: bool,
    silent_until_s: f64,
    stats: ModbusTableEmulatorStats,
}

impl Device {
    fn new(cfg: ModbusTableEmulatorConfig, source: Box<dyn TableSource>) -> Self {
        let map = cfg.map;
        let mut holding = BTreeMap::new();
        let mut input = BTreeMap::new();
        let mut add = |kind: RegisterKind, address: u16, words: u16| {
            let table = match kind {
                RegisterKind::Holding => &mut holding,
                RegisterKind::Input => &mut input,
            };
            for k in 0..words {
                table.insert(address.wrapping_add(k), 0u16);
            }
        };
        add(map.target.kind, map.target.address, map.target.words());
        add(map.actual.kind, map.actual.address, map.actual.words());
        add(map.status.kind, map.status.address, 1);
        add(RegisterKind::Holding, map.command.address, 1);
        if let Some(r) = map.ack.register {
            add(r.kind, r.address, 1);
        }
        if let Some(r) = map.fault_code {
            add(r.kind, r.address, 1);
        }
        Self {
            rng: ChaCha8Rng::seed_from_u64(cfg.faults.seed),
            faults: cfg.faults,
            map,
            source,
            start: Instant::now(),
            holding,
            input,
            acked: false,
            fault: false,
            silent_until_s: f64::NEG_INFINITY,
            stats: ModbusTableEmulatorStats::default(),
        }
    }

    fn table(&mut self, kind: RegisterKind) -> &mut BTreeMap<u16, u16> {
        match kind {
            RegisterKind::Holding => &mut self.holding,
            RegisterKind::Input => &mut self.input,
        }
    }

    fn put(&mut self, kind: RegisterKind, address: u16, words: &[u16]) {
        let t = self.table(kind);
        for (k, w) in words.iter().enumerate() {
            t.insert(address.wrapping_add(k as u16), *w);
        }
    }

    /// Bring the actual angle, status, ack and fault registers up to date.
    fn refresh(&mut self, t_s: f64) {
        if self.faults.fault_at_s.is_some_and(|f| t_s >= f) {
            self.fault = true;
        }
        let (angle, in_pos) = self.source.angle(t_s);
        let actual = self.map.actual.clone();
        let words = match actual.encode_rad(angle) {
            Ok(w) => w,
            Err(_) => actual.encode_counts(0),
        };
        self.put(actual.kind, actual.address, &words);
        let st = self.map.status.clone();
        let mut status = 0u16;
        if in_pos {
            status |= 1 << st.in_position_bit;
        }
        if let Some(b) = st.moving_bit {
            if !in_pos {
                status |= 1 << b;
            }
        }
        if self.fault {
            status |= 1 << st.fault_bit;
        }
        match self.map.ack.register {
            None => {
                if let (Some(b), true) = (self.map.ack.bit, self.acked) {
                    status |= 1 << b;
                }
            }
            Some(r) => {
                let w = match (self.map.ack.bit, self.map.ack.value, self.acked) {
                    (_, _, false) => 0,
                    (Some(b), _, true) => 1 << b,
                    (None, Some(v), true) => v,
                    (None, None, true) => 0,
                };
                self.put(r.kind, r.address, &[w]);
            }
        }
        self.put(st.kind, st.address, &[status]);
        if let Some(r) = self.map.fault_code {
            let code = if self.fault {
                self.faults.fault_code
            } else {
                0
            };
            self.put(r.kind, r.address, &[code]);
        }
    }

    fn read(
        &mut self,
        kind: RegisterKind,
        address: u16,
        count: u16,
    ) -> Result<Vec<u16>, ExceptionCode> {
        let t = self.table(kind);
        (0..count)
            .map(|k| {
                address
                    .checked_add(k)
                    .and_then(|a| t.get(&a).copied())
                    .ok_or(ExceptionCode::IllegalDataAddress)
            })
            .collect()
    }

    fn write(&mut self, address: u16, words: &[u16], t_s: f64) -> Result<(), ExceptionCode> {
        let target = self.map.target.clone();
        let cmd = self.map.command.clone();
        let writable = |a: u16| {
            a == cmd.address || (target.address..target.address + target.words()).contains(&a)
        };
        for k in 0..words.len() {
            let a = address
                .checked_add(k as u16)
                .ok_or(ExceptionCode::IllegalDataAddress)?;
            if !writable(a) {
                return Err(ExceptionCode::IllegalDataAddress);
            }
        }
        self.put(RegisterKind::Holding, address, words);
        let cmd_offset = usize::from(cmd.address.wrapping_sub(address));
        if let Some(&value) = words.get(cmd_offset).filter(|_| cmd.address >= address) {
            if value == cmd.go_value {
                let tw = self.read(RegisterKind::Holding, target.address, target.words())?;
                let target_rad = target
                    .decode_rad(&tw)
                    .ok_or(ExceptionCode::ServerDeviceFailure)?;
                self.stats.go_commands += 1;
                self.stats.last_target_rad = Some(target_rad);
                if self
                    .faults
                    .fault_at_go
                    .is_some_and(|n| self.stats.go_commands >= n)
                {
                    self.fault = true;
                }
                self.source.command(target_rad, t_s);
                self.acked = true;
            } else {
                self.acked = false;
            }
        }
        Ok(())
    }

    fn handle(&mut self, req: SlaveRequest<'static>) -> Result<Option<Response>, ExceptionCode> {
        let t_s = self.start.elapsed().as_secs_f64();
        self.stats.requests += 1;
        let n = self.stats.requests;
        if self.faults.silence_at_request == Some(n) {
            self.silent_until_s = t_s + self.faults.silence_s;
        }
        let drop = t_s < self.silent_until_s
            || self.faults.drop_at_requests.contains(&n)
            || (self.faults.drop_probability > 0.0
                && self.rng.random::<f64>() < self.faults.drop_probability);
        if drop || req.slave != self.map.unit_id {
            self.stats.dropped += 1;
            return Ok(None);
        }
        if self.faults.exception_at_requests.contains(&n) {
            self.stats.exceptions += 1;
            return Err(ExceptionCode::new(self.faults.exception_code));
        }
        self.refresh(t_s);
        let result = match req.request {
            Request::ReadHoldingRegisters(a, c) => self
                .read(RegisterKind::Holding, a, c)
                .map(Response::ReadHoldingRegisters),
            Request::ReadInputRegisters(a, c) => self
                .read(RegisterKind::Input, a, c)
                .map(Response::ReadInputRegisters),
            Request::WriteSingleRegister(a, w) => self
                .write(a, &[w], t_s)
                .map(|()| Response::WriteSingleRegister(a, w)),
            Request::WriteMultipleRegisters(a, words) => self
                .write(a, &words, t_s)
                .map(|()| Response::WriteMultipleRegisters(a, words.len() as u16)),
            _ => Err(ExceptionCode::IllegalFunction),
        };
        if result.is_err() {
            self.stats.exceptions += 1;
        } else {
            self.refresh(t_s);
        }
        result.map(Some)
    }
}

#[derive(Clone)]
struct DeviceService(Arc<Mutex<Device>>);

fn lock(d: &Mutex<Device>) -> MutexGuard<'_, Device> {
    d.lock().unwrap_or_else(|e| e.into_inner())
}

impl tokio_modbus::server::Service for DeviceService {
    type Request = SlaveRequest<'static>;
    type Response = Option<Response>;
    type Exception = ExceptionCode;
    type Future = std::future::Ready<Result<Option<Response>, ExceptionCode>>;

    fn call(&self, req: Self::Request) -> Self::Future {
        std::future::ready(lock(&self.0).handle(req))
    }
}

/// A running emulator; stops when dropped.
pub struct ModbusTableEmulator {
    device: Arc<Mutex<Device>>,
    addr: Option<SocketAddr>,
    task: JoinHandle<()>,
}

impl Drop for ModbusTableEmulator {
    fn drop(&mut self) {
        self.task.abort();
    }
}

impl ModbusTableEmulator {
    /// Serve Modbus TCP on 127.0.0.1 at a free port (see `addr()`).
    pub async fn start_tcp(
        cfg: ModbusTableEmulatorConfig,
        source: Box<dyn TableSource>,
    ) -> io::Result<Self> {
        cfg.map
            .validate()
            .map_err(|m| io::Error::new(io::ErrorKind::InvalidInput, m))?;
        let listener = TcpListener::bind("127.0.0.1:0").await?;
        let addr = listener.local_addr()?;
        let device = Arc::new(Mutex::new(Device::new(cfg, source)));
        let service = DeviceService(device.clone());
        let task = tokio::spawn(async move {
            let server = Server::new(listener);
            let on_connected = |stream, peer| {
                let service = service.clone();
                lock(&service.0).stats.connections += 1;
                async move { accept_tcp_connection(stream, peer, |_| Ok(Some(service.clone()))) }
            };
            // A connection's error ends only that connection.
            let _ = server.serve(&on_connected, |_err| {}).await;
        });
        Ok(Self {
            device,
            addr: Some(addr),
            task,
        })
    }

    /// Serve Modbus RTU on a serial stream (the master side of a pty pair). The server
    /// answers every unit id's frames that match the map's; an undecodable frame ends it.
    pub fn start_rtu(
        cfg: ModbusTableEmulatorConfig,
        source: Box<dyn TableSource>,
        serial: tokio_serial::SerialStream,
    ) -> io::Result<Self> {
        cfg.map
            .validate()
            .map_err(|m| io::Error::new(io::ErrorKind::InvalidInput, m))?;
        let device = Arc::new(Mutex::new(Device::new(cfg, source)));
        let service = DeviceService(device.clone());
        lock(&device).stats.connections += 1;
        let task = tokio::spawn(async move {
            let server = tokio_modbus::server::rtu::Server::new(serial);
            let _ = server.serve_forever(service).await;
        });
        Ok(Self {
            device,
            addr: None,
            task,
        })
    }

    /// The TCP address served (None for RTU).
    pub fn addr(&self) -> Option<SocketAddr> {
        self.addr
    }

    pub fn stats(&self) -> ModbusTableEmulatorStats {
        lock(&self.device).stats
    }

    /// Set or clear the fault bit now (with the configured fault code).
    pub fn set_fault(&self, on: bool) {
        lock(&self.device).fault = on;
    }
}
