//! The daemon's jobs: submission (validated with the strict parsers, stored under the data
//! dir), two workers — runs one at a time on the machine's devices, and beside them solves,
//! diagnoses and replays of recorded sessions one at a time — cancel and resume.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

use anyhow::Context;
use serde::Serialize;
use tokio::sync::{broadcast, Notify};
use tokio_util::sync::CancellationToken;
use utoipa::ToSchema;

use super::catalog::{Catalog, JobRecord, JobState, JobType, NewJob};
use super::config::ServeConfig;
use super::prompts::{PendingPrompt, PromptBoard};
use super::status::{Change, DaemonTap, Progress, StatusBoard};
use crate::devices::held::DeviceHolder;
use crate::kinds::{Registry, RunFlags};
use crate::run::control::RunControl;
use crate::run::RunOptions;
use crate::session::tap::{MessageTap, Tap};

/// The plan configuration of a run job, as submitted.
pub const PLAN_FILE: &str = "plan.toml";
/// The daemon's log of a job (its error, if it failed).
pub const JOB_LOG_FILE: &str = "job.log";

/// What the event stream (`GET /v1/events`) carries.
#[derive(Debug, Clone, Serialize, ToSchema)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum ServerEvent {
    /// A job changed state.
    Job {
        id: i64,
        state: JobState,
        error: Option<String>,
    },
    /// The running job's progress.
    Progress { id: i64, progress: Progress },
    /// The tracer moved to another station.
    Station { id: i64, station: String },
    /// A device reported a fault.
    Fault {
        id: i64,
        device: String,
        message: String,
    },
    /// An operator prompt waits for acknowledgement.
    Prompt { prompt: PendingPrompt },
    /// A scheduled run, compared with the machine's previous run, changed significantly or
    /// beyond a tolerance.
    MachineChange {
        change: super::machines::MachineChange,
    },
}

impl ServerEvent {
    pub fn name(&self) -> &'static str {
        match self {
            ServerEvent::Job { .. } => "job",
            ServerEvent::Progress { .. } => "progress",
            ServerEvent::Station { .. } => "station",
            ServerEvent::Fault { .. } => "fault",
            ServerEvent::Prompt { .. } => "prompt",
            ServerEvent::MachineChange { .. } => "machine_change",
        }
    }
}

/// Why a request about jobs was refused (the API maps each to a status code).
#[derive(Debug, thiserror::Error)]
pub enum JobError {
    #[error("{0}")]
    BadRequest(String),
    #[error("no job {0}")]
    NotFound(i64),
    #[error("{0}")]
    Conflict(String),
    #[error("the daemon is shutting down and accepts no jobs")]
    ShuttingDown,
    #[error(transparent)]
    Internal(#[from] anyhow::Error),
}

struct Running {
    id: i64,
    lane: Lane,
    cancel: CancellationToken,
}

/// Which worker runs a job. A run holds the machine's devices, so runs go one at a time; a
/// solve, diagnosis or replay reads a recorded session and touches no device, so it runs
/// beside the run (one at a time too: each may take the memory and cores of a whole solve).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Lane {
    Runs,
    Sessions,
}

impl Lane {
    fn of(job_type: JobType) -> Lane {
        match job_type {
            JobType::Run => Lane::Runs,
            JobType::Solve | JobType::Diagnose | JobType::Replay => Lane::Sessions,
        }
    }
}

/// Everything the API and the worker share.
pub struct Daemon {
    pub config: ServeConfig,
    catalog: Mutex<Catalog>,
    registry: Registry,
    /// Wakes the worker of runs / of session jobs when one is queued.
    wake_runs: Notify,
    wake_sessions: Notify,
    /// The jobs running now: at most one per lane.
    running: Mutex<Vec<Running>>,
    pub events: broadcast::Sender<ServerEvent>,
    pub status: StatusBoard,
    /// The running job's device readings for the live samples stream.
    pub samples: Arc<super::samples::SampleFeed>,
    pub prompts: PromptBoard,
    accepting: AtomicBool,
    /// Stops the worker once the running job has ended.
    pub shutdown: CancellationToken,
    live: Option<Arc<dyn MessageTap>>,
    /// Real devices' connections kept between jobs (`[devices] hold`).
    pub devices: Option<Arc<DeviceHolder>>,
    /// What the machines' history checks counted (for the metrics).
    pub machines: super::machines::MachineWatch,
    /// Which files a plan may name.
    read_allowance: super::config::ReadAllowance,
}

