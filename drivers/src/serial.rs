//! Serial plumbing the drivers and emulators share: opening a port (8N1, no flow control) with
//! a clear error, pseudo-terminal pairs for emulators, and checks of configured durations.

pub use tokio_serial::SerialStream;
use tokio_serial::{SerialPort, SerialPortBuilderExt};

use crate::DeviceError;

/// Open a serial port 8N1 without flow control; the error names the device and the port.
pub fn open_8n1(device: &str, path: &str, baud: u32) -> Result<SerialStream, DeviceError> {
    tokio_serial::new(path, baud)
        .data_bits(tokio_serial::DataBits::Eight)
        .parity(tokio_serial::Parity::None)
        .stop_bits(tokio_serial::StopBits::One)
        .flow_control(tokio_serial::FlowControl::None)
        .open_native_async()
        .map_err(|e| DeviceError::Disconnected {
            device: device.to_string(),
            message: format!("cannot open {path}: {e}"),
        })
}

/// A new pseudo-terminal: the device side (`master`) for an emulator, the host side for a
/// driver in this process or, by its path, in another one.
pub fn pty_pair() -> std::io::Result<(SerialStream, PtySlave)> {
    let (master, slave) = SerialStream::pair().map_err(std::io::Error::other)?;
    let path = slave.name();
    Ok((
        master,
        PtySlave {
            stream: Some(slave),
            path,
        },
    ))
}

/// The host side of an emulator's pty, kept open until a driver in this process takes it
/// (while no slave descriptor is open the pty reports errors to the device side).
#[derive(Debug, Default)]
pub struct PtySlave {
    stream: Option<SerialStream>,
    path: Option<String>,
}

impl PtySlave {
    /// Device path (`/dev/pts/N`), for a driver in another process.
    pub fn path(&self) -> Option<&str> {
        self.path.as_deref()
    }

    /// The host end itself, for a driver in this process (once).
    pub fn take(&mut self) -> Option<SerialStream> {
        self.stream.take()
    }
}

/// A usable duration in seconds (finite, not negative, not absurd): turning config into
/// `Duration`s and deadlines must not panic.
pub fn check_seconds(device: &str, name: &str, v: f64) -> Result<(), DeviceError> {
    if v.is_finite() && (0.0..=1e6).contains(&v) {
        Ok(())
    } else {
        Err(DeviceError::Protocol {
            device: device.to_string(),
            message: format!("{name} must be between 0 and 1e6 s, got {v}"),
        })
    }
}
