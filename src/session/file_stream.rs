//! A session file read message by message from disk (a chunk in memory at a time, never the
//! whole file): the header for a run's machine and date, and the raw tracer samples.

use std::collections::HashMap;
use std::io::Read;
use std::ops::ControlFlow;
use std::path::Path;

use anyhow::Context;
use mcap::sans_io::{LinearReadEvent, LinearReader, LinearReaderOptions};

use crate::session::messages::{SessionHeader, TracerSample, SESSION_FORMAT, TOPIC_SESSION};

/// Largest read asked of the file at once.
const READ_BYTES: usize = 1 << 20;

/// How a stream ended.
#[derive(Debug, Clone, PartialEq)]
pub enum StreamEnd {
    /// The callback stopped it, or the file ended cleanly.
    Complete,
    /// The file could not be read past `bytes_read` (truncated or damaged there): every
    /// message before it was delivered.
    Cut { bytes_read: u64, reason: String },
}

/// Every message of the file in file order, as (topic, log time ns, payload), until `f`
/// breaks. A damaged or cut file ends the stream with `StreamEnd::Cut`.
pub fn for_each_message(
    path: &Path,
    mut f: impl FnMut(&str, u64, &[u8]) -> anyhow::Result<ControlFlow<()>>,
) -> anyhow::Result<StreamEnd> {
    let mut file =
        std::fs::File::open(path).with_context(|| format!("opening {}", path.display()))?;
    // A file cut by a crash has no end magic: read what it has. A chunk's messages come only
    // once the whole chunk is read and its CRC checks, so a chunk cut short or damaged gives
    // none (as the session reader: up to the last complete chunk), never unchecked bytes.
    let mut reader = LinearReader::new_with_options(
        LinearReaderOptions::default()
            .with_skip_end_magic(true)
            .with_prevalidate_chunk_crcs(true),
    );
    let mut topics: HashMap<u16, String> = HashMap::new();
    let mut bytes_read = 0u64;
    while let Some(event) = reader.next_event() {
        let event = match event {
            Ok(e) => e,
            Err(e) => {
                return Ok(StreamEnd::Cut {
                    bytes_read,
                    reason: e.to_string(),
                })
            }
        };
        match event {
            LinearReadEvent::ReadRequest(n) => {
                let buf = reader.insert(n.clamp(1, READ_BYTES));
                let read = file
                    .read(buf)
                    .with_context(|| format!("reading {}", path.display()))?;
                reader.notify_read(read);
                bytes_read += read as u64;
            }
            LinearReadEvent::Record { data, opcode } => {
                match crate::session::record::parse(opcode, data) {
                    Ok(mcap::records::Record::Channel(channel)) => {
                        topics.insert(channel.id, channel.topic);
                    }
                    Ok(mcap::records::Record::Message { header, data }) => {
                        let Some(topic) = topics.get(&header.channel_id) else {
                            continue;
                        };
                        if f(topic, header.log_time, &data)?.is_break() {
                            return Ok(StreamEnd::Complete);
                        }
                    }
                    Ok(_) => {}
                    Err(e) => {
                        return Ok(StreamEnd::Cut {
                            bytes_read,
                            reason: e.to_string(),
                        })
                    }
                }
            }
        }
    }
    Ok(StreamEnd::Complete)
}

/// The session header (`/geocal/session`), read without reading the rest of the file.
pub fn read_header(path: &Path) -> anyhow::Result<SessionHeader> {
    let header: SessionHeader =
        serde_json::from_value(read_header_json(path)?).with_context(|| {
            format!(
                "{}: the {TOPIC_SESSION} message is not a session header",
                path.display()
            )
        })?;
    if header.format != SESSION_FORMAT {
        anyhow::bail!(
            "{}: session format is {:?}, expected {SESSION_FORMAT:?}",
            path.display(),
            header.format
        );
    }
    Ok(header)
}

/// The session header as JSON (any format version), read without reading the rest of the file.
pub fn read_header_json(path: &Path) -> anyhow::Result<serde_json::Value> {
    let mut header: Option<anyhow::Result<serde_json::Value>> = None;
    let end = for_each_message(path, |topic, log_time, data| {
        if topic != TOPIC_SESSION {
            return Ok(ControlFlow::Continue(()));
        }
        header = Some(serde_json::from_slice(data).with_context(|| {
            format!(
                "{}: the {TOPIC_SESSION} message at log_time {log_time} ns does not parse",
                path.display()
            )
        }));
        Ok(ControlFlow::Break(()))
    })?;
    match (header, end) {
        (Some(h), _) => h,
        (None, StreamEnd::Complete) => {
            anyhow::bail!("{}: no {TOPIC_SESSION} message", path.display())
        }
        (None, StreamEnd::Cut { bytes_read, reason }) => anyhow::bail!(
            "{}: no {TOPIC_SESSION} message in its first {bytes_read} bytes ({reason})",
            path.display()
        ),
    }
}

/// Every tracer sample of the file in file order, as (tracer id, log time ns, sample). A
/// sample that does not parse is counted in `skipped`, never dropped silently.
pub fn for_each_tracer_sample(
    path: &Path,
    skipped: &mut u64,
    mut f: impl FnMut(&str, u64, &TracerSample) -> anyhow::Result<()>,
) -> anyhow::Result<StreamEnd> {
    for_each_message(path, |topic, log_time, data| {
        if let Some(id) = topic
            .strip_prefix("/tracer/")
            .and_then(|t| t.strip_suffix("/range"))
        {
            match serde_json::from_slice::<TracerSample>(data) {
                Ok(sample) => f(id, log_time, &sample)?,
                Err(_) => *skipped += 1,
            }
        }
        Ok(ControlFlow::Continue(()))
    })
}
