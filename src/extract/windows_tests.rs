//! The streamed settled session against the whole read's, and what the stream holds at once.

use std::path::Path;

use super::stream_tests::{largest_chunk, record};
use super::windows::{SettledSession, WindowStream};
use crate::session::messages::{RunEvent, TracerSample};
use crate::session::reader::testutil::{env_sample, header};
use crate::session::reader::{read_session, stream_session};
use crate::session::recorder::{Compression, Recorder, RecorderOptions};

const DT_NS: u64 = 50_000_000;

fn any_kind(_: &str) -> bool {
    true
}

fn whole(path: &Path) -> SettledSession {
    SettledSession::of_session(&read_session(path).expect("session")).expect("settled")
}

/// The streamed settled session and the most tracer samples the sink held at once.
fn streamed(path: &Path) -> (SettledSession, usize) {
    let mut sink = WindowStream::new(any_kind);
    let read = stream_session(path, &mut sink).expect("a clean file streams");
    let peak = sink.peak_samples;
    (sink.finish(read).expect("begun"), peak)
}

/// A recording whose raw windows the whole read takes past their `point_end` or from a later
/// `point_begin`: device time that steps back after a dwell (the samples after `point_end`
/// still lie inside the settled stretch), points measured again later (a resumed run), a
/// later begin of a measured point that never ends, and an environment log. Chunks of
/// `chunk_size` bytes: small ones cut the stream between a window and its last samples.
fn record_revisits(path: &Path, points: usize, chunk_size: u64) {
    let rec = Recorder::create(
        path,
        RecorderOptions {
            chunk_size,
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
    let mut env = 0;
    let mut tracer = |length_m: f64, device_t_s: f64, at: u64| {
        seq += 1;
        let s = TracerSample {
            seq,
            t_s: device_t_s,
            length_m,
            signal: 0.9,
            tracking: true,
            beam_segment: 0,
        };
        h.tracer("tracer0", &s, at);
    };
    let begin = |point: usize| RunEvent::PointBegin {
        station: "s1".into(),
        point,
        pass: 0,
        target: "t0".into(),
        nominal_m: [point as f64 * 0.1, 0.2, 0.3],
        axes: [("x", 0.1), ("y", 0.2), ("z", point as f64)]
            .into_iter()
            .map(|(a, v)| (a.to_owned(), v))
            .collect(),
        approach: [("x".to_owned(), 1)].into_iter().collect(),
    };
    let end = |point: usize| RunEvent::PointEnd {
        station: "s1".into(),
        point,
        pass: 0,
    };
    let station_begin = RunEvent::StationBegin {
        station: "s1".into(),
        station_index: 0,
        hint_m: Some([0.0, 0.5, 0.2]),
    };
    h.event(&station_begin, t_ns);
    // Point p's dwell, then (some of the time) an earlier point again.
    let plan: Vec<(usize, bool)> = (0..points)
        .flat_map(|p| {
            let again = (p % 5 == 4).then(|| (p - 2, p % 10 != 4));
            std::iter::once((p, true)).chain(again)
        })
        .collect();
    for (point, ends) in plan {
        let length_m = 1.0 + 0.01 * point as f64;
        for k in 0..2 {
            t_ns += DT_NS;
            tracer(length_m - 0.001 * (2 - k) as f64, t_ns as f64 * 1e-9, t_ns);
        }
        t_ns += DT_NS;
        h.event(&begin(point), t_ns);
        for k in 0..12u64 {
            let at = t_ns + k * DT_NS;
            let noise = 1e-7 * (((point as u64 + k) % 5) as f64 - 2.0);
            tracer(length_m + noise, at as f64 * 1e-9, at);
        }
        t_ns += 11 * DT_NS;
        if ends {
            h.event(&end(point), t_ns);
        }
        if point % 3 == 1 {
            // The device clock steps back: the next samples' times lie inside the stretch.
            for k in 1..3u64 {
                tracer(length_m, (t_ns - 3 * DT_NS) as f64 * 1e-9, t_ns + k);
            }
        }
        env += 1;
        h.env("air", &env_sample(env), t_ns + 3);
    }
    rec.finish().expect("finish");
}

#[test]
fn streamed_settled_session_equals_the_whole_read() {
    let dir = tempfile::tempdir().expect("tempdir");
    let [a, b, c] = ["a", "b", "c"].map(|n| dir.path().join(format!("{n}.mcap")));
    record(&a, 60);
    record_revisits(&b, 40, 4096);
    record_revisits(&c, 40, 400);
    for path in [&a, &b, &c] {
        let whole = whole(path);
        let (streamed, _) = streamed(path);
        assert_eq!(streamed, whole, "{}", path.display());
        assert!(whole.windows.iter().filter(|w| w.is_some()).count() > 30);
    }
    // The revisits are there: windows from a later begin (none: it comes after the stretch),
    // windows running past their point_end.
    let whole = whole(&b);
    assert!(!whole.env.is_empty());
    let (measured, windows) = (&whole.extraction.measurements, &whole.windows);
    assert!(windows.iter().any(Option::is_none));
    let past_end = measured.iter().zip(windows).filter(|(m, w)| {
        w.as_ref()
            .is_some_and(|w| w.samples.len() > m.samples && m.point % 3 == 1)
    });
    assert!(past_end.count() > 3);
}

/// What the streamed settled session holds at once does not grow with the recording beyond
/// the settled windows' (t, length) pairs: the same plan recorded 10x longer holds no more
/// tracer samples than one window and two chunks' worth.
#[test]
fn settled_stream_holds_a_bound_whatever_the_length() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (short, long) = (dir.path().join("short.mcap"), dir.path().join("long.mcap"));
    record_revisits(&short, 40, 4096);
    record_revisits(&long, 400, 4096);
    let chunk = largest_chunk(&short).max(largest_chunk(&long)) as usize;
    assert!(chunk < 80, "{chunk} messages in a chunk");
    let mut pairs_before = 0;
    for path in [&short, &long] {
        let (settled, held) = streamed(path);
        assert!(held <= 16 + 2 * chunk, "{held} samples held");
        let pairs: usize = settled
            .windows
            .iter()
            .flatten()
            .map(|w| w.samples.len())
            .sum();
        assert!(pairs > 9 * pairs_before);
        pairs_before = pairs;
    }
}

#[test]
fn other_kinds_and_tracer_counts_are_declined() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("s.mcap");
    record(&path, 10);
    let mut refused = WindowStream::new(|kind| kind != "multilateration");
    assert!(stream_session(&path, &mut refused).is_none());
}
