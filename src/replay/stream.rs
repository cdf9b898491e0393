//! The replay's streaming reads (`session::reader::stream_session`): what the replay needs of a
//! clean session without holding its tracer samples whole.
//!
//! - `EventMarks`: the run events, each with its place among the tracer samples (a `Mark`),
//!   and the tracer's sample count: enough for the dwell windows, the event counts and the
//!   replay's placement of events.
//! - `TimeMarks`: the place of given log times (the other devices' recorded messages).
//! - `SampleFeed`: the tracer samples handed to the replay devices in order through a bounded
//!   channel from a reader thread, with a buffer that keeps only what the devices still look at.

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::mpsc::{sync_channel, Receiver, SyncSender};
use std::sync::Arc;
use std::thread::JoinHandle;

use crate::session::messages::{RunEvent, SessionHeader, TracerSample};
use crate::session::reader::{stream_session, SessionSink, Stamped};

/// Where a log time T falls among a tracer's samples (sorted by log time).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Mark {
    /// Samples with a log time before T.
    pub before: usize,
    /// Samples with a log time at or before T (a message at T is placed after them).
    pub at_or_before: usize,
    /// Seq of the first sample at or after T.
    pub first_seq_from: Option<u64>,
    /// Seq of the last sample at or before T.
    pub last_seq_to: Option<u64>,
    /// No sample carries the log time T itself: a message at T was stamped after the sample
    /// before it (a wall clock), not with its time (a virtual clock).
    pub later: bool,
}

/// Marks log times, given in nondecreasing order, against tracer samples fed in log-time order
/// (each time added before any sample at or after it is fed).
#[derive(Debug, Default)]
struct Marker {
    marks: Vec<Mark>,
    times: Vec<u64>,
    /// Marks from here on still wait for a sample after their time.
    open_from: usize,
    /// Marks from here on still wait for a sample at or after their time.
    unstarted_from: usize,
    samples: usize,
    last_seq: Option<u64>,
    /// The last sample's log time.
    last_ns: Option<u64>,
}

impl Marker {
    fn add(&mut self, log_time_ns: u64) {
        self.times.push(log_time_ns);
        self.marks.push(Mark::default());
    }

    fn sample(&mut self, log_time_ns: u64, seq: u64) {
        while self.unstarted_from < self.times.len()
            && self.times[self.unstarted_from] <= log_time_ns
        {
            let m = &mut self.marks[self.unstarted_from];
            m.before = self.samples;
            m.first_seq_from = Some(seq);
            self.unstarted_from += 1;
        }
        while self.open_from < self.times.len() && self.times[self.open_from] < log_time_ns {
            self.close(self.open_from);
            self.open_from += 1;
        }
        self.samples += 1;
        self.last_seq = Some(seq);
        self.last_ns = Some(log_time_ns);
    }

    /// Mark `k` has seen every sample at or before its time.
    fn close(&mut self, k: usize) {
        let t = self.times[k];
        let (samples, last_seq, last_ns) = (self.samples, self.last_seq, self.last_ns);
        let m = &mut self.marks[k];
        if k >= self.unstarted_from {
            m.before = samples;
        }
        m.at_or_before = samples;
        m.last_seq_to = last_seq;
        m.later = last_ns != Some(t);
    }

    /// No sample follows.
    fn finish(&mut self) {
        for k in self.open_from..self.times.len() {
            self.close(k);
        }
        self.open_from = self.times.len();
        self.unstarted_from = self.times.len();
    }
}

/// The tracer a replay follows among the ids a session defines: the header's tracer device if
/// it has a stream, else the only stream. Err: the number of streams when none or several.
pub fn choose_tracer<'a>(
    header: &SessionHeader,
    mut ids: impl Iterator<Item = &'a String> + Clone,
) -> Result<String, usize> {
    let named = header
        .devices
        .iter()
        .find(|d| d.kind == "tracer")
        .map(|d| d.id.clone());
    if let Some(id) = named.filter(|id| ids.clone().any(|x| x == id)) {
        return Ok(id);
    }
    match (ids.clone().count(), ids.next()) {
        (1, Some(id)) => Ok(id.clone()),
        (n, _) => Err(n),
    }
}

