//! The recorded session: message types (the geocal-session/1 contract), the MCAP recorder
//! and the one session reader that solve, replay, diagnose and report share.

pub mod axis_map;
pub mod damage;
pub mod file_stream;
pub mod kind_messages;
pub mod messages;
pub mod reader;
pub mod record;
pub mod recorder;
pub mod repair;
mod summary;
pub mod tap;

pub use reader::{
    read_session, read_session_bytes, Completeness, DamagedChunk, ReadError, Session, Stamped,
};
pub use recorder::{
    Compression, RecordStats, Recorder, RecorderError, RecorderHandle, RecorderOptions,
};