impl Daemon {
    /// Open the data dir's catalog; jobs found running are marked interrupted.
    pub fn open(
        config: ServeConfig,
        registry: Registry,
        live: Option<Arc<dyn MessageTap>>,
    ) -> anyhow::Result<Arc<Daemon>> {
        let mut catalog = Catalog::open(&config.data_dir)?;
        for id in catalog.mark_interrupted()? {
            tracing::warn!(
                job = id,
                "job was running when the daemon stopped: interrupted"
            );
            // Its record shows what it left: the session so far, and why it ended.
            let dir = catalog.dir_of(id);
            let logged = std::fs::write(
                dir.join(JOB_LOG_FILE),
                "interrupted: the daemon stopped while the job ran\n",
            );
            if let Err(e) = logged
                .map_err(anyhow::Error::from)
                .and_then(|()| catalog.record_files(id).map(|_| ()))
            {
                tracing::warn!(job = id, "recording the interrupted job's files: {e:#}");
            }
        }
        let read_allowance = super::config::ReadAllowance::of(&config)?;
        let devices = if config.devices.hold {
            Some(DeviceHolder::new(config.devices.release_idle_after()?)?)
        } else {
            None
        };
        let (events, _) = broadcast::channel(1024);
        let prompt_events = events.clone();
        Ok(Arc::new(Daemon {
            config,
            catalog: Mutex::new(catalog),
            registry,
            wake_runs: Notify::new(),
            wake_sessions: Notify::new(),
            running: Mutex::new(Vec::new()),
            status: StatusBoard::default(),
            samples: Arc::default(),
            prompts: PromptBoard::new(Arc::new(move |prompt: &PendingPrompt| {
                let _ = prompt_events.send(ServerEvent::Prompt {
                    prompt: prompt.clone(),
                });
            })),
            events,
            accepting: AtomicBool::new(true),
            shutdown: CancellationToken::new(),
            live,
            devices,
            machines: Default::default(),
            read_allowance,
        }))
    }

