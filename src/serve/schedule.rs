//! Scheduled jobs of the daemon (`[[schedule]]` in its configuration) and the pure,
//! clock-driven `Scheduler` that decides which of them to submit now.
//!
//! Cron syntax: six fields, seconds first — `sec min hour day-of-month month day-of-week`
//! (e.g. `0 30 2 * * *` is 02:30:00 every day), evaluated in the schedule's IANA time zone.
//! Firings missed while the daemon was down are not replayed: the scheduler only looks at
//! firings after the moment it was created.

use std::path::PathBuf;

use chrono::{DateTime, Utc};
use chrono_tz::Tz;
use croner::parser::{CronParser, Seconds};
use croner::Cron;
use serde::Deserialize;

/// What a schedule does when it fires while a job runs.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum WhenBusy {
    /// Wait until no job runs, then submit (once, however many firings were held).
    #[default]
    Queue,
    /// Drop this firing (logged with the reason).
    Skip,
}

/// One `[[schedule]]` entry as written.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct ScheduleSpec {
    name: String,
    cron: String,
    plan: PathBuf,
    #[serde(default)]
    time_zone: Option<String>,
    #[serde(default)]
    when_busy: WhenBusy,
}

/// A parsed, validated schedule.
#[derive(Debug, Clone)]
pub struct Schedule {
    pub name: String,
    pub cron: Cron,
    pub plan: PathBuf,
    pub time_zone: Tz,
    pub when_busy: WhenBusy,
}

/// The schedule `[[schedule]]` entry `index` could not be read.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("schedule[{index}]{name}: {message}")]
pub struct ScheduleError {
    pub index: usize,
    /// ` ("nightly")` when the entry has a name, else empty.
    name: String,
    pub message: String,
}

impl ScheduleError {
    fn new(index: usize, name: Option<&str>, message: String) -> ScheduleError {
        ScheduleError {
            index,
            name: name.map(|n| format!(" (\"{n}\")")).unwrap_or_default(),
            message,
        }
    }
}

const CRON_EXPECTED: &str = "six fields `sec min hour day-of-month month day-of-week`, \
     e.g. \"0 30 2 * * *\" for 02:30:00 daily";

impl Schedule {
    /// Parse entry `index` of the daemon configuration's `schedule` array.
    pub fn from_value(index: usize, value: &toml::Value) -> Result<Schedule, ScheduleError> {
        let name = value.get("name").and_then(|n| n.as_str());
        let spec: ScheduleSpec = serde_path_to_error::deserialize(value.clone()).map_err(|e| {
            let path = e.path().to_string();
            let at = if path == "." {
                String::new()
            } else {
                format!("key `{path}`: ")
            };
            ScheduleError::new(index, name, format!("{at}{}", e.inner()))
        })?;
        let name = Some(spec.name.as_str());
        if spec.name.trim().is_empty() {
            return Err(ScheduleError::new(
                index,
                None,
                "key `name`: expected a non-empty name".into(),
            ));
        }
        let cron = parse_cron(&spec.cron)
            .map_err(|m| ScheduleError::new(index, name, format!("key `cron`: {m}")))?;
        let time_zone = match &spec.time_zone {
            Some(zone) => zone.parse::<Tz>().map_err(|_| {
                ScheduleError::new(
                    index,
                    name,
                    format!(
                        "key `time_zone`: unknown zone {zone:?}; expected an IANA time zone \
                         name such as \"Europe/Berlin\" or \"UTC\""
                    ),
                )
            })?,
            None => local_zone(),
        };
        Ok(Schedule {
            name: spec.name,
            cron,
            plan: spec.plan,
            time_zone,
            when_busy: spec.when_busy,
        })
    }

    /// The latest firing at or before `now`, if any.
    pub fn latest_at_or_before(&self, now: DateTime<Utc>) -> Option<DateTime<Utc>> {
        let local = now.with_timezone(&self.time_zone);
        self.cron
            .find_previous_occurrence(&local, true)
            .ok()
            .map(|t| t.with_timezone(&Utc))
    }

    /// The first firing strictly after `after`, if any.
    pub fn next_after(&self, after: DateTime<Utc>) -> Option<DateTime<Utc>> {
        let local = after.with_timezone(&self.time_zone);
        self.cron
            .find_next_occurrence(&local, false)
            .ok()
            .map(|t| t.with_timezone(&Utc))
    }
}

