use std::collections::BTreeMap;
use std::io::Cursor;

use mcap::records::{op, MessageHeader};
use proptest::prelude::*;

use super::allocations::allocations_in;
use super::dispatch::{env_id, probe_id, rotary_id, tracer_id};
use super::indexed::{read_indexed_bounded, CHUNKS_IN_FLIGHT_PER_THREAD};
use super::testutil::*;
use super::*;
use crate::session::messages::{self, schema};
use crate::session::recorder::{Compression, Recorder, RecorderOptions};

/// Writes with mcap::Writer directly, the way another tool would: given options, channels
/// declared tracer-first, the header not physically first, hand-written JSON with extra
/// fields and another field order, an unknown topic and one broken sample.
fn foreign_file(opts: mcap::WriteOptions) -> Vec<u8> {
    let mut w = opts.create(Cursor::new(Vec::new())).unwrap();
    let no_meta = BTreeMap::new();
    let ts = w
        .add_schema(
            "geocal.TracerSample",
            "jsonschema",
            schema::TRACER.as_bytes(),
        )
        .unwrap();
    let tracer = w
        .add_channel(ts, "/tracer/laser-b/range", "json", &no_meta)
        .unwrap();
    let other = w.add_channel(0, "/vendor/pose", "json", &no_meta).unwrap();
    let es = w
        .add_schema("geocal.RunEvent", "jsonschema", schema::EVENT.as_bytes())
        .unwrap();
    let event = w.add_channel(es, "/run/event", "json", &no_meta).unwrap();
    let put = |w: &mut mcap::Writer<Cursor<Vec<u8>>>, ch: u16, t: u64, json: &str| {
        let hdr = MessageHeader {
            channel_id: ch,
            sequence: 0,
            log_time: t,
            publish_time: t + 7,
        };
        w.write_to_known_channel(&hdr, json.as_bytes()).unwrap();
    };
    // Samples before the header, and out of log-time order.
    for i in (0..50u64).rev() {
        let json = format!(
            r#"{{"beam_segment":0,"future_field":{{"a":[1,2]}},"length_m":{},"t_s":{},"seq":{i}}}"#,
            0.5 + i as f64 * 1e-6,
            i as f64 * 0.1
        );
        put(&mut w, tracer, 1_000 + i, &json);
    }
    put(&mut w, other, 1_001, r#"{"x":1}"#);
    put(&mut w, tracer, 1_002, r#"{"seq":"not a number"}"#);
    let ss = w
        .add_schema("geocal.Session", "jsonschema", schema::SESSION.as_bytes())
        .unwrap();
    let session = w
        .add_channel(ss, "/geocal/session", "json", &no_meta)
        .unwrap();
    let header = serde_json::to_string(&header()).unwrap();
    // Same header, with an extra field and the format last.
    let mut v: serde_json::Value = serde_json::from_str(&header).unwrap();
    v["vendor_notes"] = serde_json::json!("made elsewhere");
    put(&mut w, session, 500, &v.to_string());
    put(
        &mut w,
        event,
        1_200,
        r#"{"station":"s1","kind":"station_begin","station_index":0,"extra":true}"#,
    );
    put(
        &mut w,
        event,
        1_300,
        r#"{"kind":"a_new_kind","station":"s1"}"#,
    );
    w.finish().unwrap();
    w.into_inner().into_inner()
}

fn check_foreign(bytes: &[u8]) {
    let s = read_session_bytes(bytes).unwrap();
    assert_eq!(s.header, header());
    assert!(s.completeness.is_complete(), "{:?}", s.completeness);
    let t = &s.tracers["laser-b"];
    assert_eq!(t.len(), 50);
    for (i, st) in t.iter().enumerate() {
        assert_eq!(st.log_time_ns, 1_000 + i as u64);
        assert_eq!(st.publish_time_ns, st.log_time_ns + 7);
        assert_eq!(st.msg.seq, i as u64);
        assert_eq!(st.msg.length_m, 0.5 + i as f64 * 1e-6);
        // Defaults from the contract for missing optional fields.
        assert_eq!(st.msg.signal, 1.0);
        assert!(st.msg.tracking);
    }
    assert_eq!(s.skipped, 1);
    assert_eq!(s.ignored, 1);
    assert_eq!(s.events.len(), 2);
    assert_eq!(
        s.events[0].msg,
        RunEvent::StationBegin {
            station: "s1".into(),
            station_index: 0,
            hint_m: None
        }
    );
    assert_eq!(s.events[1].msg, RunEvent::Other);
    assert!(s.env.is_empty());
}

#[test]
fn reads_other_writers() {
    let variants = [
        mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Lz4))
            .chunk_size(Some(200)),
        mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Zstd))
            .chunk_size(Some(1)),
        mcap::WriteOptions::new()
            .compression(None)
            .chunk_size(Some(700)),
        mcap::WriteOptions::new().use_chunks(false),
        mcap::WriteOptions::new()
            .use_chunks(false)
            .emit_summary_records(false)
            .emit_statistics(false)
            .emit_summary_offsets(false),
        mcap::WriteOptions::new()
            .chunk_size(Some(300))
            .emit_chunk_indexes(false)
            .emit_statistics(false),
    ];
    for opts in variants {
        let bytes = foreign_file(opts.clone());
        check_foreign(&bytes);
        // And the same file cut before its summary: linear reading finds the same data.
        let data_end = data_end_offset(&bytes);
        let s = read_session_bytes(&bytes[..data_end]).unwrap();
        assert!(!s.completeness.is_complete());
        assert_eq!(s.tracers["laser-b"].len(), 50, "{opts:?}");
    }
}