    fn catalog(&self) -> anyhow::Result<std::sync::MutexGuard<'_, Catalog>> {
        self.catalog
            .lock()
            .map_err(|_| anyhow::anyhow!("job catalog lock poisoned"))
    }

    pub fn job(&self, id: i64) -> Result<JobRecord, JobError> {
        self.catalog()?.get(id)?.ok_or(JobError::NotFound(id))
    }

    pub fn jobs(&self) -> Result<Vec<JobRecord>, JobError> {
        Ok(self.catalog()?.list()?)
    }

    pub fn count_by_state(&self) -> anyhow::Result<Vec<(JobState, u64)>> {
        self.catalog()?.count_by_state()
    }

    /// The live progress of job `id` if it runs now.
    /// The devices seen in jobs, with the connections held between jobs.
    pub fn devices(&self) -> Vec<crate::serve::status::DeviceStatus> {
        let mut devices = self.status.devices();
        for held in self
            .devices
            .as_ref()
            .map(|h| h.status())
            .unwrap_or_default()
        {
            match devices.iter_mut().find(|d| d.id == held.id) {
                Some(device) => {
                    device.connected = true;
                    device.connection = Some(held);
                }
                None => devices.push(crate::serve::status::DeviceStatus {
                    id: held.id.clone(),
                    kind: "unknown".into(),
                    connected: true,
                    last_reading: None,
                    last_reading_age_s: None,
                    signal_level: None,
                    last_error: None,
                    readings: 0,
                    connection: Some(held),
                }),
            }
        }
        devices
    }

    pub fn live_progress(&self, id: i64) -> Option<Progress> {
        let running = self.running.lock().ok()?;
        // The status board follows the run; a session job reports no progress of its own.
        running
            .iter()
            .any(|r| r.id == id && r.lane == Lane::Runs)
            .then(|| self.status.progress())
    }

    fn check_accepting(&self) -> Result<(), JobError> {
        if self.accepting.load(Ordering::SeqCst) {
            Ok(())
        } else {
            Err(JobError::ShuttingDown)
        }
    }

    /// Queue a run of the plan configuration `toml`, checked with the same strict parser as
    /// `geocal check`; nothing is kept of a configuration that fails.
    pub fn submit_run(&self, toml_text: &str, submitted_by: &str) -> Result<i64, JobError> {
        self.check_accepting()?;
        let table: toml::Table = toml_text.parse().map_err(|e| {
            JobError::BadRequest(format!("the plan configuration is not TOML: {e}"))
        })?;
        self.check_reach(&table).map_err(JobError::BadRequest)?;
        // Check in a scratch folder, then move the file into the job's folder.
        let scratch = tempfile::Builder::new()
            .prefix("submit-")
            .tempdir_in(&self.config.data_dir)
            .context("creating a scratch folder in the data dir")?;
        let path = scratch.path().join(PLAN_FILE);
        std::fs::write(&path, toml_text).context("storing the submitted configuration")?;
        let kind = self
            .registry
            .of_config(&path)
            .and_then(|kind| kind.check(&path).map(|_| kind))
            .map_err(|e| {
                JobError::BadRequest(
                    error_chain(&e).replace(&*path.to_string_lossy(), "(submitted plan)"),
                )
            })?;
        let sha = super::catalog::sha256_hex(toml_text.as_bytes());
        let id = {
            let mut catalog = self.catalog()?;
            let id = catalog.add(&NewJob {
                job_type: JobType::Run,
                kind: kind.name(),
                submitted_by,
                config_sha256: Some(&sha),
                source_job: None,
            })?;
            let dir = catalog.dir_of(id);
            std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
            std::fs::rename(&path, dir.join(PLAN_FILE))
                .with_context(|| format!("storing the plan in {}", dir.display()))?;
            catalog.record_files(id)?;
            id
        };
        tracing::info!(
            job = id,
            kind = kind.name(),
            by = submitted_by,
            "run queued"
        );
        self.announce(id, JobState::Queued, None);
        self.wake_runs.notify_one();
        Ok(id)
    }

    /// What a plan may reach: the serial ports and hosts it names against `allowed_ports` and
    /// `allowed_hosts`, the files against `allowed_read_dirs`. Checked before a plan is
    /// parsed (its parsers read the files), and again before it runs.
    fn check_reach(&self, plan: &toml::Table) -> Result<(), String> {
        for (key, value) in super::config::named_endpoints(plan) {
            if !super::config::endpoint_allowed(&self.config, &value) {
                return Err(format!(
                    "key `{key}`: \"{value}\" is not in the daemon's allowed_ports or \
                     allowed_hosts"
                ));
            }
        }
        self.read_allowance.check(plan)
    }

    /// Queue a solve, diagnose or replay of the session of job `source`.
    pub fn submit_on_session(
        &self,
        job_type: JobType,
        source: i64,
        submitted_by: &str,
    ) -> Result<i64, JobError> {
        self.check_accepting()?;
        if job_type == JobType::Run {
            return Err(JobError::BadRequest(
                "a run is submitted as a plan configuration (Content-Type: application/toml)"
                    .into(),
            ));
        }
        let source_job = self.job(source)?;
        let session = source_job.dir.join(crate::run::resume::SESSION_FILE);
        if !session.is_file() {
            return Err(JobError::Conflict(format!(
                "job {source} has no recorded session yet"
            )));
        }
        let id = {
            let mut catalog = self.catalog()?;
            let id = catalog.add(&NewJob {
                job_type,
                kind: &source_job.kind,
                submitted_by,
                config_sha256: None,
                source_job: Some(source),
            })?;
            std::fs::create_dir_all(catalog.dir_of(id)).context("creating the job's folder")?;
            id
        };
        self.announce(id, JobState::Queued, None);
        self.wake_sessions.notify_one();
        Ok(id)
    }

    /// Cancel a queued job at once, or a running one cleanly (its recorder flushes and
    /// closes the file; it can be resumed).
    pub fn cancel(&self, id: i64) -> Result<JobState, JobError> {
        let job = self.job(id)?;
        match job.state {
            JobState::Queued => {
                self.catalog()?.finish(
                    id,
                    JobState::Cancelled,
                    Some("cancelled before it started"),
                )?;
                self.announce(id, JobState::Cancelled, None);
                Ok(JobState::Cancelled)
            }
            JobState::Running => {
                if let Ok(running) = self.running.lock() {
                    if let Some(r) = running.iter().find(|r| r.id == id) {
                        r.cancel.cancel();
                    }
                }
                self.prompts.clear_job(id);
                Ok(JobState::Running)
            }
            state => Err(JobError::Conflict(format!(
                "job {id} is {} and cannot be cancelled",
                state.as_str()
            ))),
        }
    }

    /// Queue an interrupted, cancelled or failed run to continue at its first unfinished point.
    pub fn resume(&self, id: i64) -> Result<(), JobError> {
        self.check_accepting()?;
        let job = self.job(id)?;
        // A failed run (a failed resume attempt among them) goes on from what it recorded.
        let resumable = job.state.resumable()
            || (job.state == JobState::Failed && crate::run::resume::has_session(&job.dir));
        if job.job_type != JobType::Run || !resumable {
            return Err(JobError::Conflict(format!(
                "job {id} is a {} job in state {}: only an interrupted, cancelled or failed run \
                 with a recorded session can be resumed",
                job.job_type.as_str(),
                job.state.as_str()
            )));
        }
        self.catalog()?.queue_resume(id)?;
        self.announce(id, JobState::Queued, None);
        self.wake_runs.notify_one();
        Ok(())
    }

    /// Stop taking jobs and cancel the running one; the worker ends once it has stopped.
    pub fn stop(&self) {
        self.accepting.store(false, Ordering::SeqCst);
        if let Ok(running) = self.running.lock() {
            for r in running.iter() {
                tracing::info!(job = r.id, "shutting down: cancelling the running job");
                r.cancel.cancel();
                self.prompts.clear_job(r.id);
            }
        }
        self.shutdown.cancel();
        self.wake_runs.notify_one();
        self.wake_sessions.notify_one();
    }

    /// What makes the daemon busy (a job running or waiting), for a schedule that skips.
    pub fn busy_reason(&self) -> Option<String> {
        if let Some(id) = self
            .running
            .lock()
            .ok()
            .and_then(|r| r.first().map(|r| r.id))
        {
            return Some(format!("job {id} is running"));
        }
        let queued = self.catalog().ok()?.next_queued().ok()??;
        Some(format!("job {} is queued", queued.id))
    }

    pub fn is_busy(&self) -> bool {
        self.running.lock().map(|r| !r.is_empty()).unwrap_or(true)
    }

    fn announce(&self, id: i64, state: JobState, error: Option<String>) {
        let _ = self.events.send(ServerEvent::Job { id, state, error });
    }

    /// Run queued jobs until `stop`: runs one at a time, and session jobs one at a time
    /// beside them. Returns once both workers have ended their jobs.
    pub async fn work(self: Arc<Self>) {
        tokio::join!(
            self.clone().work_lane(Lane::Runs),
            self.work_lane(Lane::Sessions)
        );
    }

    async fn work_lane(self: Arc<Self>, lane: Lane) {
        let wake = match lane {
            Lane::Runs => &self.wake_runs,
            Lane::Sessions => &self.wake_sessions,
        };
        loop {
            if self.shutdown.is_cancelled() {
                return;
            }
            let next = match self.catalog().and_then(|c| match lane {
                Lane::Runs => c.next_queued_run(),
                Lane::Sessions => c.next_queued_on_session(),
            }) {
                Ok(next) => next,
                Err(e) => {
                    tracing::error!("reading the job catalog: {e:#}");
                    None
                }
            };
            let Some(job) = next else {
                tokio::select! {
                    _ = wake.notified() => {}
                    _ = self.shutdown.cancelled() => return,
                    // A submission between the query and the wait is not missed.
                    _ = tokio::time::sleep(std::time::Duration::from_secs(1)) => {}
                }
                continue;
            };
            let daemon = self.clone();
            let id = job.id;
            let done = tokio::task::spawn_blocking(move || daemon.run_job(job)).await;
            if let Err(e) = done {
                tracing::error!(job = id, "job thread failed: {e}");
            }
        }
    }

    /// Run one job to its end on this (blocking) thread and record how it ended.
    fn run_job(self: &Arc<Self>, job: JobRecord) {
        let id = job.id;
        let lane = Lane::of(job.job_type);
        let cancel = CancellationToken::new();
        if let Ok(mut running) = self.running.lock() {
            running.push(Running {
                id,
                lane,
                cancel: cancel.clone(),
            });
        }
        if job.resume {
            keep_earlier_log(&job.dir);
            if let Err(e) = self.catalog().and_then(|mut c| c.record_files(id)) {
                tracing::warn!(job = id, "recording the resumed job's files: {e:#}");
            }
        }
        if let Err(e) = self.catalog().and_then(|mut c| c.start(id)) {
            tracing::error!(job = id, "marking the job running: {e:#}");
        }
        if lane == Lane::Runs {
            self.status.job_started();
        }
        self.announce(id, JobState::Running, None);
        tracing::info!(
            job = id,
            kind = job.kind,
            resume = job.resume,
            "job started"
        );

        let control = self.control(id, cancel.clone());
        // The runs build their own runtimes: run them on a thread that is outside tokio's.
        let daemon = self.clone();
        let job_for_thread = job.clone();
        let outcome = std::thread::Builder::new()
            .name(format!("geocal-job-{id}"))
            .spawn(move || daemon.execute(&job_for_thread, control))
            .map_err(anyhow::Error::from)
            .and_then(|thread| {
                thread
                    .join()
                    .unwrap_or_else(|_| Err(anyhow::anyhow!("the job's thread panicked")))
            });
        // The run's last readings go out on the samples stream before its end is announced.
        self.samples.flush();
        let (state, error) = match outcome {
            Ok(()) => (JobState::Succeeded, None),
            Err(_) if cancel.is_cancelled() => (
                JobState::Cancelled,
                Some("cancelled; the session recorded so far is kept and can be resumed".into()),
            ),
            Err(e) => (JobState::Failed, Some(error_chain(&e))),
        };
        // Every job leaves the log of its (last) attempt: how it ended, and why.
        let log = match &error {
            Some(e) => format!("{}: {e}\n", state.as_str()),
            None => format!("{}\n", state.as_str()),
        };
        if let Err(e) = std::fs::write(job.dir.join(JOB_LOG_FILE), log) {
            tracing::warn!(job = id, "writing {JOB_LOG_FILE}: {e}");
        }
        if state == JobState::Succeeded {
            self.check_machine(&job);
        }
        let progress = (lane == Lane::Runs).then(|| self.status.progress());
        let recorded = self.catalog().and_then(|mut c| {
            if let Some(progress) = progress {
                c.set_progress(id, progress.done, progress.total)?;
            }
            c.record_files(id)?;
            c.finish(id, state, error.as_deref())
        });
        if let Err(e) = recorded {
            tracing::error!(job = id, "recording the job's end: {e:#}");
        }
        self.prompts.clear_job(id);
        if let Ok(mut running) = self.running.lock() {
            running.retain(|r| r.id != id);
        }
        tracing::info!(job = id, state = state.as_str(), "job ended");
        if lane == Lane::Runs {
            // Live viewers of this run are disconnected (docs/live-view.md).
            if let Some(live) = &self.live {
                live.run_ended();
            }
        }
        self.announce(id, state, error);
        if lane == Lane::Runs {
            // Session jobs on this run's session waited for it to end.
            self.wake_sessions.notify_one();
        }
    }

    fn control(self: &Arc<Self>, id: i64, cancel: CancellationToken) -> RunControl {
        let events = self.events.clone();
        // The log tells a job's progress per station and per tenth, never per point.
        let cadence = Arc::new(Mutex::new(crate::progress::Cadence::for_log()));
        let station_cadence = cadence.clone();
        let tap = DaemonTap {
            board: self.status.clone(),
            on_change: Box::new(move |change| {
                let event = match change {
                    Change::Station(station) => {
                        if station_cadence
                            .lock()
                            .is_ok_and(|mut c| c.station(&station))
                        {
                            tracing::info!(job = id, station = %station, "station begins");
                        }
                        ServerEvent::Station { id, station }
                    }
                    Change::Fault { device, message } => ServerEvent::Fault {
                        id,
                        device,
                        message,
                    },
                };
                let _ = events.send(event);
            }),
            samples: self.samples.clone(),
            live: self.live.clone(),
        };
        let progress_events = self.events.clone();
        let board = self.status.clone();
        let prompts = self.prompts.clone();
        let daemon = Arc::downgrade(self);
        RunControl {
            cancel,
            tap: Tap::new(Arc::new(tap)),
            progress: Some(crate::progress_sink::ProgressSink::new(
                move |done, total| {
                    let before = board.progress();
                    let progress = board.set_progress(done, total);
                    if cadence.lock().is_ok_and(|mut c| c.progress(done, total)) {
                        tracing::info!(
                            job = id,
                            done,
                            total,
                            station = progress.station.as_deref().unwrap_or(""),
                            eta_s = progress.eta_s.map_or(-1.0, |e| e.round()),
                            "progress"
                        );
                    }
                    // Kept in the catalog as points finish, so a daemon killed mid-job shows how
                    // far its job came.
                    if (before.done, before.total) != (done, total) {
                        if let Some(daemon) = daemon.upgrade() {
                            if let Err(e) = daemon
                                .catalog()
                                .and_then(|mut c| c.set_progress(id, done, total))
                            {
                                tracing::warn!(job = id, "recording progress: {e:#}");
                            }
                        }
                    }
                    let _ = progress_events.send(ServerEvent::Progress { id, progress });
                },
            )),
            operator: Some(Arc::new(move || prompts.operator(id))),
            devices: self.devices.clone(),
        }
    }

    fn execute(&self, job: &JobRecord, control: RunControl) -> anyhow::Result<()> {
        let kind = self
            .registry
            .named(&job.kind)
            .ok_or_else(|| anyhow::anyhow!("no plan kind `{}`", job.kind))?;
        let options = RunOptions {
            out_dir: job.dir.clone(),
            truth: Some(job.dir.join("truth.json")),
            progress: false,
            settings: Default::default(),
            control,
        };
        let session_of = |source: Option<i64>| -> anyhow::Result<PathBuf> {
            let source =
                source.ok_or_else(|| anyhow::anyhow!("job {} names no session", job.id))?;
            Ok(self
                .job(source)
                .map_err(anyhow::Error::from)?
                .dir
                .join(crate::run::resume::SESSION_FILE))
        };
        if job.job_type == JobType::Run {
            // The files a plan names may have changed (a symlink swapped) since it was queued.
            let plan = job.dir.join(PLAN_FILE);
            let text = std::fs::read_to_string(&plan)
                .with_context(|| format!("reading {}", plan.display()))?;
            let table: toml::Table = text
                .parse()
                .map_err(|_| anyhow::anyhow!("{} is no longer TOML", plan.display()))?;
            self.check_reach(&table)
                .map_err(|e| anyhow::anyhow!("{e}"))?;
        }
        match job.job_type {
            JobType::Run if job.resume => {
                kind.resume(&job.dir, Some(&job.dir.join(PLAN_FILE)), &options)?;
                self.write_report(job, None);
            }
            JobType::Run => {
                kind.run(&job.dir.join(PLAN_FILE), &options, &RunFlags::default())?;
                self.write_report(job, None);
            }
            JobType::Solve => {
                let session = session_of(job.source_job)?;
                let results = crate::kinds::solve_file(&session, &options.settings)?;
                write(
                    &job.dir.join("results.json"),
                    results.to_json_pretty().as_bytes(),
                )?;
                self.write_report(job, Some(&session));
            }
            JobType::Diagnose => {
                let (diagnosis, residuals) = crate::kinds::diagnosis::diagnose_file_detailed(
                    &session_of(job.source_job)?,
                    &Default::default(),
                )?;
                write(
                    &job.dir.join("diagnosis.json"),
                    serde_json::to_string_pretty(&diagnosis)?.as_bytes(),
                )?;
                crate::diagnose::plot::write_svg(
                    &job.dir.join("residuals.svg"),
                    &diagnosis.session_id,
                    &residuals,
                )?;
            }
            JobType::Replay => {
                let output = crate::replay::replay(
                    &session_of(job.source_job)?,
                    &crate::replay::ReplayOptions {
                        out_dir: job.dir.clone(),
                        realtime: false,
                        settings: Default::default(),
                        progress: false,
                    },
                )?;
                if output.comparison.outcome == crate::replay::Outcome::Diverged {
                    anyhow::bail!("{}", output.comparison.message);
                }
            }
        }
        Ok(())
    }
}

