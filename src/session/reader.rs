//! The one session reader (solve, replay, diagnose, report): MCAP bytes -> typed, time-sorted
//! streams per topic. Indexed through the summary when valid, linear (crash-tolerant) otherwise.

use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use mcap::records::op;
use mcap::sans_io::{LinearReadEvent, LinearReader, LinearReaderOptions};
use serde::de::DeserializeOwned;
use serde::Deserialize;
use thiserror::Error;

pub use super::damage::DamagedChunk;
use super::damage::{
    can_follow, date_from_chunk_index, framed, known_opcode, le_u64, resync, Damage, IndexCounts,
    RECORD_PREFIX,
};
use super::messages::{
    EnvSample, MachineStateSample, ProbeSample, RotaryStateSample, RunEvent, SessionHeader,
    TracerSample, SESSION_FORMAT, TOPIC_EVENT, TOPIC_SESSION,
};
use super::summary::trusted_summary;

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

/// Reads a whole session file.
pub fn read_session(path: &Path) -> Result<Session, ReadError> {
    let bytes = std::fs::read(path).map_err(|source| ReadError::Io {
        file: path.display().to_string(),
        source,
    })?;
    read_impl(&bytes, &path.display().to_string())
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

/// A linear read whose damages are dated from the summary's chunk index when it is intact.
fn read_linear_dated(buf: &[u8], dec: Decoder) -> Result<Decoder, ReadError> {
    let mut dec = read_linear_into(buf, dec)?;
    if !dec.damages.is_empty() {
        if let Some(summary) = trusted_summary(buf, &dec.file) {
            dec.date_damages(&summary.chunk_indexes);
        }
    }
    Ok(dec)
}

/// Reads the chunks the summary lists. Returns None when the summary does not account for
/// every message (unchunked messages, odd writers): the caller then reads linearly.
fn read_indexed(
    buf: &[u8],
    file: &str,
    summary: &mcap::Summary,
) -> Result<Option<Decoder>, ReadError> {
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    read_indexed_with(buf, file, summary, threads.min(MAX_DECODE_THREADS), false)
}

/// Decompressing and parsing is most of the time a large session takes to read, and chunks
/// are independent: up to this many threads decode contiguous runs of chunks.
const MAX_DECODE_THREADS: usize = 8;
/// Fewer chunks than this per thread are not worth a thread.
const MIN_CHUNKS_PER_THREAD: usize = 2;

/// `raw`: keep every message raw and decode none (repair); serial, channels from the summary.
fn read_indexed_with(
    buf: &[u8],
    file: &str,
    summary: &mcap::Summary,
    threads: usize,
    raw: bool,
) -> Result<Option<Decoder>, ReadError> {
    let Some(stats) = &summary.stats else {
        return Ok(None);
    };
    let mut dec = Decoder::new(file);
    let threads = if raw {
        dec.raw_only = true;
        dec.raw = Some(RawLog::of_summary(summary));
        1
    } else {
        threads
    };
    for channel in summary.channels.values() {
        dec.define_channel(channel.id, &channel.topic, &channel.message_encoding);
        if let Some(&n) = stats.channel_message_counts.get(&channel.id) {
            // Counts come from the file and may be corrupt: only a hint, bounded by its size.
            dec.reserve(channel.id, n.min(buf.len() as u64 / 16));
        }
    }
    let mut chunks: Vec<_> = summary.chunk_indexes.iter().collect();
    chunks.sort_by_key(|c| c.chunk_start_offset);
    let mut ranges = Vec::with_capacity(chunks.len());
    for index in &chunks {
        let start = index.chunk_start_offset;
        let range = usize::try_from(start)
            .ok()
            .zip(usize::try_from(start.saturating_add(index.chunk_length)).ok())
            .filter(|&(s, e)| s < e && e <= buf.len());
        let Some(range) = range else {
            // The linear read that follows meets every chunk before this one in the same order,
            // so decoding them here first could not change the outcome.
            tracing::debug!("{file}: chunk index points outside the file; reading linearly");
            return Ok(None);
        };
        ranges.push(range);
    }
    // A chunk may define a channel that later chunks use: threads are only safe when the
    // summary already defines every channel that has messages.
    let all_defined = stats
        .channel_message_counts
        .keys()
        .all(|id| summary.channels.contains_key(id))
        && stats.channel_message_counts.values().sum::<u64>() == stats.message_count;
    let threads = if all_defined { threads } else { 1 };
    let groups = split_by_bytes(&ranges, threads.min(ranges.len() / MIN_CHUNKS_PER_THREAD));
    let (failure, undefined) = match groups.split_first() {
        None => (None, false),
        Some((first, [])) => (dec.feed_chunks(buf, first).err(), false),
        Some((first, rest)) => {
            // Workers keep any session header raw: only the merge, in file order, knows
            // whether it is the first one (parsed) or a later one (ignored).
            let workers: Vec<Decoder> = rest.iter().map(|_| dec.worker()).collect();
            std::thread::scope(|scope| {
                let handles: Vec<_> = rest
                    .iter()
                    .zip(workers)
                    .map(|(group, mut worker)| {
                        scope.spawn(move || {
                            let failure = worker.feed_chunks(buf, group).err();
                            (worker, failure)
                        })
                    })
                    .collect();
                let mut failure = dec.feed_chunks(buf, first).err();
                let mut undefined = false;
                for handle in handles {
                    let (worker, worker_failure) = handle
                        .join()
                        .unwrap_or_else(|panic| std::panic::resume_unwind(panic));
                    undefined |= worker.saw_undefined;
                    // The first failure in file order decides, as in a serial read.
                    if failure.is_none() {
                        failure = match dec.absorb(worker) {
                            Ok(()) => worker_failure,
                            Err(Failure::Fatal(err)) => Some(err),
                            Err(Failure::Damaged(_)) => None,
                        };
                    }
                }
                (failure, undefined)
            })
        }
    };
    if undefined {
        // A worker met a message on a channel it did not know: decode serially instead.
        return read_indexed_with(buf, file, summary, 1, raw);
    }
    if let Some(err) = failure {
        return Err(err);
    }
    // What the damaged chunks held, from the summary's chunk indexes and the message indexes.
    let mut lost = 0;
    for damage in &mut dec.damages {
        let Some(index) = chunks
            .iter()
            .find(|c| c.chunk_start_offset == damage.offset)
        else {
            continue;
        };
        damage.chunk_index_times = Some((index.message_start_time, index.message_end_time));
        damage.index = IndexCounts::of_chunk(buf, index);
        match &damage.index {
            Some(counts) => lost += counts.messages,
            None => {
                tracing::debug!("{file}: a damaged chunk has no message index; reading linearly");
                return Ok(None);
            }
        }
    }
    if dec.messages + lost != stats.message_count {
        tracing::debug!(
            "{file}: chunk indexes hold {} (+ {lost} damaged) of {} messages; reading linearly",
            dec.messages,
            stats.message_count
        );
        return Ok(None);
    }
    Ok(Some(dec))
}

/// Splits `ranges` into at most `parts` contiguous runs of about equal bytes (at least one run
/// when there are ranges), so that concatenating the runs' messages keeps file order.
fn split_by_bytes(ranges: &[(usize, usize)], parts: usize) -> Vec<&[(usize, usize)]> {
    let parts = parts.max(1);
    let total: usize = ranges.iter().map(|(s, e)| e - s).sum();
    let mut groups = Vec::with_capacity(parts);
    let mut start = 0;
    let mut bytes = 0;
    for (i, (s, e)) in ranges.iter().enumerate() {
        bytes += e - s;
        // Close the run once it holds its share of all bytes so far.
        if groups.len() + 1 < parts && bytes * parts >= total * (groups.len() + 1) {
            groups.push(&ranges[start..=i]);
            start = i + 1;
        }
    }
    if start < ranges.len() {
        groups.push(&ranges[start..]);
    }
    groups
}

fn chunk_reader() -> LinearReader {
    // Only whole records are ever fed in, so a chunk is decoded only once complete; its CRC is
    // checked before any of its messages is used.
    LinearReader::new_with_options(
        LinearReaderOptions::default()
            .with_skip_start_magic(true)
            .with_skip_end_magic(true)
            .with_prevalidate_chunk_crcs(true)
            .with_record_length_limit(MAX_RECORD_BYTES),
    )
}

/// Bound on a chunk's (de)compressed size: the sizes come from the file, and a corrupt one
/// must give an error, not an allocation of terabytes.
const MAX_RECORD_BYTES: usize = 1 << 30;

/// Walks the top-level records itself, so that a cut anywhere stops cleanly at the last
/// complete record (and so that the amount read is exact). A damaged record is skipped and
/// reading goes on at the next trustworthy one.
fn read_linear(buf: &[u8], file: &str) -> Result<Decoder, ReadError> {
    read_linear_into(buf, Decoder::new(file))
}

fn read_linear_into(buf: &[u8], mut dec: Decoder) -> Result<Decoder, ReadError> {
    let mut sans = chunk_reader();
    let mut pos = mcap::MAGIC.len();
    let mut in_data_section = true;
    let mut saw_chunk = false;
    // The damaged chunk whose message indexes (the records right after it) are being read.
    let mut indexing: Option<usize> = None;
    let truncation: Option<(usize, String)> = loop {
        let rest = &buf[pos..];
        if rest.is_empty() {
            break Some((pos, format!("the file ends at byte {pos} with no footer")));
        }
        if rest.len() < RECORD_PREFIX {
            break Some((pos, format!("record header at byte {pos} is cut short")));
        }
        let opcode = rest[0];
        let Some((_, end)) = framed(buf, pos).filter(|_| known_opcode(opcode)) else {
            let why = if known_opcode(opcode) {
                let len = le_u64(&rest[1..]);
                format!(
                    "record (opcode {opcode:#04x}, {len} bytes) at byte {pos} runs past the end \
                     of the file"
                )
            } else {
                format!("record at byte {pos} has no MCAP opcode ({opcode:#04x})")
            };
            if !in_data_section {
                // Past DataEnd only the summary follows: nothing there is a message, so a
                // damaged record costs none; a cut end is still a cut end.
                match resync(buf, pos + 1, saw_chunk, chunk_decodes) {
                    Some(next) => {
                        tracing::warn!(
                            "{}: the summary section is damaged ({why}); every message was read \
                             from the data section",
                            dec.file
                        );
                        pos = next;
                        continue;
                    }
                    None => break Some((pos, why)),
                }
            }
            // A damaged record header, or the file's cut end: the next good record tells.
            match resync(buf, pos + 1, saw_chunk, chunk_decodes) {
                Some(next) => {
                    let i = dec.damage(Damage::new(pos, next - pos, why));
                    // A chunk's message indexes follow it: they tell what it held.
                    indexing = (opcode == op::CHUNK).then_some(i);
                    pos = next;
                    continue;
                }
                None => break Some((pos, why)),
            }
        };
        let record = &buf[pos..end];
        let body = &record[RECORD_PREFIX..];
        if opcode != op::MESSAGE_INDEX {
            indexing = None;
        }
        let result = match opcode {
            op::FOOTER => {
                if buf[end..].starts_with(mcap::MAGIC) {
                    break None;
                }
                break Some((end, "the end magic after the footer is missing".into()));
            }
            op::DATA_END => {
                in_data_section = false;
                Ok(())
            }
            _ if !in_data_section => Ok(()),
            op::CHUNK => {
                saw_chunk = true;
                dec.feed_whole_chunk(&mut sans, record)
            }
            op::MESSAGE_INDEX => {
                if let Some(i) = indexing {
                    let damage = &mut dec.damages[i];
                    if !damage.index.get_or_insert_with(Default::default).add(body) {
                        damage.index = None;
                        indexing = None;
                    }
                }
                Ok(())
            }
            op::SCHEMA | op::CHANNEL | op::MESSAGE => dec.on_record(opcode, body),
            _ => Ok(()),
        };
        match result {
            Ok(()) => {
                dec.settle_neighbours();
                pos = end;
            }
            Err(Failure::Fatal(err)) => return Err(err),
            Err(Failure::Damaged(err)) => {
                sans = chunk_reader();
                let why = format!("record (opcode {opcode:#04x}) at byte {pos}: {err}");
                let i = dec.damage(Damage::new(pos, end - pos, why));
                if can_follow(buf, end) {
                    indexing = (opcode == op::CHUNK).then_some(i);
                    pos = end;
                } else {
                    // Its length is wrong too: look for the next good record inside it.
                    match resync(buf, pos + 1, saw_chunk, chunk_decodes) {
                        Some(next) => {
                            dec.damages[i].length = (next - pos) as u64;
                            pos = next;
                        }
                        None => {
                            let reason = dec.damages.pop().map(|d| d.reason).unwrap_or_default();
                            break Some((pos, reason));
                        }
                    }
                }
            }
        }
    };
    if let Some((bytes_read, reason)) = truncation {
        dec.truncation = Some((bytes_read as u64, reason));
    }
    Ok(dec)
}

/// Whether a whole chunk record decodes (CRC, decompression, records): a resync candidate.
fn chunk_decodes(record: &[u8]) -> bool {
    let mut dec = Decoder::new("");
    dec.raw_only = true;
    dec.feed_whole_chunk(&mut chunk_reader(), record).is_ok()
}

/// A chunk may not claim more than this many times its stored size, plus a floor: a corrupt
/// size must not make a small file allocate a gigabyte (zstd on JSON gives about 10x).
const MAX_CHUNK_EXPANSION: u64 = 1024;
const CHUNK_EXPANSION_FLOOR: u64 = 1 << 20;

enum Failure {
    /// This record is damaged: skip it, report it, go on.
    Damaged(String),
    /// The session itself is unusable (bad header).
    Fatal(ReadError),
}

impl From<mcap::McapError> for Failure {
    fn from(e: mcap::McapError) -> Self {
        Failure::Damaged(e.to_string())
    }
}

/// Where a decoder stood before a chunk, to take back a chunk that fails half-way.
struct Mark {
    messages: u64,
    skipped: u64,
    ignored: u64,
    events: usize,
    had_header: bool,
    raw_headers: usize,
    raw_messages: usize,
    streams: [Vec<usize>; 6],
}

#[derive(Debug, Clone, Copy)]
enum Slot {
    Undefined,
    Session,
    Tracer(usize),
    Env(usize),
    Rotary(usize),
    Machine(usize),
    Probe(usize),
    Event,
    /// A plan kind's own topic, kept as JSON (`KIND_TOPIC_PREFIXES`).
    Json(usize),
    /// A topic we do not read.
    Other,
    /// A known topic with a message encoding other than json: its messages are skipped.
    NotJson,
}

/// Accumulates messages as records arrive, whatever their physical order.
struct Decoder {
    file: String,
    /// By channel id.
    slots: Vec<Slot>,
    tracers: Streams<TracerSample>,
    env: Streams<EnvSample>,
    rotary: Streams<RotaryStateSample>,
    machines: Streams<MachineStateSample>,
    probes: Streams<ProbeSample>,
    json: Streams<serde_json::Value>,
    events: Vec<Stamped<RunEvent>>,
    header: Option<Stamped<SessionHeader>>,
    /// Worker decoders (parallel indexed read) keep `/geocal/session` messages raw, in order.
    lazy_header: bool,
    raw_headers: Vec<(u64, u64, Vec<u8>)>,
    /// A worker met a message on a channel it had no definition for.
    saw_undefined: bool,
    messages: u64,
    skipped: u64,
    ignored: u64,
    truncation: Option<(u64, String)>,
    /// Keep every message raw as well (`read_session_raw`).
    raw: Option<RawLog>,
    /// Only count and keep raw messages: no typed decoding, no header needed (repair).
    raw_only: bool,
    /// Damaged records skipped, in file order.
    damages: Vec<Damage>,
    /// Log times of the messages since the last `settle_neighbours`, and the largest before.
    span_ns: Option<(u64, u64)>,
    last_ns: Option<u64>,
    /// Damages from this index on still wait for the first message after them.
    awaiting_after: usize,
}

/// Schemas, channels and messages as recorded, for `read_session_raw`.
#[derive(Default)]
struct RawLog {
    schemas: HashMap<u16, (String, String, Vec<u8>)>,
    channels: HashMap<u16, std::sync::Arc<RawChannel>>,
    messages: Vec<RawMessage>,
}

impl RawLog {
    /// The schemas and channels the summary defines (a chunk that held a channel's own
    /// record may be the damaged one).
    fn of_summary(summary: &mcap::Summary) -> RawLog {
        let mut log = RawLog::default();
        for (&id, schema) in &summary.schemas {
            let text = (
                schema.name.clone(),
                schema.encoding.clone(),
                schema.data.to_vec(),
            );
            log.schemas.insert(id, text);
        }
        for (&id, channel) in &summary.channels {
            let raw = RawChannel {
                schema: channel
                    .schema
                    .as_ref()
                    .map(|s| (s.name.clone(), s.encoding.clone(), s.data.to_vec())),
                topic: channel.topic.clone(),
                message_encoding: channel.message_encoding.clone(),
                metadata: channel.metadata.clone(),
            };
            log.channels.insert(id, std::sync::Arc::new(raw));
        }
        log
    }
}

const MAX_SKIP_WARNINGS: u64 = 20;

/// The streams of one message kind, by device id (from the topic), in order of definition.
struct Streams<T> {
    ids: HashMap<String, usize>,
    streams: Vec<(String, Vec<Stamped<T>>)>,
}

impl<T> Default for Streams<T> {
    fn default() -> Self {
        Self {
            ids: HashMap::new(),
            streams: Vec::new(),
        }
    }
}

impl<T> Streams<T> {
    /// The index of a device's stream, created on first sight.
    fn index(&mut self, id: &str) -> usize {
        let next = self.streams.len();
        let i = *self.ids.entry(id.to_owned()).or_insert(next);
        if i == next {
            self.streams.push((id.to_owned(), Vec::new()));
        }
        i
    }

    fn push(&mut self, index: usize, log_time_ns: u64, publish_time_ns: u64, msg: T) {
        self.streams[index].1.push(Stamped {
            log_time_ns,
            publish_time_ns,
            msg,
        });
    }

    fn lens(&self) -> Vec<usize> {
        self.streams.iter().map(|(_, v)| v.len()).collect()
    }

    /// Back to the lengths `lens` had; streams created since then are emptied.
    fn truncate(&mut self, lens: &[usize]) {
        for (i, (_, v)) in self.streams.iter_mut().enumerate() {
            v.truncate(lens.get(i).copied().unwrap_or(0));
        }
    }

    /// The same streams (same indices), empty: for a worker decoding later chunks.
    fn empty_like(&self) -> Self {
        Self {
            ids: self.ids.clone(),
            streams: self
                .streams
                .iter()
                .map(|(id, _)| (id.clone(), Vec::new()))
                .collect(),
        }
    }

    /// Append a worker's streams, which come later in the file.
    fn absorb(&mut self, other: Streams<T>) {
        for (id, samples) in other.streams {
            let i = self.index(&id);
            self.streams[i].1.extend(samples);
        }
    }

    /// By id, each stream sorted by log time (stable: equal times keep file order).
    fn into_sorted_map(self) -> BTreeMap<String, Vec<Stamped<T>>> {
        self.streams
            .into_iter()
            .map(|(id, mut v)| {
                v.sort_by_key(|s| s.log_time_ns);
                (id, v)
            })
            .collect()
    }
}

impl Decoder {
    fn new(file: &str) -> Self {
        Decoder {
            file: file.to_owned(),
            slots: Vec::new(),
            tracers: Streams::default(),
            env: Streams::default(),
            rotary: Streams::default(),
            machines: Streams::default(),
            probes: Streams::default(),
            json: Streams::default(),
            events: Vec::new(),
            header: None,
            lazy_header: false,
            raw_headers: Vec::new(),
            saw_undefined: false,
            messages: 0,
            skipped: 0,
            ignored: 0,
            truncation: None,
            raw: None,
            raw_only: false,
            damages: Vec::new(),
            span_ns: None,
            last_ns: None,
            awaiting_after: 0,
        }
    }

    /// Records a damaged record; returns its index in `damages`.
    fn damage(&mut self, mut damage: Damage) -> usize {
        self.settle_neighbours();
        damage.before_ns = self.last_ns;
        self.damages.push(damage);
        self.damages.len() - 1
    }

    /// Dates the damages from the summary's chunk index (see `date_from_chunk_index`); the
    /// read is over, so every neighbour is known by now.
    fn date_damages(&mut self, chunks: &[mcap::records::ChunkIndex]) {
        self.settle_neighbours();
        date_from_chunk_index(&mut self.damages, chunks, &self.file);
        self.awaiting_after = self.damages.len();
    }

    /// The messages read since the last call are good: they bound the damages before them.
    fn settle_neighbours(&mut self) {
        let Some((first, last)) = self.span_ns.take() else {
            return;
        };
        for d in &mut self.damages[self.awaiting_after..] {
            d.after_ns = Some(first);
        }
        self.awaiting_after = self.damages.len();
        self.last_ns = Some(self.last_ns.map_or(last, |l| l.max(last)));
    }

    fn mark(&self) -> Mark {
        Mark {
            messages: self.messages,
            skipped: self.skipped,
            ignored: self.ignored,
            events: self.events.len(),
            had_header: self.header.is_some(),
            raw_headers: self.raw_headers.len(),
            raw_messages: self.raw.as_ref().map_or(0, |r| r.messages.len()),
            streams: [
                self.tracers.lens(),
                self.env.lens(),
                self.rotary.lens(),
                self.machines.lens(),
                self.probes.lens(),
                self.json.lens(),
            ],
        }
    }

    /// Takes back every message decoded since `mark`: a chunk counts whole or not at all.
    fn rollback(&mut self, mark: Mark) {
        self.messages = mark.messages;
        self.skipped = mark.skipped;
        self.ignored = mark.ignored;
        self.events.truncate(mark.events);
        if !mark.had_header {
            self.header = None;
        }
        self.raw_headers.truncate(mark.raw_headers);
        if let Some(raw) = self.raw.as_mut() {
            raw.messages.truncate(mark.raw_messages);
        }
        let [t, e, r, m, p, j] = mark.streams;
        self.tracers.truncate(&t);
        self.env.truncate(&e);
        self.rotary.truncate(&r);
        self.machines.truncate(&m);
        self.probes.truncate(&p);
        self.json.truncate(&j);
        self.span_ns = None;
    }

    /// Feeds one whole chunk record; on failure nothing of it is kept and the reader must be
    /// replaced (its state is undefined).
    fn feed_whole_chunk(&mut self, sans: &mut LinearReader, record: &[u8]) -> Result<(), Failure> {
        if record.len() >= RECORD_PREFIX + 24 {
            let claimed = le_u64(&record[RECORD_PREFIX + 16..]);
            let bound = (record.len() as u64)
                .saturating_mul(MAX_CHUNK_EXPANSION)
                .saturating_add(CHUNK_EXPANSION_FLOOR);
            if claimed > bound {
                return Err(Failure::Damaged(format!(
                    "the chunk claims {claimed} bytes uncompressed from {} stored",
                    record.len()
                )));
            }
        }
        let mark = self.mark();
        let result = self.feed_chunk(sans, record);
        if matches!(result, Err(Failure::Damaged(_))) {
            self.rollback(mark);
        }
        result
    }

    fn define_channel(&mut self, id: u16, topic: &str, encoding: &str) {
        let mut slot = if topic == TOPIC_SESSION {
            Slot::Session
        } else if topic == TOPIC_EVENT {
            Slot::Event
        } else if let Some(tid) = tracer_id(topic) {
            Slot::Tracer(self.tracers.index(tid))
        } else if let Some(eid) = env_id(topic) {
            Slot::Env(self.env.index(eid))
        } else if let Some(rid) = rotary_id(topic) {
            Slot::Rotary(self.rotary.index(rid))
        } else if let Some(mid) = machine_id(topic) {
            Slot::Machine(self.machines.index(mid))
        } else if let Some(pid) = probe_id(topic) {
            Slot::Probe(self.probes.index(pid))
        } else if KIND_TOPIC_PREFIXES.iter().any(|p| topic.starts_with(p)) {
            Slot::Json(self.json.index(topic))
        } else {
            Slot::Other
        };
        if !matches!(slot, Slot::Other) && encoding != "json" {
            tracing::warn!(
                "{}: channel {id} ({topic}) has message encoding {encoding:?}, not \"json\": \
                 its messages are skipped",
                self.file
            );
            slot = Slot::NotJson;
        }
        let i = usize::from(id);
        if self.slots.len() <= i {
            self.slots.resize(i + 1, Slot::Undefined);
        }
        self.slots[i] = slot;
    }

    /// The first `/geocal/session` message is the header; later ones are ignored.
    fn session_message(
        &mut self,
        log_time_ns: u64,
        publish_time_ns: u64,
        data: &[u8],
    ) -> Result<(), Failure> {
        if let Some(first) = &self.header {
            tracing::warn!(
                "{}: another {TOPIC_SESSION} message at log_time {log_time_ns} ns; \
                 keeping the one at {} ns",
                self.file,
                first.log_time_ns
            );
            self.ignored += 1;
            return Ok(());
        }
        let msg = parse_header(&self.file, log_time_ns, data).map_err(Failure::Fatal)?;
        self.header = Some(Stamped {
            log_time_ns,
            publish_time_ns,
            msg,
        });
        Ok(())
    }

    /// An empty decoder with the same channels, for a thread that decodes a later run of chunks.
    fn worker(&self) -> Decoder {
        let mut w = Decoder::new(&self.file);
        w.slots = self.slots.clone();
        w.tracers = self.tracers.empty_like();
        w.env = self.env.empty_like();
        w.rotary = self.rotary.empty_like();
        w.machines = self.machines.empty_like();
        w.probes = self.probes.empty_like();
        w.json = self.json.empty_like();
        w.lazy_header = true;
        w
    }

    /// Appends what a worker decoded from the chunks that follow this decoder's chunks.
    fn absorb(&mut self, other: Decoder) -> Result<(), Failure> {
        self.messages += other.messages;
        self.skipped += other.skipped;
        self.ignored += other.ignored;
        self.tracers.absorb(other.tracers);
        self.env.absorb(other.env);
        self.rotary.absorb(other.rotary);
        self.machines.absorb(other.machines);
        self.probes.absorb(other.probes);
        self.json.absorb(other.json);
        self.events.extend(other.events);
        self.damages.extend(other.damages);
        for (log_time_ns, publish_time_ns, data) in other.raw_headers {
            self.session_message(log_time_ns, publish_time_ns, &data)?;
        }
        Ok(())
    }

    /// Feeds whole chunk records, skipping (and noting) damaged ones; fails only when the
    /// session itself is unusable.
    fn feed_chunks(&mut self, buf: &[u8], ranges: &[(usize, usize)]) -> Result<(), ReadError> {
        let mut sans = chunk_reader();
        for &(s, e) in ranges {
            match self.feed_whole_chunk(&mut sans, &buf[s..e]) {
                Ok(()) => {}
                Err(Failure::Fatal(err)) => return Err(err),
                Err(Failure::Damaged(why)) => {
                    sans = chunk_reader();
                    let why = format!("chunk at byte {s}: {why}");
                    self.damage(Damage::new(s, e - s, why));
                }
            }
        }
        Ok(())
    }

    fn reserve(&mut self, channel_id: u16, n: u64) {
        let n = usize::try_from(n).unwrap_or(0);
        match self.slots.get(usize::from(channel_id)) {
            Some(Slot::Tracer(i)) => self.tracers.streams[*i].1.reserve(n),
            Some(Slot::Env(i)) => self.env.streams[*i].1.reserve(n),
            Some(Slot::Rotary(i)) => self.rotary.streams[*i].1.reserve(n),
            Some(Slot::Machine(i)) => self.machines.streams[*i].1.reserve(n),
            Some(Slot::Probe(i)) => self.probes.streams[*i].1.reserve(n),
            Some(Slot::Json(i)) => self.json.streams[*i].1.reserve(n),
            Some(Slot::Event) => self.events.reserve(n),
            _ => {}
        }
    }

    /// Feeds one whole chunk record (opcode and length included) and takes its records.
    fn feed_chunk(&mut self, sans: &mut LinearReader, record: &[u8]) -> Result<(), Failure> {
        sans.insert(record.len()).copy_from_slice(record);
        sans.notify_read(record.len());
        while let Some(event) = sans.next_event() {
            match event? {
                // The chunk is used up: the reader wants the next top-level record.
                LinearReadEvent::ReadRequest(_) => return Ok(()),
                LinearReadEvent::Record { opcode, data } => self.on_record(opcode, data)?,
            }
        }
        Ok(())
    }

    fn on_record(&mut self, opcode: u8, body: &[u8]) -> Result<(), Failure> {
        match opcode {
            op::SCHEMA => {
                if let Some(raw) = self.raw.as_mut() {
                    if let mcap::records::Record::Schema { header, data } =
                        mcap::parse_record(opcode, body)?
                    {
                        let schema = (header.name, header.encoding, data.into_owned());
                        raw.schemas.insert(header.id, schema);
                    }
                }
                Ok(())
            }
            op::CHANNEL => {
                if let mcap::records::Record::Channel(ch) = mcap::parse_record(opcode, body)? {
                    self.define_channel(ch.id, &ch.topic, &ch.message_encoding);
                    if let Some(raw) = self.raw.as_mut() {
                        let channel = RawChannel {
                            schema: raw.schemas.get(&ch.schema_id).cloned(),
                            topic: ch.topic,
                            message_encoding: ch.message_encoding,
                            metadata: ch.metadata,
                        };
                        raw.channels.insert(ch.id, std::sync::Arc::new(channel));
                    }
                }
                Ok(())
            }
            op::MESSAGE => {
                // channel_id u16, sequence u32, log_time u64, publish_time u64, then the data.
                // Parsed by hand: this runs for every message.
                if body.len() < 22 {
                    return Err(mcap::McapError::UnexpectedEoc.into());
                }
                let channel_id = u16::from_le_bytes([body[0], body[1]]);
                let log_time = le_u64(&body[6..14]);
                let publish_time = le_u64(&body[14..22]);
                if let Some(raw) = self.raw.as_mut() {
                    if let Some(channel) = raw.channels.get(&channel_id) {
                        raw.messages.push(RawMessage {
                            channel: channel.clone(),
                            log_time_ns: log_time,
                            publish_time_ns: publish_time,
                            data: body[22..].to_vec(),
                        });
                    }
                }
                self.on_message(channel_id, log_time, publish_time, &body[22..])
            }
            _ => Ok(()),
        }
    }

    fn on_message(
        &mut self,
        channel_id: u16,
        log_time_ns: u64,
        publish_time_ns: u64,
        data: &[u8],
    ) -> Result<(), Failure> {
        self.messages += 1;
        self.span_ns = Some(match self.span_ns {
            None => (log_time_ns, log_time_ns),
            Some((a, b)) => (a.min(log_time_ns), b.max(log_time_ns)),
        });
        if self.raw_only {
            return Ok(());
        }
        let slot = self
            .slots
            .get(usize::from(channel_id))
            .copied()
            .unwrap_or(Slot::Undefined);
        match slot {
            Slot::Tracer(i) => {
                if let Some(msg) = self.parse::<TracerSample>(channel_id, log_time_ns, data) {
                    self.tracers.push(i, log_time_ns, publish_time_ns, msg);
                }
            }
            Slot::Env(i) => {
                if let Some(msg) = self.parse::<EnvSample>(channel_id, log_time_ns, data) {
                    self.env.push(i, log_time_ns, publish_time_ns, msg);
                }
            }
            Slot::Rotary(i) => {
                if let Some(msg) = self.parse::<RotaryStateSample>(channel_id, log_time_ns, data) {
                    self.rotary.push(i, log_time_ns, publish_time_ns, msg);
                }
            }
            Slot::Machine(i) => {
                if let Some(msg) = self.parse::<MachineStateSample>(channel_id, log_time_ns, data) {
                    self.machines.push(i, log_time_ns, publish_time_ns, msg);
                }
            }
            Slot::Probe(i) => {
                if let Some(msg) = self.parse::<ProbeSample>(channel_id, log_time_ns, data) {
                    self.probes.push(i, log_time_ns, publish_time_ns, msg);
                }
            }
            Slot::Json(i) => {
                if let Some(msg) = self.parse::<serde_json::Value>(channel_id, log_time_ns, data) {
                    self.json.push(i, log_time_ns, publish_time_ns, msg);
                }
            }
            Slot::Event => {
                if let Some(msg) = self.parse::<RunEvent>(channel_id, log_time_ns, data) {
                    self.events.push(Stamped {
                        log_time_ns,
                        publish_time_ns,
                        msg,
                    });
                }
            }
            Slot::Session if self.lazy_header => {
                self.raw_headers
                    .push((log_time_ns, publish_time_ns, data.to_vec()));
            }
            Slot::Session => self.session_message(log_time_ns, publish_time_ns, data)?,
            Slot::NotJson => self.skip(channel_id, log_time_ns, "message encoding is not json"),
            Slot::Other => self.ignored += 1,
            Slot::Undefined if self.lazy_header => {
                self.saw_undefined = true;
                self.ignored += 1;
            }
            Slot::Undefined => {
                if self.ignored == 0 {
                    tracing::warn!(
                        "{}: message at log_time {log_time_ns} ns on channel {channel_id}, \
                         which was never declared: ignored",
                        self.file
                    );
                }
                self.ignored += 1;
            }
        }
        Ok(())
    }

    fn parse<T: DeserializeOwned>(
        &mut self,
        channel_id: u16,
        log_time_ns: u64,
        data: &[u8],
    ) -> Option<T> {
        match serde_json::from_slice(data) {
            Ok(msg) => Some(msg),
            Err(err) => {
                self.skip(channel_id, log_time_ns, &err.to_string());
                None
            }
        }
    }

    fn skip(&mut self, channel_id: u16, log_time_ns: u64, why: &str) {
        self.skipped += 1;
        if self.skipped <= MAX_SKIP_WARNINGS {
            tracing::warn!(
                "{}: skipping the message on {} at log_time {log_time_ns} ns: {why}",
                self.file,
                self.topic_of(channel_id)
            );
        }
    }

    fn topic_of(&self, channel_id: u16) -> String {
        match self.slots.get(usize::from(channel_id)) {
            Some(Slot::Tracer(i)) => format!("/tracer/{}/range", self.tracers.streams[*i].0),
            Some(Slot::Env(i)) => format!("/env/{}", self.env.streams[*i].0),
            Some(Slot::Rotary(i)) => format!("/rotary/{}/state", self.rotary.streams[*i].0),
            Some(Slot::Machine(i)) => format!("/machine/{}/state", self.machines.streams[*i].0),
            Some(Slot::Probe(i)) => format!("/probe/{}/reading", self.probes.streams[*i].0),
            Some(Slot::Json(i)) => self.json.streams[*i].0.clone(),
            Some(Slot::Event) => TOPIC_EVENT.to_owned(),
            Some(Slot::Session) => TOPIC_SESSION.to_owned(),
            _ => match self.raw.as_ref().and_then(|r| r.channels.get(&channel_id)) {
                Some(channel) => channel.topic.clone(),
                None => format!("channel {channel_id}"),
            },
        }
    }

    /// Whether the file was read to its end magic; warns when it was not.
    fn completeness(&mut self, file: &str, file_bytes: u64) -> Completeness {
        let Some((bytes_read, reason)) = self.truncation.take() else {
            return Completeness::Complete;
        };
        tracing::warn!(
            "{file} is incomplete: read {bytes_read} of {file_bytes} bytes ({} messages): \
             {reason}; run `geocal repair {file}` for a complete copy, or resume the run with \
             `geocal run --resume DIR`",
            self.messages
        );
        Completeness::Truncated {
            bytes_read,
            file_bytes,
            messages_read: self.messages,
            reason,
        }
    }

    /// The damaged records as reported, each warned about once.
    fn damaged_chunks(&mut self, file: &str) -> Vec<DamagedChunk> {
        self.settle_neighbours();
        let damages = std::mem::take(&mut self.damages);
        damages
            .into_iter()
            .map(|d| {
                let chunk = d.finish(|channel| self.topic_of(channel));
                tracing::warn!(
                    "{file}: damaged, skipped {}; run `geocal repair {file}` for a clean copy",
                    chunk.describe()
                );
                chunk
            })
            .collect()
    }

    fn into_session(mut self, file: &str, file_bytes: u64) -> Result<Session, ReadError> {
        let damaged = self.damaged_chunks(file);
        let completeness = self.completeness(file, file_bytes);
        let Some(header) = self.header else {
            let truncated = match &completeness {
                Completeness::Complete => String::new(),
                Completeness::Truncated { bytes_read, .. } => {
                    format!("; the file is cut short after byte {bytes_read}")
                }
            };
            return Err(ReadError::NoHeader {
                file: file.to_owned(),
                messages: self.messages,
                truncated,
            });
        };
        if self.skipped > 0 {
            tracing::warn!(
                "{file}: {} messages on known topics could not be parsed and were skipped",
                self.skipped
            );
        }
        // Stable sorts: equal log times keep file order. Nearly free on already sorted data.
        let tracers = self.tracers.into_sorted_map();
        let env = self.env.into_sorted_map();
        let rotary = self.rotary.into_sorted_map();
        let machines = self.machines.into_sorted_map();
        let probes = self.probes.into_sorted_map();
        let topics = self.json.into_sorted_map();
        let mut events = self.events;
        events.sort_by_key(|s| s.log_time_ns);
        let lost_before_repair = events
            .iter()
            .filter_map(|e| match &e.msg {
                RunEvent::DataLost { lost } => Some(lost.clone()),
                _ => None,
            })
            .collect();
        Ok(Session {
            header: header.msg,
            tracers,
            env,
            rotary,
            machines,
            probes,
            events,
            topics,
            completeness,
            damaged,
            lost_before_repair,
            skipped: self.skipped,
            ignored: self.ignored,
        })
    }
}

/// Topics of plan kinds that the reader keeps as JSON for the kind's method.
const KIND_TOPIC_PREFIXES: [&str; 3] = ["/probe/", "/machine/", "/hexapod/"];

fn tracer_id(topic: &str) -> Option<&str> {
    let id = topic.strip_prefix("/tracer/")?.strip_suffix("/range")?;
    (!id.is_empty() && !id.contains('/')).then_some(id)
}

fn env_id(topic: &str) -> Option<&str> {
    let id = topic.strip_prefix("/env/")?;
    (!id.is_empty() && !id.contains('/')).then_some(id)
}

fn rotary_id(topic: &str) -> Option<&str> {
    let id = topic.strip_prefix("/rotary/")?.strip_suffix("/state")?;
    (!id.is_empty() && !id.contains('/')).then_some(id)
}

fn machine_id(topic: &str) -> Option<&str> {
    let id = topic.strip_prefix("/machine/")?.strip_suffix("/state")?;
    (!id.is_empty() && !id.contains('/')).then_some(id)
}

fn probe_id(topic: &str) -> Option<&str> {
    let id = topic.strip_prefix("/probe/")?.strip_suffix("/reading")?;
    (!id.is_empty() && !id.contains('/')).then_some(id)
}

fn parse_header(file: &str, log_time_ns: u64, data: &[u8]) -> Result<SessionHeader, ReadError> {
    #[derive(Deserialize)]
    struct FormatOnly {
        format: Option<String>,
    }
    let wrong_format = |found: String| ReadError::WrongFormat {
        file: file.to_owned(),
        found,
    };
    match serde_json::from_slice::<SessionHeader>(data) {
        Ok(h) if h.format == SESSION_FORMAT => Ok(h),
        Ok(h) => Err(wrong_format(h.format)),
        Err(error) => match serde_json::from_slice::<FormatOnly>(data) {
            // A header of another format version fails for that reason first.
            Ok(FormatOnly {
                format: Some(found),
            }) if found != SESSION_FORMAT => Err(wrong_format(found)),
            _ => Err(ReadError::BadHeader {
                file: file.to_owned(),
                log_time_ns,
                error,
            }),
        },
    }
}

/// Shared by the session tests: a realistic header and sample streams.
#[cfg(test)]
pub(crate) mod testutil {
    use std::collections::BTreeMap;

    use crate::session::messages::*;

    pub fn header() -> SessionHeader {
        let mut extra = BTreeMap::new();
        extra.insert("rate_hz".to_owned(), serde_json::json!(1000));
        SessionHeader {
            format: SESSION_FORMAT.to_owned(),
            session_id: "s-test-1".to_owned(),
            started_at: "2026-11-01T10:00:00Z".to_owned(),
            kind: "multilateration".to_owned(),
            machine: MachineInfo {
                name: "mill".to_owned(),
                structure: "FYXZ".to_owned(),
                axes: vec!["x".into(), "y".into(), "z".into()],
                travel_m: [("x".to_owned(), [0.0, 0.8]), ("y".to_owned(), [0.0, 0.6])]
                    .into_iter()
                    .collect(),
                targets: vec![TargetInfo {
                    id: "t0".into(),
                    offset_m: [0.0, 0.0, 0.1],
                }],
            },
            devices: vec![DeviceInfo {
                id: "tracer0".into(),
                kind: "tracer".into(),
                driver: "sim".into(),
                noise_m: Some(5e-8),
                noise_ppm: Some(0.1),
                dead_path_m: Some(0.1),
                wavelength_m: Some(6.33e-7),
                compensated: Some(true),
                extra,
            }],
            plan: serde_json::json!({"stations": 2, "passes": 3}),
        }
    }

    pub fn tracer_sample(seq: u64) -> TracerSample {
        TracerSample {
            seq,
            t_s: seq as f64 * 1e-3,
            length_m: 0.1 + (seq as f64 * 0.37).sin() * 0.05 + seq as f64 * 1.234_567_89e-6,
            signal: 0.9 + (seq % 7) as f64 * 0.01,
            tracking: seq % 97 != 5,
            beam_segment: (seq / 1000) as u32,
        }
    }

    pub fn env_sample(i: u64) -> EnvSample {
        EnvSample {
            t_s: i as f64,
            air_temp_k: 293.15 + i as f64 * 1e-3,
            pressure_pa: 101_325.0 - i as f64,
            humidity_pct: 45.0,
            material_temp_k: if i % 2 == 0 {
                vec![293.2, 293.1]
            } else {
                vec![]
            },
        }
    }

    pub fn events() -> Vec<RunEvent> {
        vec![
            RunEvent::StationBegin {
                station: "s1".into(),
                station_index: 0,
                hint_m: Some([0.1, 0.2, 0.3]),
            },
            RunEvent::PointBegin {
                station: "s1".into(),
                point: 0,
                pass: 0,
                target: "t0".into(),
                nominal_m: [0.4, 0.3, -0.1],
                axes: [("x".to_owned(), 0.4), ("y".to_owned(), 0.3)]
                    .into_iter()
                    .collect(),
                approach: [("x".to_owned(), 1), ("y".to_owned(), -1)]
                    .into_iter()
                    .collect(),
            },
            RunEvent::PointEnd {
                station: "s1".into(),
                point: 0,
                pass: 0,
            },
            RunEvent::Rehome {
                station: "s1".into(),
                beam_segment: 1,
            },
            RunEvent::Fault {
                device: "tracer0".into(),
                code: "beam".into(),
                message: "beam broken".into(),
            },
            RunEvent::StationEnd {
                station: "s1".into(),
            },
        ]
    }
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;
    use std::io::Cursor;

    use mcap::records::MessageHeader;
    use proptest::prelude::*;

    use super::testutil::*;
    use super::*;
    use crate::session::messages::{self, schema};
    use crate::session::recorder::{Compression, Recorder, RecorderOptions};

    /// Writes with mcap::Writer directly, the way another tool would: given options, channels
    /// declared tracer-first, the header not physically first, hand-written JSON with extra
    /// fields and another field order, an unknown topic and one broken sample.
    fn foreign_file(opts: mcap::WriteOptions) -> Vec<u8> {
        let mut w = opts.create(Cursor::new(Vec::new())).unwrap();
        let no_meta = BTreeMap::new();
        let ts = w
            .add_schema(
                "geocal.TracerSample",
                "jsonschema",
                schema::TRACER.as_bytes(),
            )
            .unwrap();
        let tracer = w
            .add_channel(ts, "/tracer/laser-b/range", "json", &no_meta)
            .unwrap();
        let other = w.add_channel(0, "/vendor/pose", "json", &no_meta).unwrap();
        let es = w
            .add_schema("geocal.RunEvent", "jsonschema", schema::EVENT.as_bytes())
            .unwrap();
        let event = w.add_channel(es, "/run/event", "json", &no_meta).unwrap();
        let put = |w: &mut mcap::Writer<Cursor<Vec<u8>>>, ch: u16, t: u64, json: &str| {
            let hdr = MessageHeader {
                channel_id: ch,
                sequence: 0,
                log_time: t,
                publish_time: t + 7,
            };
            w.write_to_known_channel(&hdr, json.as_bytes()).unwrap();
        };
        // Samples before the header, and out of log-time order.
        for i in (0..50u64).rev() {
            let json = format!(
                r#"{{"beam_segment":0,"future_field":{{"a":[1,2]}},"length_m":{},"t_s":{},"seq":{i}}}"#,
                0.5 + i as f64 * 1e-6,
                i as f64 * 0.1
            );
            put(&mut w, tracer, 1_000 + i, &json);
        }
        put(&mut w, other, 1_001, r#"{"x":1}"#);
        put(&mut w, tracer, 1_002, r#"{"seq":"not a number"}"#);
        let ss = w
            .add_schema("geocal.Session", "jsonschema", schema::SESSION.as_bytes())
            .unwrap();
        let session = w
            .add_channel(ss, "/geocal/session", "json", &no_meta)
            .unwrap();
        let header = serde_json::to_string(&header()).unwrap();
        // Same header, with an extra field and the format last.
        let mut v: serde_json::Value = serde_json::from_str(&header).unwrap();
        v["vendor_notes"] = serde_json::json!("made elsewhere");
        put(&mut w, session, 500, &v.to_string());
        put(
            &mut w,
            event,
            1_200,
            r#"{"station":"s1","kind":"station_begin","station_index":0,"extra":true}"#,
        );
        put(
            &mut w,
            event,
            1_300,
            r#"{"kind":"a_new_kind","station":"s1"}"#,
        );
        w.finish().unwrap();
        w.into_inner().into_inner()
    }

    fn check_foreign(bytes: &[u8]) {
        let s = read_session_bytes(bytes).unwrap();
        assert_eq!(s.header, header());
        assert!(s.completeness.is_complete(), "{:?}", s.completeness);
        let t = &s.tracers["laser-b"];
        assert_eq!(t.len(), 50);
        for (i, st) in t.iter().enumerate() {
            assert_eq!(st.log_time_ns, 1_000 + i as u64);
            assert_eq!(st.publish_time_ns, st.log_time_ns + 7);
            assert_eq!(st.msg.seq, i as u64);
            assert_eq!(st.msg.length_m, 0.5 + i as f64 * 1e-6);
            // Defaults from the contract for missing optional fields.
            assert_eq!(st.msg.signal, 1.0);
            assert!(st.msg.tracking);
        }
        assert_eq!(s.skipped, 1);
        assert_eq!(s.ignored, 1);
        assert_eq!(s.events.len(), 2);
        assert_eq!(
            s.events[0].msg,
            RunEvent::StationBegin {
                station: "s1".into(),
                station_index: 0,
                hint_m: None
            }
        );
        assert_eq!(s.events[1].msg, RunEvent::Other);
        assert!(s.env.is_empty());
    }

    #[test]
    fn reads_other_writers() {
        let variants = [
            mcap::WriteOptions::new()
                .compression(Some(mcap::Compression::Lz4))
                .chunk_size(Some(200)),
            mcap::WriteOptions::new()
                .compression(Some(mcap::Compression::Zstd))
                .chunk_size(Some(1)),
            mcap::WriteOptions::new()
                .compression(None)
                .chunk_size(Some(700)),
            mcap::WriteOptions::new().use_chunks(false),
            mcap::WriteOptions::new()
                .use_chunks(false)
                .emit_summary_records(false)
                .emit_statistics(false)
                .emit_summary_offsets(false),
            mcap::WriteOptions::new()
                .chunk_size(Some(300))
                .emit_chunk_indexes(false)
                .emit_statistics(false),
        ];
        for opts in variants {
            let bytes = foreign_file(opts.clone());
            check_foreign(&bytes);
            // And the same file cut before its summary: linear reading finds the same data.
            let data_end = data_end_offset(&bytes);
            let s = read_session_bytes(&bytes[..data_end]).unwrap();
            assert!(!s.completeness.is_complete());
            assert_eq!(s.tracers["laser-b"].len(), 50, "{opts:?}");
        }
    }

    /// Offset of the DataEnd record, found by walking the top-level records.
    fn data_end_offset(bytes: &[u8]) -> usize {
        let mut pos = 8;
        loop {
            let len = u64::from_le_bytes(bytes[pos + 1..pos + 9].try_into().unwrap()) as usize;
            if bytes[pos] == op::DATA_END {
                return pos;
            }
            pos += 9 + len;
        }
    }

    #[test]
    fn errors_are_clear() {
        let e = read_session_bytes(b"PK\x03\x04 not an mcap at all").unwrap_err();
        assert!(matches!(e, ReadError::NotMcap { .. }), "{e}");
        assert!(e.to_string().contains("not an MCAP file"), "{e}");
        let e = read_session_bytes(&mcap::MAGIC[..3]).unwrap_err();
        assert!(matches!(e, ReadError::NotMcap { .. }), "{e}");

        // A valid MCAP with no header message.
        let mut w = mcap::Writer::new(Cursor::new(Vec::new())).unwrap();
        let ch = w
            .add_channel(0, "/tracer/a/range", "json", &BTreeMap::new())
            .unwrap();
        let hdr = MessageHeader {
            channel_id: ch,
            sequence: 0,
            log_time: 1,
            publish_time: 1,
        };
        w.write_to_known_channel(&hdr, br#"{"seq":0,"t_s":0,"length_m":0}"#)
            .unwrap();
        w.finish().unwrap();
        let e = read_session_bytes(&w.into_inner().into_inner()).unwrap_err();
        assert!(
            e.to_string().contains("has no /geocal/session message"),
            "{e}"
        );

        // Wrong format string, and a header that does not parse.
        for (json, want) in [
            (
                serde_json::to_string(&SessionHeader {
                    format: "geocal-session/2".into(),
                    ..header()
                })
                .unwrap(),
                "expected \"geocal-session/1\"",
            ),
            (
                r#"{"format":"geocal-session/1"}"#.to_owned(),
                "does not parse",
            ),
        ] {
            let mut w = mcap::Writer::new(Cursor::new(Vec::new())).unwrap();
            let ch = w
                .add_channel(0, "/geocal/session", "json", &BTreeMap::new())
                .unwrap();
            w.write_to_known_channel(
                &MessageHeader {
                    channel_id: ch,
                    ..hdr
                },
                json.as_bytes(),
            )
            .unwrap();
            w.finish().unwrap();
            let e = read_session_bytes(&w.into_inner().into_inner()).unwrap_err();
            assert!(e.to_string().contains(want), "{e}");
            assert!(e.to_string().contains("in-memory"), "{e}");
        }
    }

    #[test]
    fn missing_file_names_the_path() {
        let e = read_session(Path::new("/nonexistent/dir/s.mcap")).unwrap_err();
        assert!(e.to_string().contains("/nonexistent/dir/s.mcap"), "{e}");
    }

    /// A session written by our recorder with small chunks, plus where each chunk ends.
    struct Recorded {
        bytes: Vec<u8>,
        /// (end offset of the chunk record, last log time in it), in file order.
        chunk_ends: Vec<(usize, u64)>,
        tracers: BTreeMap<String, Vec<TracerSample>>,
        /// log times of every message, all distinct.
        all_log_times: Vec<u64>,
    }

    fn recorded() -> &'static Recorded {
        static CELL: std::sync::OnceLock<Recorded> = std::sync::OnceLock::new();
        CELL.get_or_init(|| {
            let dir = tempfile::tempdir().unwrap();
            let path = dir.path().join("t.mcap");
            let rec = Recorder::create(
                &path,
                RecorderOptions {
                    chunk_size: 2048,
                    flush_interval: std::time::Duration::from_secs(3600),
                    compression: Compression::Zstd,
                    tap: Default::default(),
                },
            )
            .unwrap();
            let h = rec.handle();
            let mut t = 1_000_000u64;
            let mut all_log_times = vec![];
            let mut stamp = || {
                t += 1000;
                all_log_times.push(t);
                t
            };
            h.session(&header(), stamp());
            let mut tracers: BTreeMap<String, Vec<TracerSample>> = BTreeMap::new();
            let evs = events();
            for i in 0..1500u64 {
                let id = if i % 3 == 0 { "tracer1" } else { "tracer0" };
                let v = tracers.entry(id.to_owned()).or_default();
                let s = tracer_sample(v.len() as u64);
                v.push(s);
                h.tracer(id, &s, stamp());
                if i % 100 == 0 {
                    h.env("air", &env_sample(i / 100), stamp());
                    h.event(&evs[(i / 100) as usize % evs.len()], stamp());
                }
            }
            rec.finish().unwrap();
            let bytes = std::fs::read(&path).unwrap();
            let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
            let mut chunk_ends: Vec<(usize, u64)> = summary
                .chunk_indexes
                .iter()
                .map(|c| {
                    (
                        (c.chunk_start_offset + c.chunk_length) as usize,
                        c.message_end_time,
                    )
                })
                .collect();
            chunk_ends.sort();
            Recorded {
                bytes,
                chunk_ends,
                tracers,
                all_log_times,
            }
        })
    }

    #[test]
    fn recorded_file_has_many_chunks_and_reads_complete() {
        let r = recorded();
        assert!(r.chunk_ends.len() > 20, "{}", r.chunk_ends.len());
        let s = read_session_bytes(&r.bytes).unwrap();
        assert!(s.completeness.is_complete());
        for (id, v) in &r.tracers {
            let got: Vec<_> = s.tracers[id].iter().map(|st| st.msg).collect();
            assert_eq!(&got, v);
        }
    }

    fn check_cut(cut: usize) {
        let r = recorded();
        let bytes = &r.bytes[..cut];
        let result = read_session_bytes(bytes);
        // The header is alone in the first chunk (the recorder flushes right after it).
        let header_end = r.chunk_ends[0].0;
        if cut < header_end {
            assert!(result.is_err(), "cut {cut}: read a header that was cut");
            return;
        }
        let s = result.unwrap_or_else(|e| panic!("cut {cut}: {e}"));
        assert_eq!(s.header, header());
        if cut == r.bytes.len() {
            assert!(s.completeness.is_complete());
        } else {
            match &s.completeness {
                Completeness::Truncated {
                    bytes_read,
                    file_bytes,
                    ..
                } => {
                    assert_eq!(*file_bytes, cut as u64);
                    assert!(*bytes_read <= cut as u64);
                }
                Completeness::Complete => panic!("cut {cut}: reported complete"),
            }
        }
        // Every sample read is the original one at that position (a prefix per tracer).
        let mut n = 1;
        for (id, got) in &s.tracers {
            let orig = &r.tracers[id];
            assert!(got.len() <= orig.len());
            for (i, st) in got.iter().enumerate() {
                assert_eq!(st.msg, orig[i], "cut {cut}, tracer {id}, index {i}");
            }
            n += got.len();
        }
        n += s.env.values().map(Vec::len).sum::<usize>() + s.events.len();
        // Every message of every chunk that ended before the cut is there, and nothing of a
        // chunk that did not.
        let last_complete = r
            .chunk_ends
            .iter()
            .take_while(|(end, _)| *end <= cut)
            .last()
            .map(|c| c.1)
            .unwrap_or(0);
        let expected = r
            .all_log_times
            .iter()
            .filter(|&&t| t <= last_complete)
            .count();
        assert_eq!(n, expected, "cut {cut}");
    }

    #[test]
    fn truncation_at_every_chunk_boundary() {
        let r = recorded();
        for &(end, _) in &r.chunk_ends {
            for cut in [end - 1, end, end + 1] {
                check_cut(cut.min(r.bytes.len()));
            }
        }
        check_cut(r.bytes.len());
        check_cut(r.bytes.len() - 1);
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(256))]
        #[test]
        fn truncated_anywhere_reads_a_prefix(frac in 0.0f64..=1.0) {
            let len = recorded().bytes.len();
            check_cut(((len as f64) * frac) as usize);
        }

        #[test]
        fn garbage_never_panics(cut in 0usize..20_000, flip in 0usize..20_000, byte: u8) {
            let r = recorded();
            let mut bytes = r.bytes[..cut.min(r.bytes.len())].to_vec();
            if let Some(b) = bytes.get_mut(flip) {
                *b ^= byte;
            }
            let _ = read_session_bytes(&bytes);
        }
    }

    #[test]
    fn complete_files_are_read_through_the_index() {
        let r = recorded();
        let summary = mcap::Summary::read(&r.bytes).unwrap().unwrap();
        let dec = read_indexed(&r.bytes, "x", &summary).unwrap();
        assert!(dec.is_some(), "indexed path fell back to linear");
        let linear = read_linear(&r.bytes, "x").unwrap();
        assert!(linear.truncation.is_none());
        let (a, b) = (
            dec.unwrap().into_session("x", 0).unwrap(),
            linear.into_session("x", 0).unwrap(),
        );
        assert_eq!(a, b);
        // Unchunked messages are not in any chunk index: the reader must notice and go linear.
        let bytes = foreign_file(mcap::WriteOptions::new().use_chunks(false));
        let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
        assert!(read_indexed(&bytes, "x", &summary).unwrap().is_none());
    }

    /// The threaded indexed read gives exactly what one thread and the linear read give.
    #[test]
    fn threads_read_the_same_session() {
        let foreign = foreign_file(
            mcap::WriteOptions::new()
                .compression(Some(mcap::Compression::Zstd))
                .chunk_size(Some(1)),
        );
        for bytes in [&recorded().bytes, &foreign] {
            let summary = mcap::Summary::read(bytes).unwrap().unwrap();
            assert!(summary.chunk_indexes.len() > 8);
            let serial = read_indexed_with(bytes, "x", &summary, 1, false)
                .unwrap()
                .expect("indexed")
                .into_session("x", 0)
                .unwrap();
            let linear = read_linear(bytes, "x")
                .unwrap()
                .into_session("x", 0)
                .unwrap();
            assert_eq!(serial, linear);
            for threads in 2..=7 {
                let dec = read_indexed_with(bytes, "x", &summary, threads, false)
                    .unwrap()
                    .expect("indexed");
                assert_eq!(
                    dec.into_session("x", 0).unwrap(),
                    serial,
                    "{threads} threads"
                );
            }
        }
        check_foreign(&foreign);
    }

    /// A second header in a later run of chunks is ignored, and a bad one there still fails
    /// only when it is the first header.
    #[test]
    fn threads_keep_the_first_header() {
        let write = |headers: &[&[u8]]| {
            let mut w = mcap::WriteOptions::new()
                .chunk_size(Some(1))
                .create(Cursor::new(Vec::new()))
                .unwrap();
            let no_meta = BTreeMap::new();
            let hs = w
                .add_schema("geocal.Session", "jsonschema", schema::SESSION.as_bytes())
                .unwrap();
            let hc = w.add_channel(hs, TOPIC_SESSION, "json", &no_meta).unwrap();
            let ts = w
                .add_schema(
                    "geocal.TracerSample",
                    "jsonschema",
                    schema::TRACER.as_bytes(),
                )
                .unwrap();
            let tc = w
                .add_channel(ts, "/tracer/a/range", "json", &no_meta)
                .unwrap();
            let mut t = 0;
            let mut put = |w: &mut mcap::Writer<_>, ch: u16, data: &[u8]| {
                t += 1;
                let hdr = MessageHeader {
                    channel_id: ch,
                    sequence: 0,
                    log_time: t,
                    publish_time: t,
                };
                w.write_to_known_channel(&hdr, data).unwrap();
            };
            // Samples before every header, so that with threads the first header lies in a
            // worker's run of chunks.
            for h in headers {
                for i in 0..20 {
                    let json = serde_json::to_vec(&tracer_sample(i)).unwrap();
                    put(&mut w, tc, &json);
                }
                put(&mut w, hc, h);
            }
            w.finish().unwrap();
            w.into_inner().into_inner()
        };
        let good = serde_json::to_vec(&header()).unwrap();
        let bad = b"{\"format\": \"geocal-session/1\"}".to_vec();
        let read = |bytes: &[u8], threads| {
            let summary = mcap::Summary::read(bytes).unwrap().unwrap();
            read_indexed_with(bytes, "x", &summary, threads, false)
                .map(|d| d.expect("indexed").into_session("x", 0).unwrap())
        };
        let bytes = write(&[&good, &bad, &good]);
        let serial = read(&bytes, 1).unwrap();
        assert_eq!(serial.header, header());
        assert_eq!(serial.ignored, 2);
        for threads in 2..=5 {
            assert_eq!(read(&bytes, threads).unwrap(), serial);
        }
        let bytes = write(&[&bad, &good]);
        for threads in 1..=5 {
            assert!(matches!(
                read(&bytes, threads),
                Err(ReadError::BadHeader { .. })
            ));
        }
    }

    #[test]
    fn split_by_bytes_keeps_order_and_balance() {
        let ranges: Vec<(usize, usize)> = (0..10).map(|i| (i * 10, i * 10 + 10)).collect();
        for parts in 0..=12 {
            let groups = split_by_bytes(&ranges, parts);
            assert!(!groups.is_empty() && groups.len() <= parts.max(1));
            assert_eq!(groups.concat(), ranges, "{parts} parts");
            assert!(groups.iter().all(|g| !g.is_empty()));
        }
        assert_eq!(
            split_by_bytes(&ranges, 2)
                .iter()
                .map(|g| g.len())
                .collect::<Vec<_>>(),
            [5, 5]
        );
        assert!(split_by_bytes(&[], 3).is_empty());
    }

    /// `cargo test --release --lib session::reader::tests::large -- --ignored --nocapture`
    #[test]
    #[ignore = "performance check, run in release"]
    fn large_session_reads_fast() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("big.mcap");
        let t0 = std::time::Instant::now();
        let rec = Recorder::create(&path, RecorderOptions::default()).unwrap();
        let h = rec.handle();
        h.session(&header(), 0);
        let n = 1_700_000u64;
        for i in 0..n {
            h.tracer(
                if i % 2 == 0 { "tracer0" } else { "tracer1" },
                &tracer_sample(i),
                i + 1,
            );
        }
        let stats = rec.finish().unwrap();
        let write = t0.elapsed();
        let t1 = std::time::Instant::now();
        let s = read_session(&path).unwrap();
        let read = t1.elapsed();
        assert_eq!(s.tracers.values().map(Vec::len).sum::<usize>(), n as usize);
        let bytes = std::fs::read(&path).unwrap();
        let t2 = std::time::Instant::now();
        let lin = read_linear(&bytes, "x").unwrap();
        let linear = t2.elapsed();
        assert_eq!(lin.messages, n + 1);
        println!(
            "{n} samples, {} bytes: write {write:?}, read {read:?}, linear {linear:?}",
            stats.bytes
        );
    }

    #[test]
    fn topic_ids() {
        assert_eq!(tracer_id("/tracer/t0/range"), Some("t0"));
        assert_eq!(tracer_id("/tracer//range"), None);
        assert_eq!(tracer_id("/tracer/a/b/range"), None);
        assert_eq!(env_id("/env/air"), Some("air"));
        assert_eq!(env_id("/env/"), None);
        assert_eq!(rotary_id("/rotary/c/state"), Some("c"));
        assert_eq!(rotary_id("/rotary//state"), None);
        assert_eq!(rotary_id("/rotary/c/x/state"), None);
        assert_eq!(probe_id("/probe/arm0/reading"), Some("arm0"));
        assert_eq!(probe_id("/probe//reading"), None);
        assert_eq!(messages::tracer_topic("x"), "/tracer/x/range");
    }
}
