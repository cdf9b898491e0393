//! From raw streams to measured points: stillstand detection (sans-I/O, shared with the
//! live sequencer) and extraction of the settled part of each dwell window of a session.

pub mod lengths;
mod pairing;
pub mod points;
pub mod stillstand;
#[cfg(test)]
mod stream_tests;
pub mod windows;
#[cfg(test)]
mod windows_tests;

pub use lengths::{LengthMeasurement, LengthStream, Lengths};
pub use points::{
    extract_points, DroppedWindow, ExtractOptions, Extraction, NoiseModel, PointMeasurement,
};
pub use stillstand::{Stillstand, StillstandDetector};
pub use windows::{
    stream_dwells, stream_settled, DwellMeasurement, RawWindow, SettledDwells, SettledSession,
    WindowSamples, WindowStream,
};
