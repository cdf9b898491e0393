//! Resuming an interrupted run (`geocal run --resume DIR`): find the first unfinished point in
//! what the killed run flushed, copy that part into a new session file, continue from there.
//!
//! Files in DIR: `run-config.toml` (stored at run start), `session.mcap` (the session), and
//! while a resume is under way `session.interrupted-N.mcap` (the N-th interrupted file, kept
//! until the continued session has been finished and read back, then deleted).
//! docs/resume.md describes the procedure and the `resume` event.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context};

use crate::clock::{system_now_ns, Clock};
use crate::session::messages::{RunEvent, TOPIC_SESSION};
use crate::session::reader::{read_session, read_session_raw, RawMessage, Session};
use crate::session::recorder::RecorderHandle;

/// The configuration of a run, stored in its output directory at run start.
pub const CONFIG_FILE: &str = "run-config.toml";
pub const SESSION_FILE: &str = "session.mcap";
/// Virtual time between the last recorded message and the continuation of a simulated run
/// (the restart), seconds.
const RESTART_S: f64 = 1.0;
/// Longest wait for a live run's host clock to pass the interrupted session's last log time.
const MAX_CLOCK_WAIT_S: f64 = 120.0;

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
    /// can be written in its place. The last step before the new file is created: a resume
    /// that fails before it leaves `session.mcap` where it was.
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
    /// (its world resumes after the last log time); an emulated run starts its clock at the
    /// host's time, or after the last log time when that is later (an emulated run skips the
    /// operator's relocations, so its log times run ahead of the host clock); a live run's
    /// clock is the host's (`wait_for_clock`).
    pub fn epoch_ns(&self, simulated: bool) -> u64 {
        if simulated {
            self.header_log_time_ns
        } else {
            system_now_ns().max(
                self.last_log_time_ns
                    .saturating_add((RESTART_S * 1e9) as u64),
            )
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

    /// A live clock must be past the interrupted session: log times must increase. A clock
    /// behind it by up to `MAX_CLOCK_WAIT_S` (stepped back since the interruption) is waited
    /// for, with a message; further behind is an error. Call before `set_aside`: an error
    /// leaves the run directory as it was, to be resumed later.
    pub fn wait_for_clock(&self, clock: &dyn Clock) -> anyhow::Result<()> {
        let behind_s = |now_ns: u64| self.last_log_time_ns.saturating_sub(now_ns) as f64 * 1e-9;
        let now_ns = clock.now_ns();
        if now_ns > self.last_log_time_ns {
            return Ok(());
        }
        let behind = behind_s(now_ns);
        if behind > MAX_CLOCK_WAIT_S {
            bail!(
                "the host clock is {behind:.1} s behind the interrupted session's last log time \
                 (log times must increase): set the clock right and resume again; the session \
                 is unchanged"
            );
        }
        tracing::warn!(
            "the host clock is {behind:.1} s behind the interrupted session's last log time: \
             waiting for it to pass before resuming"
        );
        let deadline =
            std::time::Instant::now() + std::time::Duration::from_secs_f64(MAX_CLOCK_WAIT_S + 1.0);
        while clock.now_ns() <= self.last_log_time_ns {
            if std::time::Instant::now() > deadline {
                bail!("the host clock did not pass the interrupted session's last log time");
            }
            let left = behind_s(clock.now_ns()).clamp(0.001, 0.5);
            std::thread::sleep(std::time::Duration::from_secs_f64(left));
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

/// Whether `dir` holds a recorded session to resume (`session.mcap`, or an interrupted file
/// a resume attempt set aside).
pub fn has_session(dir: &Path) -> bool {
    dir.join(SESSION_FILE).is_file() || interrupted_files(dir).is_ok_and(|f| !f.is_empty())
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

/// The configuration to resume with (`load_stored_config`) and the interrupted recording of
/// `dir`, which must be of `kind` and have been recorded with the configuration's plan
/// (`plan_of`, as the session header stores it).
pub fn read_interrupted_run<C: PartialEq, P: serde::Serialize>(
    dir: &Path,
    given: Option<&Path>,
    kind: &str,
    load: impl Fn(&Path) -> anyhow::Result<C>,
    plan_of: impl Fn(&C) -> &P,
) -> anyhow::Result<(C, Interruption)> {
    let config = load_stored_config(dir, given, load)?;
    let interruption = Interruption::read(dir)?;
    let header = &interruption.session.header;
    if header.kind != kind
        || header.plan != serde_json::to_value(plan_of(&config)).unwrap_or_default()
    {
        bail!(
            "{} was recorded with another plan than the configuration's (kind {:?})",
            dir.display(),
            header.kind
        );
    }
    Ok((config, interruption))
}

/// The first index in `0..count` that no recorded event marks finished (`finished` reads the
/// index a finishing event names); `count` when every one is finished.
pub(crate) fn first_unfinished(
    count: usize,
    session: &Session,
    finished: impl Fn(&RunEvent) -> Option<usize>,
) -> usize {
    let done: std::collections::BTreeSet<usize> = session
        .events
        .iter()
        .filter_map(|e| finished(&e.msg))
        .collect();
    (0..count).find(|i| !done.contains(i)).unwrap_or(count)
}

#[cfg(test)]
mod tests {
    use super::*;

    struct Shifted(i64);

    impl Clock for Shifted {
        fn now_ns(&self) -> u64 {
            (system_now_ns() as i64 + self.0) as u64
        }
    }

    fn interrupted_at(dir: &Path, last_log_time_ns: u64) -> Interruption {
        Interruption {
            resume_index: 1,
            session: Session {
                header: crate::session::reader::testutil::header(),
                tracers: Default::default(),
                env: Default::default(),
                rotary: Default::default(),
                machines: Default::default(),
                probes: Default::default(),
                topics: Default::default(),
                events: Vec::new(),
                completeness: crate::session::reader::Completeness::Complete,
                damaged: Vec::new(),
                lost_before_repair: Vec::new(),
                skipped: 0,
                ignored: 0,
            },
            messages: Vec::new(),
            messages_kept: 0,
            header_log_time_ns: 0,
            last_log_time_ns,
            dir: dir.to_path_buf(),
            source: dir.join(SESSION_FILE),
            interrupted_files: Vec::new(),
        }
    }

    #[test]
    fn a_clock_behind_the_session_is_waited_for_or_refused_without_touching_the_files() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join(SESSION_FILE), b"recorded").unwrap();
        let now = system_now_ns();
        // 0.3 s behind: waited for.
        let soon = interrupted_at(dir.path(), now + 300_000_000);
        soon.wait_for_clock(&Shifted(0)).unwrap();
        assert!(system_now_ns() > now + 300_000_000);
        // An hour behind: an error, and the session is where it was, still resumable.
        let far = interrupted_at(dir.path(), now + 3_600_000_000_000);
        let e = far.wait_for_clock(&Shifted(0)).unwrap_err().to_string();
        assert!(e.contains("behind") && e.contains("unchanged"), "{e}");
        assert!(dir.path().join(SESSION_FILE).is_file() && has_session(dir.path()));
        // An emulated run's clock starts after the last log time, whatever the host's says.
        assert!(far.epoch_ns(false) > now + 3_600_000_000_000);
        assert_eq!(far.epoch_ns(true), 0);
    }
}