/// Offset of the DataEnd record, found by walking the top-level records.
fn data_end_offset(bytes: &[u8]) -> usize {
    let mut pos = 8;
    loop {
        let len = u64::from_le_bytes(bytes[pos + 1..pos + 9].try_into().unwrap()) as usize;
        if bytes[pos] == op::DATA_END {
            return pos;
        }
        pos += 9 + len;
    }
}

#[test]
fn errors_are_clear() {
    let e = read_session_bytes(b"PK\x03\x04 not an mcap at all").unwrap_err();
    assert!(matches!(e, ReadError::NotMcap { .. }), "{e}");
    assert!(e.to_string().contains("not an MCAP file"), "{e}");
    let e = read_session_bytes(&mcap::MAGIC[..3]).unwrap_err();
    assert!(matches!(e, ReadError::NotMcap { .. }), "{e}");

    // A valid MCAP with no header message.
    let mut w = mcap::Writer::new(Cursor::new(Vec::new())).unwrap();
    let ch = w
        .add_channel(0, "/tracer/a/range", "json", &BTreeMap::new())
        .unwrap();
    let hdr = MessageHeader {
        channel_id: ch,
        sequence: 0,
        log_time: 1,
        publish_time: 1,
    };
    w.write_to_known_channel(&hdr, br#"{"seq":0,"t_s":0,"length_m":0}"#)
        .unwrap();
    w.finish().unwrap();
    let e = read_session_bytes(&w.into_inner().into_inner()).unwrap_err();
    assert!(
        e.to_string().contains("has no /geocal/session message"),
        "{e}"
    );

    // Wrong format string, and a header that does not parse.
    for (json, want) in [
        (
            serde_json::to_string(&SessionHeader {
                format: "geocal-session/2".into(),
                ..header()
            })
            .unwrap(),
            "expected \"geocal-session/1\"",
        ),
        (
            r#"{"format":"geocal-session/1"}"#.to_owned(),
            "does not parse",
        ),
    ] {
        let mut w = mcap::Writer::new(Cursor::new(Vec::new())).unwrap();
        let ch = w
            .add_channel(0, "/geocal/session", "json", &BTreeMap::new())
            .unwrap();
        w.write_to_known_channel(
            &MessageHeader {
                channel_id: ch,
                ..hdr
            },
            json.as_bytes(),
        )
        .unwrap();
        w.finish().unwrap();
        let e = read_session_bytes(&w.into_inner().into_inner()).unwrap_err();
        assert!(e.to_string().contains(want), "{e}");
        assert!(e.to_string().contains("in-memory"), "{e}");
    }
}

#[test]
fn missing_file_names_the_path() {
    let e = read_session(Path::new("/nonexistent/dir/s.mcap")).unwrap_err();
    assert!(e.to_string().contains("/nonexistent/dir/s.mcap"), "{e}");
}

/// A session written by our recorder with small chunks, plus where each chunk ends.
struct Recorded {
    bytes: Vec<u8>,
    /// (end offset of the chunk record, last log time in it), in file order.
    chunk_ends: Vec<(usize, u64)>,
    tracers: BTreeMap<String, Vec<TracerSample>>,
    /// log times of every message, all distinct.
    all_log_times: Vec<u64>,
}

fn recorded() -> &'static Recorded {
    static CELL: std::sync::OnceLock<Recorded> = std::sync::OnceLock::new();
    CELL.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.mcap");
        let rec = Recorder::create(
            &path,
            RecorderOptions {
                chunk_size: 2048,
                flush_interval: std::time::Duration::from_secs(3600),
                compression: Compression::Zstd,
                tap: Default::default(),
            },
        )
        .unwrap();
        let h = rec.handle();
        let mut t = 1_000_000u64;
        let mut all_log_times = vec![];
        let mut stamp = || {
            t += 1000;
            all_log_times.push(t);
            t
        };
        h.session(&header(), stamp());
        let mut tracers: BTreeMap<String, Vec<TracerSample>> = BTreeMap::new();
        let evs = events();
        for i in 0..1500u64 {
            let id = if i % 3 == 0 { "tracer1" } else { "tracer0" };
            let v = tracers.entry(id.to_owned()).or_default();
            let s = tracer_sample(v.len() as u64);
            v.push(s);
            h.tracer(id, &s, stamp());
            if i % 100 == 0 {
                h.env("air", &env_sample(i / 100), stamp());
                h.event(&evs[(i / 100) as usize % evs.len()], stamp());
            }
        }
        rec.finish().unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
        let mut chunk_ends: Vec<(usize, u64)> = summary
            .chunk_indexes
            .iter()
            .map(|c| {
                (
                    (c.chunk_start_offset + c.chunk_length) as usize,
                    c.message_end_time,
                )
            })
            .collect();
        chunk_ends.sort();
        Recorded {
            bytes,
            chunk_ends,
            tracers,
            all_log_times,
        }
    })
}

