//! The MCAP session recorder: one writer thread owns the file, fed by an unbounded channel,
//! and closes a chunk plus fsyncs every `flush_interval` so a killed run loses little.

use std::collections::HashMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{self, Receiver, RecvTimeoutError, Sender};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use mcap::records::MessageHeader;
use serde::Serialize;
use thiserror::Error;

use super::messages::{
    self, EnvSample, MachineStateSample, ProbeSample, RotaryStateSample, RunEvent, SessionHeader,
    TracerSample, SCHEMA_ENV, SCHEMA_EVENT, SCHEMA_MACHINE, SCHEMA_PROBE, SCHEMA_ROTARY,
    SCHEMA_SESSION, SCHEMA_TRACER, TOPIC_EVENT, TOPIC_SESSION,
};
use super::reader::RawMessage;
use super::tap::{Tap, TapChannel, TappedMessage};

/// Chunk compression of the recorded file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Compression {
    #[default]
    Zstd,
    Lz4,
    None,
}

#[derive(Debug, Clone)]
pub struct RecorderOptions {
    /// Target uncompressed chunk size in bytes.
    pub chunk_size: u64,
    /// Wall time between chunk closes + fsync: the most a killed process can lose.
    pub flush_interval: Duration,
    pub compression: Compression,
    /// Receives a copy of every message written (live view, progress).
    pub tap: Tap,
}

impl Default for RecorderOptions {
    fn default() -> Self {
        RecorderOptions {
            chunk_size: 1024 * 1024,
            flush_interval: Duration::from_secs(1),
            compression: Compression::Zstd,
            tap: Tap::default(),
        }
    }
}

#[derive(Debug, Error)]
pub enum RecorderError {
    #[error("cannot create session file {path}: {source}")]
    Create {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("cannot start MCAP writer on {path}: {source}")]
    Start {
        path: PathBuf,
        source: mcap::McapError,
    },
    #[error("writing session file {path} failed ({lost} later messages lost): {source}")]
    Write {
        path: PathBuf,
        lost: u64,
        source: mcap::McapError,
    },
    #[error("syncing session file {path} to disk failed: {source}")]
    Sync {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("encoding a {topic} message as JSON failed: {source}")]
    Encode {
        topic: String,
        source: serde_json::Error,
    },
    #[error("cannot start the recorder thread for {path}: {source}")]
    Thread {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("the recorder thread for {path} panicked")]
    Panicked { path: PathBuf },
}

/// What the writer thread did, returned by [`Recorder::finish`].
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct RecordStats {
    /// Messages written to the file.
    pub messages: u64,
    /// File size after finishing.
    pub bytes: u64,
    /// Messages that could not be written (after a write error, or sent after finish).
    pub lost: u64,
    /// Periodic chunk closes + fsyncs done.
    pub flushes: u64,
    pub channels: u32,
}

/// Typed payloads: JSON encoding happens in the writer thread, off the sequencer.
enum Payload {
    Session(Box<SessionHeader>),
    Tracer(String, TracerSample),
    Env(String, Box<EnvSample>),
    Rotary(String, RotaryStateSample),
    Machine(String, Box<MachineStateSample>),
    Probe(String, ProbeSample),
    Event(Box<RunEvent>),
    /// A message copied as recorded (same channel topic, payload and times).
    Raw(Box<RawMessage>),
    /// A plan kind's own topic (`kind_messages`), already as JSON.
    Json(String, TopicSchema, Box<serde_json::Value>),
}

/// Name and JSON Schema text of a topic written with [`RecorderHandle::json`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TopicSchema {
    pub name: &'static str,
    pub text: &'static str,
}

enum Command {
    Write {
        payload: Payload,
        log_time_ns: u64,
    },
    /// Close the chunk and sync the file now (after everything sent before).
    Checkpoint,
    Finish,
}

/// Cheap, cloneable sender into the recorder. Sends never block and never panic.
#[derive(Clone)]
pub struct RecorderHandle {
    tx: Sender<Command>,
    lost_after_close: Arc<AtomicU64>,
    /// Messages sent and not yet written.
    queued: Arc<AtomicU64>,
}

impl RecorderHandle {
    fn send(&self, payload: Payload, log_time_ns: u64) {
        self.queued.fetch_add(1, Ordering::Relaxed);
        if self
            .tx
            .send(Command::Write {
                payload,
                log_time_ns,
            })
            .is_err()
        {
            self.queued.fetch_sub(1, Ordering::Relaxed);
            if self.lost_after_close.fetch_add(1, Ordering::Relaxed) == 0 {
                tracing::warn!("session recorder already finished: message dropped");
            }
        }
    }

    /// Messages sent and not yet written: a producer faster than the file (a replay at full
    /// speed) waits on it rather than queue the recording up in memory.
    pub fn queued(&self) -> u64 {
        self.queued.load(Ordering::Relaxed)
    }

    /// The `/geocal/session` header; the file is flushed and synced right after it.
    pub fn session(&self, header: &SessionHeader, log_time_ns: u64) {
        self.send(Payload::Session(Box::new(header.clone())), log_time_ns);
    }

