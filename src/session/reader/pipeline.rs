//! Parallel chunk decoding with a bound on what waits: workers take chunks in file order and
//! decode each on its own, the caller merges them back in file order, and no more than a set
//! number of decoded chunks exist at once (each holds a permit from its taking to its merge).
//! A merged chunk's decoder goes back to the workers with its buffers emptied, so a read
//! reuses at most that many sets of buffers whatever the number of chunks.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{mpsc, Condvar, Mutex, MutexGuard, PoisonError};

use super::decoder::{chunk_reader, Decoder, Failure};
use super::source::Bytes;
use super::ReadError;
use crate::session::damage::Damage;

/// What a parallel decode did besides filling the decoder.
#[derive(Debug)]
pub(super) struct Outcome {
    /// The first failure in file order that makes the session unusable.
    pub(super) failure: Option<ReadError>,
    /// A chunk held a message on a channel the summary did not define.
    pub(super) undefined: bool,
    /// The most chunks that were taken for decoding and not yet merged, at any moment.
    pub(super) peak_in_flight: usize,
    /// Chunk decoders (each with its buffers) made for the read: the rest were reused.
    pub(super) decoders_made: usize,
}

/// What each range of a parallel read holds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) enum Layout {
    /// One whole chunk record.
    Chunks,
    /// A run of whole top-level records (a file whose messages are not in chunks).
    Records,
}

/// Decodes `ranges` (whole chunk records of `source`, or runs of records, in file order) on
/// `threads` workers into
/// `dec`, exactly as feeding them one by one would, with at most `max_in_flight` decoded
/// chunks alive at a time (and, reading from a file, their stored bytes). `merged(dec, k)` runs
/// after chunk `k` (file order) is merged; false stops the read (no failure is recorded).
pub(super) fn decode_chunks(
    dec: &mut Decoder,
    source: Bytes<'_>,
    ranges: &[(usize, usize)],
    layout: Layout,
    threads: usize,
    max_in_flight: usize,
    merged: &mut dyn FnMut(&mut Decoder, usize) -> bool,
) -> Outcome {
    let gate = Gate {
        state: Mutex::new(GateState::default()),
        changed: Condvar::new(),
        bound: max_in_flight.max(1),
        chunks: ranges.len(),
    };
    // Chunk decoders keep any session header raw: only the merge, in file order, knows
    // whether it is the first one (parsed) or a later one (ignored).
    let template = dec.worker();
    // Merged chunks' decoders, waiting for a worker to reuse them.
    let spare: Mutex<Vec<Decoder>> = Mutex::new(Vec::new());
    let made = AtomicUsize::new(0);
    let mut outcome = Outcome {
        failure: None,
        undefined: false,
        peak_in_flight: 0,
        decoders_made: 0,
    };
    std::thread::scope(|scope| {
        let (sender, decoded) = mpsc::channel();
        for _ in 0..threads.max(1) {
            let sender = sender.clone();
            let (gate, template, spare, made) = (&gate, &template, &spare, &made);
            scope.spawn(move || {
                let mut sans = chunk_reader();
                let mut stored = Vec::new();
                while let Some((i, permit)) = gate.take() {
                    let (start, end) = ranges[i];
                    let reused = lock(spare).pop();
                    let mut chunk = match reused {
                        Some(spent) => spent.recycled(template),
                        None => {
                            made.fetch_add(1, Ordering::Relaxed);
                            template.worker()
                        }
                    };
                    let result = match source.range(start, end, &mut stored) {
                        Ok(records) if layout == Layout::Records => chunk.feed_records(records),
                        Ok(record) => chunk.feed_whole_chunk(&mut sans, record),
                        Err(source) => Err(Failure::Fatal(ReadError::Io {
                            file: chunk.file.clone(),
                            source,
                        })),
                    };
                    if result.is_err() {
                        // Its state is undefined after a failure.
                        sans = chunk_reader();
                    }
                    if sender.send((i, result.map(|()| chunk), permit)).is_err() {
                        return;
                    }
                }
            });
        }
        drop(sender);
        let mut waiting = BTreeMap::new();
        let mut next = 0;
        let mut stopped = false;
        for (i, result, permit) in decoded {
            waiting.insert(i, (result, permit));
            while let Some((result, permit)) = waiting.remove(&next) {
                let (start, end) = ranges[next];
                next += 1;
                // The first failure in file order decides, as in a serial read.
                if outcome.failure.is_none() && !stopped {
                    let (failure, spent) = merge(dec, result, start, end);
                    outcome.failure = failure;
                    if outcome.failure.is_some() {
                        gate.stop();
                    } else if !merged(dec, next - 1) {
                        stopped = true;
                        gate.stop();
                    }
                    // Back before its permit: decoders not spare never outnumber the permits.
                    lock(&spare).extend(spent);
                }
                drop(permit);
            }
        }
    });
    outcome.undefined = dec.saw_undefined;
    outcome.peak_in_flight = gate.lock().peak;
    outcome.decoders_made = made.into_inner();
    outcome
}

fn lock<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(PoisonError::into_inner)
}

/// Merges one decoded chunk (or notes its damage) as a serial read would have fed it; gives
/// back the chunk's emptied decoder for reuse.
fn merge(
    dec: &mut Decoder,
    result: Result<Decoder, Failure>,
    start: usize,
    end: usize,
) -> (Option<ReadError>, Option<Decoder>) {
    match result {
        Ok(mut chunk) => {
            dec.saw_undefined |= chunk.saw_undefined;
            let failure = match dec.absorb(&mut chunk) {
                Ok(()) | Err(Failure::Damaged(_)) => None,
                Err(Failure::Fatal(err)) => Some(err),
            };
            (failure, Some(chunk))
        }
        Err(Failure::Damaged(why)) => {
            let why = format!("chunk at byte {start}: {why}");
            dec.damage(Damage::new(start, end - start, why));
            (None, None)
        }
        Err(Failure::Fatal(err)) => (Some(err), None),
    }
}

struct Gate {
    state: Mutex<GateState>,
    changed: Condvar,
    bound: usize,
    chunks: usize,
}

#[derive(Default)]
struct GateState {
    /// The next chunk to take.
    next: usize,
    /// Chunks taken and not yet merged.
    live: usize,
    peak: usize,
    stop: bool,
}

/// A decoded chunk's right to exist: taken before decoding, given back once merged.
struct Permit<'a> {
    gate: &'a Gate,
}

impl Drop for Permit<'_> {
    fn drop(&mut self) {
        self.gate.lock().live -= 1;
        self.gate.changed.notify_all();
    }
}

impl Gate {
    fn lock(&self) -> MutexGuard<'_, GateState> {
        lock(&self.state)
    }

    /// The next chunk in file order and its permit, once fewer than `bound` are alive; None
    /// when every chunk is taken or the read stopped. The oldest unmerged chunk is always
    /// being decoded or already sent, so waiting here cannot deadlock.
    fn take(&self) -> Option<(usize, Permit<'_>)> {
        let mut state = self.lock();
        loop {
            if state.stop || state.next >= self.chunks {
                return None;
            }
            if state.live < self.bound {
                break;
            }
            state = self
                .changed
                .wait(state)
                .unwrap_or_else(PoisonError::into_inner);
        }
        let i = state.next;
        state.next += 1;
        state.live += 1;
        state.peak = state.peak.max(state.live);
        Some((i, Permit { gate: self }))
    }

    fn stop(&self) {
        self.lock().stop = true;
        self.changed.notify_all();
    }
}
