//! Resuming an interrupted tracer-plan run (`geocal run --resume DIR`): find the first
//! unfinished point in what the killed run flushed, copy that part into a new session file,
//! continue from there. The kind-neutral part (the run directory, the interrupted file and
//! its copy) is `run::resume`; docs/resume.md describes the procedure and the `resume` event.

use std::collections::BTreeSet;
use std::path::Path;

use anyhow::bail;

use crate::clock::Clock;
use crate::config::Config;
use crate::devices::BuiltDevices;
use crate::plan::{Plan, AXES};
use crate::run::resume::{load_stored_config, Interruption};
use crate::run::{RunOptions, RunOutput};
use crate::sequencer::ResumeAt;
use crate::session::messages::RunEvent;
use crate::session::reader::Session;
use crate::session::recorder::RecorderHandle;

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
            let commanded: Option<Vec<f64>> = AXES.iter().map(|a| axes.get(a).copied()).collect();
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
            return self.interruption.wait_for_clock(built.clock.as_ref());
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

    /// Move the interrupted file aside: the step just before the new one is created.
    pub fn set_aside(&mut self) -> anyhow::Result<()> {
        self.interruption.set_aside()
    }

    /// Copy the interrupted session into the new file and record the `resume` event;
    /// returns where the sequencer goes on.
    pub fn record_start(&mut self, handle: &RecorderHandle, clock: &dyn Clock) -> ResumeAt {
        let at = self.continues_at.clone();
        let event = RunEvent::Resume {
            resume_index: self.interruption.resume_index,
            messages_kept: self.interruption.messages_kept(),
            station: at.as_ref().map(|w| w.0.as_str().into()),
            target: at.as_ref().map(|w| w.1.as_str().into()),
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
    let interruption = Interruption::read(dir)?;
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
    super::run::execute(&config, options, Some(&mut continuation))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::run::resume::{store_config, CONFIG_FILE};
    use crate::session::reader::Stamped;

    fn config() -> Config {
        let text = include_str!("../../../config/demo-multilateration.toml")
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
            lost_before_repair: Vec::new(),
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