/// Parse every entry of the configuration's `schedule` array; names must be unique.
pub fn parse_schedules(values: &[toml::Value]) -> Result<Vec<Schedule>, ScheduleError> {
    let mut schedules: Vec<Schedule> = Vec::with_capacity(values.len());
    for (index, value) in values.iter().enumerate() {
        let schedule = Schedule::from_value(index, value)?;
        if schedules.iter().any(|s| s.name == schedule.name) {
            return Err(ScheduleError::new(
                index,
                Some(&schedule.name),
                "key `name`: another schedule already has this name; expected unique names".into(),
            ));
        }
        schedules.push(schedule);
    }
    Ok(schedules)
}

fn parse_cron(expression: &str) -> Result<Cron, String> {
    let fields = expression.split_whitespace().count();
    if fields != 6 {
        return Err(format!(
            "{expression:?} has {fields} field(s); expected {CRON_EXPECTED}"
        ));
    }
    let cron = CronParser::builder()
        .seconds(Seconds::Required)
        .build()
        .parse(expression)
        .map_err(|e| {
            format!("{expression:?} is not a valid cron expression ({e}); expected {CRON_EXPECTED}")
        })?;
    // Patterns such as the 30th of February parse but never fire.
    let probe = Utc::now();
    if cron.find_next_occurrence(&probe, false).is_err() {
        return Err(format!(
            "{expression:?} never fires; expected {CRON_EXPECTED}"
        ));
    }
    Ok(cron)
}

/// The machine's zone, or UTC (logged) when it cannot be read or is not an IANA name.
fn local_zone() -> Tz {
    match iana_time_zone::get_timezone() {
        Ok(name) => name.parse::<Tz>().unwrap_or_else(|_| {
            tracing::warn!(zone = %name, "the machine's time zone is not an IANA name; schedules without time_zone use UTC");
            Tz::UTC
        }),
        Err(e) => {
            tracing::warn!("cannot read the machine's time zone ({e}); schedules without time_zone use UTC");
            Tz::UTC
        }
    }
}

/// Where the scheduler's "now" comes from: the system clock in the daemon, a virtual one in
/// tests.
pub trait Clock {
    fn now(&self) -> DateTime<Utc>;
}

pub struct SystemClock;

impl Clock for SystemClock {
    fn now(&self) -> DateTime<Utc> {
        Utc::now()
    }
}

/// What to do with one firing of a schedule.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Decision {
    /// Submit the schedule's plan as a job now.
    Submit {
        schedule: String,
        plan: PathBuf,
        due: DateTime<Utc>,
    },
    /// Held until no job runs (`when_busy = "queue"`).
    Queued {
        schedule: String,
        due: DateTime<Utc>,
    },
    /// Dropped (`when_busy = "skip"`).
    Skip {
        schedule: String,
        due: DateTime<Utc>,
        reason: String,
    },
}

/// Decides, each time it is evaluated, which schedules fired since the last evaluation and
/// whether to submit, queue or skip them. It never sleeps: the caller feeds it "now".
#[derive(Debug)]
pub struct Scheduler {
    schedules: Vec<Schedule>,
    /// Firings up to and including this instant are dealt with.
    last: DateTime<Utc>,
    /// (schedule index, first held firing), oldest first; one entry per schedule.
    queued: Vec<(usize, DateTime<Utc>)>,
}

impl Scheduler {
    /// A scheduler that considers firings after `start` only (missed ones are not replayed).
    pub fn new(schedules: Vec<Schedule>, start: DateTime<Utc>) -> Scheduler {
        Scheduler {
            schedules,
            last: start,
            queued: Vec::new(),
        }
    }

    pub fn schedules(&self) -> &[Schedule] {
        &self.schedules
    }

    /// Evaluate at the clock's now.
    pub fn evaluate_with(&mut self, clock: &dyn Clock, job_running: bool) -> Vec<Decision> {
        self.evaluate(clock.now(), job_running)
    }

