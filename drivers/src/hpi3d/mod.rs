//! Lasertex HPI-3D laser interferometer: frames, sans-I/O codec, tokio-serial driver and a
//! pty device emulator that reuses the codec. Protocol notes: docs/protocols/hpi3d.md.

pub mod codec;
pub mod frame;
