//! A session written by another recorder that follows the contract (different compression,
//! chunking, field order, extra fields, channel order, no summary, a lower sample rate, no
//! declared noise model) must solve just like geocal's own recording.

use crate::common;

use std::collections::BTreeMap;
use std::io::Cursor;
use std::path::{Path, PathBuf};

use geocal::config::Config;
use geocal::kinds::solve_file;
use geocal::kinds::tracer_plan::run::run;
use geocal::method::Results;
use geocal::run::RunOptions;
use geocal::session::messages::{schema, tracer_topic};
use geocal::session::reader::{read_session, Session};
use serde_json::Value;

/// The demo shrunk to 4 stations x 3x3x2 points, two passes.
fn small_run(dir: &Path) -> (PathBuf, Results) {
    let text = common::small_demo();
    let config = Config::parse(&text, Path::new("small.toml")).expect("config");
    let out = run(
        &config,
        &RunOptions {
            out_dir: dir.to_path_buf(),
            truth: None,
            progress: false,
            settings: Default::default(),
            control: Default::default(),
        },
    )
    .expect("run");
    (out.session_path, out.results)
}

/// JSON with the object's keys in reverse order and a field no reader knows.
fn foreign_json(value: &Value) -> Vec<u8> {
    let Value::Object(map) = value else {
        return serde_json::to_vec(value).expect("json");
    };
    let mut parts = vec![String::from(
        "\"vendor_extension\":{\"firmware\":\"4.2\",\"n\":[1,2]}",
    )];
    for (k, v) in map.iter().rev() {
        parts.push(format!("{}:{}", serde_json::to_string(k).expect("key"), v));
    }
    format!("{{{}}}", parts.join(",")).into_bytes()
}

struct Options {
    keep_every: usize,
    declare_noise: bool,
}

/// Re-record a session the way another tool might.
fn rewrite(session: &Session, options: &Options) -> Vec<u8> {
    let mut writer = mcap::WriteOptions::new()
        .compression(Some(mcap::Compression::Lz4))
        .chunk_size(Some(4096))
        .emit_summary_records(false)
        .create(Cursor::new(Vec::new()))
        .expect("writer");
    let no_meta = BTreeMap::new();
    // Channels declared in another order than geocal's recorder uses, plus one nobody knows.
    let event_schema = writer
        .add_schema("geocal.RunEvent", "jsonschema", schema::EVENT.as_bytes())
        .expect("schema");
    let event_ch = writer
        .add_channel(event_schema, "/run/event", "json", &no_meta)
        .expect("channel");
    let other = writer
        .add_channel(0, "/vendor/diagnostics", "json", &no_meta)
        .expect("channel");
    let tracer_schema = writer
        .add_schema(
            "geocal.TracerSample",
            "jsonschema",
            schema::TRACER.as_bytes(),
        )
        .expect("schema");
    let session_schema = writer
        .add_schema("geocal.Session", "jsonschema", schema::SESSION.as_bytes())
        .expect("schema");
    let session_ch = writer
        .add_channel(session_schema, "/geocal/session", "json", &no_meta)
        .expect("channel");

    let mut messages: Vec<(u64, u16, Vec<u8>)> = Vec::new();
    let mut header = serde_json::to_value(&session.header).expect("header");
    if !options.declare_noise {
        for device in header["devices"].as_array_mut().expect("devices") {
            let obj = device.as_object_mut().expect("device");
            obj.remove("noise_m");
            obj.remove("noise_ppm");
        }
    }
    let first_time = session.events.first().map_or(0, |e| e.log_time_ns);
    messages.push((first_time, other, br#"{"cpu_load":0.3}"#.to_vec()));
    messages.push((first_time, session_ch, foreign_json(&header)));
    for event in &session.events {
        let value = serde_json::to_value(&event.msg).expect("event");
        messages.push((event.log_time_ns, event_ch, foreign_json(&value)));
    }
    for (id, samples) in &session.tracers {
        let ch = writer
            .add_channel(tracer_schema, &tracer_topic(id), "json", &no_meta)
            .expect("channel");
        for (k, s) in samples.iter().enumerate() {
            if k % options.keep_every == 0 {
                let value = serde_json::to_value(s.msg).expect("sample");
                messages.push((s.log_time_ns, ch, foreign_json(&value)));
            }
        }
    }
    // A stable sort keeps the original order among equal times (events before samples).
    messages.sort_by_key(|m| m.0);
    for (seq, (time, channel_id, data)) in messages.iter().enumerate() {
        writer
            .write_to_known_channel(
                &mcap::records::MessageHeader {
                    channel_id: *channel_id,
                    sequence: seq as u32,
                    log_time: *time,
                    publish_time: *time,
                },
                data,
            )
            .expect("write");
    }
    writer.finish().expect("finish");
    writer.into_inner().into_inner()
}

#[test]
fn a_foreign_recording_of_the_same_data_solves_identically() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (session_path, results) = small_run(dir.path());
    let session = read_session(&session_path).expect("read");
    let foreign = dir.path().join("foreign.mcap");
    std::fs::write(
        &foreign,
        rewrite(
            &session,
            &Options {
                keep_every: 1,
                declare_noise: true,
            },
        ),
    )
    .expect("write");
    let again = solve_file(&foreign, &Default::default()).expect("solve foreign session");
    assert_eq!(again.to_json_pretty(), results.to_json_pretty());
}

#[test]
fn a_slower_recorder_without_a_noise_model_still_solves() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (session_path, results) = small_run(dir.path());
    let reference = results.multilateration().expect("tracer results");
    let session = read_session(&session_path).expect("read");
    let foreign = dir.path().join("slow.mcap");
    // Every third sample: an 8.3 Hz recorder. No noise model: sigmas come from the scatter.
    std::fs::write(
        &foreign,
        rewrite(
            &session,
            &Options {
                keep_every: 3,
                declare_noise: false,
            },
        ),
    )
    .expect("write");
    let slow = solve_file(&foreign, &Default::default()).expect("solve slow session");
    let slow = slow.multilateration().expect("tracer results");
    assert_eq!(
        slow.extraction.windows_dropped, 0,
        "{:?}",
        slow.extraction.dropped_reasons
    );
    assert_eq!(slow.points.len(), reference.points.len());
    assert!(
        slow.noise_model.contains("none declared"),
        "{}",
        slow.noise_model
    );
    // Same points within the combined uncertainty: both estimate the same truth.
    let mut normalised = Vec::new();
    for (a, b) in slow.points.iter().zip(&reference.points) {
        assert_eq!(a.point, b.point);
        for k in 0..3 {
            let sigma = (a.sigma_m[k].powi(2) + b.sigma_m[k].powi(2)).sqrt();
            normalised.push((a.actual_m[k] - b.actual_m[k]) / sigma);
        }
    }
    let worst = normalised.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    assert!(worst < 5.0, "a point moved by {worst} combined sigmas");
}
