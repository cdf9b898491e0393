//! The streaming extraction against the whole-session one, and its memory bound.

use std::path::Path;

use super::{extract_points, ExtractOptions, LengthStream, Lengths, NoiseModel};
use crate::session::messages::{RunEvent, TracerSample};
use crate::session::reader::testutil::header;
use crate::session::reader::{read_session, stream_session, Streamed};
use crate::session::recorder::{Compression, Recorder, RecorderOptions};

const DT_NS: u64 = 50_000_000;

/// A two-station multilateration recording of `points` points per station, in small chunks,
/// with every kind of window the extraction meets: settled, beam broken, never ended,
/// mismatched, repeated after re-homing; events at the log time of a sample, and samples
/// recorded after an event that precedes them in log time (a device's late delivery).
pub(super) fn record(path: &Path, points: usize) {
    let rec = Recorder::create(
        path,
        RecorderOptions {
            chunk_size: 4096,
            flush_interval: std::time::Duration::from_secs(3600),
            compression: Compression::Zstd,
            tap: Default::default(),
        },
    )
    .expect("recorder");
    let h = rec.handle();
    h.session(&header(), 1);
    let mut seq = 0u64;
    let mut t_ns = 1_000_000_000u64;
    let mut sample = |length_m: f64, tracking: bool, t_ns: u64| {
        seq += 1;
        let s = TracerSample {
            seq,
            t_s: t_ns as f64 * 1e-9,
            length_m,
            signal: 0.9,
            tracking,
            beam_segment: 0,
        };
        (s, t_ns)
    };
    for (station_index, station) in ["s1", "s2"].into_iter().enumerate() {
        let station_begin = RunEvent::StationBegin {
            station: station.into(),
            station_index,
            hint_m: Some([station_index as f64, 0.5, 0.2]),
        };
        h.event(&station_begin, t_ns);
        for point in 0..points {
            let length_m = 1.0 + 0.01 * point as f64 + 0.3 * station_index as f64;
            // Motion.
            for k in 0..2 {
                t_ns += DT_NS;
                let (s, at) = sample(length_m - 0.001 * (2 - k) as f64, true, t_ns);
                h.tracer("tracer0", &s, at);
            }
            t_ns += DT_NS;
            let begin_ns = t_ns;
            let begin = RunEvent::PointBegin {
                station: station.into(),
                point,
                pass: 0,
                target: if point % 2 == 0 { "t0" } else { "t1" }.into(),
                nominal_m: [point as f64 * 0.1, 0.2, 0.3],
                axes: [("x", 0.1), ("y", 0.2), ("z", point as f64)]
                    .into_iter()
                    .map(|(a, v)| (a.to_owned(), v))
                    .collect(),
                approach: [("x".to_owned(), 1)].into_iter().collect(),
            };
            let mut dwell = Vec::new();
            for k in 0..12u64 {
                // The dwell's first sample shares the point_begin's log time.
                let at = begin_ns + k * DT_NS;
                let noise = 1e-7 * (((point as u64 + k) % 5) as f64 - 2.0);
                let tracking = !(point % 17 == 3 && k == 6);
                dwell.push(sample(length_m + noise, tracking, at));
            }
            t_ns = begin_ns + 11 * DT_NS;
            if point % 13 == 4 {
                // Late delivery: the first dwell samples are written after the point_begin.
                h.event(&begin, begin_ns);
                for (s, at) in &dwell {
                    h.tracer("tracer0", s, *at);
                }
            } else {
                for (s, at) in &dwell[..3] {
                    h.tracer("tracer0", s, *at);
                }
                h.event(&begin, begin_ns);
                for (s, at) in &dwell[3..] {
                    h.tracer("tracer0", s, *at);
                }
            }
            if point % 31 == 9 {
                h.event(
                    &RunEvent::Rehome {
                        station: station.into(),
                        beam_segment: 0,
                    },
                    t_ns,
                );
                continue;
            }
            if point % 23 == 5 {
                continue; // no point_end: dropped at the next point_begin
            }
            let end = RunEvent::PointEnd {
                station: station.into(),
                point: if point % 29 == 7 { point + 1 } else { point },
                pass: 0,
            };
            // At the log time of the dwell's last sample.
            h.event(&end, t_ns);
        }
        h.event(
            &RunEvent::StationEnd {
                station: station.into(),
            },
            t_ns + 1,
        );
    }
    rec.finish().expect("finish");
}

