//! The daemon's machines: their history from the catalog's succeeded runs (`/v1/machines`,
//! `/v1/machines/{name}/history`, `/v1/machines/{name}/trend`), and the check after each
//! scheduled calibration: compared with the machine's previous run, a significant change or a
//! tolerance breach raises an event, counts in the metrics and is posted to `notify_url`.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Mutex;

use anyhow::Context;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::catalog::{Catalog, JobRecord, JobState, JobType, CATALOG_FILE};
use crate::history::{compare, CompareOptions, Run, Tolerances, TrendOptions};

/// The comparison a scheduled run leaves in its folder (geocal-compare/1).
pub const COMPARISON_FILE: &str = "comparison.json";

/// `[history]` in the daemon's configuration.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HistoryConfig {
    /// Family-wise significance level of a comparison and of a trend.
    #[serde(default = "default_alpha")]
    pub alpha: f64,
    /// Allowed change of a parameter in metres, radians, or without a unit.
    #[serde(default)]
    pub tolerance_m: Option<f64>,
    #[serde(default)]
    pub tolerance_rad: Option<f64>,
    #[serde(default)]
    pub tolerance_other: Option<f64>,
    /// Runs that make a trend's baseline.
    #[serde(default = "default_baseline_runs")]
    pub baseline_runs: usize,
    /// An `http://` URL the daemon POSTs each machine-change event to (JSON).
    #[serde(default)]
    pub notify_url: Option<String>,
}

fn default_alpha() -> f64 {
    0.05
}

fn default_baseline_runs() -> usize {
    5
}

impl Default for HistoryConfig {
    fn default() -> Self {
        HistoryConfig {
            alpha: default_alpha(),
            tolerance_m: None,
            tolerance_rad: None,
            tolerance_other: None,
            baseline_runs: default_baseline_runs(),
            notify_url: None,
        }
    }
}

impl HistoryConfig {
    pub fn tolerances(&self) -> Tolerances {
        Tolerances {
            m: self.tolerance_m,
            rad: self.tolerance_rad,
            other: self.tolerance_other,
        }
    }

    pub fn compare_options(&self) -> CompareOptions {
        CompareOptions {
            alpha: self.alpha,
            tolerances: self.tolerances(),
        }
    }

    pub fn trend_options(&self) -> TrendOptions {
        TrendOptions {
            alpha: self.alpha,
            tolerances: self.tolerances(),
            baseline_runs: self.baseline_runs,
        }
    }

    /// A bad key refuses the start, naming it.
    pub fn check(&self) -> anyhow::Result<()> {
        self.compare_options()
            .check()
            .context("[history] in the daemon configuration")?;
        self.trend_options()
            .check()
            .context("[history] in the daemon configuration")?;
        if let Some(url) = &self.notify_url {
            let parsed = reqwest::Url::parse(url)
                .with_context(|| format!("[history] notify_url \"{url}\": not a URL"))?;
            if parsed.scheme() != "http" {
                anyhow::bail!(
                    "[history] notify_url \"{url}\": expected an http:// URL (the daemon \
                     posts without TLS; put a local relay in front of an https endpoint)"
                );
            }
        }
        Ok(())
    }
}

/// A machine-change event: on the event stream, in the notification's body.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct MachineChange {
    /// The machine (configured name, or serial).
    pub machine: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub serial: Option<String>,
    /// The machine's key (docs/fleet.md, "One machine").
    #[serde(default)]
    pub key: String,
    pub kind: String,
    /// The scheduled run and the run it was compared with.
    pub job: i64,
    pub previous_job: i64,
    /// Parameters that changed significantly (Holm–Bonferroni at `alpha`), largest |z| first.
    pub significant: Vec<String>,
    /// Parameters whose change exceeds their tolerance.
    pub exceeding_tolerance: Vec<String>,
    pub alpha: f64,
    /// The largest |z| of the comparison.
    pub max_abs_z: f64,
}

/// One machine as `/v1/machines` lists it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct MachineView {
    /// Its configured name (or its serial, or its declared id, without one); its other
    /// routes take it when no other machine has it.
    pub name: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub serial: Option<String>,
    /// Its key (docs/fleet.md, "One machine"): its other routes always take it.
    #[serde(default)]
    pub key: String,
    /// Plan kinds it was calibrated with.
    pub kinds: Vec<String>,
    /// Succeeded runs in the catalog.
    pub runs: usize,
    pub last_job: i64,
    pub last_started_at: String,
    /// Whether its last run, compared with the one before, showed a change.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub last_changed: Option<bool>,
}

