//! Damaged parts of a session file: what the reader skipped (byte range, log-time range, the
//! messages lost), and how it finds the next trustworthy record after a damaged one.

use std::collections::BTreeMap;

use mcap::records::{op, ChunkIndex, Record};
use serde::{Deserialize, Serialize};

/// A chunk (or other record) that failed its CRC, decompression or parsing: skipped whole,
/// reading went on with the next record.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DamagedChunk {
    /// The skipped bytes: `byte_offset .. byte_offset + byte_length` of the file.
    pub byte_offset: u64,
    pub byte_length: u64,
    /// The lost messages' log times lie in `start_log_time_ns ..= end_log_time_ns`.
    pub start_log_time_ns: u64,
    pub end_log_time_ns: u64,
    /// Where that range comes from, never from the damaged bytes themselves: `chunk_index`
    /// (the summary's chunk index, checked by the summary's CRC: exact) or `neighbours` (from
    /// the last message read before to the first after, in the chunks that decoded).
    pub time_source: String,
    /// Messages lost, from the file's message indexes when they survived and agree with the
    /// time range (they carry no CRC); null otherwise.
    #[serde(default)]
    pub messages: Option<u64>,
    /// Messages lost by topic (from the message indexes), when known.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub lost_by_topic: BTreeMap<String, u64>,
    pub reason: String,
}

/// What is known of a damaged record while reading; becomes a [`DamagedChunk`] at the end.
#[derive(Debug, Clone)]
pub(crate) struct Damage {
    pub offset: u64,
    pub length: u64,
    pub reason: String,
    /// Start and end log times of the chunks the summary's chunk index places in this byte
    /// range (the summary's CRC covers them; a chunk's own header and message indexes have
    /// none, and the damage may have changed them).
    pub chunk_index_times: Option<(u64, u64)>,
    /// From the message indexes: count, first and last log time, count by channel id.
    pub index: Option<IndexCounts>,
    /// Largest log time read before the damage, smallest after it (file order).
    pub before_ns: Option<u64>,
    pub after_ns: Option<u64>,
}

#[derive(Debug, Clone, Default)]
pub(crate) struct IndexCounts {
    pub messages: u64,
    pub first_ns: u64,
    pub last_ns: u64,
    pub by_channel: BTreeMap<u16, u64>,
}

impl IndexCounts {
    /// Adds one MessageIndex record (the body after opcode and length).
    pub fn add(&mut self, body: &[u8]) -> bool {
        let Ok(Record::MessageIndex(index)) =
            crate::session::record::parse(op::MESSAGE_INDEX, body)
        else {
            return false;
        };
        for entry in &index.records {
            if self.messages == 0 {
                self.first_ns = entry.log_time;
                self.last_ns = entry.log_time;
            }
            self.first_ns = self.first_ns.min(entry.log_time);
            self.last_ns = self.last_ns.max(entry.log_time);
            self.messages += 1;
        }
        *self.by_channel.entry(index.channel_id).or_insert(0) += index.records.len() as u64;
        true
    }

    /// The message indexes a chunk index points to, or None if any is unreadable.
    pub fn of_chunk(buf: &[u8], chunk: &mcap::records::ChunkIndex) -> Option<IndexCounts> {
        let mut counts = IndexCounts::default();
        for &offset in chunk.message_index_offsets.values() {
            let pos = usize::try_from(offset).ok()?;
            let (opcode, end) = framed(buf, pos)?;
            if opcode != op::MESSAGE_INDEX || !counts.add(&buf[pos + RECORD_PREFIX..end]) {
                return None;
            }
        }
        (!chunk.message_index_offsets.is_empty()).then_some(counts)
    }
}

impl Damage {
    pub fn new(offset: usize, length: usize, reason: String) -> Damage {
        Damage {
            offset: offset as u64,
            length: length as u64,
            reason,
            chunk_index_times: None,
            index: None,
            before_ns: None,
            after_ns: None,
        }
    }

    /// The report: the summary's chunk-index times when there are some, else the neighbours'.
    /// The message indexes only count the loss, and only when their times agree.
    pub fn finish(self, topic_of: impl Fn(u16) -> String) -> DamagedChunk {
        let (start, end, source) = match self.chunk_index_times {
            Some((start, end)) => (start, end, "chunk_index"),
            None => (
                self.before_ns.unwrap_or(0),
                self.after_ns.unwrap_or(u64::MAX),
                "neighbours",
            ),
        };
        let index = self
            .index
            .filter(|ix| ix.messages > 0 && start <= ix.first_ns && ix.last_ns <= end);
        let lost_by_topic = index
            .as_ref()
            .map(|ix| {
                let mut by_topic = BTreeMap::new();
                for (&channel, &n) in &ix.by_channel {
                    *by_topic.entry(topic_of(channel)).or_insert(0) += n;
                }
                by_topic
            })
            .unwrap_or_default();
        DamagedChunk {
            byte_offset: self.offset,
            byte_length: self.length,
            start_log_time_ns: start,
            end_log_time_ns: end,
            time_source: source.into(),
            messages: index.map(|ix| ix.messages),
            lost_by_topic,
            reason: self.reason,
        }
    }
}

