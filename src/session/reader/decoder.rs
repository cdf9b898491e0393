//! Chunk decoding: whole chunk records in, their messages out, a chunk kept whole or not at all
//! (a chunk that fails half-way is taken back), and the state a read accumulates.

use mcap::records::op;
use mcap::sans_io::{LinearReadEvent, LinearReader, LinearReaderOptions};

use super::streams::{RawLog, Streams};
use super::{RawChannel, RawMessage, ReadError, Stamped};
use crate::session::damage::{date_from_chunk_index, framed, le_u64, Damage, RECORD_PREFIX};
use crate::session::messages::{
    EnvSample, MachineStateSample, ProbeSample, RotaryStateSample, RunEvent, SessionHeader,
    TracerSample,
};

/// A chunk may not claim more than this many times its stored size, plus a floor: a corrupt
/// size must not make a small file allocate a gigabyte (zstd on JSON gives about 10x).
pub(super) const MAX_CHUNK_EXPANSION: u64 = 1024;
pub(super) const CHUNK_EXPANSION_FLOOR: u64 = 1 << 20;

pub(super) enum Failure {
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
pub(super) struct Mark {
    pub(super) messages: u64,
    pub(super) skipped: u64,
    pub(super) ignored: u64,
    pub(super) events: usize,
    pub(super) had_header: bool,
    pub(super) raw_headers: usize,
    pub(super) raw_messages: usize,
    pub(super) streams: [Vec<usize>; 6],
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) enum Slot {
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
pub(super) struct Decoder {
    pub(super) file: String,
    /// By channel id.
    pub(super) slots: Vec<Slot>,
    pub(super) tracers: Streams<TracerSample>,
    pub(super) env: Streams<EnvSample>,
    pub(super) rotary: Streams<RotaryStateSample>,
    pub(super) machines: Streams<MachineStateSample>,
    pub(super) probes: Streams<ProbeSample>,
    pub(super) json: Streams<serde_json::Value>,
    pub(super) events: Vec<Stamped<RunEvent>>,
    pub(super) header: Option<Stamped<SessionHeader>>,
    /// Worker decoders (parallel indexed read) keep `/geocal/session` messages raw, in order.
    pub(super) lazy_header: bool,
    pub(super) raw_headers: Vec<(u64, u64, Vec<u8>)>,
    /// A worker met a message on a channel it had no definition for.
    pub(super) saw_undefined: bool,
    pub(super) messages: u64,
    pub(super) skipped: u64,
    pub(super) ignored: u64,
    pub(super) truncation: Option<(u64, String)>,
    /// Keep every message raw as well (`read_session_raw`).
    pub(super) raw: Option<RawLog>,
    /// Only count and keep raw messages: no typed decoding, no header needed (repair).
    pub(super) raw_only: bool,
    /// Damaged records skipped, in file order.
    pub(super) damages: Vec<Damage>,
    /// Log times of the messages since the last `settle_neighbours`, and the largest before.
    pub(super) span_ns: Option<(u64, u64)>,
    pub(super) last_ns: Option<u64>,
    /// Damages from this index on still wait for the first message after them.
    pub(super) awaiting_after: usize,
    /// The most decoded chunks alive at once in a parallel read (0 when serial).
    pub(super) peak_chunks_in_flight: usize,
    /// Chunk decoders a parallel read made (each merged one is reused; 0 when serial).
    pub(super) chunk_decoders_made: usize,
}

impl Decoder {
    pub(super) fn new(file: &str) -> Self {
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
            peak_chunks_in_flight: 0,
            chunk_decoders_made: 0,
        }
    }

    /// Records a damaged record; returns its index in `damages`.
    pub(super) fn damage(&mut self, mut damage: Damage) -> usize {
        self.settle_neighbours();
        damage.before_ns = self.last_ns;
        self.damages.push(damage);
        self.damages.len() - 1
    }

    /// Dates the damages from the summary's chunk index (see `date_from_chunk_index`); the
    /// read is over, so every neighbour is known by now.
    pub(super) fn date_damages(&mut self, chunks: &[mcap::records::ChunkIndex]) {
        self.settle_neighbours();
        date_from_chunk_index(&mut self.damages, chunks, &self.file);
        self.awaiting_after = self.damages.len();
    }

    /// The messages read since the last call are good: they bound the damages before them.
    pub(super) fn settle_neighbours(&mut self) {
        let Some((first, last)) = self.span_ns.take() else {
            return;
        };
        for d in &mut self.damages[self.awaiting_after..] {
            d.after_ns = Some(first);
        }
        self.awaiting_after = self.damages.len();
        self.last_ns = Some(self.last_ns.map_or(last, |l| l.max(last)));
    }

    pub(super) fn mark(&self) -> Mark {
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
    pub(super) fn rollback(&mut self, mark: Mark) {
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
    pub(super) fn feed_whole_chunk(
        &mut self,
        sans: &mut ChunkReader,
        record: &[u8],
    ) -> Result<(), Failure> {
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

    /// Feeds a run of whole top-level records (the data section of a file without chunks);
    /// on failure nothing of it is kept.
    pub(super) fn feed_records(&mut self, mut records: &[u8]) -> Result<(), Failure> {
        let mark = self.mark();
        let mut result = Ok(());
        while !records.is_empty() {
            let Some((opcode, end)) = framed(records, 0) else {
                result = Err(Failure::Damaged(
                    "a record runs past its run of records".into(),
                ));
                break;
            };
            result = self.on_record(opcode, &records[RECORD_PREFIX..end]);
            if result.is_err() {
                break;
            }
            records = &records[end..];
        }
        if matches!(result, Err(Failure::Damaged(_))) {
            self.rollback(mark);
        }
        result
    }

    /// An empty decoder with the same channels, for a thread that decodes a later run of chunks.
    pub(super) fn worker(&self) -> Decoder {
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

    /// `template.worker()` holding this spent worker's sample and event buffers, emptied with
    /// their capacity kept: a read's chunks reuse a bounded set of buffers instead of growing
    /// (and freeing) new ones per chunk.
    pub(super) fn recycled(mut self, template: &Decoder) -> Decoder {
        let mut fresh = template.worker();
        fresh.tracers.reuse_buffers(&mut self.tracers);
        fresh.env.reuse_buffers(&mut self.env);
        fresh.rotary.reuse_buffers(&mut self.rotary);
        fresh.machines.reuse_buffers(&mut self.machines);
        fresh.probes.reuse_buffers(&mut self.probes);
        fresh.json.reuse_buffers(&mut self.json);
        self.events.clear();
        fresh.events = self.events;
        fresh
    }

    /// Appends what a worker decoded from the chunks that follow this decoder's chunks,
    /// leaving the worker empty (its buffers can be reused).
    pub(super) fn absorb(&mut self, other: &mut Decoder) -> Result<(), Failure> {
        self.messages += other.messages;
        self.skipped += other.skipped;
        self.ignored += other.ignored;
        // Its messages count as read since the last settling, as in a serial read.
        if let Some((first, last)) = other.span_ns {
            self.span_ns = Some(match self.span_ns {
                None => (first, last),
                Some((a, b)) => (a.min(first), b.max(last)),
            });
        }
        take_streams(&mut self.tracers, &mut other.tracers);
        self.env.absorb(&mut other.env);
        self.rotary.absorb(&mut other.rotary);
        self.machines.absorb(&mut other.machines);
        self.probes.absorb(&mut other.probes);
        self.json.absorb(&mut other.json);
        take_or_append(&mut self.events, &mut other.events);
        self.damages.append(&mut other.damages);
        for (log_time_ns, publish_time_ns, data) in std::mem::take(&mut other.raw_headers) {
            self.session_message(log_time_ns, publish_time_ns, &data)?;
        }
        Ok(())
    }

    /// Feeds whole chunk records, skipping (and noting) damaged ones; fails only when the
    /// session itself is unusable.
    pub(super) fn feed_chunks(
        &mut self,
        buf: &[u8],
        ranges: &[(usize, usize)],
    ) -> Result<(), ReadError> {
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

    pub(super) fn reserve(&mut self, channel_id: u16, n: u64) {
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
    pub(super) fn feed_chunk(
        &mut self,
        reader: &mut ChunkReader,
        record: &[u8],
    ) -> Result<(), Failure> {
        if let Some(records) = reader.records_of(record) {
            let mut pos = 0;
            while let Some((opcode, end)) = framed(records, pos) {
                self.on_record(opcode, &records[pos + RECORD_PREFIX..end])?;
                pos = end;
            }
            return Ok(());
        }
        let sans = &mut reader.sans;
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

    pub(super) fn on_record(&mut self, opcode: u8, body: &[u8]) -> Result<(), Failure> {
        match opcode {
            op::SCHEMA => {
                if let Some(raw) = self.raw.as_mut() {
                    if let mcap::records::Record::Schema { header, data } =
                        crate::session::record::parse(opcode, body)?
                    {
                        let schema = (header.name, header.encoding, data.into_owned());
                        raw.schemas.insert(header.id, schema);
                    }
                }
                Ok(())
            }
            op::CHANNEL => {
                if let mcap::records::Record::Channel(ch) =
                    crate::session::record::parse(opcode, body)?
                {
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
}

/// `Streams::absorb` without copying the high-rate samples where it can be helped.
fn take_streams<T>(into: &mut Streams<T>, from: &mut Streams<T>) {
    for (id, samples) in &mut from.streams {
        let i = into.index(id);
        take_or_append(&mut into.streams[i].1, samples);
    }
}

/// Moves `more` to the end of `into`, exchanging the buffers instead of copying when `into`
/// is empty and has no more room reserved (a streamed read empties its streams after every
/// chunk; a whole read reserves them once for the file). `more` is left empty either way,
/// with a buffer to reuse.
pub(super) fn take_or_append<T>(into: &mut Vec<T>, more: &mut Vec<T>) {
    if into.is_empty() && more.capacity() >= into.capacity() {
        std::mem::swap(into, more);
    } else {
        into.append(more);
    }
}

/// Decodes whole chunk records. The common chunk — zstd, lz4 or uncompressed, whose records fill
/// exactly the size it claims, CRC right — is decompressed into a buffer kept from chunk to
/// chunk; any other goes through the `mcap` reader, whose verdict and errors it keeps.
pub(super) struct ChunkReader {
    sans: LinearReader,
    zstd: Option<zstd::bulk::Decompressor<'static>>,
    decompressed: Vec<u8>,
}

pub(super) fn chunk_reader() -> ChunkReader {
    // Only whole records are ever fed in, so a chunk is decoded only once complete; its CRC is
    // checked before any of its messages is used.
    let sans = LinearReader::new_with_options(
        LinearReaderOptions::default()
            .with_skip_start_magic(true)
            .with_skip_end_magic(true)
            .with_prevalidate_chunk_crcs(true)
            .with_record_length_limit(MAX_RECORD_BYTES),
    );
    ChunkReader {
        sans,
        zstd: None,
        decompressed: Vec::new(),
    }
}

impl ChunkReader {
    /// The records of a whole chunk record (opcode and length included) when the chunk is
    /// the common one, every record framed whole: None for anything else (the `mcap` reader
    /// then decides).
    fn records_of<'a>(&'a mut self, record: &'a [u8]) -> Option<&'a [u8]> {
        if record.first() != Some(&op::CHUNK)
            || usize::try_from(le_u64(record.get(1..RECORD_PREFIX)?)).ok()?
                != record.len() - RECORD_PREFIX
        {
            return None;
        }
        // message start and end times, uncompressed size, CRC, compression, compressed size.
        let body = &record[RECORD_PREFIX..];
        let uncompressed = usize::try_from(le_u64(body.get(16..24)?)).ok()?;
        let crc = u32::from_le_bytes(body.get(24..28)?.try_into().ok()?);
        let name_len =
            usize::try_from(u32::from_le_bytes(body.get(28..32)?.try_into().ok()?)).ok()?;
        let name_end = 32usize.checked_add(name_len)?;
        let compression = body.get(32..name_end)?;
        let size_end = name_end.checked_add(8)?;
        let compressed = usize::try_from(le_u64(body.get(name_end..size_end)?)).ok()?;
        let stored = body.get(size_end..size_end.checked_add(compressed)?)?;
        if uncompressed > MAX_RECORD_BYTES {
            return None;
        }
        if compression.is_empty() {
            return self::records(stored, crc).filter(|_| compressed == uncompressed);
        }
        // Zeroed only where it grows: the decompression overwrites what is used.
        if self.decompressed.len() < uncompressed {
            self.decompressed.resize(uncompressed, 0);
        }
        let out = &mut self.decompressed[..uncompressed];
        match compression {
            b"zstd" => {
                let zstd = match &mut self.zstd {
                    Some(zstd) => zstd,
                    none => none.insert(zstd::bulk::Decompressor::new().ok()?),
                };
                let wrote = zstd.decompress_to_buffer(stored, out).ok()?;
                (wrote == uncompressed).then_some(())?;
            }
            b"lz4" => {
                let mut lz4 = lz4::Decoder::new(stored).ok()?;
                std::io::Read::read_exact(&mut lz4, out).ok()?;
            }
            _ => return None,
        }
        self::records(&self.decompressed[..uncompressed], crc)
    }
}

/// `records` when their CRC (0: none) is right and they are whole records end to end.
fn records(records: &[u8], crc: u32) -> Option<&[u8]> {
    if crc != 0 && crc32fast::hash(records) != crc {
        return None;
    }
    let mut pos = 0;
    while pos < records.len() {
        pos = framed(records, pos)?.1;
    }
    Some(records)
}

/// Bound on a chunk's (de)compressed size: the sizes come from the file, and a corrupt one
/// must give an error, not an allocation of terabytes.
pub(super) const MAX_RECORD_BYTES: usize = 1 << 30;
