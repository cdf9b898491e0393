//! The one session reader (solve, replay, diagnose, report): MCAP bytes -> typed, time-sorted
//! streams per topic. Indexed through the summary when valid, linear (crash-tolerant) otherwise.

#[cfg(test)]
mod allocations;
mod assemble;
mod decoder;
mod dispatch;
mod event_json;
mod indexed;
mod linear;
mod pipeline;
mod progress;
mod runs;
mod source;
mod stream;
mod streams;
#[cfg(test)]
mod tests;
#[cfg(test)]
pub(crate) mod testutil;
mod tracer_json;

use std::collections::BTreeMap;
use std::path::Path;

use thiserror::Error;

pub use super::damage::DamagedChunk;
use super::messages::{
    EnvSample, MachineStateSample, ProbeSample, RotaryStateSample, RunEvent, SessionHeader,
    TracerSample, SESSION_FORMAT, TOPIC_SESSION,
};
use super::summary::{trusted_summary, trusted_summary_of_file};
use decoder::Decoder;
use indexed::{read_indexed, read_indexed_file, read_indexed_with};
use linear::{read_linear, read_linear_dated};
pub use progress::ReadProgress;
pub use stream::{stream_session, stream_session_reporting, KeepingEvents, SessionSink, Streamed};
use streams::RawLog;

/// A message with its MCAP times.
#[derive(Debug, Clone, PartialEq)]
pub struct Stamped<T> {
    pub log_time_ns: u64,
    pub publish_time_ns: u64,
    pub msg: T,
}

#[derive(Debug, Clone, PartialEq)]
pub enum Completeness {
    /// The file ends with its footer and end magic.
    Complete,
    /// The file was cut short (crash, power loss) or is damaged after `bytes_read`; everything
    /// before that point was read.
    Truncated {
        bytes_read: u64,
        file_bytes: u64,
        messages_read: u64,
        reason: String,
    },
}

impl Completeness {
    pub fn is_complete(&self) -> bool {
        matches!(self, Completeness::Complete)
    }
}

#[derive(Debug, Clone, PartialEq)]
pub struct Session {
    pub header: SessionHeader,
    /// Key: tracer id from the topic `/tracer/<id>/range`. Each Vec is sorted by log time.
    pub tracers: BTreeMap<String, Vec<Stamped<TracerSample>>>,
    /// Key: id from the topic `/env/<id>`.
    pub env: BTreeMap<String, Vec<Stamped<EnvSample>>>,
    /// Key: table id from the topic `/rotary/<id>/state`.
    pub rotary: BTreeMap<String, Vec<Stamped<RotaryStateSample>>>,
    /// Key: machine id from the topic `/machine/<id>/state`.
    pub machines: BTreeMap<String, Vec<Stamped<MachineStateSample>>>,
    /// Key: probe id from the topic `/probe/<id>/reading`.
    pub probes: BTreeMap<String, Vec<Stamped<ProbeSample>>>,
    pub events: Vec<Stamped<RunEvent>>,
    /// Plan kinds' own topics (`/probe/…`, `/machine/…`, `/hexapod/…`), by topic, as JSON
    /// (each kind's method parses them: `session::kind_messages`). Sorted by log time.
    pub topics: BTreeMap<String, Vec<Stamped<serde_json::Value>>>,
    pub completeness: Completeness,
    /// Chunks that failed their CRC, decompression or parsing: skipped, in file order.
    pub damaged: Vec<DamagedChunk>,
    /// Spans a repaired copy's original had lost (`data_lost` events written by `geocal
    /// repair`): its windows there are dropped as in the damaged original.
    pub lost_before_repair: Vec<DamagedChunk>,
    /// Messages on known topics that did not parse (each one is warned about).
    pub skipped: u64,
    /// Messages on topics this reader does not know (other plan kinds, other tools).
    pub ignored: u64,
}

impl Session {
    /// Whether messages with a log time in `from_ns ..= to_ns` may have been lost in a
    /// damaged chunk: a window there must be dropped, never half-used.
    pub fn lost_between(&self, from_ns: u64, to_ns: u64) -> bool {
        self.damaged
            .iter()
            .chain(&self.lost_before_repair)
            .any(|d| d.overlaps(from_ns, to_ns))
    }
}

#[derive(Debug, Error)]
pub enum ReadError {
    #[error("cannot read session file {file}: {source}")]
    Io {
        file: String,
        source: std::io::Error,
    },
    #[error("{file} is not an MCAP file: {reason}")]
    NotMcap { file: String, reason: String },
    #[error("{file} has no {TOPIC_SESSION} message ({messages} messages read{truncated})")]
    NoHeader {
        file: String,
        messages: u64,
        truncated: String,
    },
    #[error(
        "{file}: the {TOPIC_SESSION} message at log_time {log_time_ns} ns does not parse: {error}"
    )]
    BadHeader {
        file: String,
        log_time_ns: u64,
        error: serde_json::Error,
    },
    #[error("{file}: session format is {found:?}, expected {SESSION_FORMAT:?}")]
    WrongFormat { file: String, found: String },
}

/// Reads a whole session file. A complete, clean file is read chunk by chunk from the disk
/// (never held whole); any other is read into memory and walked as `read_session_bytes` does.
pub fn read_session(path: &Path) -> Result<Session, ReadError> {
    let name = path.display().to_string();
    let io = |source| ReadError::Io {
        file: name.clone(),
        source,
    };
    let file = std::fs::File::open(path).map_err(io)?;
    let len = file.metadata().map_err(io)?.len();
    if let Some(decoded) = read_clean_file(&file, len, &name) {
        return decoded.into_session(&name, len);
    }
    let mut bytes = Vec::with_capacity(usize::try_from(len).unwrap_or(0));
    std::io::Read::read_to_end(&mut &file, &mut bytes).map_err(io)?;
    read_impl(&bytes, &name)
}

