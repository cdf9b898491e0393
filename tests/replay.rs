//! `geocal replay`: the real sequencer and stillstand detection re-run against recorded
//! sessions through the replay drivers. A replay of a complete recording must find the same
//! dwell windows (the same samples in each) and so give identical results: the replay sees
//! exactly the recorded samples, so no noise enters and the bound is zero, not a tolerance.

mod common;

use std::path::Path;

use common::{hil_config, small_demo, HIL_FAULTS};
use geocal::config::Config;
use geocal::kinds::tracer_plan::run::run;
use geocal::replay::{replay, Outcome, ReplayOptions, ReplayOutput};
use geocal::run::{RunOptions, RunOutput};
use geocal::session::reader::read_session;

fn record(config_text: &str, dir: &Path) -> RunOutput {
    let config = Config::parse(config_text, Path::new("replay-test.toml")).expect("config");
    run(
        &config,
        &RunOptions {
            out_dir: dir.to_path_buf(),
            truth: None,
            progress: false,
            settings: Default::default(),
            control: Default::default(),
        },
    )
    .expect("recorded run")
}

fn replay_into(session: &Path, out: &Path) -> ReplayOutput {
    replay(
        session,
        &ReplayOptions {
            out_dir: out.to_path_buf(),
            realtime: false,
            settings: Default::default(),
            progress: false,
        },
    )
    .expect("replay")
}

/// Same windows with the same samples, every sample replayed, the same faults and re-homings,
/// and results equal to the last bit.
fn assert_identical_replay(recorded: &RunOutput, out: &ReplayOutput) {
    let c = &out.comparison;
    print!("{}", geocal::replay::text(c));
    assert_eq!(c.outcome, Outcome::Completed, "{}", c.message);
    assert_eq!(c.samples_replayed, c.samples_recorded);
    assert_eq!(c.samples_recorded as u64, recorded.summary.samples);
    assert!(c.windows.recorded > 0);
    assert_eq!(
        c.windows.recorded,
        recorded.summary.points_measured as usize
    );
    assert_eq!(c.windows.replayed, c.windows.recorded);
    assert_eq!(
        c.windows.identical, c.windows.recorded,
        "{:?}",
        c.windows.first_difference
    );
    assert_eq!(c.events_replayed, c.events_recorded);
    let results = c.results.as_ref().expect("both sessions solve");
    assert!(results.identical, "{results:?}");
    assert_eq!(results.values_differing, 0);
    // The replay's results.json is the recording's, bar the session id.
    let replayed = std::fs::read_to_string(out.results_path.as_ref().expect("results.json"))
        .expect("replayed results");
    let original = std::fs::read_to_string(&recorded.results_path).expect("recorded results");
    let strip = |s: &str| {
        let mut v: serde_json::Value = serde_json::from_str(s).expect("json");
        v.as_object_mut().expect("object").remove("session_id");
        v
    };
    assert_eq!(strip(&replayed), strip(&original));
}

#[test]
fn simulated_session_replays_identically() {
    let dir = tempfile::tempdir().expect("tempdir");
    let recorded = record(&small_demo(), &dir.path().join("run"));
    let out = replay_into(&recorded.session_path, &dir.path().join("replay"));
    assert_identical_replay(&recorded, &out);
    // The replayed session is a session like any other, marked as a replay.
    let session = read_session(&out.session_path).expect("replayed session");
    assert!(session.header.session_id.ends_with("-replay"));
    assert!(session.header.devices.iter().all(|d| d.driver == "replay"));
    assert!(out.comparison_path.exists());
}

