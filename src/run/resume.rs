//! Resuming an interrupted run (`geocal run --resume DIR`): find the first unfinished point in
//! what the killed run flushed, copy that part into a new session file, continue from there.
//!
//! Files in DIR: `run-config.toml` (stored at run start), `session.mcap` (the session), and
//! while a resume is under way `session.interrupted-N.mcap` (the N-th interrupted file, kept
//! until the continued session has been finished and read back, then deleted).
//! docs/resume.md describes the procedure and the `resume` event.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context};

use crate::clock::{system_now_ns, Clock};
use crate::config::Config;
use crate::devices::BuiltDevices;
use crate::plan::{Plan, AXES};
use crate::run::{RunOptions, RunOutput};
use crate::sequencer::ResumeAt;
use crate::session::messages::{RunEvent, TOPIC_SESSION};
use crate::session::reader::{read_session, read_session_raw, RawMessage, Session};
use crate::session::recorder::RecorderHandle;

/// The configuration of a run, stored in its output directory at run start.
pub const CONFIG_FILE: &str = "run-config.toml";
pub const SESSION_FILE: &str = "session.mcap";
/// Virtual time between the last recorded message and the continuation of a simulated run
/// (the restart), seconds.
const RESTART_S: f64 = 1.0;

/// Store the run's configuration in its output directory, so `--resume DIR` needs nothing else.
pub fn store_config<C: serde::Serialize>(config: &C, dir: &Path) -> anyhow::Result<()> {
    let text = toml::to_string(config).context("serialising the run's configuration")?;
    let path = dir.join(CONFIG_FILE);
    let tmp = dir.join(format!("{CONFIG_FILE}.tmp"));
    let text = format!(
        "# The configuration of the run recorded in this directory, stored by geocal at run\n\
         # start: `geocal run --resume DIR` reads it.\n{text}"
    );
    std::fs::write(&tmp, text).with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, &path).with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}

/// Where an interrupted session stops, read from its events and samples (sans I/O).
#[derive(Debug, Clone, PartialEq)]
pub struct Interrupted {
    /// Where to continue (a station index past the last: nothing left to measure).
    pub at: ResumeAt,
    /// Windows with a `point_end`: (station, target, pass, point).
    pub finished: BTreeSet<(String, String, usize, usize)>,
    /// Finished windows that lie after the resume point in plan order (not expected from
    /// geocal's sequencer; they are measured again).
    pub out_of_order: usize,
    /// The last resume of this session (0 if it was never resumed).
    pub resumes: u32,
}

impl Interrupted {
    pub fn from_session(plan: &Plan, session: &Session) -> Interrupted {
        let mut finished = BTreeSet::new();
        let mut begun: BTreeSet<&str> = BTreeSet::new();
        let mut open: Option<(&str, &str, usize, usize)> = None;
        let mut last_begin = None;
        let mut resumes = 0;
        for e in &session.events {
            match &e.msg {
                RunEvent::StationBegin { station, .. } => {
                    begun.insert(station);
                }
                RunEvent::PointBegin {
                    station,
                    point,
                    pass,
                    target,
                    axes,
                    approach,
                    ..
                } => {
                    open = Some((station, target, *pass, *point));
                    last_begin = Some((axes, approach));
                }
                RunEvent::PointEnd {
                    station,
                    point,
                    pass,
                } => {
                    if let Some((s, t, p, q)) = open.take() {
                        if (s, p, q) == (station.as_str(), *pass, *point) {
                            finished.insert((s.to_string(), t.to_string(), p, q));
                        }
                    }
                }
                RunEvent::Rehome { .. } => open = None,
                RunEvent::Resume { resume_index, .. } => {
                    open = None;
                    resumes = resumes.max(*resume_index);
                }
                _ => {}
            }
        }
        let mut at = ResumeAt {
            station: plan.stations.len(),
            ..ResumeAt::default()
        };
        let mut step = 0u64;
        let mut found = false;
        let mut out_of_order = 0;
        for (si, station) in plan.stations.iter().enumerate() {
            for (ti, target) in plan.targets.iter().enumerate() {
                for (pass, &direction) in plan.passes.iter().enumerate() {
                    for (k, &point) in plan.pass_order(direction).iter().enumerate() {
                        let key = (station.id.clone(), target.id.clone(), pass, point);
                        let done = finished.contains(&key);
                        if !found && !done {
                            found = true;
                            at.station = si;
                            at.target = ti;
                            at.pass = pass;
                            at.order_index = k;
                            at.station_begun = begun.contains(station.id.as_str());
                            at.done = step;
                        } else if found && done {
                            out_of_order += 1;
                        }
                        step += 1;
                    }
                }
            }
        }
        if !found {
            at.done = step;
        }
        at.segment_offset = session
            .tracers
            .values()
            .flatten()
            .map(|s| s.msg.beam_segment + 1)
            .max()
            .unwrap_or(0);
        if let Some((axes, approach)) = last_begin {
            let commanded: Option<Vec<f64>> = AXES.iter().map(|a| axes.get(*a).copied()).collect();
            at.commanded = commanded.and_then(|c| <[f64; 3]>::try_from(c).ok());
            at.approach = approach.clone();
        }
        Interrupted {
            at,
            finished,
            out_of_order,
            resumes,
        }
    }