/// A session's run events with their marks among one tracer's samples, streamed.
#[derive(Debug, Default)]
pub struct EventMarks {
    /// The tracer to mark against: None chooses as the replay does (`choose_tracer`).
    pub tracer_id: Option<String>,
    pub header: Option<SessionHeader>,
    tracer_index: Option<usize>,
    pub events: Vec<Stamped<RunEvent>>,
    marker: Marker,
    /// The chosen tracer's first sample (log time) and last sample (its own time, s).
    pub first_log_ns: Option<u64>,
    pub last_t_s: Option<f64>,
}

/// What `EventMarks` read of a session.
#[derive(Debug)]
pub struct MarkedEvents {
    pub header: SessionHeader,
    pub tracer_id: String,
    pub events: Vec<Stamped<RunEvent>>,
    pub marks: Vec<Mark>,
    pub samples: usize,
    pub first_log_ns: Option<u64>,
    pub last_t_s: Option<f64>,
}

impl EventMarks {
    pub fn new(tracer_id: Option<String>) -> Self {
        EventMarks {
            tracer_id,
            ..Default::default()
        }
    }

    /// Streams the session at `path`; None when it cannot be streamed exactly (read it whole).
    pub fn read(
        path: &Path,
        tracer_id: Option<String>,
    ) -> Option<(MarkedEvents, crate::session::reader::Session)> {
        let mut sink = EventMarks::new(tracer_id);
        let streamed = stream_session(path, &mut sink)?;
        let mut marker = sink.marker;
        marker.finish();
        let tracer_id = match (sink.tracer_id, sink.tracer_index) {
            (Some(id), _) => id,
            (None, Some(i)) => streamed.session.tracers.keys().nth(i)?.clone(),
            (None, None) => return None,
        };
        Some((
            MarkedEvents {
                header: sink.header?,
                tracer_id,
                events: sink.events,
                marks: marker.marks,
                samples: marker.samples,
                first_log_ns: sink.first_log_ns,
                last_t_s: sink.last_t_s,
            },
            streamed.session,
        ))
    }
}

impl SessionSink for EventMarks {
    fn begin(&mut self, header: &SessionHeader, tracers: &[String], run_events: usize) -> bool {
        self.header = Some(header.clone());
        self.tracer_index = match &self.tracer_id {
            Some(id) => tracers.iter().position(|t| t == id),
            None => match choose_tracer(header, tracers.iter()) {
                Ok(id) => tracers.iter().position(|t| *t == id),
                // The whole read gives the replay's error.
                Err(_) => return false,
            },
        };
        self.events.reserve(run_events);
        true
    }

    fn batch(
        &mut self,
        tracers: &mut [Vec<Stamped<TracerSample>>],
        events: &mut Vec<Stamped<RunEvent>>,
    ) -> bool {
        // Every later sample lies at or after this batch's bound, beyond these events.
        for e in events.iter() {
            self.marker.add(e.log_time_ns);
        }
        self.events.append(events);
        if let Some(samples) = self.tracer_index.and_then(|i| tracers.get(i)) {
            for s in samples {
                self.first_log_ns.get_or_insert(s.log_time_ns);
                self.marker.sample(s.log_time_ns, s.msg.seq);
            }
            if let Some(s) = samples.last() {
                self.last_t_s = Some(s.msg.t_s);
            }
        }
        true
    }
}

/// Marks of given log times (sorted) among one tracer's samples, streamed.
pub struct TimeMarks {
    tracer_id: String,
    tracer_index: Option<usize>,
    marker: Marker,
}

impl TimeMarks {
    /// The marks of `times_ns` (nondecreasing) among the samples of `tracer_id` in the session
    /// at `path`; None when it does not stream.
    pub fn read(path: &Path, tracer_id: &str, times_ns: &[u64]) -> Option<Vec<Mark>> {
        let mut sink = TimeMarks {
            tracer_id: tracer_id.to_string(),
            tracer_index: None,
            marker: Marker::default(),
        };
        for &t in times_ns {
            sink.marker.add(t);
        }
        stream_session(path, &mut sink)?;
        sink.marker.finish();
        Some(sink.marker.marks)
    }
}

impl SessionSink for TimeMarks {
    fn begin(&mut self, _: &SessionHeader, tracers: &[String], _: usize) -> bool {
        self.tracer_index = tracers.iter().position(|t| *t == self.tracer_id);
        true
    }