/// One run in a machine's history.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct HistoryEntry {
    pub job: i64,
    pub kind: String,
    pub session_id: String,
    pub started_at: String,
    pub submitted_by: String,
    /// The comparison with the previous run (scheduled runs), when one was made.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub comparison: Option<ComparisonSummary>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct ComparisonSummary {
    pub previous_job: i64,
    pub changed: bool,
    pub compared: usize,
    pub significant: Vec<String>,
    pub exceeding_tolerance: Vec<String>,
}

/// `/v1/machines/{name}/history`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct MachineHistory {
    pub machine: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub serial: Option<String>,
    #[serde(default)]
    pub key: String,
    /// Oldest first.
    pub runs: Vec<HistoryEntry>,
}

/// What the daemon counts of its machines since it started (for the metrics), by machine key.
#[derive(Debug, Default)]
pub struct MachineWatch {
    counts: Mutex<BTreeMap<String, WatchCounts>>,
}

#[derive(Debug, Default, Clone)]
pub struct WatchCounts {
    /// The machine's name (its last run's).
    pub name: String,
    pub comparisons: u64,
    pub changes: u64,
    pub notifications_failed: u64,
    /// Significant parameters of the last comparison.
    pub last_significant: u64,
}

impl MachineWatch {
    fn update(&self, key: &str, name: &str, f: impl FnOnce(&mut WatchCounts)) {
        if let Ok(mut counts) = self.counts.lock() {
            let c = counts.entry(key.to_owned()).or_default();
            c.name = name.to_owned();
            f(c);
        }
    }

    pub fn counts(&self) -> BTreeMap<String, WatchCounts> {
        self.counts.lock().map(|c| c.clone()).unwrap_or_default()
    }
}

/// A run job of the catalog with its loaded results.
struct CatalogRun {
    job: JobRecord,
    run: Run,
}

/// The machine's name as the daemon shows it, when the run names one.
fn name_of(run: &Run) -> Option<String> {
    let m = &run.machine;
    m.name
        .clone()
        .or_else(|| m.serial.clone())
        .or_else(|| m.id.clone())
}

/// The succeeded runs among the catalog's `jobs` that left results, oldest first (by job id).
fn succeeded_runs(mut jobs: Vec<JobRecord>) -> Vec<CatalogRun> {
    jobs.retain(|j| {
        j.job_type == JobType::Run
            && j.state == JobState::Succeeded
            && j.dir.join(crate::history::load::RESULTS_FILE).is_file()
    });
    jobs.sort_by_key(|j| j.id);
    let mut runs = Vec::new();
    for job in jobs {
        match Run::load(&job.dir) {
            Ok(mut run) => {
                run.label = format!("job {}", job.id);
                runs.push(CatalogRun { job, run });
            }
            Err(e) => tracing::warn!(job = job.id, "history: results not readable: {e:#}"),
        }
    }
    runs
}

/// The catalog's succeeded runs as a series for `geocal trend --catalog DATA_DIR`.
pub fn catalog_runs(data_dir: &Path) -> anyhow::Result<Vec<Run>> {
    let path = data_dir.join(CATALOG_FILE);
    if !path.is_file() {
        anyhow::bail!(
            "{}: no job catalog ({CATALOG_FILE}): is it the daemon's data dir?",
            data_dir.display()
        );
    }
    let catalog = Catalog::open(data_dir)?;
    let runs: Vec<Run> = succeeded_runs(catalog.list()?)
        .into_iter()
        .map(|r| r.run)
        .collect();
    if runs.is_empty() {
        anyhow::bail!("{}: the catalog holds no succeeded run", data_dir.display());
    }
    Ok(runs)
}

/// The summary of a comparison.json.
fn summary_of(value: &serde_json::Value) -> Option<ComparisonSummary> {
    let ids = |key: &str| -> Vec<String> {
        value[key]
            .as_array()
            .map(|a| {
                a.iter()
                    .filter_map(|s| s.as_str().map(str::to_owned))
                    .collect()
            })
            .unwrap_or_default()
    };
    let significant = ids("significant");
    let exceeding_tolerance = ids("exceeding_tolerance");
    Some(ComparisonSummary {
        previous_job: value["previous_job"].as_i64()?,
        changed: !(significant.is_empty() && exceeding_tolerance.is_empty()),
        compared: value["compared"].as_u64().unwrap_or(0) as usize,
        significant,
        exceeding_tolerance,
    })
}