fn whole_session_lengths(path: &Path) -> Lengths {
    let session = read_session(path).expect("session");
    let noise = NoiseModel::from_header(&session.header, "tracer0");
    let options = ExtractOptions::from_header(&session.header);
    let extraction = extract_points(&session, Some("tracer0"), noise, &options).expect("extract");
    Lengths::of_extraction(&extraction)
}

fn streamed(path: &Path) -> (Lengths, Streamed, usize) {
    let mut sink = LengthStream::new("multilateration");
    let streamed = stream_session(path, &mut sink).expect("a clean file streams");
    let peak_samples = sink.peak_samples;
    let (lengths, tracer, _) = sink.finish().expect("begun");
    assert_eq!(tracer, "tracer0");
    (lengths, streamed, peak_samples)
}

#[test]
fn streamed_lengths_equal_the_whole_session_extraction() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("s.mcap");
    record(&path, 60);
    let whole = whole_session_lengths(&path);
    let (lengths, streamed, _) = streamed(&path);
    assert_eq!(lengths, whole);
    // Every kind of window occurs.
    assert!(
        whole.measurements.len() > 80,
        "{}",
        whole.measurements.len()
    );
    let reasons: std::collections::BTreeSet<_> =
        whole.dropped.iter().map(|d| d.reason.as_str()).collect();
    assert_eq!(reasons.len(), 3, "{reasons:?}");
    assert_eq!(whole.repeated.len(), 4);
    // The rest of the session is the whole read's, without the tracer samples and events.
    let mut session = read_session(&path).expect("session");
    for samples in session.tracers.values_mut() {
        samples.clear();
    }
    session.events.clear();
    assert_eq!(streamed.session, session);
}

/// The most messages any chunk of the file holds (from its message indexes).
pub(super) fn largest_chunk(path: &Path) -> u64 {
    let bytes = std::fs::read(path).expect("read");
    let summary = mcap::Summary::read(&bytes)
        .expect("summary")
        .expect("summary");
    summary
        .chunk_indexes
        .iter()
        .map(|c| crate::session::damage::IndexCounts::of_chunk(&bytes, c).expect("index"))
        .map(|counts| counts.messages)
        .max()
        .expect("chunks")
}

/// What the streaming extraction holds at once does not grow with the recording: the same
/// plan recorded 10x longer holds no more than one window and two chunks' worth of messages,
/// and no more decoded chunks, however long it is.
#[test]
fn streaming_holds_a_bound_whatever_the_length() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (short, long) = (dir.path().join("short.mcap"), dir.path().join("long.mcap"));
    record(&short, 40);
    record(&long, 400);
    let chunk = largest_chunk(&short).max(largest_chunk(&long)) as usize;
    assert!(chunk < 60, "{chunk} messages in a chunk");
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let chunks_bound = 2 * threads.clamp(1, 8);
    let mut measured = 0;
    for path in [&short, &long] {
        let (lengths, read, samples) = streamed(path);
        // The open window's 14 samples (12 of dwell, 2 of motion) and two chunks' worth: the
        // one merged and what an earlier one left waiting for the watermark.
        assert!(samples <= 14 + 2 * chunk, "{samples} samples held");
        assert!(
            read.peak_held_messages <= 2 * chunk,
            "{}",
            read.peak_held_messages
        );
        assert!((1..=chunks_bound).contains(&read.peak_chunks_in_flight));
        assert!(lengths.measurements.len() > 9 * measured);
        measured = lengths.measurements.len();
    }
}

/// `from`'s messages written again by the mcap crate's writer without chunks (as an
/// unchunked recorder lays them out), in the same order.
fn rewrite_unchunked(from: &Path, to: &Path) {
    let bytes = std::fs::read(from).expect("read");
    let file = std::io::BufWriter::new(std::fs::File::create(to).expect("create"));
    let mut writer = mcap::WriteOptions::new()
        .use_chunks(false)
        .create(file)
        .expect("writer");
    for message in mcap::MessageStream::new(&bytes).expect("messages") {
        writer.write(&message.expect("message")).expect("write");
    }
    writer.finish().expect("finish");
}

