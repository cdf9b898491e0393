//! The streaming read of a complete, clean file: chunks decoded in parallel as for
//! `read_session`, but the tracer samples and run events go to a consumer in log-time order as
//! soon as no later chunk can hold an earlier one, and are not kept. The other (small) streams
//! are assembled into the `Session` as usual.
//!
//! Order: a chunk's index gives the earliest log time of its messages, so once chunk k is
//! merged (file order), every message before the earliest start of the chunks after k has been
//! seen (the watermark). What lies below it is sorted (stable: equal times keep file order)
//! and handed on: the concatenation of the hand-overs is exactly the stable sort of the whole
//! stream that `read_session` gives. A chunk holding a message earlier than its index says
//! ends the stream (the caller reads the whole session instead).
//!
//! A file without chunks is read in runs of whole records, which have no index: after run k
//! is merged, what lies below its earliest message is handed on, and a later run holding a
//! message below a bound already used ends the stream (as a misindexed chunk does).
//!
//! The messages move between the decoder, this reorder and the sink by exchanging buffers
//! wherever the receiving one is empty (the common case), not by copying.

use std::path::Path;

use super::decoder::{take_or_append, Decoder};
use super::progress::ReadProgress;
use super::Stamped;
use crate::session::messages::{RunEvent, SessionHeader, TracerSample, TOPIC_EVENT};

/// What consumes a streamed session.
pub trait SessionSink {
    /// The session header, the tracer ids the file defines (indices of `batch`'s `tracers`)
    /// and how many run events the file's summary counts (a hint, bounded by the file's
    /// size). False: this sink does not take this session (the stream stops).
    fn begin(&mut self, header: &SessionHeader, tracers: &[String], run_events: usize) -> bool;
    /// The next messages in log-time order: every message of the file whose log time lies
    /// between the previous batch's and this one's bound, each stream sorted. The sink takes
    /// what it keeps (the rest is dropped). False: stop the stream.
    fn batch(
        &mut self,
        tracers: &mut [Vec<Stamped<TracerSample>>],
        events: &mut Vec<Stamped<RunEvent>>,
    ) -> bool;
}

/// A sink that hands every batch on to `inner` and keeps beside it the run events `keep`
/// selects (what a method or a report reads of the events besides `inner`'s extraction).
pub struct KeepingEvents<S> {
    pub inner: S,
    keep: fn(&RunEvent) -> bool,
    pub kept: Vec<Stamped<RunEvent>>,
}

impl<S> KeepingEvents<S> {
    pub fn new(inner: S, keep: fn(&RunEvent) -> bool) -> Self {
        KeepingEvents {
            inner,
            keep,
            kept: Vec::new(),
        }
    }
}

impl<S: SessionSink> SessionSink for KeepingEvents<S> {
    fn begin(&mut self, header: &SessionHeader, tracers: &[String], run_events: usize) -> bool {
        self.inner.begin(header, tracers, run_events)
    }

    fn batch(
        &mut self,
        tracers: &mut [Vec<Stamped<TracerSample>>],
        events: &mut Vec<Stamped<RunEvent>>,
    ) -> bool {
        let keep = self.keep;
        self.kept
            .extend(events.iter().filter(|e| keep(&e.msg)).cloned());
        self.inner.batch(tracers, events)
    }
}

/// Streams the session at `path` through `sink`. None whenever the stream could differ from `read_session`'s (no trusted summary, damaged
/// chunks, chunks out of their index's order, a sink that stopped, odd writers): the caller
/// then discards what the sink saw and reads the whole session.
pub fn stream_session(path: &Path, sink: &mut dyn SessionSink) -> Option<Streamed> {
    stream_session_reporting(path, sink, None)
}