fn comparison_summary(dir: &Path) -> Option<ComparisonSummary> {
    let text = std::fs::read_to_string(dir.join(COMPARISON_FILE)).ok()?;
    summary_of(&serde_json::from_str(&text).ok()?)
}

/// Every machine with a succeeded run among the catalog's `jobs`, by name.
pub fn machines(jobs: Vec<JobRecord>) -> Vec<MachineView> {
    let mut out: Vec<MachineView> = Vec::new();
    for r in succeeded_runs(jobs) {
        let Some(name) = name_of(&r.run) else {
            continue;
        };
        let key = r.run.machine.key();
        let changed = comparison_summary(&r.job.dir).map(|s| s.changed);
        match out.iter_mut().find(|m| m.key == key) {
            Some(m) => {
                if !m.kinds.contains(&r.run.kind) {
                    m.kinds.push(r.run.kind.clone());
                }
                m.runs += 1;
                m.last_job = r.job.id;
                m.last_started_at = r.run.started_text();
                m.last_changed = changed;
                // A declared id keeps the machine while its name changes: show the last.
                m.name = name;
                m.serial = r.run.machine.serial.clone();
            }
            None => out.push(MachineView {
                name,
                serial: r.run.machine.serial.clone(),
                key,
                kinds: vec![r.run.kind.clone()],
                runs: 1,
                last_job: r.job.id,
                last_started_at: r.run.started_text(),
                last_changed: changed,
            }),
        }
    }
    out
}

/// The runs of the machine `name` (its key, id, name or serial); a name several machines
/// share is an error naming their keys.
fn runs_of(jobs: Vec<JobRecord>, name: &str) -> Result<Vec<CatalogRun>, MachineError> {
    crate::history::load::runs_of_machine(succeeded_runs(jobs), name, |r| &r.run.machine)
        .map_err(|e| MachineError::Ambiguous(format!("{e:#}")))
}

/// The history of machine `name` (its key, id, name or serial).
pub fn history(jobs: Vec<JobRecord>, name: &str) -> Result<MachineHistory, MachineError> {
    let runs = runs_of(jobs, name)?;
    let Some(last) = runs.last() else {
        return Err(MachineError::NoMachine(name.to_owned()));
    };
    Ok(MachineHistory {
        machine: name_of(&last.run).unwrap_or_else(|| name.to_owned()),
        serial: last.run.machine.serial.clone(),
        key: last.run.machine.key(),
        runs: runs
            .iter()
            .map(|r| HistoryEntry {
                job: r.job.id,
                kind: r.run.kind.clone(),
                session_id: r.run.session_id.clone(),
                started_at: r.run.started_text(),
                submitted_by: r.job.submitted_by.clone(),
                comparison: comparison_summary(&r.job.dir),
            })
            .collect(),
    })
}

