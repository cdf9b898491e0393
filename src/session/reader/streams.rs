//! Where decoded messages accumulate: one time-stamped stream per device and message kind,
//! and the raw log of records kept for copying (resume, repair).

use std::collections::{BTreeMap, HashMap};

use super::{RawChannel, RawMessage, Stamped};

/// Schemas, channels and messages as recorded, for `read_session_raw`.
#[derive(Default)]
pub(super) struct RawLog {
    pub(super) schemas: HashMap<u16, (String, String, Vec<u8>)>,
    pub(super) channels: HashMap<u16, std::sync::Arc<RawChannel>>,
    pub(super) messages: Vec<RawMessage>,
}

impl RawLog {
    /// The schemas and channels the summary defines (a chunk that held a channel's own
    /// record may be the damaged one).
    pub(super) fn of_summary(summary: &mcap::Summary) -> RawLog {
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

/// The streams of one message kind, by device id (from the topic), in order of definition.
pub(super) struct Streams<T> {
    pub(super) ids: HashMap<String, usize>,
    pub(super) streams: Vec<(String, Vec<Stamped<T>>)>,
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
    pub(super) fn index(&mut self, id: &str) -> usize {
        let next = self.streams.len();
        let i = *self.ids.entry(id.to_owned()).or_insert(next);
        if i == next {
            self.streams.push((id.to_owned(), Vec::new()));
        }
        i
    }

    pub(super) fn push(&mut self, index: usize, log_time_ns: u64, publish_time_ns: u64, msg: T) {
        self.streams[index].1.push(Stamped {
            log_time_ns,
            publish_time_ns,
            msg,
        });
    }

    pub(super) fn lens(&self) -> Vec<usize> {
        self.streams.iter().map(|(_, v)| v.len()).collect()
    }

    /// Back to the lengths `lens` had; streams created since then are emptied.
    pub(super) fn truncate(&mut self, lens: &[usize]) {
        for (i, (_, v)) in self.streams.iter_mut().enumerate() {
            v.truncate(lens.get(i).copied().unwrap_or(0));
        }
    }

    /// The same streams (same indices), empty: for a worker decoding later chunks.
    pub(super) fn empty_like(&self) -> Self {
        Self {
            ids: self.ids.clone(),
            streams: self
                .streams
                .iter()
                .map(|(id, _)| (id.clone(), Vec::new()))
                .collect(),
        }
    }

    /// Append a worker's streams, which come later in the file (they are left empty).
    pub(super) fn absorb(&mut self, other: &mut Streams<T>) {
        for (id, samples) in &mut other.streams {
            let i = self.index(id);
            self.streams[i].1.append(samples);
        }
    }

    /// Takes over `spent`'s buffers, emptied, for the streams both have at the same index.
    pub(super) fn reuse_buffers(&mut self, spent: &mut Streams<T>) {
        for ((id, samples), (spent_id, buffer)) in self.streams.iter_mut().zip(&mut spent.streams) {
            if id == spent_id {
                buffer.clear();
                std::mem::swap(samples, buffer);
            }
        }
    }

    /// By id, each stream sorted by log time (stable: equal times keep file order).
    pub(super) fn into_sorted_map(self) -> BTreeMap<String, Vec<Stamped<T>>> {
        self.streams
            .into_iter()
            .map(|(id, mut v)| {
                v.sort_by_key(|s| s.log_time_ns);
                (id, v)
            })
            .collect()
    }
}