    fn batch(
        &mut self,
        tracers: &mut [Vec<Stamped<TracerSample>>],
        _: &mut Vec<Stamped<RunEvent>>,
    ) -> bool {
        if let Some(samples) = self.tracer_index.and_then(|i| tracers.get(i)) {
            for s in samples {
                self.marker.sample(s.log_time_ns, s.msg.seq);
            }
        }
        true
    }
}

/// Samples sent to the replay at once.
const FEED_BLOCK: usize = 4096;
/// Blocks queued between the reader thread and the replay.
const FEED_BLOCKS_QUEUED: usize = 2;
/// The most recorded samples a streamed replay holds at once, whatever the recording's length
/// (a recording without recorded arrivals may hold more: the homing search looks ahead to
/// the next point): the buffer (a block and the sample before the cursor) and the blocks
/// queued or being sent by the reader thread.
pub const SAMPLES_HELD_BOUND: usize = FEED_BLOCK + 1 + (FEED_BLOCKS_QUEUED + 1) * FEED_BLOCK;

/// The sink of the reader thread: the followed tracer's samples, in blocks.
struct FeedSink {
    tracer_id: String,
    tracer_index: Option<usize>,
    to_replay: SyncSender<Vec<Stamped<TracerSample>>>,
    /// Samples taken for sending so far.
    sent: Arc<AtomicUsize>,
}

impl SessionSink for FeedSink {
    fn begin(&mut self, _: &SessionHeader, tracers: &[String], _: usize) -> bool {
        self.tracer_index = tracers.iter().position(|t| *t == self.tracer_id);
        self.tracer_index.is_some()
    }

    fn batch(
        &mut self,
        tracers: &mut [Vec<Stamped<TracerSample>>],
        _: &mut Vec<Stamped<RunEvent>>,
    ) -> bool {
        let Some(samples) = self.tracer_index.and_then(|i| tracers.get_mut(i)) else {
            return false;
        };
        for block in samples.chunks(FEED_BLOCK) {
            self.sent.fetch_add(block.len(), Ordering::Relaxed);
            // The replay hung up: it needs no more.
            if self.to_replay.send(block.to_vec()).is_err() {
                return false;
            }
        }
        samples.clear();
        true
    }
}

/// A recording's tracer samples, by index: all in memory (a session read whole), or streamed
/// from the file, keeping those the replay may still look at.
#[derive(Debug)]
pub struct Samples {
    /// Samples in the recording.
    len: usize,
    /// Index of `held`'s first sample.
    base: usize,
    held: VecDeque<Stamped<TracerSample>>,
    feed: Option<Feed>,
    /// The most samples held at once (here, queued and being sent).
    peak_held: usize,
    /// The stream ended before `len` samples.
    cut_short: bool,
}

#[derive(Debug)]
struct Feed {
    from_reader: Option<Receiver<Vec<Stamped<TracerSample>>>>,
    reader: Option<JoinHandle<()>>,
    /// Samples the reader thread took for sending, and those received here.
    sent: Arc<AtomicUsize>,
    received: usize,
}

impl Drop for Feed {
    fn drop(&mut self) {
        // Hang up first so that a reader blocked on a full channel stops.
        self.from_reader = None;
        if let Some(reader) = self.reader.take() {
            let _ = reader.join();
        }
    }
}

impl Samples {
    /// Samples held whole.
    pub fn whole(samples: Vec<Stamped<TracerSample>>) -> Samples {
        Samples {
            len: samples.len(),
            base: 0,
            peak_held: samples.len(),
            held: samples.into(),
            feed: None,
            cut_short: false,
        }
    }

    /// The `len` samples of tracer `tracer_id` in the (clean, already streamed once) session at
    /// `path`, read by a thread as the replay asks for them.
    pub fn streamed(path: &Path, tracer_id: &str, len: usize) -> std::io::Result<Samples> {
        let (to_replay, from_reader) = sync_channel(FEED_BLOCKS_QUEUED);
        let path: PathBuf = path.to_path_buf();
        let sent = Arc::new(AtomicUsize::new(0));
        let mut sink = FeedSink {
            tracer_id: tracer_id.to_string(),
            tracer_index: None,
            to_replay,
            sent: sent.clone(),
        };
        let reader = std::thread::Builder::new()
            .name("replay-feed".into())
            .spawn(move || {
                stream_session(&path, &mut sink);
            })?;
        Ok(Samples {
            len,
            base: 0,
            held: VecDeque::new(),
            feed: Some(Feed {
                from_reader: Some(from_reader),
                reader: Some(reader),
                sent,
                received: 0,
            }),
            peak_held: 0,
            cut_short: false,
        })
    }

    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The most samples held at once (whole: all of them).
    pub fn peak_held(&self) -> usize {
        self.peak_held
    }

