//! The indexed read of a complete file: the chunks the summary lists, decoded in parallel.

use super::decoder::Decoder;
use super::pipeline::{decode_chunks, Layout};
use super::runs::record_runs;
use super::source::Bytes;
use super::stream::Reorder;
use super::streams::RawLog;
use super::ReadError;
use crate::session::damage::IndexCounts;

/// Reads the chunks the summary lists. Returns None when the summary does not account for
/// every message (unchunked messages, odd writers): the caller then reads linearly.
pub(super) fn read_indexed(
    buf: &[u8],
    file: &str,
    summary: &mcap::Summary,
) -> Result<Option<Decoder>, ReadError> {
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    read_indexed_with(buf, file, summary, threads.min(MAX_DECODE_THREADS), false)
}

/// The indexed read of a complete, clean file straight from the file, one chunk at a time:
/// None whenever the read from memory could differ (no summary, damaged chunks, channels the
/// summary does not define, odd writers); the caller then reads the file whole.
pub(super) fn read_indexed_file(
    file: &std::fs::File,
    len: u64,
    name: &str,
    summary: &mcap::Summary,
) -> Result<Option<Decoder>, ReadError> {
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let source = Bytes::File { file, len };
    let threads = threads.clamp(1, MAX_DECODE_THREADS);
    let decoded = read_indexed_from(source, name, summary, threads, false, None, None)?;
    Ok(decoded.filter(|dec| dec.damages.is_empty()))
}

/// As `read_indexed_file`, the tracer samples and run events handed to `reorder` chunk by chunk
/// instead of kept; None (or damages in the decoder) when the stream is not the session.
pub(super) fn stream_indexed_file(
    file: &std::fs::File,
    len: u64,
    name: &str,
    summary: &mcap::Summary,
    reorder: &mut Reorder<'_>,
) -> Result<Option<Decoder>, ReadError> {
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let source = Bytes::File { file, len };
    let threads = threads.clamp(1, MAX_DECODE_THREADS);
    read_indexed_from(source, name, summary, threads, false, None, Some(reorder))
}

/// Decompressing and parsing is most of the time a large session takes to read, and chunks
/// are independent: up to this many threads decode them.
pub(super) const MAX_DECODE_THREADS: usize = 8;
/// Decoded chunks waiting for their in-order merge, per thread: enough to keep every thread
/// busy while one slow chunk holds up the order, and a bound on what a read holds besides the
/// merged streams (a chunk is about 1 MiB decompressed as the recorder writes it).
pub(super) const CHUNKS_IN_FLIGHT_PER_THREAD: usize = 2;

/// `raw`: keep every message raw and decode none (repair); serial, channels from the summary.
pub(super) fn read_indexed_with(
    buf: &[u8],
    file: &str,
    summary: &mcap::Summary,
    threads: usize,
    raw: bool,
) -> Result<Option<Decoder>, ReadError> {
    read_indexed_bounded(buf, file, summary, threads, raw, None)
}

/// As `read_indexed_with`, with at most `max_in_flight` decoded chunks alive at once (None:
/// `CHUNKS_IN_FLIGHT_PER_THREAD` per thread).
pub(super) fn read_indexed_bounded(
    buf: &[u8],
    file: &str,
    summary: &mcap::Summary,
    threads: usize,
    raw: bool,
    max_in_flight: Option<usize>,
) -> Result<Option<Decoder>, ReadError> {
    read_indexed_from(
        Bytes::Memory(buf),
        file,
        summary,
        threads,
        raw,
        max_in_flight,
        None,
    )
}

fn read_indexed_from(
    source: Bytes<'_>,
    file: &str,
    summary: &mcap::Summary,
    threads: usize,
    raw: bool,
    max_in_flight: Option<usize>,
    mut reorder: Option<&mut Reorder<'_>>,
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
        // A streamed read keeps no tracer samples or events: nothing to reserve for.
        if reorder.is_some() {
            continue;
        }
        if let Some(&n) = stats.channel_message_counts.get(&channel.id) {
            // Counts come from the file and may be corrupt: only a hint, bounded by its size.
            dec.reserve(channel.id, n.min(source.len() / 16));
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
            .filter(|&(s, e)| s < e && e as u64 <= source.len());
        let Some(range) = range else {
            // The linear read that follows meets every chunk before this one in the same order,
            // so decoding them here first could not change the outcome.
            tracing::debug!("{file}: chunk index points outside the file; reading linearly");
            return Ok(None);
        };
        ranges.push(range);
    }
    let mut layout = Layout::Chunks;
    if ranges.is_empty() && stats.message_count > 0 {
        // No chunks: from the file, in runs of records; in memory the linear read applies.
        let runs = match source {
            Bytes::File { file, len } => record_runs(file, len),
            Bytes::Memory(_) => None,
        };
        let Some(runs) = runs else {
            return Ok(None);
        };
        ranges = runs;
        layout = Layout::Records;
    }
    // A chunk may define a channel that later chunks use: threads are only safe when the
    // summary already defines every channel that has messages.
    let all_defined = stats
        .channel_message_counts
        .keys()
        .all(|id| summary.channels.contains_key(id))
        && stats.channel_message_counts.values().sum::<u64>() == stats.message_count;
    let threads = if all_defined { threads } else { 1 };
    let serial = match source.memory() {
        Some(_) if reorder.is_some() => None,
        Some(buf) if threads <= 1 || ranges.len() < 2 => Some(buf),
        Some(_) => None,
        // From a file, chunk by chunk: only when the threads' result is certain.
        None if all_defined => None,
        None if reorder.is_some() => return Ok(None),
        None => return Ok(None),
    };
    let (failure, undefined) = if let Some(buf) = serial {
        (dec.feed_chunks(buf, &ranges).err(), false)
    } else {
        let file_bytes = source.len();
        let ranges_done = &ranges;
        let mut merged = |dec: &mut Decoder, k: usize| match reorder.as_deref_mut() {
            Some(reorder) => {
                let go_on = reorder.merged(dec, k);
                if let (Some(progress), Some(&(_, end))) = (reorder.progress, ranges_done.get(k)) {
                    progress.report(end as u64, file_bytes);
                }
                go_on
            }
            None => true,
        };
        let outcome = decode_chunks(
            &mut dec,
            source,
            &ranges,
            layout,
            threads,
            max_in_flight.unwrap_or(threads * CHUNKS_IN_FLIGHT_PER_THREAD),
            &mut merged,
        );
        dec.peak_chunks_in_flight = outcome.peak_in_flight;
        dec.chunk_decoders_made = outcome.decoders_made;
        (outcome.failure, outcome.undefined)
    };
    if undefined {
        // A worker met a message on a channel it did not know: decode serially instead.
        return match source.memory() {
            Some(buf) => read_indexed_bounded(buf, file, summary, 1, raw, None),
            None => Ok(None),
        };
    }
    if let Some(err) = failure {
        return Err(err);
    }
    // What the damaged chunks held, from the summary's chunk indexes and the message indexes.
    let mut lost = 0;
    let buf = match source.memory() {
        Some(buf) => buf,
        None if dec.damages.is_empty() => &[],
        None => return Ok(None),
    };
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