#[test]
fn recorded_file_has_many_chunks_and_reads_complete() {
    let r = recorded();
    assert!(r.chunk_ends.len() > 20, "{}", r.chunk_ends.len());
    let s = read_session_bytes(&r.bytes).unwrap();
    assert!(s.completeness.is_complete());
    for (id, v) in &r.tracers {
        let got: Vec<_> = s.tracers[id].iter().map(|st| st.msg).collect();
        assert_eq!(&got, v);
    }
}

fn check_cut(cut: usize) {
    let r = recorded();
    let bytes = &r.bytes[..cut];
    let result = read_session_bytes(bytes);
    // The header is alone in the first chunk (the recorder flushes right after it).
    let header_end = r.chunk_ends[0].0;
    if cut < header_end {
        assert!(result.is_err(), "cut {cut}: read a header that was cut");
        return;
    }
    let s = result.unwrap_or_else(|e| panic!("cut {cut}: {e}"));
    assert_eq!(s.header, header());
    if cut == r.bytes.len() {
        assert!(s.completeness.is_complete());
    } else {
        match &s.completeness {
            Completeness::Truncated {
                bytes_read,
                file_bytes,
                ..
            } => {
                assert_eq!(*file_bytes, cut as u64);
                assert!(*bytes_read <= cut as u64);
            }
            Completeness::Complete => panic!("cut {cut}: reported complete"),
        }
    }
    // Every sample read is the original one at that position (a prefix per tracer).
    let mut n = 1;
    for (id, got) in &s.tracers {
        let orig = &r.tracers[id];
        assert!(got.len() <= orig.len());
        for (i, st) in got.iter().enumerate() {
            assert_eq!(st.msg, orig[i], "cut {cut}, tracer {id}, index {i}");
        }
        n += got.len();
    }
    n += s.env.values().map(Vec::len).sum::<usize>() + s.events.len();
    // Every message of every chunk that ended before the cut is there, and nothing of a
    // chunk that did not.
    let last_complete = r
        .chunk_ends
        .iter()
        .take_while(|(end, _)| *end <= cut)
        .last()
        .map(|c| c.1)
        .unwrap_or(0);
    let expected = r
        .all_log_times
        .iter()
        .filter(|&&t| t <= last_complete)
        .count();
    assert_eq!(n, expected, "cut {cut}");
}

