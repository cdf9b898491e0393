//! `geocal replay`: re-runs the real sequencer and stillstand detection against a recorded
//! session through replay drivers, records a new session, and compares it with the recording.
//!
//! The plan comes from the session header. The tracer replays every recorded sample in order;
//! the machine arrives where the recording shows (`recording::Recording::arrival`); recorded
//! device faults (timeouts, protocol errors) are raised again at the same place, so the
//! sequencer retries and records them as it did. Time follows the recorded log times, at full
//! speed or paced by the wall clock (`realtime`).
//!
//! A clean recording is streamed (`stream`): neither it nor the replayed session is held whole.

pub mod compare;
pub mod devices;
pub mod kinds;
pub mod recording;
pub mod stream;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::Context;
use geocal_drivers::DeviceError;
use serde::Serialize;

use crate::config::Config;
use crate::kinds::registry::solve_session;
use crate::method::{MethodError, Results, SolveSettings};
use crate::plan::Plan;
use crate::sequencer::{Devices, Sequencer, SequencerError};
use crate::session::messages::SessionHeader;
use crate::session::reader::{read_session, Completeness, Session};
use crate::session::recorder::{Recorder, RecorderOptions};
use compare::{
    compare_windows, event_counts, results_difference, ResultsDifference, WindowComparison,
};
use devices::{
    ReplayEnvironment, ReplayMachine, ReplayOperator, ReplayRotaryTable, ReplayState, ReplayTracer,
};
use recording::Recording;
use stream::{EventMarks, MarkedEvents};

pub const COMPARISON_FORMAT: &str = "geocal-replay/1";

pub struct ReplayOptions {
    /// Where the replayed session.mcap, results.json and comparison.json go.
    pub out_dir: PathBuf,
    /// Deliver samples at the recorded pace (wall clock) instead of at full speed.
    pub realtime: bool,
    pub settings: SolveSettings,
    pub progress: bool,
}

/// How the replayed run ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Outcome {
    /// The sequencer finished the whole plan.
    Completed,
    /// The recording ran out before the plan was done (a cut-short or interrupted run).
    RecordingEnded,
    /// The sequencer asked for something the recording does not contain, or failed otherwise.
    Diverged,
}

/// The comparison printed by `geocal replay` and written to comparison.json.
#[derive(Debug, Clone, Serialize)]
pub struct Comparison {
    pub format: &'static str,
    pub recording: String,
    pub replay: String,
    pub outcome: Outcome,
    /// What ended the replay, in words.
    pub message: String,
    /// Set when the recorded file is cut short: what the reader says was lost.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub truncation: Option<String>,
    pub samples_recorded: usize,
    pub samples_replayed: usize,
    pub windows: WindowComparison,
    /// `fault:<code>` and `rehome` event counts.
    pub events_recorded: BTreeMap<String, usize>,
    pub events_replayed: BTreeMap<String, usize>,
    /// When the replay diverged: its last decisions (moves, where they end and why, homings)
    /// and the recorded events around the sample where it stopped.
    #[serde(skip_serializing_if = "Vec::is_empty", default)]
    pub trail: Vec<String>,
    #[serde(skip_serializing_if = "Vec::is_empty", default)]
    pub recorded_nearby: Vec<String>,
    /// Both sessions solved with the same settings; None when either cannot be solved.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub results: Option<ResultsDifference>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub results_error: Option<String>,
}

pub struct ReplayOutput {
    pub session_path: PathBuf,
    pub results_path: Option<PathBuf>,
    pub comparison_path: PathBuf,
    pub comparison: Comparison,
    /// The most recorded tracer samples the replay devices held at once (all of them when
    /// the recording was read whole; 0 for the kinds with their own replay).
    pub peak_samples_held: usize,
}

