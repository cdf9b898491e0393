//! Schedules: cron expressions in a time zone that submit a named plan. A pure, clock-driven
//! scheduler: the daemon feeds it the time, the tests a virtual clock.

use std::path::{Path, PathBuf};
use std::str::FromStr;

use chrono::{DateTime, Utc};
use chrono_tz::Tz;
use croner::parser::{CronParser, Seconds};
use croner::Cron;
use serde::Deserialize;

/// `[[schedule]]` in the daemon's configuration.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScheduleConfig {
    pub name: String,
    /// Five fields (minute hour day-of-month month day-of-week, as crontab), or six with
    /// seconds first.
    pub cron: String,
    /// The plan configuration it submits (relative to the daemon's configuration file).
    pub plan: PathBuf,
    /// IANA zone the expression is read in (default: the machine's zone).
    #[serde(default)]
    pub time_zone: Option<String>,
    #[serde(default)]
    pub when_busy: WhenBusy,
}

/// What a schedule does when it fires while a job runs or waits.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum WhenBusy {
    /// Submit anyway: the job waits in the queue until the running one has ended.
    #[default]
    Queue,
    /// Do not submit; log why.
    Skip,
}

/// What to do about one firing.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Decision {
    Submit,
    Skip { reason: String },
}

#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Firing {
    pub schedule: String,
    pub plan: PathBuf,
    /// The occurrence that fired.
    pub at: DateTime<Utc>,
    pub decision: Decision,
}

struct Schedule {
    name: String,
    cron: Cron,
    zone: Tz,
    plan: PathBuf,
    when_busy: WhenBusy,
    next: Option<DateTime<Utc>>,
}

pub struct Scheduler {
    schedules: Vec<Schedule>,
}

/// The machine's IANA time zone, UTC when it cannot be told.
pub fn local_zone() -> Tz {
    iana_time_zone::get_timezone()
        .ok()
        .and_then(|name| Tz::from_str(&name).ok())
        .unwrap_or(Tz::UTC)
}

fn next_after(cron: &Cron, zone: Tz, after: DateTime<Utc>) -> Option<DateTime<Utc>> {
    cron.find_next_occurrence(&after.with_timezone(&zone), false)
        .ok()
        .map(|t| t.with_timezone(&Utc))
}

impl Scheduler {
    /// Check every schedule (expression, zone, plan file) and find its first occurrence after
    /// `now`. Errors name the key (`schedule[i].cron`) and what was expected; plans are
    /// resolved against `base_dir`.
    pub fn new(
        configs: &[ScheduleConfig],
        base_dir: &Path,
        now: DateTime<Utc>,
    ) -> anyhow::Result<Scheduler> {
        let parser = CronParser::builder().seconds(Seconds::Optional).build();
        let mut schedules = Vec::new();
        for (i, config) in configs.iter().enumerate() {
            let key = |field: &str| format!("schedule[{i}].{field} (\"{}\")", config.name);
            let cron = parser.parse(&config.cron).map_err(|e| {
                anyhow::anyhow!(
                    "{}: \"{}\" is not a cron expression ({e}); expected five fields \
                     (minute hour day-of-month month day-of-week) or six with seconds first",
                    key("cron"),
                    config.cron
                )
            })?;
            let zone = match &config.time_zone {
                Some(name) => Tz::from_str(name).map_err(|_| {
                    anyhow::anyhow!(
                        "{}: \"{name}\" is not an IANA time zone (e.g. \"Europe/Berlin\")",
                        key("time_zone")
                    )
                })?,
                None => local_zone(),
            };
            let plan = base_dir.join(&config.plan);
            if !plan.is_file() {
                anyhow::bail!(
                    "{}: no plan configuration at {}",
                    key("plan"),
                    plan.display()
                );
            }
            if configs[..i].iter().any(|c| c.name == config.name) {
                anyhow::bail!("{}: the name is used twice", key("name"));
            }
            let next = next_after(&cron, zone, now);
            schedules.push(Schedule {
                name: config.name.clone(),
                cron,
                zone,
                plan,
                when_busy: config.when_busy,
                next,
            });
        }
        Ok(Scheduler { schedules })
    }

    pub fn is_empty(&self) -> bool {
        self.schedules.is_empty()
    }

    /// The schedules whose occurrence has come by `now`, each at most once (occurrences
    /// missed while the daemon was down or busy are not made up), and what to do given
    /// whether a job runs or waits (`busy`).
    pub fn due(&mut self, now: DateTime<Utc>, busy: Option<&str>) -> Vec<Firing> {
        let mut firings = Vec::new();
        for schedule in &mut self.schedules {
            let Some(at) = schedule.next.filter(|next| *next <= now) else {
                continue;
            };
            schedule.next = next_after(&schedule.cron, schedule.zone, now);
            let decision = match (schedule.when_busy, busy) {
                (WhenBusy::Skip, Some(what)) => Decision::Skip {
                    reason: format!("{what}; the schedule skips when busy"),
                },
                _ => Decision::Submit,
            };
            firings.push(Firing {
                schedule: schedule.name.clone(),
                plan: schedule.plan.clone(),
                at,
                decision,
            });
        }
        firings
    }