#[test]
fn truncation_at_every_chunk_boundary() {
    let r = recorded();
    for &(end, _) in &r.chunk_ends {
        for cut in [end - 1, end, end + 1] {
            check_cut(cut.min(r.bytes.len()));
        }
    }
    check_cut(r.bytes.len());
    check_cut(r.bytes.len() - 1);
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]
    #[test]
    fn truncated_anywhere_reads_a_prefix(frac in 0.0f64..=1.0) {
        let len = recorded().bytes.len();
        check_cut(((len as f64) * frac) as usize);
    }

    #[test]
    fn garbage_never_panics(cut in 0usize..20_000, flip in 0usize..20_000, byte: u8) {
        let r = recorded();
        let mut bytes = r.bytes[..cut.min(r.bytes.len())].to_vec();
        if let Some(b) = bytes.get_mut(flip) {
            *b ^= byte;
        }
        let _ = read_session_bytes(&bytes);
    }
}

#[test]
fn complete_files_are_read_through_the_index() {
    let r = recorded();
    let summary = mcap::Summary::read(&r.bytes).unwrap().unwrap();
    let dec = read_indexed(&r.bytes, "x", &summary).unwrap();
    assert!(dec.is_some(), "indexed path fell back to linear");
    let linear = read_linear(&r.bytes, "x").unwrap();
    assert!(linear.truncation.is_none());
    let (a, b) = (
        dec.unwrap().into_session("x", 0).unwrap(),
        linear.into_session("x", 0).unwrap(),
    );
    assert_eq!(a, b);
    // Unchunked messages are not in any chunk index: the reader must notice and go linear.
    let bytes = foreign_file(mcap::WriteOptions::new().use_chunks(false));
    let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
    assert!(read_indexed(&bytes, "x", &summary).unwrap().is_none());
}

/// The threaded indexed read gives exactly what one thread and the linear read give.
#[test]
fn threads_read_the_same_session() {
    let foreign = foreign_file(
        mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Zstd))
            .chunk_size(Some(1)),
    );
    for bytes in [&recorded().bytes, &foreign] {
        let summary = mcap::Summary::read(bytes).unwrap().unwrap();
        assert!(summary.chunk_indexes.len() > 8);
        let serial = read_indexed_with(bytes, "x", &summary, 1, false)
            .unwrap()
            .expect("indexed")
            .into_session("x", 0)
            .unwrap();
        let linear = read_linear(bytes, "x")
            .unwrap()
            .into_session("x", 0)
            .unwrap();
        assert_eq!(serial, linear);
        for threads in 2..=7 {
            let dec = read_indexed_with(bytes, "x", &summary, threads, false)
                .unwrap()
                .expect("indexed");
            assert_eq!(
                dec.into_session("x", 0).unwrap(),
                serial,
                "{threads} threads"
            );
        }
    }
    check_foreign(&foreign);
}