/// A file without chunks streams from the file in runs of records (parallel, bounded: the
/// runs are a few kB in tests) to exactly the whole read's extraction and session.
#[test]
fn unchunked_files_stream_as_read_whole() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (chunked, unchunked) = (dir.path().join("c.mcap"), dir.path().join("u.mcap"));
    record(&chunked, 300);
    rewrite_unchunked(&chunked, &unchunked);
    let bytes = std::fs::read(&unchunked).expect("read");
    let summary = mcap::Summary::read(&bytes)
        .expect("summary")
        .expect("summary");
    assert!(summary.chunk_indexes.is_empty());
    let whole = whole_session_lengths(&chunked);
    assert_eq!(whole_session_lengths(&unchunked), whole);
    let (lengths, streamed, samples) = streamed(&unchunked);
    assert_eq!(lengths, whole);
    let mut session = read_session(&unchunked).expect("session");
    for samples in session.tracers.values_mut() {
        samples.clear();
    }
    session.events.clear();
    assert_eq!(streamed.session, session);
    // Bounded as a chunked file is: a run holds fewer than 100 messages here.
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let runs_bound = 2 * threads.clamp(1, 8);
    assert!(samples <= 14 + 200, "{samples} samples held");
    assert!(
        streamed.peak_held_messages <= 200,
        "{}",
        streamed.peak_held_messages
    );
    assert!((1..=runs_bound).contains(&streamed.peak_chunks_in_flight));
    assert!((1..=runs_bound).contains(&streamed.chunk_decoders_made));
}

/// A session the stream cannot reproduce exactly is declined, and the caller reads it whole.
#[test]
fn damaged_other_kinds_and_repaired_copies_are_not_streamed() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("s.mcap");
    record(&path, 20);
    assert!(stream_session(&path, &mut LengthStream::new("rotary_tracer")).is_none());
    let mut bytes = std::fs::read(&path).expect("read");
    let at = bytes.len() / 3;
    bytes[at] ^= 0x55;
    std::fs::write(&path, &bytes).expect("write");
    assert!(stream_session(&path, &mut LengthStream::new("multilateration")).is_none());
    std::fs::write(&path, &bytes[..bytes.len() / 2]).expect("write");
    assert!(stream_session(&path, &mut LengthStream::new("multilateration")).is_none());
}

/// Another recorder's sessions (tests/data/outside, copies of ../shared/sessions) stream to
/// exactly the whole read's extraction.
#[test]
fn outside_sessions_stream_as_read_whole() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/outside");
    for name in ["outside-clean-7", "outside-reversal-8"] {
        let path = dir.join(name).join("session.mcap");
        let session = read_session(&path).expect("session");
        let tracer = session.tracers.keys().next().expect("tracer").clone();
        let noise = NoiseModel::from_header(&session.header, &tracer);
        let options = ExtractOptions::from_header(&session.header);
        let whole = extract_points(&session, Some(&tracer), noise, &options).expect("extract");
        let mut sink = LengthStream::new(&session.header.kind);
        let streamed =
            stream_session(&path, &mut sink).unwrap_or_else(|| panic!("{name} does not stream"));
        let (lengths, streamed_tracer, _) = sink.finish().expect("begun");
        assert_eq!(streamed_tracer, tracer);
        assert_eq!(lengths, Lengths::of_extraction(&whole), "{name}");
        assert_eq!(streamed.session.header, session.header);
    }
}

/// The streamed read reports the bytes merged: from 0, growing, several times for a file of
/// many chunks, ending at the file's size.
#[test]
fn the_streamed_read_reports_its_progress() {
    use crate::session::reader::{stream_session_reporting, ReadProgress};
    use std::sync::{Arc, Mutex};

    let seen = Arc::new(Mutex::new(Vec::<(u64, u64)>::new()));
    let log = seen.clone();
    let progress = ReadProgress::new(move |done, total| log.lock().unwrap().push((done, total)));
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("s.mcap");
    record(&path, 60);
    let len = std::fs::metadata(&path).expect("size").len();
    let mut sink = LengthStream::new("multilateration");
    stream_session_reporting(&path, &mut sink, Some(&progress)).expect("a clean file streams");
    let seen = seen.lock().unwrap().clone();
    assert!(seen.len() > 5, "{seen:?}");
    assert_eq!(seen.first(), Some(&(0, len)));
    assert_eq!(seen.last(), Some(&(len, len)));
    assert!(seen.iter().all(|&(_, total)| total == len));
    assert!(seen.windows(2).all(|w| w[0].0 < w[1].0), "{seen:?}");
}