/// A clean recording replays streamed: the replay devices hold a bounded number of recorded
/// tracer samples at once, and the same plan recorded 10x denser does not raise it (held
/// whole, the dense recording would exceed the bound many times over).
#[test]
fn a_denser_recording_replays_holding_the_same_bounded_samples() {
    use geocal::replay::stream::SAMPLES_HELD_BOUND;
    let dir = tempfile::tempdir().expect("tempdir");
    let mut replays = Vec::new();
    for (name, rate) in [("sparse", "25.0"), ("dense", "250.0")] {
        let config =
            small_demo().replace("sample_rate_hz = 25.0", &format!("sample_rate_hz = {rate}"));
        assert!(config.contains(&format!("sample_rate_hz = {rate}")));
        let recorded = record(&config, &dir.path().join(name));
        let out = replay_into(
            &recorded.session_path,
            &dir.path().join(format!("{name}-replay")),
        );
        assert_identical_replay(&recorded, &out);
        replays.push((out.comparison.samples_recorded, out.peak_samples_held));
    }
    let ((sparse, sparse_held), (dense, dense_held)) = (replays[0], replays[1]);
    println!("recorded samples {sparse} and {dense}; held at most {sparse_held} and {dense_held}");
    assert!(dense >= 9 * sparse, "{dense} samples vs {sparse}");
    assert!(dense > 10 * SAMPLES_HELD_BOUND, "{dense} samples");
    assert!(
        sparse_held > 0 && sparse_held <= SAMPLES_HELD_BOUND,
        "{sparse_held}"
    );
    assert!(
        dense_held > 0 && dense_held <= SAMPLES_HELD_BOUND,
        "{dense_held}"
    );
}

/// A recording made before the sequencer wrote its arrivals (`/machine/<id>/state`): the
/// replay infers where each move ended from the events and replays it identically still.
#[test]
fn a_recording_without_arrivals_replays_identically() {
    use geocal::session::reader::read_session_raw;
    use geocal::session::{Recorder, RecorderOptions};
    let dir = tempfile::tempdir().expect("tempdir");
    let recorded = record(&small_demo(), &dir.path().join("run"));
    let (_, messages) = read_session_raw(&recorded.session_path).expect("raw read");
    let older = dir.path().join("older").join("session.mcap");
    std::fs::create_dir_all(older.parent().expect("dir")).expect("dir");
    let recorder = Recorder::create(&older, RecorderOptions::default()).expect("recorder");
    let handle = recorder.handle();
    let mut dropped = 0;
    for m in messages {
        if m.channel.topic.starts_with("/machine/") {
            dropped += 1;
        } else {
            handle.raw(m);
        }
    }
    recorder.finish().expect("finish");
    assert!(dropped > 0, "the recording holds its arrivals");
    let out = replay_into(&older, &dir.path().join("replay"));
    assert_identical_replay(&recorded, &out);
    assert!(
        out.comparison.trail.is_empty(),
        "a completed replay shows no trail"
    );
}

/// 4 table stations 90° apart and one off the table, 10 Hz.
fn small_rotary_tracer() -> String {
    include_str!("../config/rotary-tracer.toml")
        .replace("count = 6 }", "count = 3 }")
        .replace(
            "step_rad = 0.5235987755982988",
            "step_rad = 1.5707963267948966",
        )
        .replace("count = 12", "count = 4")
        .replace("sample_rate_hz = 25.0", "sample_rate_hz = 10.0")
        .replace("dwell_s = 2.0", "dwell_s = 1.0")
        .replace("window_s = 0.6", "window_s = 0.4")
}

/// The tracer on a rotary table: the table reports in position where the recording shows it,
/// at the recorded encoder angle.
#[test]
fn rotary_tracer_session_replays_identically() {
    assert_rotary_tracer_replays(&small_rotary_tracer());
}

/// ISO 230-2's cycle for the table: each run's first station is reached through its
/// overshoot angle, two moves under one `rotation` event, on a table with reversal and
/// scatter.
#[test]
fn rotary_tracer_cycle_with_overshoots_replays_identically() {
    let config = small_rotary_tracer()
        .replace("count = 4", "count = 4\nruns = 2")
        .replace(
            "axis_tilt_rad = 1e-4 }",
            "axis_tilt_rad = 1e-4, reversal_rad = 2e-5, repeatability_rad = 5e-6 }",
        );
    assert!(config.contains("runs = 2") && config.contains("reversal_rad"));
    assert_rotary_tracer_replays(&config);
}

fn assert_rotary_tracer_replays(config: &str) {
    let dir = tempfile::tempdir().expect("tempdir");
    let recorded = record(config, &dir.path().join("run"));
    let out = replay_into(&recorded.session_path, &dir.path().join("replay"));
    assert_identical_replay(&recorded, &out);
    let rotary = |path: &Path| {
        let session = read_session(path).expect("session");
        session.rotary.into_values().next().expect("rotary stream")
    };
    let (a, b) = (rotary(&recorded.session_path), rotary(&out.session_path));
    assert!(a.iter().any(|r| r.msg.in_position));
    assert_eq!(
        a.iter().map(|r| r.msg).collect::<Vec<_>>(),
        b.iter().map(|r| r.msg).collect::<Vec<_>>()
    );
}