/// A second header in a later run of chunks is ignored, and a bad one there still fails
/// only when it is the first header.
#[test]
fn threads_keep_the_first_header() {
    let write = |headers: &[&[u8]]| {
        let mut w = mcap::WriteOptions::new()
            .chunk_size(Some(1))
            .create(Cursor::new(Vec::new()))
            .unwrap();
        let no_meta = BTreeMap::new();
        let hs = w
            .add_schema("geocal.Session", "jsonschema", schema::SESSION.as_bytes())
            .unwrap();
        let hc = w.add_channel(hs, TOPIC_SESSION, "json", &no_meta).unwrap();
        let ts = w
            .add_schema(
                "geocal.TracerSample",
                "jsonschema",
                schema::TRACER.as_bytes(),
            )
            .unwrap();
        let tc = w
            .add_channel(ts, "/tracer/a/range", "json", &no_meta)
            .unwrap();
        let mut t = 0;
        let mut put = |w: &mut mcap::Writer<_>, ch: u16, data: &[u8]| {
            t += 1;
            let hdr = MessageHeader {
                channel_id: ch,
                sequence: 0,
                log_time: t,
                publish_time: t,
            };
            w.write_to_known_channel(&hdr, data).unwrap();
        };
        // Samples before every header, so that with threads the first header lies in a
        // worker's run of chunks.
        for h in headers {
            for i in 0..20 {
                let json = serde_json::to_vec(&tracer_sample(i)).unwrap();
                put(&mut w, tc, &json);
            }
            put(&mut w, hc, h);
        }
        w.finish().unwrap();
        w.into_inner().into_inner()
    };
    let good = serde_json::to_vec(&header()).unwrap();
    let bad = b"{\"format\": \"geocal-session/1\"}".to_vec();
    let read = |bytes: &[u8], threads| {
        let summary = mcap::Summary::read(bytes).unwrap().unwrap();
        read_indexed_with(bytes, "x", &summary, threads, false)
            .map(|d| d.expect("indexed").into_session("x", 0).unwrap())
    };
    let bytes = write(&[&good, &bad, &good]);
    let serial = read(&bytes, 1).unwrap();
    assert_eq!(serial.header, header());
    assert_eq!(serial.ignored, 2);
    for threads in 2..=5 {
        assert_eq!(read(&bytes, threads).unwrap(), serial);
    }
    let bytes = write(&[&bad, &good]);
    for threads in 1..=5 {
        assert!(matches!(
            read(&bytes, threads),
            Err(ReadError::BadHeader { .. })
        ));
    }
}

/// A complete file is read straight from the disk, chunk by chunk, to exactly the session the
/// whole-file read gives; a damaged or cut one goes the whole-file way, with the same report.
#[test]
fn file_read_equals_the_whole_file_read() {
    let r = recorded();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("s.mcap");
    std::fs::write(&path, &r.bytes).unwrap();
    let file = std::fs::File::open(&path).unwrap();
    let len = r.bytes.len() as u64;
    let summary = trusted_summary_of_file(&file, len, "x");
    assert!(summary.is_some());
    assert_eq!(summary, trusted_summary(&r.bytes, "x"));
    assert!(read_clean_file(&file, len, "x").is_some());
    assert_eq!(
        read_session(&path).unwrap(),
        read_session_bytes(&r.bytes).unwrap()
    );
    let mut damaged = r.bytes.clone();
    damaged[r.chunk_ends[5].0 - 100] ^= 0x55;
    let cut = &r.bytes[..r.chunk_ends[7].0 + 3];
    for bytes in [&damaged[..], cut] {
        std::fs::write(&path, bytes).unwrap();
        let file = std::fs::File::open(&path).unwrap();
        assert!(read_clean_file(&file, bytes.len() as u64, "x").is_none());
        let from_file = read_session(&path).unwrap();
        assert!(!from_file.damaged.is_empty() || !from_file.completeness.is_complete());
        let mut from_memory = read_session_bytes(bytes).unwrap();
        // The whole-file read names the file it was given in its reasons.
        let name = path.display().to_string();
        for d in &mut from_memory.damaged {
            d.reason = d.reason.replace("<in-memory session>", &name);
        }
        if let Completeness::Truncated { reason, .. } = &mut from_memory.completeness {
            *reason = reason.replace("<in-memory session>", &name);
        }
        assert_eq!(from_file, from_memory);
    }
}