    /// The decisions for firings in (last evaluation, `now`], at most one per schedule
    /// (several firings since the last evaluation count as one, at the latest), plus held
    /// ones. At most one `Submit`: a scheduled job never starts while another runs, so after
    /// it the rest see a busy daemon. A `now` earlier than the last evaluation (the clock
    /// stepped back) fires nothing.
    pub fn evaluate(&mut self, now: DateTime<Utc>, job_running: bool) -> Vec<Decision> {
        let mut decisions = Vec::new();
        let mut busy = job_running;
        if now <= self.last {
            return decisions;
        }

        if !busy && !self.queued.is_empty() {
            let (index, due) = self.queued.remove(0);
            decisions.push(self.submit(index, due));
            busy = true;
        }

        let mut due_now: Vec<(usize, DateTime<Utc>)> = self
            .schedules
            .iter()
            .enumerate()
            .filter_map(|(i, s)| {
                s.latest_at_or_before(now)
                    .filter(|t| *t > self.last)
                    .map(|t| (i, t))
            })
            .collect();
        due_now.sort_by_key(|&(i, t)| (t, i));
        for (index, due) in due_now {
            if !busy {
                decisions.push(self.submit(index, due));
                busy = true;
                continue;
            }
            let schedule = &self.schedules[index];
            match schedule.when_busy {
                WhenBusy::Queue => {
                    if !self.queued.iter().any(|&(i, _)| i == index) {
                        self.queued.push((index, due));
                    }
                    decisions.push(Decision::Queued {
                        schedule: schedule.name.clone(),
                        due,
                    });
                }
                WhenBusy::Skip => decisions.push(Decision::Skip {
                    schedule: schedule.name.clone(),
                    due,
                    reason: "another job is running (when_busy = \"skip\")".into(),
                }),
            }
        }
        self.last = now;
        for decision in &decisions {
            log(decision);
        }
        decisions
    }

    /// The next instant at which `evaluate` could return something new (held jobs aside).
    pub fn next_due(&self) -> Option<DateTime<Utc>> {
        self.schedules
            .iter()
            .filter_map(|s| s.next_after(self.last))
            .min()
    }

    /// Schedules held until the running job ends, oldest first.
    pub fn queued(&self) -> Vec<&str> {
        self.queued
            .iter()
            .map(|&(i, _)| self.schedules[i].name.as_str())
            .collect()
    }

    fn submit(&self, index: usize, due: DateTime<Utc>) -> Decision {
        let schedule = &self.schedules[index];
        Decision::Submit {
            schedule: schedule.name.clone(),
            plan: schedule.plan.clone(),
            due,
        }
    }
}