    /// One `/tracer/<id>/range` sample; publish_time = log_time.
    pub fn tracer(&self, tracer_id: &str, sample: &TracerSample, log_time_ns: u64) {
        self.send(Payload::Tracer(tracer_id.to_owned(), *sample), log_time_ns);
    }

    pub fn env(&self, env_id: &str, sample: &EnvSample, log_time_ns: u64) {
        self.send(
            Payload::Env(env_id.to_owned(), Box::new(sample.clone())),
            log_time_ns,
        );
    }

    /// One `/rotary/<id>/state` sample.
    pub fn rotary(&self, table_id: &str, sample: &RotaryStateSample, log_time_ns: u64) {
        self.send(Payload::Rotary(table_id.to_owned(), *sample), log_time_ns);
    }

    /// One `/machine/<id>/state` report.
    pub fn machine_state(&self, machine_id: &str, sample: &MachineStateSample, log_time_ns: u64) {
        self.send(
            Payload::Machine(machine_id.to_owned(), Box::new(sample.clone())),
            log_time_ns,
        );
    }

    /// One `/probe/<id>/reading`.
    pub fn probe(&self, probe_id: &str, sample: &ProbeSample, log_time_ns: u64) {
        self.send(Payload::Probe(probe_id.to_owned(), *sample), log_time_ns);
    }

    pub fn event(&self, event: &RunEvent, log_time_ns: u64) {
        self.send(Payload::Event(Box::new(event.clone())), log_time_ns);
    }

    /// A message copied from another session file with its topic, payload and both times
    /// (`geocal run --resume`). Its channel is shared with later messages on the same topic.
    pub fn raw(&self, message: RawMessage) {
        let log_time_ns = message.log_time_ns;
        self.send(Payload::Raw(Box::new(message)), log_time_ns);
    }

    /// Close the current chunk and sync the file once everything sent so far is written:
    /// a kill after this loses none of it.
    pub fn checkpoint(&self) {
        if self.tx.send(Command::Checkpoint).is_err()
            && self.lost_after_close.fetch_add(1, Ordering::Relaxed) == 0
        {
            tracing::warn!("session recorder already finished: checkpoint dropped");
        }
    }

    /// One message on a plan kind's own topic (e.g. `/probe/<id>/reading`), with its schema.
    pub fn json(
        &self,
        topic: &str,
        schema: TopicSchema,
        message: serde_json::Value,
        log_time_ns: u64,
    ) {
        self.send(
            Payload::Json(topic.to_owned(), schema, Box::new(message)),
            log_time_ns,
        );
    }
}

/// Owns the writer thread. Call [`Recorder::finish`]; dropping it finishes too but hides errors.
pub struct Recorder {
    handle: RecorderHandle,
    thread: Option<JoinHandle<Result<RecordStats, RecorderError>>>,
    path: PathBuf,
}

impl Recorder {
    pub fn create(path: &Path, options: RecorderOptions) -> Result<Recorder, RecorderError> {
        let file = File::create(path).map_err(|source| RecorderError::Create {
            path: path.to_owned(),
            source,
        })?;
        // A second descriptor on the same open file: the mcap Writer owns the first.
        let sync_file = file.try_clone().map_err(|source| RecorderError::Create {
            path: path.to_owned(),
            source,
        })?;
        sync_parent_dir(path);
        let compression = match options.compression {
            Compression::Zstd => Some(mcap::Compression::Zstd),
            Compression::Lz4 => Some(mcap::Compression::Lz4),
            Compression::None => None,
        };
        let writer = mcap::WriteOptions::new()
            .compression(compression)
            .chunk_size(Some(options.chunk_size))
            // The default spawns one zstd worker per physical core; one thread is plenty here.
            .compression_threads(0)
            .library(concat!("geocal/", env!("CARGO_PKG_VERSION")))
            .create(BufWriter::with_capacity(256 * 1024, file))
            .map_err(|source| RecorderError::Start {
                path: path.to_owned(),
                source,
            })?;
        let (tx, rx) = mpsc::channel();
        let queued = Arc::new(AtomicU64::new(0));
        let mut state = WriterThread {
            queued: queued.clone(),
            path: path.to_owned(),
            writer: Some(writer),
            sync_file,
            flush_interval: options.flush_interval,
            schemas: [0; 7],
            session_channel: None,
            event_channel: None,
            tracer_channels: HashMap::new(),
            env_channels: HashMap::new(),
            rotary_channels: HashMap::new(),
            machine_channels: HashMap::new(),
            probe_channels: HashMap::new(),
            by_topic: HashMap::new(),
            json_schemas: HashMap::new(),
            sequences: HashMap::new(),
            buf: Vec::with_capacity(512),
            stats: RecordStats::default(),
            error: None,
            dirty: false,
            last_sync: Instant::now(),
            tap: options.tap.clone(),
            tap_channels: HashMap::new(),
        };
        let thread = std::thread::Builder::new()
            .name("geocal-recorder".into())
            .spawn(move || state.run(rx))
            .map_err(|source| RecorderError::Thread {
                path: path.to_owned(),
                source,
            })?;
        Ok(Recorder {
            handle: RecorderHandle {
                tx,
                lost_after_close: Arc::new(AtomicU64::new(0)),
                queued,
            },
            thread: Some(thread),
            path: path.to_owned(),
        })
    }