    /// Nothing left to measure.
    pub fn complete(&self, plan: &Plan) -> bool {
        self.at.station >= plan.stations.len()
    }
}

/// The interrupted recording of a run directory, whatever the kind: its messages to copy into
/// the new session file, its times and the files to delete once the continuation is safe.
pub struct Interruption {
    /// This resume's number (1 for the first).
    pub resume_index: u32,
    /// The interrupted session as read (up to its last complete chunk).
    pub session: Session,
    messages: Vec<RawMessage>,
    messages_kept: u64,
    /// Log time of the interrupted session's header: the epoch of a simulated run's clock.
    header_log_time_ns: u64,
    last_log_time_ns: u64,
    dir: PathBuf,
    /// The file read: `session.mcap`, or an interrupted file when the last resume's copy
    /// never reached the disk.
    source: PathBuf,
    /// The interrupted files to delete once the continued session is safely finished.
    interrupted_files: Vec<PathBuf>,
}

impl Interruption {
    /// Read the interrupted session of `dir` (nothing is moved yet: see `set_aside`).
    pub fn read(dir: &Path) -> anyhow::Result<Interruption> {
        let (source, resume_index) = find_source(dir)?;
        let (session, messages) =
            read_session_raw(&source).with_context(|| format!("reading {}", source.display()))?;
        let header_log_time_ns = messages
            .iter()
            .find(|m| m.channel.topic == TOPIC_SESSION)
            .map(|m| m.log_time_ns)
            .context("the interrupted session has no header message")?;
        let last_log_time_ns = messages.iter().map(|m| m.log_time_ns).max().unwrap_or(0);
        Ok(Interruption {
            resume_index,
            session,
            messages_kept: messages.len() as u64,
            messages,
            header_log_time_ns,
            last_log_time_ns,
            dir: dir.to_path_buf(),
            source,
            interrupted_files: Vec::new(),
        })
    }

    /// Move `session.mcap` aside (as `session.interrupted-N.mcap`) so that the continuation
    /// can be written in its place.
    pub fn set_aside(&mut self) -> anyhow::Result<()> {
        let session_path = self.dir.join(SESSION_FILE);
        let kept = self
            .dir
            .join(format!("session.interrupted-{}.mcap", self.resume_index));
        if self.source == session_path {
            std::fs::rename(&self.source, &kept).with_context(|| {
                format!("moving {} to {}", self.source.display(), kept.display())
            })?;
        }
        self.interrupted_files = interrupted_files(&self.dir)?
            .into_iter()
            .map(|f| f.1)
            .collect();
        Ok(())
    }

    /// How many messages of the interrupted file the continuation keeps (all it could read).
    pub fn messages_kept(&self) -> u64 {
        self.messages_kept
    }

    /// The clock epoch of the continuation: a simulated run keeps its virtual clock's epoch
    /// (its world resumes after the last log time); a live or emulated run uses the host clock.
    pub fn epoch_ns(&self, simulated: bool) -> u64 {
        if simulated {
            self.header_log_time_ns
        } else {
            system_now_ns()
        }
    }