fn log(decision: &Decision) {
    match decision {
        Decision::Submit { schedule, due, .. } => {
            tracing::info!(%schedule, %due, "schedule fired: submitting its job")
        }
        Decision::Queued { schedule, due } => {
            tracing::info!(%schedule, %due, "schedule fired while a job runs: queued")
        }
        Decision::Skip {
            schedule,
            due,
            reason,
        } => tracing::warn!(%schedule, %due, %reason, "schedule fired: skipped"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use chrono::TimeZone;

    fn schedule(toml_text: &str) -> Result<Schedule, ScheduleError> {
        let value: toml::Value = toml::from_str(toml_text).expect("test TOML");
        Schedule::from_value(0, &value)
    }

    fn utc(y: i32, mo: u32, d: u32, h: u32, mi: u32, s: u32) -> DateTime<Utc> {
        Utc.with_ymd_and_hms(y, mo, d, h, mi, s)
            .single()
            .expect("valid UTC time")
    }

    /// A virtual clock stepped by the test.
    struct Virtual(std::cell::Cell<DateTime<Utc>>);

    impl Clock for Virtual {
        fn now(&self) -> DateTime<Utc> {
            self.0.get()
        }
    }

    fn submits(decisions: &[Decision]) -> Vec<(String, DateTime<Utc>)> {
        decisions
            .iter()
            .filter_map(|d| match d {
                Decision::Submit { schedule, due, .. } => Some((schedule.clone(), *due)),
                _ => None,
            })
            .collect()
    }

    #[test]
    fn firings_across_a_day_once_each_at_their_time() {
        let s = schedule(
            r#"name = "every6h"
               cron = "0 15 */6 * * *"
               plan = "p.toml"
               time_zone = "UTC""#,
        )
        .unwrap();
        let start = utc(2026, 6, 1, 0, 0, 0);
        let mut scheduler = Scheduler::new(vec![s], start);
        let clock = Virtual(std::cell::Cell::new(start));
        let mut fired = Vec::new();
        // Evaluate every minute of a day.
        for minute in 1..=24 * 60 {
            clock.set_minutes(start, minute);
            fired.extend(submits(&scheduler.evaluate_with(&clock, false)));
        }
        let expected: Vec<_> = [0, 6, 12, 18]
            .iter()
            .map(|&h| ("every6h".to_string(), utc(2026, 6, 1, h, 15, 0)))
            .collect();
        assert_eq!(fired, expected);
    }

    impl Virtual {
        fn set_minutes(&self, start: DateTime<Utc>, minutes: i64) {
            self.0.set(start + chrono::Duration::minutes(minutes));
        }
    }

    #[test]
    fn several_firings_since_the_last_evaluation_count_once_and_missed_ones_are_not_replayed() {
        let s = schedule(
            r#"name = "hourly"
               cron = "0 0 * * * *"
               plan = "p.toml"
               time_zone = "UTC""#,
        )
        .unwrap();
        // The daemon starts at 10:30: the 10:00 firing (and earlier) is not replayed.
        let mut scheduler = Scheduler::new(vec![s], utc(2026, 6, 1, 10, 30, 0));
        assert!(scheduler
            .evaluate(utc(2026, 6, 1, 10, 59, 59), false)
            .is_empty());
        // Stalled until 13:10: 11:00, 12:00 and 13:00 are due, one job at the latest.
        let d = scheduler.evaluate(utc(2026, 6, 1, 13, 10, 0), false);
        assert_eq!(
            submits(&d),
            vec![("hourly".to_string(), utc(2026, 6, 1, 13, 0, 0))]
        );
        assert_eq!(d.len(), 1);
    }

    #[test]
    fn dst_changes_in_the_schedules_zone() {
        let s = schedule(
            r#"name = "nightly"
               cron = "0 30 2 * * *"
               plan = "p.toml"
               time_zone = "Europe/Berlin""#,
        )
        .unwrap();
        let berlin = chrono_tz::Europe::Berlin;
        // Spring forward, 2026-03-29: 02:00 CET becomes 03:00 CEST, so 02:30 does not exist.
        let start = utc(2026, 3, 27, 12, 0, 0);
        let mut scheduler = Scheduler::new(vec![s.clone()], start);
        let mut fired = Vec::new();
        for minute in 1..=4 * 24 * 60 {
            let now = start + chrono::Duration::minutes(minute);
            fired.extend(submits(&scheduler.evaluate(now, false)));
        }
        let local: Vec<String> = fired
            .iter()
            .map(|(_, t)| t.with_timezone(&berlin).format("%F %T %Z").to_string())
            .collect();
        assert_eq!(
            local,
            [
                "2026-03-28 02:30:00 CET",
                // In the gap a fixed-time job runs at the first valid time after it.
                "2026-03-29 03:00:00 CEST",
                "2026-03-30 02:30:00 CEST",
                "2026-03-31 02:30:00 CEST",
            ]
        );
        // Fall back, 2026-10-25: 03:00 CEST becomes 02:00 CET, so 02:30 happens twice; the
        // job runs once, at the first.
        let start = utc(2026, 10, 24, 12, 0, 0);
        let mut scheduler = Scheduler::new(vec![s], start);
        let mut fired = Vec::new();
        for minute in 1..=2 * 24 * 60 {
            let now = start + chrono::Duration::minutes(minute);
            fired.extend(submits(&scheduler.evaluate(now, false)));
        }
        let at: Vec<DateTime<Utc>> = fired.iter().map(|(_, t)| *t).collect();
        assert_eq!(
            at,
            [
                utc(2026, 10, 25, 0, 30, 0), // 02:30 CEST
                utc(2026, 10, 26, 1, 30, 0), // 02:30 CET
            ]
        );
    }

    #[test]
    fn queue_waits_for_the_running_job_and_skip_drops() {
        let queued = schedule(
            r#"name = "q"
               cron = "0 0 2 * * *"
               plan = "q.toml"
               time_zone = "UTC"
               when_busy = "queue""#,
        )
        .unwrap();
        let skipped = Schedule::from_value(
            1,
            &toml::from_str(
                r#"name = "s"
                   cron = "0 0 2 * * *"
                   plan = "s.toml"
                   time_zone = "UTC"
                   when_busy = "skip""#,
            )
            .unwrap(),
        )
        .unwrap();
        let mut scheduler = Scheduler::new(vec![queued, skipped], utc(2026, 6, 1, 0, 0, 0));
        let due = utc(2026, 6, 1, 2, 0, 0);
        // Both fire while a job runs.
        let d = scheduler.evaluate(utc(2026, 6, 1, 2, 0, 5), true);
        assert_eq!(
            d,
            vec![
                Decision::Queued {
                    schedule: "q".into(),
                    due
                },
                Decision::Skip {
                    schedule: "s".into(),
                    due,
                    reason: "another job is running (when_busy = \"skip\")".into()
                },
            ]
        );
        assert_eq!(scheduler.queued(), vec!["q"]);
        // Still busy: nothing starts.
        assert!(scheduler
            .evaluate(utc(2026, 6, 1, 2, 30, 0), true)
            .is_empty());
        // Idle: the held job is submitted, once.
        let d = scheduler.evaluate(utc(2026, 6, 1, 3, 0, 0), false);
        assert_eq!(
            d,
            vec![Decision::Submit {
                schedule: "q".into(),
                plan: "q.toml".into(),
                due
            }]
        );
        assert!(scheduler.queued().is_empty());
        assert!(scheduler
            .evaluate(utc(2026, 6, 1, 3, 1, 0), false)
            .is_empty());
    }

    #[test]
    fn two_schedules_due_together_never_start_two_jobs() {
        let a = schedule(
            r#"name = "a"
               cron = "0 0 2 * * *"
               plan = "a.toml"
               time_zone = "UTC""#,
        )
        .unwrap();
        let mut b = a.clone();
        b.name = "b".into();
        let mut scheduler = Scheduler::new(vec![a, b], utc(2026, 6, 1, 0, 0, 0));
        let d = scheduler.evaluate(utc(2026, 6, 1, 2, 0, 0), false);
        assert_eq!(submits(&d).len(), 1);
        assert!(matches!(&d[1], Decision::Queued { schedule, .. } if schedule == "b"));
        // The daemon now runs a's job; b waits for it.
        assert!(submits(&scheduler.evaluate(utc(2026, 6, 1, 2, 10, 0), true)).is_empty());
        assert_eq!(
            submits(&scheduler.evaluate(utc(2026, 6, 1, 2, 20, 0), false)),
            vec![("b".to_string(), utc(2026, 6, 1, 2, 0, 0))]
        );
    }

    #[test]
    fn bad_expressions_and_zones_name_the_key_and_what_was_expected() {
        let five = schedule(
            r#"name = "nightly"
               cron = "30 2 * * *"
               plan = "p.toml""#,
        )
        .unwrap_err()
        .to_string();
        assert_eq!(
            five,
            "schedule[0] (\"nightly\"): key `cron`: \"30 2 * * *\" has 5 field(s); expected \
             six fields `sec min hour day-of-month month day-of-week`, e.g. \"0 30 2 * * *\" \
             for 02:30:00 daily"
        );
        let bad = schedule(
            r#"name = "nightly"
               cron = "0 61 2 * * *"
               plan = "p.toml""#,
        )
        .unwrap_err()
        .to_string();
        assert!(
            bad.starts_with("schedule[0] (\"nightly\"): key `cron`: \"0 61 2 * * *\" is not a valid cron expression"),
            "{bad}"
        );
        let zone = schedule(
            r#"name = "nightly"
               cron = "0 30 2 * * *"
               plan = "p.toml"
               time_zone = "Europe/Atlantis""#,
        )
        .unwrap_err()
        .to_string();
        assert_eq!(
            zone,
            "schedule[0] (\"nightly\"): key `time_zone`: unknown zone \"Europe/Atlantis\"; \
             expected an IANA time zone name such as \"Europe/Berlin\" or \"UTC\""
        );
        let busy = schedule(
            r#"name = "nightly"
               cron = "0 30 2 * * *"
               plan = "p.toml"
               when_busy = "later""#,
        )
        .unwrap_err()
        .to_string();
        assert!(
            busy.starts_with("schedule[0] (\"nightly\"): key `when_busy`: unknown variant `later`"),
            "{busy}"
        );
        let unknown = schedule(
            r#"name = "nightly"
               cron = "0 30 2 * * *"
               plan = "p.toml"
               tz = "UTC""#,
        )
        .unwrap_err()
        .to_string();
        assert!(unknown.contains("unknown field `tz`"), "{unknown}");
        let never = schedule(
            r#"name = "never"
               cron = "0 0 0 30 2 *"
               plan = "p.toml""#,
        )
        .unwrap_err()
        .to_string();
        assert!(never.contains("never fires"), "{never}");
    }

    #[test]
    fn duplicate_names_are_refused() {
        let entry: toml::Value = toml::from_str(
            r#"name = "n"
               cron = "0 0 2 * * *"
               plan = "p.toml""#,
        )
        .unwrap();
        let e = parse_schedules(&[entry.clone(), entry]).unwrap_err();
        assert_eq!(e.index, 1);
        assert!(e.to_string().contains("already has this name"), "{e}");
    }
}
