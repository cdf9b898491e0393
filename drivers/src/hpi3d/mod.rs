//! Lasertex HPI-3D laser interferometer: frames, sans-I/O codec, tokio-serial driver and a
//! pty device emulator that reuses the codec. Protocol notes: docs/protocols/hpi3d.md.

pub mod clock;
pub mod codec;
pub mod driver;
pub mod emulator;
pub mod frame;

pub use clock::StreamClock;
pub use codec::{crc8, CodecError, Decoder, DecoderStats, DeviceDecoder, HostDecoder, WireFrame};
pub use driver::{Hpi3dConfig, Hpi3dCounters, Hpi3dEnvironment, Hpi3dStream, Hpi3dTracer};
pub use emulator::{
    EmulatorConfig, EmulatorStats, FaultConfig, FnSource, Hpi3dEmulator, MeteoSensorReading,
    SourceReading, TracerSource, Window,
};
pub use frame::{DeviceFrame, Distance, HostCommand, HostFrame, Meteo, Status, Velocity};