    /// Where a simulated world resumes: its time (s since the epoch, after a restart pause)
    /// and a noise seed of its own for this resume.
    pub fn simulated_restart(&self, seed: u64) -> (f64, u64) {
        let t_s = self
            .last_log_time_ns
            .saturating_sub(self.header_log_time_ns) as f64
            * 1e-9
            + RESTART_S;
        let noise_seed = seed
            .wrapping_add(1)
            .wrapping_add(u64::from(self.resume_index).wrapping_mul(0x9e37_79b9_7f4a_7c15));
        (t_s, noise_seed)
    }

    /// A live clock must be past the interrupted session: log times must increase.
    pub fn check_live_clock(&self, now_ns: u64) -> anyhow::Result<()> {
        if now_ns <= self.last_log_time_ns {
            bail!(
                "the host clock ({now_ns} ns) is not past the interrupted session's last log \
                 time ({} ns): log times must increase",
                self.last_log_time_ns
            );
        }
        Ok(())
    }

    /// Copy the interrupted session into the new file, record the `resume` event and make
    /// both durable before anything new happens.
    pub fn record_copy(&mut self, handle: &RecorderHandle, resume: RunEvent, clock: &dyn Clock) {
        for m in self.messages.drain(..) {
            handle.raw(m);
        }
        handle.event(&resume, clock.now_ns());
        handle.checkpoint();
    }

    /// The continued session is finished: read it back, and once it holds at least every
    /// kept message and reads complete, delete the interrupted files.
    pub fn finished(&self, session_path: &Path) -> anyhow::Result<()> {
        let session = read_session(session_path)
            .with_context(|| format!("reading back {}", session_path.display()))?;
        let recorded = session.events.iter().any(|e| {
            matches!(e.msg, RunEvent::Resume { resume_index, .. } if resume_index == self.resume_index)
        });
        if !session.completeness.is_complete() || !recorded {
            bail!(
                "{} did not read back complete with its resume event; the interrupted files \
                 are kept",
                session_path.display()
            );
        }
        for file in &self.interrupted_files {
            std::fs::remove_file(file)
                .with_context(|| format!("removing {} (no longer needed)", file.display()))?;
        }
        Ok(())
    }
}

/// What a resumed tracer run needs from the interrupted one: its recording, where to go on.
pub struct Continuation {
    interruption: Interruption,
    interrupted: Interrupted,
    /// (station, target, pass, point) where the run goes on; None when nothing is left.
    continues_at: Option<(String, String, usize, usize)>,
}

/// A simulated run in virtual time (not emulated, not live).
fn simulated(config: &Config) -> bool {
    config.sim.is_some() && !config.emulated()
}

impl Continuation {
    pub fn epoch_ns(&self, config: &Config) -> u64 {
        self.interruption.epoch_ns(simulated(config))
    }

    /// Bring a rebuilt simulated world to the moment after the interruption.
    pub fn prepare_world(&self, config: &Config, built: &BuiltDevices) -> anyhow::Result<()> {
        if !simulated(config) {
            return self.interruption.check_live_clock(built.clock.now_ns());
        }
        let (Some(world), Some(sim)) = (&built.world, &config.sim) else {
            return Ok(());
        };
        let (t_s, noise_seed) = self.interruption.simulated_restart(sim.seed);
        world
            .lock()
            .map_err(|_| anyhow::anyhow!("simulated world poisoned"))?
            .resume_at(t_s, noise_seed);
        Ok(())
    }

    /// Copy the interrupted session into the new file and record the `resume` event;
    /// returns where the sequencer goes on.
    pub fn record_start(&mut self, handle: &RecorderHandle, clock: &dyn Clock) -> ResumeAt {
        let at = self.continues_at.clone();
        let event = RunEvent::Resume {
            resume_index: self.interruption.resume_index,
            messages_kept: self.interruption.messages_kept(),
            station: at.as_ref().map(|w| w.0.clone()),
            target: at.as_ref().map(|w| w.1.clone()),
            pass: at.as_ref().map(|w| w.2),
            point: at.as_ref().map(|w| w.3),
            height_index: None,
            angle_index: None,
            posture: None,
            pose: None,
        };
        self.interruption.record_copy(handle, event, clock);
        self.interrupted.at.clone()
    }