impl Daemon {
    /// `geocal report` of the job's folder as `REPORT_FILE` (its session from `session`
    /// when it is not in the folder). The results stand without it: a report that cannot be
    /// made is logged, and the job keeps its state.
    fn write_report(&self, job: &JobRecord, session: Option<&Path>) {
        let inputs = crate::report::Inputs::read(&job.dir);
        let inputs = match session {
            Some(path) => inputs.and_then(|i| i.with_session(path)),
            None => inputs,
        };
        let made = inputs.and_then(|inputs| {
            let document = crate::report::build(&inputs, &self.registry)?;
            crate::report::write(
                &document,
                &job.dir.join(REPORT_FILE),
                crate::report::Format::Html,
            )
        });
        if let Err(e) = made {
            tracing::warn!(job = job.id, "no report: {}", error_chain(&e));
        }
    }
}

/// Before a resumed run starts, the log of its previous attempt becomes `job.attempt-N.log`
/// (N: 1 for the first attempt), so `job.log` is always the last attempt's.
fn keep_earlier_log(dir: &Path) {
    let log = dir.join(JOB_LOG_FILE);
    if !log.is_file() {
        return;
    }
    let Some(kept) = (1..10_000)
        .map(|n| dir.join(format!("job.attempt-{n}.log")))
        .find(|p| !p.exists())
    else {
        return;
    };
    if let Err(e) = std::fs::rename(&log, &kept) {
        tracing::warn!(
            "keeping the earlier attempt's log as {}: {e}",
            kept.display()
        );
    }
}

/// The report a run or solve job leaves in its folder.
pub const REPORT_FILE: &str = "report.html";

fn write(path: &Path, data: &[u8]) -> anyhow::Result<()> {
    std::fs::write(path, data).with_context(|| format!("writing {}", path.display()))
}

/// An error with its causes on one line.
pub fn error_chain(error: &anyhow::Error) -> String {
    error
        .chain()
        .map(|e| e.to_string())
        .collect::<Vec<_>>()
        .join(": ")
}