    pub fn handle(&self) -> RecorderHandle {
        self.handle.clone()
    }

    /// Writes everything sent so far, the summary and indexes, and fsyncs the file.
    pub fn finish(mut self) -> Result<RecordStats, RecorderError> {
        self.stop()
    }

    fn stop(&mut self) -> Result<RecordStats, RecorderError> {
        let Some(thread) = self.thread.take() else {
            return Ok(RecordStats::default());
        };
        // Handles may outlive the recorder, so ask the thread to stop instead of waiting for
        // every sender to drop. A send error means the thread is gone already; join tells why.
        let _ = self.handle.tx.send(Command::Finish);
        match thread.join() {
            Ok(result) => result,
            Err(_) => Err(RecorderError::Panicked {
                path: self.path.clone(),
            }),
        }
    }
}

impl Drop for Recorder {
    fn drop(&mut self) {
        if self.thread.is_some() {
            if let Err(err) = self.stop() {
                tracing::error!("session recorder dropped without finish(): {err}");
            }
        }
    }
}

/// Makes the new file's directory entry durable too (best effort: not every OS allows it).
fn sync_parent_dir(path: &Path) {
    #[cfg(unix)]
    if let Some(dir) = path.parent() {
        let dir = if dir.as_os_str().is_empty() {
            Path::new(".")
        } else {
            dir
        };
        if let Ok(d) = File::open(dir) {
            let _ = d.sync_all();
        }
    }
    #[cfg(not(unix))]
    let _ = path;
}

type McapWriter = mcap::Writer<BufWriter<File>>;

#[derive(Clone, Copy)]
enum SchemaKind {
    Session = 0,
    Tracer = 1,
    Env = 2,
    Event = 3,
    Rotary = 4,
    Probe = 5,
    Machine = 6,
}

impl SchemaKind {
    fn name_and_text(self) -> (&'static str, &'static str) {
        match self {
            SchemaKind::Session => (SCHEMA_SESSION, messages::schema::SESSION),
            SchemaKind::Tracer => (SCHEMA_TRACER, messages::schema::TRACER),
            SchemaKind::Env => (SCHEMA_ENV, messages::schema::ENV),
            SchemaKind::Event => (SCHEMA_EVENT, messages::schema::EVENT),
            SchemaKind::Rotary => (SCHEMA_ROTARY, messages::schema::ROTARY),
            SchemaKind::Machine => (SCHEMA_MACHINE, messages::schema::MACHINE),
            SchemaKind::Probe => (SCHEMA_PROBE, messages::schema::PROBE),
        }
    }
}

struct WriterThread {
    path: PathBuf,
    /// None once finished or after into_inner.
    writer: Option<McapWriter>,
    sync_file: File,
    flush_interval: Duration,
    /// Schema ids by SchemaKind; 0 = not added yet.
    schemas: [u16; 7],
    session_channel: Option<u16>,
    event_channel: Option<u16>,
    tracer_channels: HashMap<String, u16>,
    env_channels: HashMap<String, u16>,
    rotary_channels: HashMap<String, u16>,
    machine_channels: HashMap<String, u16>,
    probe_channels: HashMap<String, u16>,
    /// Every channel by topic: one channel per topic, whoever writes to it first.
    by_topic: HashMap<String, u16>,
    /// Plan kinds' own topics' schema ids by schema name.
    json_schemas: HashMap<&'static str, u16>,
    sequences: HashMap<u16, u32>,
    buf: Vec<u8>,
    stats: RecordStats,
    /// First write error; later messages are counted as lost.
    error: Option<RecorderError>,
    /// Messages written since the last flush.
    dirty: bool,
    last_sync: Instant,
    tap: Tap,
    queued: Arc<AtomicU64>,
    /// Every channel as a tap sees it, by id (kept only when tapped).
    tap_channels: HashMap<u16, Arc<TapChannel>>,
}

/// Checkpoints (`RecorderHandle::checkpoint`) closer together than this are merged: a real
/// run's points take seconds, so each gets its own; a simulated run is not slowed by fsyncs.
const MIN_CHECKPOINT_INTERVAL: Duration = Duration::from_millis(100);

