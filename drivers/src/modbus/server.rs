//! The device side of a Modbus register map: a register bank served on loopback TCP (or a
//! pty, RTU) by tokio-modbus, the go/ack handshake, and seeded fault injection.

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

use super::registers::{Handshake, RegisterKind};

/// Faults an emulator injects; requests are counted from 1 over all connections.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ModbusFaults {
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

impl Default for ModbusFaults {
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

/// What the server saw and did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ServerStats {
    pub connections: u64,
    pub requests: u64,
    pub dropped: u64,
    pub exceptions: u64,
    pub go_commands: u64,
}

/// The device's registers, holding and input.
#[derive(Debug, Default)]
pub struct RegisterBank {
    holding: BTreeMap<u16, u16>,
    input: BTreeMap<u16, u16>,
}

impl RegisterBank {
    fn table(&mut self, kind: RegisterKind) -> &mut BTreeMap<u16, u16> {
        match kind {
            RegisterKind::Holding => &mut self.holding,
            RegisterKind::Input => &mut self.input,
        }
    }

    /// Declare `words` registers from `address` (reading others is IllegalDataAddress).
    pub fn add(&mut self, kind: RegisterKind, address: u16, words: u16) {
        let t = self.table(kind);
        for k in 0..words {
            t.insert(address.wrapping_add(k), 0u16);
        }
    }

    pub fn put(&mut self, kind: RegisterKind, address: u16, words: &[u16]) {
        let t = self.table(kind);
        for (k, w) in words.iter().enumerate() {
            t.insert(address.wrapping_add(k as u16), *w);
        }
    }

    pub fn read(
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
}

/// What a particular device (table, hexapod) adds to the shared server: its value registers,
/// what a go command does, and whether it is in position.
pub trait RegisterDevice: Send + 'static {
    /// Registers besides the handshake's: (kind, address, words).
    fn registers(&self) -> Vec<(RegisterKind, u16, u16)>;
    /// Holding registers a client may write besides the command register (the target).
    fn writable(&self, address: u16) -> bool;
    /// Bring the value registers up to date at `t_s` (seconds since start); in position?
    fn refresh(&mut self, bank: &mut RegisterBank, t_s: f64) -> bool;
    /// A go command was written: read the target from `bank` and start the move.
    fn go(&mut self, bank: &mut RegisterBank, t_s: f64) -> Result<(), ExceptionCode>;
    /// A read of `count` words of `kind` from `address` is about to be served: latch values
    /// that are sampled only when read (encoder counts), none by default.
    fn before_read(
        &mut self,
        _bank: &mut RegisterBank,
        _kind: RegisterKind,
        _address: u16,
        _count: u16,
        _t_s: f64,
    ) {
    }
}

struct Inner<D> {
    device: D,
    hs: Handshake,
    faults: ModbusFaults,
    rng: ChaCha8Rng,
    start: Instant,
    bank: RegisterBank,
    acked: bool,
    fault: bool,
    silent_until_s: f64,
    stats: ServerStats,
}

impl<D: RegisterDevice> Inner<D> {
    fn new(device: D, hs: Handshake, faults: ModbusFaults) -> Self {
        let mut bank = RegisterBank::default();
        for (kind, address, words) in device.registers() {
            bank.add(kind, address, words);
        }
        bank.add(hs.status.kind, hs.status.address, 1);
        bank.add(RegisterKind::Holding, hs.command.address, 1);
        if let Some(r) = hs.ack.register {
            bank.add(r.kind, r.address, 1);
        }
        if let Some(r) = hs.fault_code {
            bank.add(r.kind, r.address, 1);
        }
        Self {
            rng: ChaCha8Rng::seed_from_u64(faults.seed),
            device,
            hs,
            faults,
            start: Instant::now(),
            bank,
            acked: false,
            fault: false,
            silent_until_s: f64::NEG_INFINITY,
            stats: ServerStats::default(),
        }
    }

    /// Bring the value, status, ack and fault registers up to date.
    fn refresh(&mut self, t_s: f64) {
        if self.faults.fault_at_s.is_some_and(|f| t_s >= f) {
            self.fault = true;
        }
        let in_pos = self.device.refresh(&mut self.bank, t_s);
        let (status, ack) = self.hs.device_words(in_pos, self.fault, self.acked);
        self.bank
            .put(self.hs.status.kind, self.hs.status.address, &[status]);
        if let (Some(r), Some(w)) = (self.hs.ack.register, ack) {
            self.bank.put(r.kind, r.address, &[w]);
        }
        if let Some(r) = self.hs.fault_code {
            let code = if self.fault {
                self.faults.fault_code
            } else {
                0
            };
            self.bank.put(r.kind, r.address, &[code]);
        }
    }