/// A parallel read never holds more than its bound of decoded, not yet merged chunks, however
/// many threads decode, and reads exactly what one thread reads.
#[test]
fn parallel_read_holds_a_bounded_number_of_chunks() {
    let r = recorded();
    let summary = mcap::Summary::read(&r.bytes).unwrap().unwrap();
    assert!(summary.chunk_indexes.len() > 20);
    let serial = read_indexed_with(&r.bytes, "x", &summary, 1, false)
        .unwrap()
        .expect("indexed")
        .into_session("x", 0)
        .unwrap();
    for (threads, bound) in [(2, 1), (2, 2), (3, 2), (4, 3)] {
        let dec = read_indexed_bounded(&r.bytes, "x", &summary, threads, false, Some(bound))
            .unwrap()
            .expect("indexed");
        let peak = dec.peak_chunks_in_flight;
        assert!(
            (1..=bound).contains(&peak),
            "{threads} threads, bound {bound}: {peak} chunks alive at once"
        );
        // Each merged chunk's decoder and buffers are reused: no more are made than can be
        // alive at once, however many chunks the file has.
        let made = dec.chunk_decoders_made;
        assert!(
            (1..=bound).contains(&made),
            "{threads} threads, bound {bound}: {made} chunk decoders for {} chunks",
            summary.chunk_indexes.len()
        );
        assert_eq!(dec.into_session("x", 0).unwrap(), serial);
    }
    let dec = read_indexed_with(&r.bytes, "x", &summary, 2, false)
        .unwrap()
        .expect("indexed");
    assert!(dec.peak_chunks_in_flight <= 2 * CHUNKS_IN_FLIGHT_PER_THREAD);
}

/// `cargo test --release --lib session::reader::tests::large -- --ignored --nocapture`
#[test]
#[ignore = "performance check, run in release"]
fn large_session_reads_fast() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("big.mcap");
    let t0 = std::time::Instant::now();
    let rec = Recorder::create(&path, RecorderOptions::default()).unwrap();
    let h = rec.handle();
    h.session(&header(), 0);
    let n = 1_700_000u64;
    for i in 0..n {
        h.tracer(
            if i % 2 == 0 { "tracer0" } else { "tracer1" },
            &tracer_sample(i),
            i + 1,
        );
    }
    let stats = rec.finish().unwrap();
    let write = t0.elapsed();
    let t1 = std::time::Instant::now();
    let s = read_session(&path).unwrap();
    let read = t1.elapsed();
    assert_eq!(s.tracers.values().map(Vec::len).sum::<usize>(), n as usize);
    let bytes = std::fs::read(&path).unwrap();
    let t2 = std::time::Instant::now();
    let lin = read_linear(&bytes, "x").unwrap();
    let linear = t2.elapsed();
    assert_eq!(lin.messages, n + 1);
    println!(
        "{n} samples, {} bytes: write {write:?}, read {read:?}, linear {linear:?}",
        stats.bytes
    );
}

#[test]
fn topic_ids() {
    assert_eq!(tracer_id("/tracer/t0/range"), Some("t0"));
    assert_eq!(tracer_id("/tracer//range"), None);
    assert_eq!(tracer_id("/tracer/a/b/range"), None);
    assert_eq!(env_id("/env/air"), Some("air"));
    assert_eq!(env_id("/env/"), None);
    assert_eq!(rotary_id("/rotary/c/state"), Some("c"));
    assert_eq!(rotary_id("/rotary//state"), None);
    assert_eq!(rotary_id("/rotary/c/x/state"), None);
    assert_eq!(probe_id("/probe/arm0/reading"), Some("arm0"));
    assert_eq!(probe_id("/probe//reading"), None);
    assert_eq!(messages::tracer_topic("x"), "/tracer/x/range");
}