impl WriterThread {
    fn run(&mut self, rx: Receiver<Command>) -> Result<RecordStats, RecorderError> {
        let mut next_flush = Instant::now() + self.flush_interval;
        loop {
            let wait = next_flush.saturating_duration_since(Instant::now());
            match rx.recv_timeout(wait) {
                Ok(Command::Write {
                    payload,
                    log_time_ns,
                }) => {
                    let is_header = matches!(payload, Payload::Session(_));
                    self.write(payload, log_time_ns);
                    if is_header {
                        // A run that crashes in its first second still has its header on disk.
                        self.flush_and_sync();
                        next_flush = Instant::now() + self.flush_interval;
                    }
                }
                Ok(Command::Checkpoint) => {
                    // At most one checkpoint per MIN_CHECKPOINT_INTERVAL: a later one is
                    // deferred to then (fast simulated runs finish points in microseconds).
                    let due = self.last_sync + MIN_CHECKPOINT_INTERVAL;
                    next_flush = next_flush.min(due);
                }
                Ok(Command::Finish) | Err(RecvTimeoutError::Disconnected) => break,
                Err(RecvTimeoutError::Timeout) => {}
            }
            if Instant::now() >= next_flush {
                if self.dirty {
                    self.flush_and_sync();
                    self.stats.flushes += 1;
                }
                next_flush = Instant::now() + self.flush_interval;
            }
        }
        // Messages still queued behind Finish were sent before finish() returned: count them.
        while let Ok(cmd) = rx.try_recv() {
            if let Command::Write {
                payload,
                log_time_ns,
            } = cmd
            {
                self.write(payload, log_time_ns);
            }
        }
        self.finish()
    }

    fn finish(&mut self) -> Result<RecordStats, RecorderError> {
        if let Some(err) = self.error.take() {
            return Err(match err {
                RecorderError::Write { path, source, .. } => RecorderError::Write {
                    path,
                    lost: self.stats.lost,
                    source,
                },
                other => other,
            });
        }
        let Some(mut writer) = self.writer.take() else {
            return Ok(self.stats.clone());
        };
        writer.finish().map_err(|source| RecorderError::Write {
            path: self.path.clone(),
            lost: 0,
            source,
        })?;
        let file = writer
            .into_inner()
            .into_inner()
            .map_err(|e| RecorderError::Sync {
                path: self.path.clone(),
                source: e.into_error(),
            })?;
        file.sync_all().map_err(|source| RecorderError::Sync {
            path: self.path.clone(),
            source,
        })?;
        self.stats.bytes = file
            .metadata()
            .map_err(|source| RecorderError::Sync {
                path: self.path.clone(),
                source,
            })?
            .len();
        self.stats.channels = self.by_topic.len() as u32;
        Ok(self.stats.clone())
    }

    fn flush_and_sync(&mut self) {
        if self.error.is_some() {
            return;
        }
        let Some(writer) = self.writer.as_mut() else {
            return;
        };
        if let Err(source) = writer.flush() {
            self.fail(source);
            return;
        }
        if let Err(source) = self.sync_file.sync_data() {
            self.error = Some(RecorderError::Sync {
                path: self.path.clone(),
                source,
            });
            return;
        }
        self.dirty = false;
        self.last_sync = Instant::now();
    }

    fn fail(&mut self, source: mcap::McapError) {
        tracing::error!(
            "session recorder: writing {} failed: {source}",
            self.path.display()
        );
        self.error = Some(RecorderError::Write {
            path: self.path.clone(),
            lost: 0,
            source,
        });
    }

    fn write(&mut self, payload: Payload, log_time_ns: u64) {
        self.queued.fetch_sub(1, Ordering::Relaxed);
        if self.error.is_some() || self.writer.is_none() {
            self.stats.lost += 1;
            return;
        }
        match self.try_write(&payload, log_time_ns) {
            Ok(()) => {
                self.stats.messages += 1;
                self.dirty = true;
            }
            Err(WriteFailure::Encode(err)) => {
                // One unencodable message (e.g. a NaN in a header) must not end the recording.
                tracing::error!("session recorder: {err}");
                self.stats.lost += 1;
            }
            Err(WriteFailure::Mcap(source)) => {
                self.stats.lost += 1;
                self.fail(source);
            }
        }
    }