/// As `stream_session`, reporting the bytes of the file read to `progress` as the chunks are
/// merged, and the whole file once the stream is complete (a stream that gives up leaves
/// the last report short of the total: the caller's whole read finishes it).
pub fn stream_session_reporting(
    path: &Path,
    sink: &mut dyn SessionSink,
    progress: Option<&ReadProgress>,
) -> Option<Streamed> {
    let name = path.display().to_string();
    let file = std::fs::File::open(path).ok()?;
    let len = file.metadata().ok()?.len();
    let mut magic = [0u8; 8];
    std::os::unix::fs::FileExt::read_exact_at(&file, &mut magic, 0).ok()?;
    if magic[..] != mcap::MAGIC[..] {
        return None;
    }
    if let Some(progress) = progress {
        progress.report(0, len);
    }
    let summary = crate::session::summary::trusted_summary_of_file(&file, len, &name)?;
    let mut reorder = Reorder::new(sink, &summary, len);
    reorder.progress = progress;
    let decoded = super::indexed::stream_indexed_file(&file, len, &name, &summary, &mut reorder);
    let mut dec = decoded.ok().flatten()?;
    if !dec.damages.is_empty() || !reorder.finish(&mut dec) {
        return None;
    }
    let peak_held_messages = reorder.peak_held;
    let peak_chunks_in_flight = dec.peak_chunks_in_flight;
    let chunk_decoders_made = dec.chunk_decoders_made;
    let session = dec.into_session(&name, len).ok()?;
    if let Some(progress) = progress {
        progress.finish(len);
    }
    Some(Streamed {
        session,
        peak_held_messages,
        peak_chunks_in_flight,
        chunk_decoders_made,
    })
}

/// A streamed read's result.
#[derive(Debug)]
pub struct Streamed {
    /// Everything but the tracer samples and run events (which went to the sink): `tracers`
    /// keeps each tracer's id with an empty stream, `events` is empty.
    pub session: super::Session,
    /// The most tracer samples and run events the read held at once, waiting for their turn
    /// in log-time order (besides the decoded chunks in flight).
    pub peak_held_messages: usize,
    /// The most decoded chunks alive at once.
    pub peak_chunks_in_flight: usize,
    /// Chunk decoders (with their sample and event buffers) made; every other chunk reused a
    /// merged one's.
    pub chunk_decoders_made: usize,
}

/// Holds the tracer samples and events that a later chunk might still precede.
pub(super) struct Reorder<'s> {
    sink: &'s mut dyn SessionSink,
    bounds: Bounds,
    /// The summary's count of run events, at most one per 16 bytes of the file.
    run_events: usize,
    begun: bool,
    stopped: bool,
    tracers: Vec<Vec<Stamped<TracerSample>>>,
    events: Vec<Stamped<RunEvent>>,
    out_tracers: Vec<Vec<Stamped<TracerSample>>>,
    out_events: Vec<Stamped<RunEvent>>,
    /// The most tracer samples and events held here at once (tests).
    pub(super) peak_held: usize,
    /// Told the bytes of the file merged so far.
    pub(super) progress: Option<&'s ReadProgress>,
}

/// What bounds the log times of the chunks still to come.
enum Bounds {
    /// From the summary's chunk indexes.
    Indexed {
        /// For each chunk in file order: the earliest start among the chunks after it (beyond
        /// every log time after the last chunk).
        later_start_ns: Vec<u128>,
        /// Each chunk's claimed earliest log time, in file order.
        start_ns: Vec<u64>,
    },
    /// Runs of records without an index: the bound already handed on below.
    Runs { released_ns: u64 },
}

impl<'s> Reorder<'s> {
    fn new(sink: &'s mut dyn SessionSink, summary: &mcap::Summary, file_bytes: u64) -> Self {
        let run_events = summary.stats.as_ref().map_or(0, |stats| {
            let counted: u64 = summary
                .channels
                .values()
                .filter(|c| c.topic == TOPIC_EVENT)
                .filter_map(|c| stats.channel_message_counts.get(&c.id))
                .sum();
            counted.min(file_bytes / 16)
        });
        let bounds = if summary.chunk_indexes.is_empty() {
            Bounds::Runs { released_ns: 0 }
        } else {
            let mut chunks: Vec<_> = summary.chunk_indexes.iter().collect();
            chunks.sort_by_key(|c| c.chunk_start_offset);
            let start_ns: Vec<u64> = chunks.iter().map(|c| c.message_start_time).collect();
            let mut later_start_ns = vec![u128::MAX; start_ns.len()];
            for k in (0..start_ns.len().saturating_sub(1)).rev() {
                later_start_ns[k] = later_start_ns[k + 1].min(u128::from(start_ns[k + 1]));
            }
            Bounds::Indexed {
                later_start_ns,
                start_ns,
            }
        };
        Reorder {
            sink,
            bounds,
            run_events: usize::try_from(run_events).unwrap_or(0),
            begun: false,
            stopped: false,
            tracers: Vec::new(),
            events: Vec::new(),
            out_tracers: Vec::new(),
            out_events: Vec::new(),
            peak_held: 0,
            progress: None,
        }
    }