/// The indexed read straight from the file when it is complete and undamaged; None sends the
/// caller to the whole-file read, which gives the errors and the damage report.
fn read_clean_file(file: &std::fs::File, len: u64, name: &str) -> Option<Decoder> {
    let mut magic = [0u8; 8];
    std::os::unix::fs::FileExt::read_exact_at(file, &mut magic, 0).ok()?;
    if magic[..] != mcap::MAGIC[..] {
        return None;
    }
    let summary = trusted_summary_of_file(file, len, name)?;
    read_indexed_file(file, len, name, &summary).ok().flatten()
}

/// One channel of a session file as recorded (topic, encodings, schema), for copying.
#[derive(Debug, Clone, PartialEq)]
pub struct RawChannel {
    pub topic: String,
    pub message_encoding: String,
    pub metadata: BTreeMap<String, String>,
    /// Schema name, encoding and text; None for a schemaless channel.
    pub schema: Option<(String, String, Vec<u8>)>,
}

/// One message of a session file exactly as recorded: channel, times and payload bytes.
#[derive(Debug, Clone, PartialEq)]
pub struct RawMessage {
    pub channel: std::sync::Arc<RawChannel>,
    pub log_time_ns: u64,
    pub publish_time_ns: u64,
    pub data: Vec<u8>,
}

/// Reads a session file linearly (up to its last complete chunk, as for a truncated file),
/// returning the decoded session and every message in file order as raw records: what
/// `geocal run --resume` (src/run/resume.rs) copies into the continued file.
pub fn read_session_raw(path: &Path) -> Result<(Session, Vec<RawMessage>), ReadError> {
    let file = path.display().to_string();
    let buf = std::fs::read(path).map_err(|source| ReadError::Io {
        file: file.clone(),
        source,
    })?;
    check_magic(&buf, &file)?;
    let mut dec = Decoder::new(&file);
    dec.raw = Some(RawLog::default());
    let mut dec = read_linear_dated(&buf, dec)?;
    let raw = dec.raw.take().map(|r| r.messages).unwrap_or_default();
    Ok((dec.into_session(&file, buf.len() as u64)?, raw))
}

/// Every readable message of a session file exactly as recorded, without decoding them, and
/// what could not be read: what `geocal repair` copies.
#[derive(Debug, Clone)]
pub struct RawRead {
    /// In file order.
    pub messages: Vec<RawMessage>,
    pub damaged: Vec<DamagedChunk>,
    pub completeness: Completeness,
    pub file_bytes: u64,
}

/// Reads a session file linearly for its raw messages; needs no session header.
pub fn read_raw(path: &Path) -> Result<RawRead, ReadError> {
    let file = path.display().to_string();
    let buf = std::fs::read(path).map_err(|source| ReadError::Io {
        file: file.clone(),
        source,
    })?;
    check_magic(&buf, &file)?;
    // Through the summary when it is intact, as `geocal solve` reads: the copy then holds
    // exactly the messages the solve of the damaged file uses.
    let indexed = match trusted_summary(&buf, &file) {
        Some(summary) => read_indexed_with(&buf, &file, &summary, 1, true)?.map(|mut dec| {
            dec.date_damages(&summary.chunk_indexes);
            dec
        }),
        None => None,
    };
    let mut dec = match indexed {
        Some(dec) => dec,
        None => {
            let mut dec = Decoder::new(&file);
            dec.raw = Some(RawLog::default());
            dec.raw_only = true;
            read_linear_dated(&buf, dec)?
        }
    };
    let damaged = dec.damaged_chunks(&file);
    let completeness = dec.completeness(&file, buf.len() as u64);
    Ok(RawRead {
        messages: dec.raw.take().map(|r| r.messages).unwrap_or_default(),
        damaged,
        completeness,
        file_bytes: buf.len() as u64,
    })
}

/// Reads a session held in memory (tests, data received over the network).
pub fn read_session_bytes(bytes: &[u8]) -> Result<Session, ReadError> {
    read_impl(bytes, "<in-memory session>")
}

fn check_magic(buf: &[u8], file: &str) -> Result<(), ReadError> {
    if buf.len() < mcap::MAGIC.len() || &buf[..mcap::MAGIC.len()] != mcap::MAGIC {
        let reason = if mcap::MAGIC.starts_with(buf) {
            format!("only {} bytes, less than the MCAP magic", buf.len())
        } else {
            "it does not start with the MCAP magic bytes".to_owned()
        };
        return Err(ReadError::NotMcap {
            file: file.to_owned(),
            reason,
        });
    }
    Ok(())
}

fn read_impl(buf: &[u8], file: &str) -> Result<Session, ReadError> {
    check_magic(buf, file)?;
    let summary = trusted_summary(buf, file);
    let mut decoded = match &summary {
        Some(summary) => match read_indexed(buf, file, summary)? {
            Some(d) => d,
            None => read_linear(buf, file)?,
        },
        None => read_linear(buf, file)?,
    };
    if let Some(summary) = &summary {
        decoded.date_damages(&summary.chunk_indexes);
    }
    decoded.into_session(file, buf.len() as u64)
}