    fn try_write(&mut self, payload: &Payload, log_time_ns: u64) -> Result<(), WriteFailure> {
        let mut publish_time = log_time_ns;
        let channel_id = match payload {
            Payload::Raw(m) => {
                self.buf.clear();
                self.buf.extend_from_slice(&m.data);
                publish_time = m.publish_time_ns;
                self.raw_channel(m)?
            }
            Payload::Session(h) => {
                encode(&mut self.buf, TOPIC_SESSION, h.as_ref())?;
                match self.session_channel {
                    Some(id) => id,
                    None => {
                        let id = self.add_channel(SchemaKind::Session, TOPIC_SESSION)?;
                        self.session_channel = Some(id);
                        id
                    }
                }
            }
            Payload::Event(e) => {
                encode(&mut self.buf, TOPIC_EVENT, e.as_ref())?;
                match self.event_channel {
                    Some(id) => id,
                    None => {
                        let id = self.add_channel(SchemaKind::Event, TOPIC_EVENT)?;
                        self.event_channel = Some(id);
                        id
                    }
                }
            }
            Payload::Tracer(tracer_id, s) => match self.tracer_channels.get(tracer_id.as_str()) {
                Some(&id) => {
                    encode(&mut self.buf, "/tracer/*/range", s)?;
                    id
                }
                None => {
                    let topic = messages::tracer_topic(tracer_id);
                    encode(&mut self.buf, &topic, s)?;
                    let id = self.add_channel(SchemaKind::Tracer, &topic)?;
                    self.tracer_channels.insert(tracer_id.clone(), id);
                    id
                }
            },
            Payload::Env(env_id, s) => match self.env_channels.get(env_id.as_str()) {
                Some(&id) => {
                    encode(&mut self.buf, "/env/*", s.as_ref())?;
                    id
                }
                None => {
                    let topic = messages::env_topic(env_id);
                    encode(&mut self.buf, &topic, s.as_ref())?;
                    let id = self.add_channel(SchemaKind::Env, &topic)?;
                    self.env_channels.insert(env_id.clone(), id);
                    id
                }
            },
            Payload::Rotary(table_id, s) => match self.rotary_channels.get(table_id.as_str()) {
                Some(&id) => {
                    encode(&mut self.buf, "/rotary/*/state", s)?;
                    id
                }
                None => {
                    let topic = messages::rotary_topic(table_id);
                    encode(&mut self.buf, &topic, s)?;
                    let id = self.add_channel(SchemaKind::Rotary, &topic)?;
                    self.rotary_channels.insert(table_id.clone(), id);
                    id
                }
            },
            Payload::Machine(machine_id, s) => {
                match self.machine_channels.get(machine_id.as_str()) {
                    Some(&id) => {
                        encode(&mut self.buf, "/machine/*/state", s.as_ref())?;
                        id
                    }
                    None => {
                        let topic = messages::machine_state_topic(machine_id);
                        encode(&mut self.buf, &topic, s.as_ref())?;
                        let id = self.add_channel(SchemaKind::Machine, &topic)?;
                        self.machine_channels.insert(machine_id.clone(), id);
                        id
                    }
                }
            }
            Payload::Json(topic, schema, value) => {
                encode(&mut self.buf, topic, value.as_ref())?;
                match self.by_topic.get(topic.as_str()) {
                    Some(&id) => id,
                    None => {
                        let id = self.add_json_channel(*schema, topic)?;
                        self.by_topic.insert(topic.clone(), id);
                        id
                    }
                }
            }
            Payload::Probe(probe_id, s) => match self.probe_channels.get(probe_id.as_str()) {
                Some(&id) => {
                    encode(&mut self.buf, "/probe/*/reading", s)?;
                    id
                }
                None => {
                    let topic = messages::probe_topic(probe_id);
                    encode(&mut self.buf, &topic, s)?;
                    let id = self.add_channel(SchemaKind::Probe, &topic)?;
                    self.probe_channels.insert(probe_id.clone(), id);
                    id
                }
            },
        };
        let seq = self.sequences.entry(channel_id).or_insert(0);
        let sequence = *seq;
        *seq = seq.wrapping_add(1);
        let Some(writer) = self.writer.as_mut() else {
            return Err(WriteFailure::Mcap(
                mcap::McapError::AttemptedWriteAfterFailure,
            ));
        };
        writer
            .write_to_known_channel(
                &MessageHeader {
                    channel_id,
                    sequence,
                    log_time: log_time_ns,
                    publish_time,
                },
                &self.buf,
            )
            .map_err(WriteFailure::Mcap)?;
        if let (Some(tap), Some(channel)) = (&self.tap.0, self.tap_channels.get(&channel_id)) {
            tap.message(&TappedMessage {
                channel,
                sequence,
                log_time_ns,
                publish_time_ns: publish_time,
                data: &self.buf,
                queue_depth: self.queued.load(Ordering::Relaxed),
            });
        }
        Ok(())
    }

    /// Remember a new channel for the tap (nothing without one).
    fn note_channel(
        &mut self,
        id: u16,
        topic: &str,
        message_encoding: &str,
        schema: Option<(&str, &str, &[u8])>,
    ) {
        if self.tap.0.is_none() {
            return;
        }
        self.tap_channels.insert(
            id,
            Arc::new(TapChannel {
                id,
                topic: topic.to_owned(),
                message_encoding: message_encoding.to_owned(),
                schema: schema.map(|(n, e, d)| (n.to_owned(), e.to_owned(), d.to_vec())),
            }),
        );
    }