/// Why a machine's history or trend cannot be given.
#[derive(Debug, thiserror::Error)]
pub enum MachineError {
    #[error("no machine \"{0}\" has a succeeded run")]
    NoMachine(String),
    /// The name is shared by several machines: the message names their keys.
    #[error("{0}")]
    Ambiguous(String),
    #[error("{0}")]
    NotEnough(String),
    #[error(transparent)]
    Internal(#[from] anyhow::Error),
}

/// The trend (geocal-trend/1) of machine `name` over its runs of the kind of its last run.
pub fn trend(
    jobs: Vec<JobRecord>,
    name: &str,
    config: &HistoryConfig,
) -> Result<serde_json::Value, MachineError> {
    let runs = runs_of(jobs, name)?;
    let Some(last) = runs.last() else {
        return Err(MachineError::NoMachine(name.to_owned()));
    };
    let kind = last.run.kind.clone();
    let series: Vec<Run> = runs
        .into_iter()
        .filter(|r| r.run.kind == kind)
        .map(|r| r.run)
        .collect();
    if series.len() < 2 {
        return Err(MachineError::NotEnough(format!(
            "machine \"{name}\" has {} succeeded {kind} run: a trend needs 2",
            series.len()
        )));
    }
    let trend = crate::history::trend(&series, &config.trend_options())
        .map_err(|e| MachineError::NotEnough(format!("{e:#}")))?;
    Ok(serde_json::to_value(&trend).context("serialising the trend")?)
}

/// After a scheduled run of job `job` succeeded: compare it with the previous succeeded run
/// of the same machine and kind, keep the comparison in the job's folder, and on a change
/// return the event (the caller sends it, counts it and notifies).
pub fn check_scheduled_run(
    jobs: Vec<JobRecord>,
    job: &JobRecord,
    config: &HistoryConfig,
    watch: &MachineWatch,
) -> anyhow::Result<Option<MachineChange>> {
    let run = Run::load(&job.dir)?;
    let Some(name) = name_of(&run) else {
        tracing::info!(
            job = job.id,
            "history: the run names no machine ([machine] name): not compared"
        );
        return Ok(None);
    };
    let previous = succeeded_runs(jobs).into_iter().rfind(|r| {
        r.job.id < job.id && r.run.kind == run.kind && r.run.machine.same_machine(&run.machine)
    });
    let Some(previous) = previous else {
        tracing::info!(
            job = job.id,
            machine = name,
            "history: first run of the machine"
        );
        return Ok(None);
    };
    let mut this = run;
    this.label = format!("job {}", job.id);
    let comparison = compare(&previous.run, &this, &config.compare_options())?;
    let mut json = serde_json::to_value(&comparison)?;
    json["previous_job"] = serde_json::json!(previous.job.id);
    json["job"] = serde_json::json!(job.id);
    std::fs::write(
        job.dir.join(COMPARISON_FILE),
        serde_json::to_string_pretty(&json)?,
    )
    .with_context(|| format!("writing {COMPARISON_FILE} of job {}", job.id))?;
    let key = this.machine.key();
    watch.update(&key, &name, |c| {
        c.comparisons += 1;
        c.last_significant = comparison.significant.len() as u64;
        if comparison.changed() {
            c.changes += 1;
        }
    });
    tracing::info!(
        job = job.id,
        previous = previous.job.id,
        machine = name,
        significant = comparison.significant.len(),
        beyond_tolerance = comparison.exceeding_tolerance.len(),
        "history: compared with the previous run"
    );
    if !comparison.changed() {
        return Ok(None);
    }
    Ok(Some(MachineChange {
        machine: name,
        serial: this.machine.serial.clone(),
        key,
        kind: this.kind.clone(),
        job: job.id,
        previous_job: previous.job.id,
        significant: comparison.significant.clone(),
        exceeding_tolerance: comparison.exceeding_tolerance.clone(),
        alpha: comparison.alpha,
        max_abs_z: comparison
            .parameters
            .iter()
            .map(|p| p.z.abs())
            .fold(0.0, f64::max),
    }))
}

/// POST the change to `url` as JSON (on a thread of its own: the blocking client must not run
/// inside the async runtime); a failure is logged and counted, never fatal.
pub fn notify(url: &str, change: &MachineChange, watch: &MachineWatch) {
    let body = change.clone();
    let target = url.to_owned();
    let sent = std::thread::Builder::new()
        .name("geocal-notify".into())
        .spawn(move || -> anyhow::Result<()> {
            let client = reqwest::blocking::Client::builder()
                .timeout(std::time::Duration::from_secs(10))
                .build()?;
            let response = client.post(&target).json(&body).send()?;
            if !response.status().is_success() {
                anyhow::bail!("{target} answered {}", response.status());
            }
            Ok(())
        })
        .map_err(anyhow::Error::from)
        .and_then(|t| {
            t.join()
                .unwrap_or_else(|_| Err(anyhow::anyhow!("the notification thread panicked")))
        });
    if let Err(e) = sent {
        tracing::warn!(machine = change.machine, "history: notifying {url}: {e:#}");
        watch.update(&change.key, &change.machine, |c| {
            c.notifications_failed += 1
        });
    }
}

/// The machines' metrics: comparisons, changes, failed notifications (since the daemon
/// started) and the significant parameters of each machine's last comparison.
pub fn register_metrics(
    registry: &mut prometheus_client::registry::Registry,
    watch: &MachineWatch,
) {
    use prometheus_client::metrics::counter::Counter;
    use prometheus_client::metrics::family::Family;
    use prometheus_client::metrics::gauge::Gauge;
    type Labels = Vec<(String, String)>;
    let comparisons = Family::<Labels, Counter>::default();
    let changes = Family::<Labels, Counter>::default();
    let failed = Family::<Labels, Counter>::default();
    let significant = Family::<Labels, Gauge>::default();
    for (key, c) in watch.counts() {
        let labels = vec![("machine".to_owned(), c.name), ("key".to_owned(), key)];
        comparisons.get_or_create(&labels).inc_by(c.comparisons);
        changes.get_or_create(&labels).inc_by(c.changes);
        failed.get_or_create(&labels).inc_by(c.notifications_failed);
        significant
            .get_or_create(&labels)
            .set(c.last_significant as i64);
    }
    registry.register(
        "machine_comparisons",
        "Scheduled runs compared with the machine's previous run",
        comparisons,
    );
    registry.register(
        "machine_changes",
        "Scheduled runs that showed a significant change or a tolerance breach",
        changes,
    );
    registry.register(
        "machine_notifications_failed",
        "Machine-change notifications that could not be delivered",
        failed,
    );
    registry.register(
        "machine_significant_parameters",
        "Parameters that changed significantly in the machine's last comparison",
        significant,
    );
}

impl super::jobs::Daemon {
    /// The history check after a run job succeeded: scheduled runs only (a run submitted by
    /// hand is the user's own comparison to make). Its failure is logged, never the job's.
    pub(super) fn check_machine(&self, job: &JobRecord) {
        if job.job_type != JobType::Run || !job.submitted_by.starts_with("schedule:") {
            return;
        }
        let checked = self
            .jobs()
            .map_err(|e| anyhow::anyhow!("{e}"))
            .and_then(|jobs| check_scheduled_run(jobs, job, &self.config.history, &self.machines));
        match checked {
            Ok(Some(change)) => {
                tracing::warn!(
                    job = job.id,
                    machine = change.machine,
                    significant = ?change.significant,
                    beyond_tolerance = ?change.exceeding_tolerance,
                    "history: the machine changed"
                );
                let _ = self.events.send(super::jobs::ServerEvent::MachineChange {
                    change: change.clone(),
                });
                if let Some(url) = &self.config.history.notify_url {
                    notify(url, &change, &self.machines);
                }
            }
            Ok(None) => {}
            Err(e) => tracing::warn!(job = job.id, "history: not compared: {e:#}"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A succeeded run job of machine `name` with `serial`, its folder under `root`.
    fn job(root: &Path, id: i64, name: &str, serial: &str) -> JobRecord {
        let dir = root.join(format!("job-{id}"));
        std::fs::create_dir_all(&dir).expect("job folder");
        std::fs::write(
            dir.join(crate::history::load::RESULTS_FILE),
            format!(
                r#"{{"format": "geocal-results/1", "kind": "hexapod", "session_id": "s{id}"}}"#
            ),
        )
        .expect("results");
        std::fs::write(
            dir.join("run-config.toml"),
            format!("kind = \"hexapod\"\n[machine]\nname = {name:?}\nserial = {serial:?}\n"),
        )
        .expect("config");
        JobRecord {
            id,
            job_type: JobType::Run,
            kind: "hexapod".into(),
            state: JobState::Succeeded,
            submitted_at: "2026-11-28T00:00:00Z".into(),
            started_at: None,
            finished_at: None,
            submitted_by: "127.0.0.1".into(),
            config_sha256: None,
            source_job: None,
            dir,
            error: None,
            progress_done: 0,
            progress_total: 0,
            resume: false,
            files: Vec::new(),
        }
    }

    #[test]
    fn a_shared_name_is_refused_naming_each_machines_key() {
        let root = tempfile::tempdir().expect("tempdir");
        let jobs = vec![
            job(root.path(), 1, "Bridge", "BR-1001"),
            job(root.path(), 2, "Bridge", "BR-1002"),
        ];
        let keys: Vec<String> = machines(jobs.clone()).into_iter().map(|m| m.key).collect();
        assert_eq!(keys.len(), 2);
        for answer in [
            history(jobs.clone(), "Bridge").map(|_| ()),
            trend(jobs.clone(), "Bridge", &HistoryConfig::default()).map(|_| ()),
        ] {
            match answer {
                Err(MachineError::Ambiguous(message)) => {
                    for key in &keys {
                        assert!(message.contains(key.as_str()), "{message}");
                    }
                }
                other => panic!("expected the shared name refused, got {other:?}"),
            }
        }
        let one = history(jobs.clone(), &keys[1]).expect("by key");
        assert_eq!((one.key.as_str(), one.runs.len()), (keys[1].as_str(), 1));
        assert_eq!(
            history(jobs.clone(), "BR-1001").expect("by serial").runs[0].job,
            1
        );
        assert!(matches!(
            history(jobs, "Mill"),
            Err(MachineError::NoMachine(_))
        ));
    }
}