    /// The next occurrence of every schedule (name, time).
    pub fn upcoming(&self) -> Vec<(String, Option<DateTime<Utc>>)> {
        self.schedules
            .iter()
            .map(|s| (s.name.clone(), s.next))
            .collect()
    }
}

/// A schedule as the API shows it: what runs when, its next run and its last job.
#[derive(Debug, Clone, PartialEq, serde::Serialize, Deserialize, utoipa::ToSchema)]
pub struct ScheduleView {
    pub name: String,
    pub cron: String,
    /// The IANA zone the expression is read in.
    pub time_zone: String,
    /// `queue` or `skip`.
    pub when_busy: String,
    /// The plan file it submits, as configured.
    pub plan: String,
    /// RFC 3339 UTC; none when the expression never comes due again.
    pub next_run: Option<String>,
    /// Its newest job, when it submitted one.
    pub last_job: Option<ScheduledJob>,
}

/// The last job a schedule submitted.
#[derive(Debug, Clone, PartialEq, serde::Serialize, Deserialize, utoipa::ToSchema)]
pub struct ScheduledJob {
    pub id: i64,
    pub state: crate::serve::catalog::JobState,
    pub submitted_at: String,
    pub finished_at: Option<String>,
    pub error: Option<String>,
}

/// Every configured schedule with its next occurrence after `now` and its newest job among
/// `jobs` (submitted by `schedule:<name>`).
pub fn overview(
    configs: &[ScheduleConfig],
    base_dir: &Path,
    now: DateTime<Utc>,
    jobs: &[crate::serve::catalog::JobRecord],
) -> Vec<ScheduleView> {
    let upcoming = Scheduler::new(configs, base_dir, now)
        .map(|s| s.upcoming())
        .unwrap_or_default();
    configs
        .iter()
        .map(|config| {
            let by = format!("schedule:{}", config.name);
            let last_job = jobs
                .iter()
                .filter(|job| job.submitted_by == by)
                .max_by_key(|job| job.id)
                .map(|job| ScheduledJob {
                    id: job.id,
                    state: job.state,
                    submitted_at: job.submitted_at.clone(),
                    finished_at: job.finished_at.clone(),
                    error: job.error.clone(),
                });
            ScheduleView {
                name: config.name.clone(),
                cron: config.cron.clone(),
                time_zone: config
                    .time_zone
                    .clone()
                    .unwrap_or_else(|| local_zone().name().to_owned()),
                when_busy: match config.when_busy {
                    WhenBusy::Queue => "queue",
                    WhenBusy::Skip => "skip",
                }
                .to_owned(),
                plan: config.plan.display().to_string(),
                next_run: upcoming
                    .iter()
                    .find(|(name, _)| *name == config.name)
                    .and_then(|(_, next)| *next)
                    .map(|t| t.to_rfc3339_opts(chrono::SecondsFormat::Secs, true)),
                last_job,
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use chrono::TimeZone;

    fn config(name: &str, cron: &str, zone: &str, when_busy: WhenBusy) -> ScheduleConfig {
        ScheduleConfig {
            name: name.into(),
            cron: cron.into(),
            plan: "plan.toml".into(),
            time_zone: Some(zone.into()),
            when_busy,
        }
    }

    fn plan_dir() -> tempfile::TempDir {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("plan.toml"), "kind = \"multilateration\"\n").unwrap();
        dir
    }

    /// Every firing from `start` for `hours`, the virtual clock stepping by `step_s`.
    fn run(
        scheduler: &mut Scheduler,
        start: DateTime<Utc>,
        hours: i64,
        step_s: i64,
    ) -> Vec<Firing> {
        let mut firings = Vec::new();
        let mut now = start;
        while now < start + chrono::Duration::hours(hours) {
            now += chrono::Duration::seconds(step_s);
            firings.extend(scheduler.due(now, None));
        }
        firings
    }

    #[test]
    fn a_nightly_schedule_fires_once_a_night_at_its_local_time() {
        let dir = plan_dir();
        let start = Utc.with_ymd_and_hms(2026, 11, 24, 0, 0, 0).unwrap();
        let nightly = config("nightly", "30 2 * * *", "Europe/Berlin", WhenBusy::Queue);
        let mut scheduler = Scheduler::new(&[nightly], dir.path(), start).unwrap();
        let firings = run(&mut scheduler, start, 72, 60);
        let times: Vec<String> = firings.iter().map(|f| f.at.to_rfc3339()).collect();
        // 02:30 in Berlin is 01:30 UTC in winter (CET, UTC+1).
        assert_eq!(
            times,
            [
                "2026-11-24T01:30:00+00:00",
                "2026-11-25T01:30:00+00:00",
                "2026-11-26T01:30:00+00:00"
            ]
        );
        assert!(firings.iter().all(|f| f.decision == Decision::Submit));
        assert!(firings[0].plan.ends_with("plan.toml"));
    }

    #[test]
    fn daylight_saving_changes_move_the_firing_in_utc_and_never_double_it() {
        let dir = plan_dir();
        // Berlin goes to CEST on 2026-03-29 (02:00 -> 03:00) and back on 2026-10-25
        // (03:00 -> 02:00, so 02:30 happens twice).
        let spring = Utc.with_ymd_and_hms(2026, 3, 27, 12, 0, 0).unwrap();
        let daily = config("daily", "0 9 * * *", "Europe/Berlin", WhenBusy::Queue);
        let mut scheduler = Scheduler::new(&[daily], dir.path(), spring).unwrap();
        let times: Vec<String> = run(&mut scheduler, spring, 72, 60)
            .iter()
            .map(|f| f.at.to_rfc3339())
            .collect();
        assert_eq!(
            times,
            [
                "2026-03-28T08:00:00+00:00",
                "2026-03-29T07:00:00+00:00",
                "2026-03-30T07:00:00+00:00"
            ]
        );
        let autumn = Utc.with_ymd_and_hms(2026, 10, 24, 12, 0, 0).unwrap();
        let twice = config("twice", "30 2 * * *", "Europe/Berlin", WhenBusy::Queue);
        let mut scheduler = Scheduler::new(&[twice], dir.path(), autumn).unwrap();
        let on_the_day: Vec<Firing> = run(&mut scheduler, autumn, 36, 60)
            .into_iter()
            .filter(|f| {
                f.at.with_timezone(&Tz::Europe__Berlin)
                    .date_naive()
                    .to_string()
                    == "2026-10-25"
            })
            .collect();
        assert_eq!(on_the_day.len(), 1, "{on_the_day:?}");
    }

    #[test]
    fn a_busy_daemon_queues_or_skips_as_configured() {
        let dir = plan_dir();
        let start = Utc.with_ymd_and_hms(2026, 11, 24, 0, 0, 0).unwrap();
        let mut scheduler = Scheduler::new(
            &[
                config("queues", "0 * * * *", "UTC", WhenBusy::Queue),
                config("skips", "0 * * * *", "UTC", WhenBusy::Skip),
            ],
            dir.path(),
            start,
        )
        .unwrap();
        let firings = scheduler.due(
            start + chrono::Duration::minutes(61),
            Some("job 7 is running"),
        );
        assert_eq!(firings.len(), 2);
        assert_eq!(firings[0].decision, Decision::Submit);
        assert_eq!(
            firings[1].decision,
            Decision::Skip {
                reason: "job 7 is running; the schedule skips when busy".into()
            }
        );
        // A daemon that was down for three hours fires once, not three times.
        let later = scheduler.due(start + chrono::Duration::minutes(240), None);
        assert_eq!(later.len(), 2);
        assert!(later.iter().all(|f| f.decision == Decision::Submit));
        assert!(scheduler
            .due(start + chrono::Duration::minutes(241), None)
            .is_empty());
    }

    #[test]
    fn six_fields_fire_by_the_second() {
        let dir = plan_dir();
        let start = Utc.with_ymd_and_hms(2026, 11, 24, 0, 0, 0).unwrap();
        let mut scheduler = Scheduler::new(
            &[config("fast", "*/10 * * * * *", "UTC", WhenBusy::Queue)],
            dir.path(),
            start,
        )
        .unwrap();
        let mut firings = Vec::new();
        for s in 1..=60 {
            firings.extend(scheduler.due(start + chrono::Duration::seconds(s), None));
        }
        assert_eq!(firings.len(), 6);
    }

    #[test]
    fn bad_schedules_name_their_key() {
        let dir = plan_dir();
        let now = Utc::now();
        let err = |c: ScheduleConfig| {
            Scheduler::new(&[c], dir.path(), now)
                .err()
                .map(|e| e.to_string())
                .unwrap_or_default()
        };
        let bad_cron = err(config("n", "61 * * * *", "UTC", WhenBusy::Queue));
        assert!(
            bad_cron.contains("schedule[0].cron") && bad_cron.contains("61 * * * *"),
            "{bad_cron}"
        );
        let bad_zone = err(config("n", "0 * * * *", "Mars/Olympus", WhenBusy::Queue));
        assert!(
            bad_zone.contains("schedule[0].time_zone") && bad_zone.contains("IANA"),
            "{bad_zone}"
        );
        let mut missing = config("n", "0 * * * *", "UTC", WhenBusy::Queue);
        missing.plan = "nowhere.toml".into();
        assert!(err(missing).contains("schedule[0].plan"));
        let parsed: Result<ScheduleConfig, _> = toml::from_str(
            "name = \"n\"\ncron = \"0 * * * *\"\nplan = \"p\"\nwhen_busy = \"later\"\n",
        );
        assert!(parsed.is_err());
    }
}
