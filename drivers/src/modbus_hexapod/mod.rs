//! Hexapod controller over Modbus TCP/RTU: register map from config (pose command, leg
//! encoders, handshake), driver (`Hexapod`) and emulator. See docs/hexapod.md.

pub mod driver;
pub mod emulator;
pub mod map;

pub use driver::{ModbusHexapod, ModbusHexapodConfig};
pub use emulator::{HexapodSource, ModbusHexapodEmulator};
pub use map::{HexapodRegisterMap, LegRegisters, PoseRegisters};