/// The plan the session header records (`plan`, with the machine's targets), expanded as
/// the live run expanded it.
pub fn plan_from_header(header: &SessionHeader) -> anyhow::Result<Plan> {
    if header.kind == crate::monitor::KIND {
        anyhow::bail!("a `monitor` session records one device and no plan: nothing to replay");
    }
    let value = serde_json::json!({
        "kind": header.kind,
        "machine": {
            "name": header.machine.name,
            "structure": header.machine.structure,
            "travel_m": header.machine.travel_m,
            "targets": header.machine.targets,
        },
        // Placeholders: expanding the plan does not look at the devices.
        "devices": {
            "tracer": {"id": "tracer", "driver": "sim", "noise_m": 0.0, "noise_ppm": 0.0,
                       "sample_rate_hz": 1.0},
            "machine": {"id": "machine", "driver": "sim", "feed_m_s": 1.0},
        },
        "plan": header.plan,
    });
    let config: Config = serde_path_to_error::deserialize(value).map_err(|e| {
        anyhow::anyhow!(
            "the session header cannot be replayed: key `{}`: {}",
            e.path(),
            e.inner()
        )
    })?;
    Ok(Plan::from_config(&config))
}

pub fn replay(session_path: &Path, options: &ReplayOptions) -> anyhow::Result<ReplayOutput> {
    // A clean session streams: its tracer samples are never held whole.
    if let Some((marked, rest)) = EventMarks::read(session_path, None) {
        let own_replay = crate::kinds::kind_named(&marked.header.kind)
            .and_then(|k| k.own_replay())
            .is_some();
        if !own_replay {
            if let Some(recording) = Recording::streamed(session_path, &marked, &rest) {
                let recorded = Recorded {
                    header: &marked.header,
                    completeness: &rest.completeness,
                    last_t_s: marked.last_t_s.unwrap_or(0.0),
                    digest: Digest::of_marked(&marked),
                    session: None,
                };
                return replay_recording(session_path, recorded, recording, options);
            }
        }
    }
    let session = read_session(session_path)
        .with_context(|| format!("reading {}", session_path.display()))?;
    // Kinds with their own sequencer and devices replay through it.
    if let Some(replay_sequence) =
        crate::kinds::kind_named(&session.header.kind).and_then(|k| k.own_replay())
    {
        return kinds::replay(&session, session_path, options, replay_sequence);
    }
    let recording = Recording::new(&session)?;
    let tracer_id = recording.tracer_id.clone();
    let recorded = Recorded {
        header: &session.header,
        completeness: &session.completeness,
        last_t_s: last_t_s(&session, &tracer_id),
        digest: Digest::of_session(&session, &tracer_id),
        session: Some(&session),
    };
    replay_recording(session_path, recorded, recording, options)
}

/// What the replay needs of the recorded session besides its `Recording`.
struct Recorded<'a> {
    header: &'a SessionHeader,
    completeness: &'a Completeness,
    /// The followed tracer's last sample time (s).
    last_t_s: f64,
    digest: Digest,
    /// The session read whole (damaged, cut short or repaired files), solved as it is.
    session: Option<&'a Session>,
}

/// What the comparison needs of a session: its windows, event counts and tracer samples.
struct Digest {
    windows: Vec<compare::Window>,
    events: BTreeMap<String, usize>,
    samples: usize,
}

impl Digest {
    fn of_session(session: &Session, tracer_id: &str) -> Digest {
        Digest {
            windows: compare::windows(session, tracer_id),
            events: event_counts(session),
            samples: session.tracers.get(tracer_id).map_or(0, Vec::len),
        }
    }

    fn of_marked(marked: &MarkedEvents) -> Digest {
        Digest {
            windows: compare::windows_marked(&marked.events, &marked.marks),
            events: compare::event_counts_of(&marked.events),
            samples: marked.samples,
        }
    }

    /// The digest of the session file at `path`, streamed when it is clean.
    fn of_file(path: &Path, tracer_id: &str) -> anyhow::Result<Digest> {
        if let Some((marked, _)) = EventMarks::read(path, Some(tracer_id.to_string())) {
            return Ok(Digest::of_marked(&marked));
        }
        let session =
            read_session(path).with_context(|| format!("reading back {}", path.display()))?;
        Ok(Digest::of_session(&session, tracer_id))
    }
}