/// A file of `points` dwell points, each a `point_begin`, four tracer samples and a
/// `point_end`, in geocal's compact JSON or (`spaced`) as another writer might lay it out:
/// spaces after the separators and the fields in another order.
fn dwell_file(points: usize, spaced: bool) -> Vec<u8> {
    let mut w = mcap::WriteOptions::new()
        .compression(None)
        .create(Cursor::new(Vec::new()))
        .unwrap();
    let no_meta = BTreeMap::new();
    let channel = |w: &mut mcap::Writer<Cursor<Vec<u8>>>, name, schema: &str, topic| {
        let id = w.add_schema(name, "jsonschema", schema.as_bytes()).unwrap();
        w.add_channel(id, topic, "json", &no_meta).unwrap()
    };
    let session = channel(&mut w, "geocal.Session", schema::SESSION, "/geocal/session");
    let tracer = channel(
        &mut w,
        "geocal.TracerSample",
        schema::TRACER,
        "/tracer/t0/range",
    );
    let event = channel(&mut w, "geocal.RunEvent", schema::EVENT, "/run/event");
    let mut t = 0;
    let mut put = |w: &mut mcap::Writer<Cursor<Vec<u8>>>, channel_id, json: &str| {
        t += 1000;
        let header = MessageHeader {
            channel_id,
            sequence: 0,
            log_time: t,
            publish_time: t,
        };
        w.write_to_known_channel(&header, json.as_bytes()).unwrap();
    };
    put(&mut w, session, &serde_json::to_string(&header()).unwrap());
    for point in 0..points {
        let x = point as f64 * 1e-3;
        let (begin, end) = if spaced {
            (
                format!(
                    r#"{{"point": {point}, "kind": "point_begin", "station": "s1", "pass": 0, "target": "t0", "nominal_m": [{x}, 0.25, -0.5], "axes": {{"z": -0.5, "x": {x}, "y": 0.25}}, "approach": {{"x": 1, "y": 0, "z": -1}}}}"#
                ),
                format!(r#"{{"station": "s1", "kind": "point_end", "point": {point}, "pass": 0}}"#),
            )
        } else {
            let begin = RunEvent::PointBegin {
                station: "s1".into(),
                point,
                pass: 0,
                target: "t0".into(),
                nominal_m: [x, 0.25, -0.5],
                axes: messages::AxisMap::from([("x", x), ("y", 0.25), ("z", -0.5)]),
                approach: messages::AxisMap::from([("x", 1), ("y", 0), ("z", -1)]),
            };
            let end = RunEvent::PointEnd {
                station: "s1".into(),
                point,
                pass: 0,
            };
            (
                serde_json::to_string(&begin).unwrap(),
                serde_json::to_string(&end).unwrap(),
            )
        };
        put(&mut w, event, &begin);
        for k in 0..4 {
            let sample = tracer_sample((4 * point + k) as u64);
            put(&mut w, tracer, &serde_json::to_string(&sample).unwrap());
        }
        put(&mut w, event, &end);
    }
    w.finish().unwrap();
    w.into_inner().into_inner()
}

/// Decoding run events and tracer samples allocates nothing per message, in geocal's compact
/// layout (the fast path) and in another writer's (serde): a read of eight times the points
/// allocates only what its growing containers take (a few doublings), not one per message.
#[test]
fn decoding_allocates_nothing_per_message() {
    for spaced in [false, true] {
        let allocations = |points| {
            let bytes = dwell_file(points, spaced);
            let (decoder, count) = allocations_in(|| read_linear(&bytes, "x").unwrap());
            let session = decoder.into_session("x", 0).unwrap();
            assert_eq!(session.events.len(), 2 * points);
            assert_eq!(session.tracers["t0"].len(), 4 * points);
            assert!(session.completeness.is_complete());
            count
        };
        let (few, many) = (allocations(500), allocations(4000));
        println!("spaced {spaced}: {few} allocations for 500 points, {many} for 4000");
        assert!(
            many.saturating_sub(few) < 64,
            "spaced {spaced}: 21 000 more messages cost {} more allocations",
            many.saturating_sub(few)
        );
    }
}