/// Dropped and corrupted frames, a silent tracer (timeouts), a lost GRBL `ok` and a beam
/// break with its re-homing and repeated windows: all replay as recorded.
#[test]
fn hil_session_with_faults_replays_identically() {
    let dir = tempfile::tempdir().expect("tempdir");
    let recorded = record(&hil_config(HIL_FAULTS), &dir.path().join("run"));
    let out = replay_into(&recorded.session_path, &dir.path().join("replay"));
    let events = &out.comparison.events_recorded;
    for kind in [
        "fault:frames_lost",
        "fault:timeout",
        "fault:beam_break",
        "rehome",
    ] {
        assert!(events.contains_key(kind), "no {kind} in {events:?}");
    }
    assert_identical_replay(&recorded, &out);
}

/// A recording cut in the middle (a crash): the replay runs up to its last sample, says so,
/// and every window the cut file still holds is found again.
#[test]
fn truncated_session_replays_up_to_its_end() {
    let dir = tempfile::tempdir().expect("tempdir");
    let recorded = record(&small_demo(), &dir.path().join("run"));
    let bytes = std::fs::read(&recorded.session_path).expect("session bytes");
    let cut = dir.path().join("cut.mcap");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).expect("write cut file");
    let out = replay_into(&cut, &dir.path().join("replay"));
    let c = &out.comparison;
    print!("{}", geocal::replay::text(c));
    assert_eq!(c.outcome, Outcome::RecordingEnded, "{}", c.message);
    assert!(
        c.message.contains("the recording ends after"),
        "{}",
        c.message
    );
    assert!(c.message.contains("cut short"), "{}", c.message);
    assert!(c.truncation.is_some());
    assert!(c.samples_recorded > 0 && (c.samples_recorded as u64) < recorded.summary.samples);
    assert_eq!(c.samples_replayed, c.samples_recorded);
    assert!(
        c.windows.recorded > 0 && c.windows.recorded < recorded.summary.points_measured as usize
    );
    assert_eq!(c.windows.replayed, c.windows.recorded);
    assert_eq!(c.windows.identical, c.windows.recorded);
}

/// The CLI: text by default, geocal-replay/1 JSON with --json; a file that is not a session
/// gives an error naming it.
#[test]
fn replay_command_prints_the_comparison() {
    let dir = tempfile::tempdir().expect("tempdir");
    let recorded = record(&small_demo(), &dir.path().join("run"));
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_geocal"))
        .arg("replay")
        .arg(&recorded.session_path)
        .arg("--out")
        .arg(dir.path().join("replay"))
        .arg("--json")
        .output()
        .expect("geocal replay");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let c: serde_json::Value = serde_json::from_slice(&out.stdout).expect("json");
    assert_eq!(c["format"], "geocal-replay/1");
    assert_eq!(c["outcome"], "completed");
    assert_eq!(c["windows"]["identical"], c["windows"]["recorded"]);
    assert_eq!(c["results"]["identical"], true);

    let bogus = dir.path().join("bogus.mcap");
    std::fs::write(&bogus, b"not a session").expect("write");
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_geocal"))
        .arg("replay")
        .arg(&bogus)
        .output()
        .expect("geocal replay");
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("bogus.mcap") && err.contains("MCAP"), "{err}");
}

/// Run a configuration of a kind with its own layout (rotary_sphere, probe_install, hexapod).
fn record_kind(config_text: &str, dir: &Path) -> RunOutput {
    std::fs::create_dir_all(dir).expect("dir");
    let config = dir.join("kind.toml");
    std::fs::write(&config, config_text).expect("write config");
    if config_text.contains("kind = \"rotary_sphere\"") {
        let cfg = geocal::kinds::rotary_sphere::config::RotarySphereConfig::load(&config)
            .expect("config");
        let out = geocal::kinds::rotary_sphere::run::run(
            &cfg,
            &RunOptions {
                out_dir: dir.to_path_buf(),
                truth: None,
                progress: false,
                settings: Default::default(),
                control: Default::default(),
            },
        )
        .expect("recorded run");
        return RunOutput {
            session_path: out.session_path,
            results_path: out.results_path,
            summary: Default::default(),
            results: out.results,
        };
    }
    geocal::kinds::run_file(
        &config,
        &RunOptions {
            out_dir: dir.to_path_buf(),
            truth: None,
            progress: false,
            settings: Default::default(),
            control: Default::default(),
        },
    )
    .expect("recorded run")
    .expect("a kind run by geocal::kinds")
}