    /// Chunk `k` (file order) was merged into `dec`: takes its samples and events, hands on
    /// what can no longer be preceded. False: stop reading.
    pub(super) fn merged(&mut self, dec: &mut Decoder, k: usize) -> bool {
        if self.stopped || !dec.damages.is_empty() {
            self.stopped = true;
            return false;
        }
        if self.tracers.len() < dec.tracers.streams.len() {
            self.tracers
                .resize_with(dec.tracers.streams.len(), Vec::new);
        }
        let mut earliest = u64::MAX;
        for (held, (_, new)) in self.tracers.iter_mut().zip(&mut dec.tracers.streams) {
            earliest = new.iter().map(|s| s.log_time_ns).fold(earliest, u64::min);
            take_or_append(held, new);
        }
        earliest = dec
            .events
            .iter()
            .map(|e| e.log_time_ns)
            .fold(earliest, u64::min);
        take_or_append(&mut self.events, &mut dec.events);
        let (claimed_start, bound_ns) = match &mut self.bounds {
            Bounds::Indexed {
                later_start_ns,
                start_ns,
            } => match (start_ns.get(k), later_start_ns.get(k)) {
                (Some(&start), Some(&later)) => (start, later),
                _ => {
                    self.stopped = true;
                    return false;
                }
            },
            Bounds::Runs { released_ns } => {
                let claimed = *released_ns;
                if earliest != u64::MAX && earliest >= claimed {
                    *released_ns = earliest;
                }
                (claimed, u128::from(*released_ns))
            }
        };
        if earliest < claimed_start {
            tracing::debug!(
                "{}: chunk {k} holds a message at {earliest} ns, before its index's start \
                 {claimed_start} ns; reading the whole session",
                dec.file
            );
            self.stopped = true;
            return false;
        }
        let held = self.events.len() + self.tracers.iter().map(Vec::len).sum::<usize>();
        self.peak_held = self.peak_held.max(held);
        if !self.begun {
            match self.begin(dec) {
                None => return true,
                Some(false) => {
                    self.stopped = true;
                    return false;
                }
                Some(true) => {}
            }
        }
        self.release(bound_ns)
    }

    /// Hands the header and the tracer ids to the sink once the header is read: None before
    /// that, else whether the sink takes the session.
    fn begin(&mut self, dec: &Decoder) -> Option<bool> {
        let header = dec.header.as_ref()?;
        let ids: Vec<String> = dec
            .tracers
            .streams
            .iter()
            .map(|(id, _)| id.clone())
            .collect();
        self.begun = true;
        Some(self.sink.begin(&header.msg, &ids, self.run_events))
    }

    /// The read is over: hands on the rest. False when the stream stopped or never began.
    fn finish(&mut self, dec: &mut Decoder) -> bool {
        if self.stopped || !self.begun && dec.header.is_none() {
            return false;
        }
        if !self.begun && self.begin(dec) != Some(true) {
            return false;
        }
        self.release(u128::MAX) && !self.stopped
    }

    /// Hands on every held message with a log time below `bound_ns`.
    fn release(&mut self, bound_ns: u128) -> bool {
        self.out_tracers.resize_with(self.tracers.len(), Vec::new);
        for (held, out) in self.tracers.iter_mut().zip(&mut self.out_tracers) {
            take_below(held, out, bound_ns);
        }
        take_below(&mut self.events, &mut self.out_events, bound_ns);
        let go_on = self.sink.batch(&mut self.out_tracers, &mut self.out_events);
        for out in &mut self.out_tracers {
            out.clear();
        }
        self.out_events.clear();
        if !go_on {
            self.stopped = true;
        }
        go_on
    }
}

/// Moves the messages of `held` below `bound_ns` to `out`, sorted by log time (stable).
fn take_below<T>(held: &mut Vec<Stamped<T>>, out: &mut Vec<Stamped<T>>, bound_ns: u128) {
    // A recorder writes each stream in order: sorting it again would only copy it.
    if !held.is_sorted_by_key(|s| s.log_time_ns) {
        held.sort_by_key(|s| s.log_time_ns);
    }
    let cut = held.partition_point(|s| u128::from(s.log_time_ns) < bound_ns);
    if cut == held.len() {
        take_or_append(out, held);
    } else {
        out.extend(held.drain(..cut));
    }
}
