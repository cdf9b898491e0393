//! `geocal replay` of the plan kinds rotary_sphere, probe_install and hexapod: their own
//! sequencers re-run against the recording through replay devices, recorded anew and compared.
//!
//! Every device hands out its recorded stream in order and sets the replay clock to the
//! recorded log time of what it hands out (a machine's or hexapod's arrival: the recorded
//! arrival), so the replayed events and samples carry the recorded log times and the method
//! sees the same windows. Recorded `out_of_range` probe readings are raised again; other
//! recorded device faults (retries) are not (these kinds run on simulated devices so far).

use std::path::Path;
use std::sync::Arc;

use anyhow::Context;
use geocal_drivers::DeviceError;

use super::compare::{compare_windows, event_counts, Window};
use super::devices::ReplayClock;
use super::{
    write_comparison, Comparison, Outcome, ReplayOptions, ReplayOutput, COMPARISON_FORMAT,
};
use crate::run::replay::ReplaySequence;
use crate::sequencer::SequencerError;
use crate::session::messages::RunEvent;
use crate::session::reader::{read_session, Session};
use crate::session::recorder::{Recorder, RecorderOptions};

/// Windows of a kind (`probe_begin`..`probe_end`, `probe_point_begin`..`probe_point_end` or
/// `pose_begin`..`pose_end`) and the readings inside, as `Window`s (station: the posture, the
/// sphere or `pose`).
fn kind_windows(session: &Session) -> Vec<Window> {
    let probe: Vec<(u64, Option<u64>)> = session
        .probes
        .values()
        .flatten()
        .map(|s| (s.log_time_ns, Some(s.msg.seq)))
        .collect();
    let legs: Vec<(u64, Option<u64>)> = session
        .topics
        .iter()
        .filter(|(t, _)| t.starts_with("/hexapod/") && t.ends_with("/legs"))
        .flat_map(|(_, v)| v.iter().map(|m| (m.log_time_ns, None)))
        .collect();
    let mut out = Vec::new();
    let mut open: Option<u64> = None;
    for e in &session.events {
        let (station, point, samples) = match &e.msg {
            RunEvent::ProbeBegin { .. }
            | RunEvent::PoseBegin { .. }
            | RunEvent::ProbePointBegin { .. } => {
                open = Some(e.log_time_ns);
                continue;
            }
            RunEvent::ProbeEnd { posture, point } => (format!("posture {posture}"), *point, &probe),
            RunEvent::PoseEnd { pose } => ("pose".to_string(), *pose, &legs),
            RunEvent::ProbePointEnd {
                height_index,
                angle_index,
                point,
            } => (
                format!("height {height_index} angle {angle_index}"),
                *point,
                &probe,
            ),
            _ => continue,
        };
        let Some(begin) = open.take() else { continue };
        let inside: Vec<&(u64, Option<u64>)> = samples
            .iter()
            .filter(|(t, _)| *t >= begin && *t <= e.log_time_ns)
            .collect();
        out.push(Window {
            station,
            point,
            pass: 0,
            target: String::new(),
            samples: inside.len(),
            first_seq: inside.first().and_then(|s| s.1),
            last_seq: inside.last().and_then(|s| s.1),
        });
    }
    out
}

fn readings(session: &Session) -> usize {
    session.probes.values().map(Vec::len).sum::<usize>()
        + session
            .topics
            .iter()
            .filter(|(t, _)| t.starts_with("/hexapod/") && t.ends_with("/legs"))
            .map(|(_, v)| v.len())
            .sum::<usize>()
}

/// Replay a probe_install or hexapod recording (`replays(kind)`).
pub fn replay(
    session: &Session,
    session_path: &Path,
    options: &ReplayOptions,
    replay_sequence: ReplaySequence,
) -> anyhow::Result<ReplayOutput> {
    std::fs::create_dir_all(&options.out_dir)
        .with_context(|| format!("creating output directory {}", options.out_dir.display()))?;
    let out_path = options.out_dir.join("session.mcap");
    if super::same_file(session_path, &out_path) {
        anyhow::bail!(
            "the replay would overwrite its recording {}: choose another --out",
            session_path.display()
        );
    }
    let _clock = Arc::new(ReplayClock::default());
    let _first_event_ns = session.events.first().map_or(0, |e| e.log_time_ns);
    let recorder = Recorder::create(&out_path, RecorderOptions::default())
        .with_context(|| format!("creating {}", out_path.display()))?;
    let handle = recorder.handle();
    let _runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    let _sequencer_end = |e: SequencerError| match e {
        SequencerError::Device(DeviceError::EndOfStream { device }) => {
            (Some(device), String::new())
        }
        e => (None, e.to_string()),
    };
    let ended = replay_sequence(session, handle)?;
    recorder
        .finish()
        .context("finishing the replayed session file")?;
    let replayed =
        read_session(&out_path).with_context(|| format!("reading back {}", out_path.display()))?;
    let (outcome, message) = match &ended {
        Ok(()) => (
            Outcome::Completed,
            "the sequencer completed the plan".to_string(),
        ),
        Err((Some(device), _)) => (
            Outcome::RecordingEnded,
            format!("the recording of {device} ends before the plan is done: replayed up to there"),
        ),
        Err((None, e)) => (Outcome::Diverged, format!("the replay stopped: {e}")),
    };
    let (results, results_error, results_path) =
        super::compare_results(session, &replayed, options)?;
    let comparison = Comparison {
        format: COMPARISON_FORMAT,
        recording: session_path.display().to_string(),
        replay: out_path.display().to_string(),
        outcome,
        message,
        truncation: match &session.completeness {
            crate::session::reader::Completeness::Complete => None,
            crate::session::reader::Completeness::Truncated { reason, .. } => Some(reason.clone()),
        },
        samples_recorded: readings(session),
        samples_replayed: readings(&replayed),
        windows: compare_windows(&kind_windows(session), &kind_windows(&replayed)),
        events_recorded: event_counts(session),
        events_replayed: event_counts(&replayed),
        trail: Vec::new(),
        recorded_nearby: Vec::new(),
        results,
        results_error,
    };
    write_comparison(options, out_path, results_path, comparison)
}