/// The replay of a kind's recording: every reading and window again, the same events, every
/// event and kind topic message at the same log time with the same content, and results.json
/// identical to the last bit (bar the session id).
fn assert_identical_kind_replay(recorded: &RunOutput, out: &ReplayOutput, windows: usize) {
    let c = &out.comparison;
    print!("{}", geocal::replay::text(c));
    assert_eq!(c.outcome, Outcome::Completed, "{}", c.message);
    assert!(c.samples_recorded > 0);
    assert_eq!(c.samples_replayed, c.samples_recorded);
    assert_eq!(c.windows.recorded, windows);
    assert_eq!(c.windows.replayed, windows);
    assert_eq!(
        c.windows.identical, windows,
        "{:?}",
        c.windows.first_difference
    );
    assert_eq!(c.events_replayed, c.events_recorded);
    let results = c.results.as_ref().expect("both sessions solve");
    assert!(results.identical, "{results:?}");
    let replayed = std::fs::read_to_string(out.results_path.as_ref().expect("results.json"))
        .expect("replayed results");
    let original = std::fs::read_to_string(&recorded.results_path).expect("recorded results");
    let strip = |s: &str| {
        let mut v: serde_json::Value = serde_json::from_str(s).expect("json");
        v.as_object_mut().expect("object").remove("session_id");
        serde_json::to_string_pretty(&v).expect("json")
    };
    assert_eq!(strip(&replayed), strip(&original));
    // The sessions themselves: same events, readings and kind topics at the same log times.
    let a = read_session(&recorded.session_path).expect("recording");
    let b = read_session(&out.session_path).expect("replay");
    let events = |s: &geocal::session::reader::Session| {
        s.events
            .iter()
            .map(|e| (e.log_time_ns, serde_json::to_string(&e.msg).expect("json")))
            .collect::<Vec<_>>()
    };
    assert_eq!(events(&b), events(&a));
    assert_eq!(device_stream(&b.probes), device_stream(&a.probes));
    let topics = |s: &geocal::session::reader::Session| {
        s.topics
            .iter()
            .flat_map(|(t, v)| {
                v.iter()
                    .map(move |m| (t.clone(), m.log_time_ns, m.msg.clone()))
            })
            .collect::<Vec<_>>()
    };
    assert_eq!(topics(&b), topics(&a));
    assert_eq!(device_stream(&b.rotary), device_stream(&a.rotary));
    assert!(b.header.session_id.ends_with("-replay"));
    assert!(b.header.devices.iter().all(|d| d.driver == "replay"));
}

/// probe_install: 4 postures × 10 points, 3 readings each, a narrow probe range so that some
/// readings are out of range (recorded as null with a fault) and come back as such.
#[test]
fn probe_install_session_replays_identically() {
    let dir = tempfile::tempdir().expect("tempdir");
    let text = include_str!("../config/probe-install.toml")
        .replace("points_per_posture = 25", "points_per_posture = 10")
        .replace("readings_per_point = 5", "readings_per_point = 3")
        .replace("ga_population = 100", "ga_population = 10")
        .replace("ga_generations = 2000", "ga_generations = 5")
        .replace("range_m = [-8.0e-3, 8.0e-3]", "range_m = [-2.1e-3, 2.1e-3]");
    let recorded = record_kind(&text, &dir.path().join("run"));
    let out = replay_into(&recorded.session_path, &dir.path().join("replay"));
    assert!(
        out.comparison
            .events_recorded
            .get("fault:out_of_range")
            .is_some_and(|n| *n > 0),
        "{:?}",
        out.comparison.events_recorded
    );
    assert_identical_kind_replay(&recorded, &out, 40);
}