    pub fn finished(&self, session_path: &Path) -> anyhow::Result<()> {
        self.interruption.finished(session_path)
    }
}

/// `session.interrupted-N.mcap` files in `dir`, by N.
fn interrupted_files(dir: &Path) -> anyhow::Result<Vec<(u32, PathBuf)>> {
    let mut out = Vec::new();
    let entries = std::fs::read_dir(dir).with_context(|| format!("listing {}", dir.display()))?;
    for entry in entries {
        let entry = entry.with_context(|| format!("listing {}", dir.display()))?;
        let name = entry.file_name();
        let n = name
            .to_str()
            .and_then(|n| n.strip_prefix("session.interrupted-"))
            .and_then(|n| n.strip_suffix(".mcap"))
            .and_then(|n| n.parse::<u32>().ok());
        if let Some(n) = n {
            out.push((n, entry.path()));
        }
    }
    out.sort();
    Ok(out)
}

/// Which file holds the interrupted run, and the number of this resume. `session.mcap` is
/// the source unless an earlier resume was itself interrupted before its copy was durable
/// (no `resume` event with the last number in it): then the last interrupted file is.
fn find_source(dir: &Path) -> anyhow::Result<(PathBuf, u32)> {
    let session = dir.join(SESSION_FILE);
    let files = interrupted_files(dir)?;
    let Some((last, last_path)) = files.last().cloned() else {
        if !session.exists() {
            bail!("{}: no {SESSION_FILE} to resume", dir.display());
        }
        return Ok((session, 1));
    };
    let copied = read_session(&session).is_ok_and(|s| {
        s.events
            .iter()
            .any(|e| matches!(e.msg, RunEvent::Resume { resume_index, .. } if resume_index == last))
    });
    Ok(if copied {
        (session, last + 1)
    } else {
        (last_path, last)
    })
}

/// The configuration to resume with: the one stored in DIR, or `given` (which must then
/// equal the stored one, if any).
pub fn load_stored_config<C: PartialEq>(
    dir: &Path,
    given: Option<&Path>,
    load: impl Fn(&Path) -> anyhow::Result<C>,
) -> anyhow::Result<C> {
    let stored_path = dir.join(CONFIG_FILE);
    let stored = if stored_path.exists() {
        Some(load(&stored_path)?)
    } else {
        None
    };
    match (given, stored) {
        (Some(path), Some(stored)) => {
            let config = load(path)?;
            if config != stored {
                bail!(
                    "{} differs from the configuration the run in {} was started with ({}); \
                     resume without CONFIG to use the stored one",
                    path.display(),
                    dir.display(),
                    stored_path.display()
                );
            }
            Ok(config)
        }
        (Some(path), None) => load(path),
        (None, Some(stored)) => Ok(stored),
        (None, None) => bail!(
            "{} holds no {CONFIG_FILE}: give the run's configuration file as well",
            dir.display()
        ),
    }
}