/// Replays `recording` (of the session at `session_path`) and compares the replay with it.
fn replay_recording(
    session_path: &Path,
    recorded: Recorded<'_>,
    recording: Recording,
    options: &ReplayOptions,
) -> anyhow::Result<ReplayOutput> {
    let plan = plan_from_header(recorded.header)
        .with_context(|| format!("rebuilding the plan of {}", session_path.display()))?;
    std::fs::create_dir_all(&options.out_dir)
        .with_context(|| format!("creating output directory {}", options.out_dir.display()))?;
    let out_path = options.out_dir.join("session.mcap");
    if same_file(session_path, &out_path) {
        anyhow::bail!(
            "the replay would overwrite its recording {}: choose another --out",
            session_path.display()
        );
    }

    let tracer_id = recording.tracer_id.clone();
    let ran = run_sequencer(recorded.header, recording, plan, &out_path, options)?;
    if ran.feed_cut_short {
        anyhow::bail!(
            "{} changed while it was replayed: it gave fewer tracer samples than its first read",
            session_path.display()
        );
    }
    let (ended, samples_replayed) = (ran.ended, ran.delivered);
    let replayed = Digest::of_file(&out_path, &tracer_id)?;
    let (outcome, mut message) = match &ended {
        Ok(()) => (
            Outcome::Completed,
            "the sequencer completed the plan".to_string(),
        ),
        Err(SequencerError::Device(DeviceError::EndOfStream { .. })) => (
            Outcome::RecordingEnded,
            format!(
                "the recording ends after {} tracer samples (t = {:.3} s), before the plan is \
                 done: replayed up to there",
                samples_replayed, recorded.last_t_s
            ),
        ),
        Err(e) => (Outcome::Diverged, format!("the replay stopped: {e}")),
    };
    let diverged = outcome == Outcome::Diverged;
    let truncation = match recorded.completeness {
        Completeness::Complete => None,
        Completeness::Truncated {
            bytes_read,
            file_bytes,
            reason,
            ..
        } => {
            message.push_str(&format!(
                "; the recorded file is cut short (read {bytes_read} of {file_bytes} bytes: {reason})"
            ));
            Some(reason.clone())
        }
    };

    let windows = compare_windows(&recorded.digest.windows, &replayed.windows);
    let (results, results_error, results_path) = compare_results_of(
        solve_file_as_session(&out_path, options)?,
        || match recorded.session {
            Some(session) => Ok(solve_session(session, &options.settings)),
            None => solve_file_as_session(session_path, options),
        },
        options,
    )?;
    let comparison = Comparison {
        format: COMPARISON_FORMAT,
        recording: session_path.display().to_string(),
        replay: out_path.display().to_string(),
        outcome,
        message,
        truncation,
        samples_recorded: recorded.digest.samples,
        samples_replayed: replayed.samples,
        windows,
        events_recorded: recorded.digest.events,
        events_replayed: replayed.events,
        trail: if diverged { ran.trail } else { Vec::new() },
        recorded_nearby: if diverged {
            ran.recorded_nearby
        } else {
            Vec::new()
        },
        results,
        results_error,
    };
    let mut output = write_comparison(options, out_path, results_path, comparison)?;
    output.peak_samples_held = ran.peak_samples_held;
    Ok(output)
}

/// Write `comparison.json` into the output directory; the replay's output.
pub(crate) fn write_comparison(
    options: &ReplayOptions,
    session_path: PathBuf,
    results_path: Option<PathBuf>,
    comparison: Comparison,
) -> anyhow::Result<ReplayOutput> {
    let comparison_path = options.out_dir.join("comparison.json");
    std::fs::write(
        &comparison_path,
        serde_json::to_string_pretty(&comparison)? + "\n",
    )
    .with_context(|| format!("writing {}", comparison_path.display()))?;
    Ok(ReplayOutput {
        session_path,
        results_path,
        comparison_path,
        comparison,
        peak_samples_held: 0,
    })
}

pub(crate) fn same_file(a: &Path, b: &Path) -> bool {
    match (a.canonicalize(), b.canonicalize()) {
        (Ok(x), Ok(y)) => x == y,
        _ => false,
    }
}

fn last_t_s(session: &Session, tracer_id: &str) -> f64 {
    session
        .tracers
        .get(tracer_id)
        .and_then(|v| v.last())
        .map_or(0.0, |s| s.msg.t_s)
}