/// hexapod: home and 12 poses, with the pose sensor; and once without it (commanded poses).
#[test]
fn hexapod_session_replays_identically() {
    let dir = tempfile::tempdir().expect("tempdir");
    let text = include_str!("../config/hexapod.toml").replace("count = 29", "count = 12");
    let recorded = record_kind(&text, &dir.path().join("run"));
    let out = replay_into(&recorded.session_path, &dir.path().join("replay"));
    assert_identical_kind_replay(&recorded, &out, 13);

    let start = text
        .find("[devices.pose_sensor]")
        .expect("pose sensor table");
    let end = text[start..].find("[plan]").expect("plan table") + start;
    let without = format!("{}{}", &text[..start], &text[end..]);
    let recorded = record_kind(&without, &dir.path().join("run2"));
    let out = replay_into(&recorded.session_path, &dir.path().join("replay2"));
    assert_identical_kind_replay(&recorded, &out, 13);
}

/// rotary_sphere: 12 angles on three heights, 5 points each; the table states, the probe
/// readings and every event come back at their recorded log times.
#[test]
fn rotary_sphere_session_replays_identically() {
    let dir = tempfile::tempdir().expect("tempdir");
    let text = include_str!("../config/rotary-sphere.toml")
        .replace(
            "step_rad = 0.17453292519943295 # 10°",
            "step_rad = 0.5235987755982988",
        )
        .replace("count = 36", "count = 12")
        .replace("max_harmonic_order = 8", "max_harmonic_order = 4");
    let recorded = record_kind(&text, &dir.path().join("run"));
    let out = replay_into(&recorded.session_path, &dir.path().join("replay"));
    assert_identical_kind_replay(&recorded, &out, 3 * 12 * 5);
}

/// A per-device stream of a session as (device, log time, message JSON), for comparing two
/// sessions message by message.
fn device_stream<T: serde::Serialize>(
    streams: &std::collections::BTreeMap<String, Vec<geocal::session::reader::Stamped<T>>>,
) -> Vec<(String, u64, String)> {
    streams
        .iter()
        .flat_map(|(id, v)| {
            v.iter().map(move |r| {
                (
                    id.clone(),
                    r.log_time_ns,
                    serde_json::to_string(&r.msg).expect("json"),
                )
            })
        })
        .collect()
}

/// A recording the sequencer cannot follow (one point moved in the recorded events): the
/// replay stops, says where and why, and shows its last decisions beside the recorded events
/// around that sample.
#[test]
fn a_diverging_replay_shows_its_decisions_and_the_recorded_events() {
    use geocal::session::reader::read_session_raw;
    use geocal::session::{Recorder, RecorderOptions};
    let dir = tempfile::tempdir().expect("tempdir");
    let recorded = record(&small_demo(), &dir.path().join("run"));
    let (_, messages) = read_session_raw(&recorded.session_path).expect("raw read");
    let altered = dir.path().join("altered.mcap");
    let recorder = Recorder::create(&altered, RecorderOptions::default()).expect("recorder");
    let handle = recorder.handle();
    let mut moved = false;
    for mut m in messages {
        let text = String::from_utf8_lossy(&m.data).to_string();
        if !moved && text.contains("\"point_begin\"") && text.contains("\"point\":3") {
            let mut event: serde_json::Value = serde_json::from_str(&text).expect("event json");
            event["axes"]["x"] = serde_json::json!(0.55);
            m.data = serde_json::to_vec(&event).expect("json");
            moved = true;
        }
        handle.raw(m);
    }
    recorder.finish().expect("finish");
    assert!(moved, "a point_begin of point 3 in the recording");
    let out = replay_into(&altered, &dir.path().join("replay"));
    let c = &out.comparison;
    let text = geocal::replay::text(c);
    print!("{text}");
    assert_eq!(c.outcome, Outcome::Diverged, "{}", c.message);
    assert!(c.message.contains("x=0.55 m"), "{}", c.message);
    assert!(
        c.trail.last().is_some_and(|d| d.contains("move to")),
        "{:?}",
        c.trail
    );
    assert!(
        c.recorded_nearby.iter().any(|e| e.contains("x\":0.55")),
        "{:?}",
        c.recorded_nearby
    );
    assert!(text.contains("the replay's last decisions:"), "{text}");
    assert!(
        text.contains("recorded events near where it stopped:"),
        "{text}"
    );
}