    /// The channel of a copied message: geocal's own schema for its own topics (so that
    /// later typed messages share the channel), else the message's schema as recorded.
    fn raw_channel(&mut self, m: &RawMessage) -> Result<u16, WriteFailure> {
        if let Some(&id) = self.by_topic.get(&m.channel.topic) {
            return Ok(id);
        }
        let own = [
            SchemaKind::Session,
            SchemaKind::Tracer,
            SchemaKind::Env,
            SchemaKind::Event,
            SchemaKind::Rotary,
            SchemaKind::Probe,
            SchemaKind::Machine,
        ]
        .into_iter()
        .find(|k| {
            m.channel.message_encoding == "json"
                && m.channel
                    .schema
                    .as_ref()
                    .is_some_and(|(name, _, _)| name == k.name_and_text().0)
        });
        if let Some(kind) = own {
            return self.add_channel(kind, &m.channel.topic);
        }
        let Some(writer) = self.writer.as_mut() else {
            return Err(WriteFailure::Mcap(
                mcap::McapError::AttemptedWriteAfterFailure,
            ));
        };
        let schema_id = match &m.channel.schema {
            Some((name, encoding, data)) => writer
                .add_schema(name, encoding, data)
                .map_err(WriteFailure::Mcap)?,
            None => 0,
        };
        let id = writer
            .add_channel(
                schema_id,
                &m.channel.topic,
                &m.channel.message_encoding,
                &m.channel.metadata,
            )
            .map_err(WriteFailure::Mcap)?;
        self.by_topic.insert(m.channel.topic.clone(), id);
        let schema = m
            .channel
            .schema
            .as_ref()
            .map(|(n, e, d)| (n.as_str(), e.as_str(), d.as_slice()));
        self.note_channel(id, &m.channel.topic, &m.channel.message_encoding, schema);
        Ok(id)
    }

    fn add_channel(&mut self, kind: SchemaKind, topic: &str) -> Result<u16, WriteFailure> {
        if let Some(&id) = self.by_topic.get(topic) {
            return Ok(id);
        }
        let Some(writer) = self.writer.as_mut() else {
            return Err(WriteFailure::Mcap(
                mcap::McapError::AttemptedWriteAfterFailure,
            ));
        };
        let slot = kind as usize;
        if self.schemas[slot] == 0 {
            let (name, text) = kind.name_and_text();
            self.schemas[slot] = writer
                .add_schema(name, "jsonschema", text.as_bytes())
                .map_err(WriteFailure::Mcap)?;
        }
        let id = writer
            .add_channel(self.schemas[slot], topic, "json", &Default::default())
            .map_err(WriteFailure::Mcap)?;
        self.by_topic.insert(topic.to_owned(), id);
        let (name, text) = kind.name_and_text();
        self.note_channel(
            id,
            topic,
            "json",
            Some((name, "jsonschema", text.as_bytes())),
        );
        Ok(id)
    }
}

impl WriterThread {
    fn add_json_channel(&mut self, schema: TopicSchema, topic: &str) -> Result<u16, WriteFailure> {
        let Some(writer) = self.writer.as_mut() else {
            return Err(WriteFailure::Mcap(
                mcap::McapError::AttemptedWriteAfterFailure,
            ));
        };
        let schema_id = match self.json_schemas.get(schema.name) {
            Some(&id) => id,
            None => {
                let id = writer
                    .add_schema(schema.name, "jsonschema", schema.text.as_bytes())
                    .map_err(WriteFailure::Mcap)?;
                self.json_schemas.insert(schema.name, id);
                id
            }
        };
        let id = writer
            .add_channel(schema_id, topic, "json", &Default::default())
            .map_err(WriteFailure::Mcap)?;
        self.note_channel(
            id,
            topic,
            "json",
            Some((schema.name, "jsonschema", schema.text.as_bytes())),
        );
        Ok(id)
    }
}

enum WriteFailure {
    Encode(RecorderError),
    Mcap(mcap::McapError),
}