    fn write(&mut self, address: u16, words: &[u16], t_s: f64) -> Result<(), ExceptionCode> {
        let cmd = self.hs.command.clone();
        for k in 0..words.len() {
            let a = address
                .checked_add(k as u16)
                .ok_or(ExceptionCode::IllegalDataAddress)?;
            if a != cmd.address && !self.device.writable(a) {
                return Err(ExceptionCode::IllegalDataAddress);
            }
        }
        self.bank.put(RegisterKind::Holding, address, words);
        let cmd_offset = usize::from(cmd.address.wrapping_sub(address));
        if let Some(&value) = words.get(cmd_offset).filter(|_| cmd.address >= address) {
            if value == cmd.go_value {
                self.device.go(&mut self.bank, t_s)?;
                self.stats.go_commands += 1;
                if self
                    .faults
                    .fault_at_go
                    .is_some_and(|n| self.stats.go_commands >= n)
                {
                    self.fault = true;
                }
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
        if drop || req.slave != self.hs.unit_id {
            self.stats.dropped += 1;
            return Ok(None);
        }
        if self.faults.exception_at_requests.contains(&n) {
            self.stats.exceptions += 1;
            return Err(ExceptionCode::new(self.faults.exception_code));
        }
        self.refresh(t_s);
        let result = match req.request {
            Request::ReadHoldingRegisters(a, c) => {
                self.device
                    .before_read(&mut self.bank, RegisterKind::Holding, a, c, t_s);
                self.bank
                    .read(RegisterKind::Holding, a, c)
                    .map(Response::ReadHoldingRegisters)
            }
            Request::ReadInputRegisters(a, c) => {
                self.device
                    .before_read(&mut self.bank, RegisterKind::Input, a, c, t_s);
                self.bank
                    .read(RegisterKind::Input, a, c)
                    .map(Response::ReadInputRegisters)
            }
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

struct Service<D>(Arc<Mutex<Inner<D>>>);

impl<D> Clone for Service<D> {
    fn clone(&self) -> Self {
        Self(self.0.clone())
    }
}

fn lock<D>(d: &Mutex<Inner<D>>) -> MutexGuard<'_, Inner<D>> {
    d.lock().unwrap_or_else(|e| e.into_inner())
}

impl<D: RegisterDevice> tokio_modbus::server::Service for Service<D> {
    type Request = SlaveRequest<'static>;
    type Response = Option<Response>;
    type Exception = ExceptionCode;
    type Future = std::future::Ready<Result<Option<Response>, ExceptionCode>>;

    fn call(&self, req: Self::Request) -> Self::Future {
        std::future::ready(lock(&self.0).handle(req))
    }
}

/// A running register server; stops when dropped.
pub struct RegisterServer<D> {
    inner: Arc<Mutex<Inner<D>>>,
    addr: Option<SocketAddr>,
    task: JoinHandle<()>,
}

impl<D> Drop for RegisterServer<D> {
    fn drop(&mut self) {
        self.task.abort();
    }
}

fn invalid(message: String) -> io::Error {
    io::Error::new(io::ErrorKind::InvalidInput, message)
}

impl<D: RegisterDevice> RegisterServer<D> {
    /// Serve Modbus TCP on 127.0.0.1 at a free port (see `addr()`).
    pub async fn start_tcp(device: D, hs: Handshake, faults: ModbusFaults) -> io::Result<Self> {
        hs.validate().map_err(invalid)?;
        let listener = TcpListener::bind("127.0.0.1:0").await?;
        let addr = listener.local_addr()?;
        let inner = Arc::new(Mutex::new(Inner::new(device, hs, faults)));
        let service = Service(inner.clone());
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
            inner,
            addr: Some(addr),
            task,
        })
    }

    /// Serve Modbus RTU on a serial stream (the master side of a pty pair). The server
    /// answers every unit id's frames that match the map's; an undecodable frame ends it.
    pub fn start_rtu(
        device: D,
        hs: Handshake,
        faults: ModbusFaults,
        serial: tokio_serial::SerialStream,
    ) -> io::Result<Self> {
        hs.validate().map_err(invalid)?;
        let inner = Arc::new(Mutex::new(Inner::new(device, hs, faults)));
        let service = Service(inner.clone());
        lock(&inner).stats.connections += 1;
        let task = tokio::spawn(async move {
            let server = tokio_modbus::server::rtu::Server::new(serial);
            let _ = server.serve_forever(service).await;
        });
        Ok(Self {
            inner,
            addr: None,
            task,
        })
    }

    /// The TCP address served (None for RTU).
    pub fn addr(&self) -> Option<SocketAddr> {
        self.addr
    }

    pub fn stats(&self) -> ServerStats {
        lock(&self.inner).stats
    }

    /// Look at the device (for its own statistics).
    pub fn with_device<T>(&self, f: impl FnOnce(&D) -> T) -> T {
        f(&lock(&self.inner).device)
    }

    /// Set or clear the fault bit now (with the configured fault code).
    pub fn set_fault(&self, on: bool) {
        lock(&self.inner).fault = on;
    }
}