    /// The file gave fewer samples than its first read counted (it changed meanwhile).
    pub fn cut_short(&self) -> bool {
        self.cut_short
    }

    /// Sample `i`: None past the end, or when it was released (a bug: the devices look back
    /// at most to the sample before their cursor).
    pub fn get(&mut self, i: usize) -> Option<Stamped<TracerSample>> {
        if i >= self.len || i < self.base {
            return None;
        }
        while i >= self.base + self.held.len() {
            let feed = self.feed.as_mut()?;
            let block = feed.from_reader.as_ref().and_then(|rx| rx.recv().ok());
            match block {
                Some(block) => {
                    feed.received += block.len();
                    self.held.extend(block);
                    let in_flight = feed.sent.load(Ordering::Relaxed) - feed.received;
                    self.peak_held = self.peak_held.max(self.held.len() + in_flight);
                }
                None => {
                    self.cut_short = true;
                    self.len = self.base + self.held.len();
                    return None;
                }
            }
        }
        self.held.get(i - self.base).cloned()
    }

    /// The devices will not look at samples before `i` again: a streamed buffer drops them.
    pub fn release_before(&mut self, i: usize) {
        if self.feed.is_none() {
            return;
        }
        let n = i.saturating_sub(self.base).min(self.held.len());
        self.held.drain(..n);
        self.base += n;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(log_time_ns: u64, seq: u64) -> Stamped<TracerSample> {
        Stamped {
            log_time_ns,
            publish_time_ns: log_time_ns,
            msg: TracerSample {
                seq,
                t_s: log_time_ns as f64 * 1e-9,
                length_m: 0.1,
                signal: 1.0,
                tracking: true,
                beam_segment: 0,
            },
        }
    }

    /// The marks of times fed in batches equal those found by searching the whole stream:
    /// times before, between, at (several samples, several marks) and after the samples.
    #[test]
    fn streamed_marks_equal_the_searched_ones() {
        let times = [10, 20, 20, 20, 30, 40, 40, 50];
        let samples: Vec<_> = (times.iter().enumerate())
            .map(|(i, &t)| sample(t, 100 + i as u64))
            .collect();
        let marked = [0, 5, 10, 15, 20, 20, 25, 40, 45, 50, 60, 60];
        let searched: Vec<Mark> = (marked.iter())
            .map(|&t| crate::replay::recording::mark_in(&samples, t))
            .collect();
        // Batches as the reader hands them: every mark below a batch's bound, with its samples.
        for bounds in [
            vec![u64::MAX],
            vec![20, 41, u64::MAX],
            vec![5, 21, 30, 50, u64::MAX],
        ] {
            let mut marker = Marker::default();
            let (mut s, mut m) = (0, 0);
            for bound in bounds {
                while m < marked.len() && marked[m] < bound {
                    marker.add(marked[m]);
                    m += 1;
                }
                while s < samples.len() && samples[s].log_time_ns < bound {
                    marker.sample(samples[s].log_time_ns, samples[s].msg.seq);
                    s += 1;
                }
            }
            marker.finish();
            assert_eq!(marker.marks, searched);
        }
        assert_eq!(
            searched[4],
            Mark {
                before: 1,
                at_or_before: 4,
                first_seq_from: Some(101),
                last_seq_to: Some(103),
                later: false,
            }
        );
        assert!(searched[0].later && searched[0].last_seq_to.is_none());
        assert_eq!(
            (searched[10].before, searched[10].first_seq_from),
            (8, None)
        );
    }

    /// Samples held whole stay held whatever is released, and all count as held.
    #[test]
    fn the_whole_buffer_keeps_everything_and_counts_it() {
        let mut whole = Samples::whole((0..10).map(|i| sample(i, i)).collect());
        whole.release_before(5);
        assert_eq!(whole.get(0).map(|s| s.msg.seq), Some(0));
        assert_eq!(whole.get(10), None);
        assert_eq!(whole.peak_held(), 10);
    }
}