fn encode<T: Serialize + ?Sized>(
    buf: &mut Vec<u8>,
    topic: &str,
    msg: &T,
) -> Result<(), WriteFailure> {
    buf.clear();
    serde_json::to_writer(&mut *buf, msg).map_err(|source| {
        WriteFailure::Encode(RecorderError::Encode {
            topic: topic.to_owned(),
            source,
        })
    })
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;

    use super::*;
    use crate::session::reader::testutil::*;
    use crate::session::reader::{read_session, read_session_bytes, Completeness};

    fn opts(compression: Compression, flush_interval: Duration) -> RecorderOptions {
        RecorderOptions {
            chunk_size: 64 * 1024,
            flush_interval,
            compression,
            tap: Default::default(),
        }
    }

    /// A tapped message as (topic, schema name, log time, bytes).
    type Kept = (String, Option<String>, u64, Vec<u8>);

    #[derive(Default)]
    struct Collect(std::sync::Mutex<Vec<Kept>>);

    impl crate::session::tap::MessageTap for Collect {
        fn message(&self, m: &TappedMessage<'_>) {
            let schema = m.channel.schema.as_ref().map(|(name, _, _)| name.clone());
            if let Ok(mut all) = self.0.lock() {
                all.push((
                    m.channel.topic.clone(),
                    schema,
                    m.log_time_ns,
                    m.data.to_vec(),
                ));
            }
        }
    }

    #[test]
    fn a_tap_sees_every_message_as_written() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("tap.mcap");
        let collect = Arc::new(Collect::default());
        let options = RecorderOptions {
            tap: Tap::new(collect.clone()),
            ..opts(Compression::Zstd, Duration::from_secs(1))
        };
        let rec = Recorder::create(&path, options).unwrap();
        let h = rec.handle();
        h.session(&header(), 1);
        for i in 0..50u64 {
            h.tracer("tracer0", &tracer_sample(i), 10 + i);
        }
        h.event(&events()[0], 100);
        rec.finish().unwrap();
        let (_, raw) = crate::session::reader::read_session_raw(&path).unwrap();
        let tapped = collect.0.lock().unwrap();
        assert_eq!(tapped.len(), raw.len());
        for (t, r) in tapped.iter().zip(&raw) {
            assert_eq!(t.0, r.channel.topic);
            assert_eq!(t.1, r.channel.schema.as_ref().map(|(n, _, _)| n.clone()));
            assert_eq!(t.2, r.log_time_ns);
            assert_eq!(t.3, r.data);
        }
        assert_eq!(tapped[1].0, "/tracer/tracer0/range");
    }

    #[test]
    fn round_trip() {
        for compression in [Compression::Zstd, Compression::Lz4, Compression::None] {
            let dir = tempfile::tempdir().unwrap();
            let path = dir.path().join("rt.mcap");
            let rec = Recorder::create(&path, opts(compression, Duration::from_secs(1))).unwrap();
            let h = rec.handle();
            let h2 = h.clone();
            let mut t = 1_700_000_000_000_000_000u64;
            h.session(&header(), t);
            let evs = events();
            let mut want_tracer: BTreeMap<&str, Vec<(u64, TracerSample)>> = BTreeMap::new();
            let mut want_env = vec![];
            let mut want_events = vec![];
            let mut want_rotary = vec![];
            for i in 0..4000u64 {
                t += 100_000;
                let id = if i % 2 == 0 { "tracer0" } else { "tracer1" };
                let s = tracer_sample(i / 2);
                // Two handles from two threads' worth of clones share one file.
                if i % 5 == 0 { &h2 } else { &h }.tracer(id, &s, t);
                want_tracer.entry(id).or_default().push((t, s));
                if i % 400 == 0 {
                    let e = env_sample(i);
                    h.env("air0", &e, t);
                    want_env.push((t, e));
                    let ev = evs[(i / 400) as usize % evs.len()].clone();
                    h.event(&ev, t);
                    want_events.push((t, ev));
                }
                if i % 1000 == 0 {
                    let r = RotaryStateSample {
                        t_s: i as f64 * 1e-4,
                        commanded_rad: 0.25,
                        encoder_rad: (i % 2000 == 0).then_some(0.2501),
                        in_position: i % 2000 == 0,
                    };
                    h.rotary("c", &r, t);
                    want_rotary.push((t, r));
                }
            }
            let stats = rec.finish().unwrap();
            assert_eq!(stats.messages, 1 + 4000 + 2 * 10 + 4);
            assert_eq!(stats.lost, 0);
            assert_eq!(stats.channels, 6);
            assert_eq!(stats.bytes, std::fs::metadata(&path).unwrap().len());

            let s = read_session(&path).unwrap();
            assert_eq!(s.completeness, Completeness::Complete);
            assert_eq!(s.header, header());
            assert_eq!((s.skipped, s.ignored), (0, 0));
            assert_eq!(s.tracers.len(), 2);
            for (id, want) in &want_tracer {
                let got: Vec<_> = s.tracers[*id]
                    .iter()
                    .map(|st| {
                        assert_eq!(st.publish_time_ns, st.log_time_ns);
                        (st.log_time_ns, st.msg)
                    })
                    .collect();
                assert_eq!(&got, want);
            }
            let got: Vec<_> = s.env["air0"]
                .iter()
                .map(|st| (st.log_time_ns, st.msg.clone()))
                .collect();
            assert_eq!(got, want_env);
            let got: Vec<_> = s.rotary["c"]
                .iter()
                .map(|st| (st.log_time_ns, st.msg))
                .collect();
            assert_eq!(got, want_rotary);
            let got: Vec<_> = s
                .events
                .iter()
                .map(|st| (st.log_time_ns, st.msg.clone()))
                .collect();
            assert_eq!(got, want_events);
        }
    }

    fn poll<T>(limit: Duration, mut f: impl FnMut() -> Option<T>) -> T {
        let deadline = Instant::now() + limit;
        loop {
            if let Some(v) = f() {
                return v;
            }
            assert!(Instant::now() < deadline, "nothing on disk after {limit:?}");
            std::thread::sleep(Duration::from_millis(5));
        }
    }

    #[test]
    fn killed_run_keeps_everything_before_the_last_flush() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("kill.mcap");
        let interval = Duration::from_millis(100);
        let rec = Recorder::create(&path, opts(Compression::Zstd, interval)).unwrap();
        let h = rec.handle();
        h.session(&header(), 1);
        // The header alone is on disk at once, long before the first periodic flush.
        let early = poll(Duration::from_millis(90), || {
            read_session_bytes(&std::fs::read(&path).unwrap()).ok()
        });
        assert_eq!(early.header, header());
        assert!(!early.completeness.is_complete());

        for i in 0..500 {
            h.tracer("tracer0", &tracer_sample(i), 10 + i);
        }
        // "kill -9": take the bytes on disk while the recorder still runs, once a flush
        // interval has passed (polled, so a loaded machine does not make this flaky).
        std::thread::sleep(interval);
        let copy = poll(Duration::from_secs(5), || {
            let bytes = std::fs::read(&path).unwrap();
            let s = read_session_bytes(&bytes).ok()?;
            (s.tracers.get("tracer0").map_or(0, Vec::len) == 500).then_some(bytes)
        });
        for i in 500..600 {
            h.tracer("tracer0", &tracer_sample(i), 10 + i);
        }
        let s = read_session_bytes(&copy).unwrap();
        match &s.completeness {
            Completeness::Truncated {
                bytes_read,
                file_bytes,
                ..
            } => assert_eq!(bytes_read, file_bytes),
            Completeness::Complete => panic!("a running recording cannot be complete"),
        }
        let got: Vec<_> = s.tracers["tracer0"].iter().map(|st| st.msg).collect();
        let want: Vec<_> = (0..500).map(tracer_sample).collect();
        assert_eq!(got, want);

        let stats = rec.finish().unwrap();
        assert!(stats.flushes >= 1, "{stats:?}");
        let s = read_session(&path).unwrap();
        assert!(s.completeness.is_complete());
        assert_eq!(s.tracers["tracer0"].len(), 600);
    }

    #[test]
    fn a_checkpoint_puts_everything_sent_before_it_on_disk() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("cp.mcap");
        // The periodic flush would come only after 60 s.
        let rec =
            Recorder::create(&path, opts(Compression::Zstd, Duration::from_secs(60))).unwrap();
        let h = rec.handle();
        h.session(&header(), 1);
        for i in 0..300 {
            h.tracer("tracer0", &tracer_sample(i), 10 + i);
        }
        h.checkpoint();
        let s = poll(Duration::from_secs(5), || {
            let s = read_session_bytes(&std::fs::read(&path).unwrap()).ok()?;
            (s.tracers.get("tracer0").map_or(0, Vec::len) == 300).then_some(s)
        });
        assert!(!s.completeness.is_complete());
        rec.finish().unwrap();
    }

    #[test]
    fn copied_messages_keep_topic_payload_and_times_and_share_channels() {
        let dir = tempfile::tempdir().unwrap();
        let first = dir.path().join("first.mcap");
        let rec =
            Recorder::create(&first, opts(Compression::Zstd, Duration::from_secs(1))).unwrap();
        let h = rec.handle();
        h.session(&header(), 1);
        for i in 0..100 {
            h.tracer("tracer0", &tracer_sample(i), 10 + i);
        }
        for (i, e) in events().iter().enumerate() {
            h.event(e, 200 + i as u64);
        }
        rec.finish().unwrap();
        let (_, raw) = crate::session::reader::read_session_raw(&first).unwrap();
        assert_eq!(raw.len(), 1 + 100 + events().len());

        let second = dir.path().join("second.mcap");
        let rec =
            Recorder::create(&second, opts(Compression::Lz4, Duration::from_secs(1))).unwrap();
        let h = rec.handle();
        for m in raw.clone() {
            h.raw(m);
        }
        h.tracer("tracer0", &tracer_sample(100), 1000);
        h.event(&events()[0], 1001);
        let stats = rec.finish().unwrap();
        assert_eq!(
            stats.channels, 3,
            "copied and new messages share their topics' channels"
        );
        let (s, again) = crate::session::reader::read_session_raw(&second).unwrap();
        assert_eq!(&again[..raw.len()], &raw[..]);
        assert_eq!(s.header, header());
        assert_eq!(s.tracers["tracer0"].len(), 101);
        assert_eq!(s.events.len(), events().len() + 1);
    }

    #[test]
    fn sends_after_finish_are_counted_not_panics() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("late.mcap");
        let rec = Recorder::create(&path, RecorderOptions::default()).unwrap();
        let h = rec.handle();
        h.session(&header(), 1);
        rec.finish().unwrap();
        h.tracer("tracer0", &tracer_sample(0), 2);
        h.tracer("tracer0", &tracer_sample(1), 3);
        assert_eq!(h.lost_after_close.load(Ordering::Relaxed), 2);
    }

    #[test]
    fn handles_cross_threads() {
        fn assert_send_sync<T: Send + Sync + Clone>() {}
        fn assert_send<T: Send>() {}
        assert_send_sync::<RecorderHandle>();
        assert_send::<Recorder>();
    }

    #[test]
    fn unwritable_path_is_a_clear_error() {
        let Err(e) = Recorder::create(
            Path::new("/nonexistent/dir/x.mcap"),
            RecorderOptions::default(),
        ) else {
            panic!("created a file in a missing directory");
        };
        assert!(e.to_string().contains("/nonexistent/dir/x.mcap"), "{e}");
    }

    #[test]
    fn dropping_without_finish_still_finishes_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("drop.mcap");
        {
            let rec = Recorder::create(&path, RecorderOptions::default()).unwrap();
            rec.handle().session(&header(), 1);
        }
        assert!(read_session(&path).unwrap().completeness.is_complete());
    }
}