impl DamagedChunk {
    /// Whether the lost messages may hold any with a log time in `from_ns ..= to_ns`.
    pub fn overlaps(&self, from_ns: u64, to_ns: u64) -> bool {
        self.start_log_time_ns <= to_ns && from_ns <= self.end_log_time_ns
    }

    /// One line for a warning or a report.
    pub fn describe(&self) -> String {
        let messages = match self.messages {
            Some(n) => format!("{n} messages lost"),
            None => "messages lost: unknown (no index)".into(),
        };
        format!(
            "bytes {}..{} (log time {}..={} ns, from the {}; {messages}): {}",
            self.byte_offset,
            self.byte_offset + self.byte_length,
            self.start_log_time_ns,
            self.end_log_time_ns,
            self.time_source.replace('_', " "),
            self.reason
        )
    }
}

/// Dates each damage from the summary's chunk index: the log-time span of the chunks that
/// start inside its byte range (a damaged record header can hide several). The index lists
/// every chunk, so damaged bytes where no chunk starts held no message (message indexes
/// between chunks): they are warned about and dropped from the list of losses.
pub(crate) fn date_from_chunk_index(damages: &mut Vec<Damage>, chunks: &[ChunkIndex], file: &str) {
    damages.retain_mut(|damage| {
        let bytes = damage.offset..damage.offset.saturating_add(damage.length);
        damage.chunk_index_times = chunks
            .iter()
            .filter(|c| bytes.contains(&c.chunk_start_offset))
            .map(|c| (c.message_start_time, c.message_end_time))
            .reduce(|a, b| (a.0.min(b.0), a.1.max(b.1)));
        if damage.chunk_index_times.is_none() {
            tracing::warn!(
                "{file}: damaged bytes {}..{} hold no chunk by the summary's chunk index, so \
                 no message was lost there: {}",
                bytes.start,
                bytes.end,
                damage.reason
            );
        }
        damage.chunk_index_times.is_some()
    });
}

pub(crate) const RECORD_PREFIX: usize = 9; // opcode u8 + length u64

pub(crate) fn le_u64(b: &[u8]) -> u64 {
    let mut a = [0u8; 8];
    a.copy_from_slice(&b[..8]);
    u64::from_le_bytes(a)
}

/// The opcode and end offset of the record at `pos` when its length stays inside `buf`.
pub(crate) fn framed(buf: &[u8], pos: usize) -> Option<(u8, usize)> {
    let prefix = buf.get(pos..pos.checked_add(RECORD_PREFIX)?)?;
    let len = usize::try_from(le_u64(&prefix[1..])).ok()?;
    let end = pos.checked_add(RECORD_PREFIX)?.checked_add(len)?;
    (end <= buf.len()).then_some((prefix[0], end))
}

/// A record of an MCAP opcode (private records 0x80.. are skipped by readers, not damage).
pub(crate) fn known_opcode(opcode: u8) -> bool {
    (op::HEADER..=op::DATA_END).contains(&opcode) || opcode >= 0x80
}

/// Whether a record can follow at `pos`: the end of the buffer, or a framed known record.
pub(crate) fn can_follow(buf: &[u8], pos: usize) -> bool {
    pos == buf.len() || framed(buf, pos).is_some_and(|(opcode, _)| known_opcode(opcode))
}

/// The first offset from `from` on where a record starts that can be trusted after damage: a
/// chunk that decodes (`chunk_ok`, CRC checked), a message index, DataEnd or footer that
/// parses and is followed by a record or the end; in a file without chunks so far, a
/// schema, channel or message followed by a record. None when nothing follows: the file is
/// cut short there rather than damaged.
pub(crate) fn resync(
    buf: &[u8],
    from: usize,
    saw_chunk: bool,
    chunk_ok: impl Fn(&[u8]) -> bool,
) -> Option<usize> {
    (from..buf.len()).find(|&pos| {
        let Some((opcode, end)) = framed(buf, pos) else {
            return false;
        };
        let body = &buf[pos + RECORD_PREFIX..end];
        match opcode {
            op::CHUNK => chunk_ok(&buf[pos..end]),
            op::MESSAGE_INDEX => can_follow(buf, end) && IndexCounts::default().add(body),
            op::DATA_END => body.len() == 4 && can_follow(buf, end),
            op::FOOTER => body.len() == 20 && buf[end..].starts_with(mcap::MAGIC),
            op::SCHEMA | op::CHANNEL | op::MESSAGE if !saw_chunk => {
                can_follow(buf, end) && crate::session::record::parse(opcode, body).is_ok()
            }
            _ => false,
        }
    })
}