/// What a replayed sequencer run left: how it ended, how many samples it was given, its last
/// decisions and the recorded events where it stopped.
struct SequencerRun {
    ended: Result<(), SequencerError>,
    delivered: usize,
    /// The most recorded samples the devices held at once.
    peak_samples_held: usize,
    /// The streamed recording gave fewer samples than counted.
    feed_cut_short: bool,
    trail: Vec<String>,
    recorded_nearby: Vec<String>,
}

/// Decisions and recorded events shown when a replay diverges.
const TRAIL_SHOWN: usize = 8;
const NEARBY_BEFORE: usize = 8;
const NEARBY_AFTER: usize = 4;

/// Runs the sequencer on the replay drivers into `out_path`.
fn run_sequencer(
    header: &SessionHeader,
    recording: Recording,
    plan: Plan,
    out_path: &Path,
    options: &ReplayOptions,
) -> anyhow::Result<SequencerRun> {
    let tracer_id = recording.tracer_id.clone();
    let machine_id = recording.machine_id.clone();
    let env_id = recording.env_id.clone();
    let table_id = recording.table_id.clone();
    let start_ns = recording.start_ns;
    let header_ns = start_ns.min(recording.earliest_ns);
    let (shared, clock) = ReplayState::new(recording, plan.clone(), options.realtime);
    let devices = Devices {
        tracer: Box::new(ReplayTracer {
            id: tracer_id,
            shared: shared.clone(),
        }),
        environment: env_id.map(|id| {
            Box::new(ReplayEnvironment {
                id,
                shared: shared.clone(),
            }) as Box<dyn geocal_drivers::Environment>
        }),
        machine: Box::new(ReplayMachine {
            id: machine_id,
            shared: shared.clone(),
        }),
        operator: Box::new(ReplayOperator {
            shared: shared.clone(),
        }),
        rotary: table_id.map(|id| {
            Box::new(ReplayRotaryTable {
                id,
                shared: shared.clone(),
            }) as Box<dyn geocal_drivers::RotaryTable>
        }),
    };
    let recorder = Recorder::create(out_path, RecorderOptions::default())
        .with_context(|| format!("creating {}", out_path.display()))?;
    let handle = recorder.handle();
    if let Ok(mut s) = shared.lock() {
        s.recorder = Some(handle.clone());
    }
    handle.session(&crate::run::replay::replay_header(header), header_ns);
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    let bar = crate::run::progress_bar(options.progress, "points");
    let mut progress = |done: u64, total: u64| {
        bar.set_length(total);
        bar.set_position(done);
    };
    // The sequencer takes its start time from the clock when created (rotary state times
    // count from it): give it the recorded run's start, then the first recorded stamp.
    clock.set_fixed(start_ns);
    let sequencer = Sequencer::new(&plan, devices, handle, clock.clone());
    if let Ok(mut s) = shared.lock() {
        clock.at_cursor(s.recording_mut(), 0);
    }
    let ended = runtime.block_on(sequencer.run(&mut progress)).map(|_| ());
    bar.finish_and_clear();
    recorder
        .finish()
        .context("finishing the replayed session file")?;
    let (delivered, trail, recorded_nearby, peak_samples_held, feed_cut_short) =
        shared.lock().map_or_else(
            |_| (0, Vec::new(), Vec::new(), 0, false),
            |s| {
                let skip = s.trail.len().saturating_sub(TRAIL_SHOWN);
                let samples = &s.recording().samples;
                (
                    s.cursor(),
                    s.trail[skip..].to_vec(),
                    s.recorded_events_near(NEARBY_BEFORE, NEARBY_AFTER),
                    samples.peak_held(),
                    samples.cut_short(),
                )
            },
        );
    Ok(SequencerRun {
        ended,
        delivered,
        peak_samples_held,
        feed_cut_short,
        trail,
        recorded_nearby,
    })
}

pub(crate) type ResultsComparison = (Option<ResultsDifference>, Option<String>, Option<PathBuf>);

/// Solve both sessions; write the replay's results; their difference, or why there is none.
pub(crate) fn compare_results(
    recorded: &Session,
    replayed: &Session,
    options: &ReplayOptions,
) -> anyhow::Result<ResultsComparison> {
    compare_results_of(
        solve_session(replayed, &options.settings),
        || Ok(solve_session(recorded, &options.settings)),
        options,
    )
}