/// `geocal run [CONFIG] --resume DIR`: continue the interrupted run recorded in DIR.
pub fn resume(
    dir: &Path,
    config: Option<&Path>,
    options: &RunOptions,
) -> anyhow::Result<RunOutput> {
    let config = load_stored_config(dir, config, |p| Ok(Config::load(p)?))?;
    if config.devices.machine.driver == crate::config::DriverKind::Passive {
        bail!("a passive run cannot be resumed: its machine restarts its NC program");
    }
    let plan = Plan::from_config(&config);
    let mut interruption = Interruption::read(dir)?;
    let session = &interruption.session;
    if session.header.kind != config.kind.as_str()
        || session.header.plan != serde_json::to_value(&config.plan).unwrap_or_default()
    {
        bail!(
            "{} was recorded with another plan than the configuration's (kind {:?})",
            dir.display(),
            session.header.kind
        );
    }
    let interrupted = Interrupted::from_session(&plan, session);
    if interrupted.out_of_order > 0 {
        tracing::warn!(
            "{}: {} finished windows lie after the first unfinished point; they are measured again",
            dir.display(),
            interrupted.out_of_order
        );
    }
    let continues_at = (!interrupted.complete(&plan)).then(|| {
        let at = &interrupted.at;
        let order = plan.pass_order(plan.passes[at.pass]);
        (
            plan.stations[at.station].id.clone(),
            plan.targets[at.target].id.clone(),
            at.pass,
            order[at.order_index],
        )
    });
    interruption.set_aside()?;
    tracing::info!(
        kept = interruption.messages_kept(),
        finished = interrupted.finished.len(),
        "resuming {} at {:?}",
        dir.display(),
        continues_at
    );
    let mut continuation = Continuation {
        interruption,
        interrupted,
        continues_at,
    };
    crate::run::execute(&config, options, Some(&mut continuation))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::session::reader::Stamped;

    fn config() -> Config {
        let text = include_str!("../../config/demo-multilateration.toml")
            .replace("count = 5 }", "count = 3 }")
            .replace("count = 4 }", "count = 2 }");
        Config::parse(&text, Path::new("demo.toml")).unwrap()
    }

    #[test]
    fn the_stored_configuration_reads_back_equal() {
        let dir = tempfile::tempdir().unwrap();
        let c = config();
        store_config(&c, dir.path()).unwrap();
        assert_eq!(Config::load(&dir.path().join(CONFIG_FILE)).unwrap(), c);
    }

    /// A session with every window of station s1 and pass 0 of s2 up to its 3rd point
    /// finished, and the 4th window left open by the kill.
    #[test]
    fn resumes_at_the_first_unfinished_point() {
        let c = config();
        let plan = Plan::from_config(&c);
        let mut events = vec![];
        let mut t = 0;
        let mut push = |e: RunEvent| {
            t += 1;
            events.push(Stamped {
                log_time_ns: t,
                publish_time_ns: t,
                msg: e,
            })
        };
        let begin = |station: &str, pass: usize, point: usize| RunEvent::PointBegin {
            station: station.into(),
            point,
            pass,
            target: "t0".into(),
            nominal_m: [0.0; 3],
            axes: AXES.iter().map(|a| (a.to_string(), point as f64)).collect(),
            approach: AXES.iter().map(|a| (a.to_string(), 1)).collect(),
        };
        let end = |station: &str, pass: usize, point: usize| RunEvent::PointEnd {
            station: station.into(),
            point,
            pass,
        };
        for (station, passes) in [("s1", 2), ("s2", 1)] {
            push(RunEvent::StationBegin {
                station: station.into(),
                station_index: 0,
                hint_m: None,
            });
            for pass in 0..passes {
                for &point in &plan.pass_order(plan.passes[pass]) {
                    push(begin(station, pass, point));
                    push(end(station, pass, point));
                }
            }
        }
        let pass1 = plan.pass_order(plan.passes[1]);
        for &point in &pass1[..3] {
            push(begin("s2", 1, point));
            push(end("s2", 1, point));
        }
        push(begin("s2", 1, pass1[3]));
        let session = Session {
            header: crate::session::reader::testutil::header(),
            tracers: Default::default(),
            env: Default::default(),
            rotary: Default::default(),
            machines: Default::default(),
            probes: Default::default(),
            topics: Default::default(),
            events,
            completeness: crate::session::reader::Completeness::Complete,
            damaged: Vec::new(),
            skipped: 0,
            ignored: 0,
        };
        let r = Interrupted::from_session(&plan, &session);
        let n = plan.points.len() as u64;
        assert_eq!((r.at.station, r.at.target, r.at.pass), (1, 0, 1));
        assert_eq!(r.at.order_index, 3);
        assert!(r.at.station_begun);
        assert_eq!(r.at.done, 2 * n + n + 3);
        assert_eq!(r.finished.len() as u64, r.at.done);
        assert_eq!(r.out_of_order, 0);
        assert_eq!(r.at.commanded, Some([pass1[3] as f64; 3]));
        assert!(!r.complete(&plan));
    }
}
