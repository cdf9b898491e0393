//! Modbus pieces every Modbus device of geocal shares: register layouts and the go/ack
//! handshake (pure), the client link (timeouts, reconnect, retry) and the register server.

pub mod client;
pub mod registers;
pub mod server;

pub use client::{ModbusClient, ModbusStats, ModbusTiming, ModbusTransport};
pub use registers::{
    Acknowledge, CommandRegister, Handshake, RegisterKind, RegisterRef, StatusRegister, WordLayout,
    WordOrder,
};
pub use server::{ModbusFaults, RegisterBank, RegisterDevice, RegisterServer, ServerStats};