/// The session file at `path` solved as `solve_session` solves it, streamed when it is a
/// clean multilateration session (its samples never held whole).
fn solve_file_as_session(
    path: &Path,
    options: &ReplayOptions,
) -> anyhow::Result<Result<Results, MethodError>> {
    if let Some(solved) =
        crate::method::multilateration::solve_file_streaming(path, &options.settings)
    {
        return Ok(solved.map(Results::new).map_err(MethodError::from));
    }
    let session = read_session(path).with_context(|| format!("reading {}", path.display()))?;
    Ok(solve_session(&session, &options.settings))
}

/// The replay's results (written to results.json) against the recording's, solved after it.
fn compare_results_of(
    replayed_results: Result<Results, MethodError>,
    solve_recorded: impl FnOnce() -> anyhow::Result<Result<Results, MethodError>>,
    options: &ReplayOptions,
) -> anyhow::Result<ResultsComparison> {
    let mut results_path = None;
    if let Ok(results) = &replayed_results {
        let path = options.out_dir.join("results.json");
        std::fs::write(&path, results.to_json_pretty())
            .with_context(|| format!("writing {}", path.display()))?;
        results_path = Some(path);
    }
    let recorded_results = solve_recorded()?;
    Ok(match (recorded_results, replayed_results) {
        (Ok(a), Ok(b)) => (
            Some(results_difference(&a.to_json_value()?, &b.to_json_value()?)),
            None,
            results_path,
        ),
        (a, b) => {
            let why = |r: &Result<_, MethodError>, which: &str| {
                r.as_ref()
                    .err()
                    .map(|e| format!("the {which} session does not solve: {e}"))
            };
            let parts: Vec<String> = [why(&a, "recorded"), why(&b, "replayed")]
                .into_iter()
                .flatten()
                .collect();
            (None, Some(parts.join("; ")), results_path)
        }
    })
}

/// The comparison in words, for the terminal.
pub fn text(c: &Comparison) -> String {
    let mut s = String::new();
    s.push_str(&format!("replay of {}\n", c.recording));
    s.push_str(&format!("  outcome: {:?}: {}\n", c.outcome, c.message));
    s.push_str(&format!(
        "  samples: {} recorded, {} replayed\n",
        c.samples_recorded, c.samples_replayed
    ));
    let w = &c.windows;
    s.push_str(&format!(
        "  windows: {} recorded, {} replayed, {} identical\n",
        w.recorded, w.replayed, w.identical
    ));
    if let Some(d) = &w.first_difference {
        s.push_str(&format!("  first difference: {d}\n"));
    }
    let show = |m: &BTreeMap<String, usize>| {
        if m.is_empty() {
            "none".to_string()
        } else {
            m.iter()
                .map(|(k, v)| format!("{k} {v}"))
                .collect::<Vec<_>>()
                .join(", ")
        }
    };
    s.push_str(&format!(
        "  events: recorded {}; replayed {}\n",
        show(&c.events_recorded),
        show(&c.events_replayed)
    ));
    if !c.trail.is_empty() {
        s.push_str("  the replay's last decisions:\n");
        for line in &c.trail {
            s.push_str(&format!("    {line}\n"));
        }
    }
    if !c.recorded_nearby.is_empty() {
        s.push_str("  recorded events near where it stopped:\n");
        for line in &c.recorded_nearby {
            s.push_str(&format!("    {line}\n"));
        }
    }
    match (&c.results, &c.results_error) {
        (Some(r), _) if r.identical => s.push_str(&format!(
            "  results: identical ({} values compared)\n",
            r.values_compared
        )),
        (Some(r), _) => s.push_str(&format!(
            "  results: {} of {} values differ; largest length difference {:.3e} m at {}\n",
            r.values_differing,
            r.values_compared,
            r.max_abs_difference_m,
            r.max_at.as_deref().unwrap_or("-")
        )),
        (None, Some(e)) => s.push_str(&format!("  results: not compared: {e}\n")),
        (None, None) => {}
    }
    s.push_str(&format!("  replayed session: {}\n", c.replay));
    s
}
