//! Rotary table over Modbus TCP/RTU: register map from config (pure conversions), driver
//! (`RotaryTable`) and a Modbus TCP emulator of the table. See docs/protocols/modbus-table.md.

pub mod driver;
pub mod emulator;
pub mod map;

pub use driver::{ModbusTable, ModbusTableConfig, ModbusTableStats, ModbusTransport};
pub use emulator::{
    KinematicTable, ModbusTableEmulator, ModbusTableEmulatorConfig, ModbusTableEmulatorStats,
    ModbusTableFaults, TableSource,
};
pub use map::{
    Acknowledge, AngleRegister, CommandRegister, RegisterKind, RegisterMap, RegisterRef,
    StatusRegister, WordLayout, WordOrder,
};
