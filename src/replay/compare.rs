//! How a replay compares with its recording: the dwell windows each holds (the samples point
//! extraction sees), faults and re-homings by kind, and the difference of the solved results.

use std::collections::BTreeMap;

use serde::Serialize;

use super::stream::Mark;
use crate::session::messages::RunEvent;
use crate::session::reader::{Session, Stamped};

/// One closed dwell window (`point_begin` .. `point_end`) and the tracer samples inside it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct Window {
    pub station: String,
    pub point: usize,
    pub pass: usize,
    pub target: String,
    pub samples: usize,
    pub first_seq: Option<u64>,
    pub last_seq: Option<u64>,
}

impl std::fmt::Display for Window {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "station {} point {} pass {} target {}: {} samples, seq {:?}..{:?}",
            self.station,
            self.point,
            self.pass,
            self.target,
            self.samples,
            self.first_seq,
            self.last_seq
        )
    }
}

/// The closed windows of a session's tracer, in order (samples with begin <= log time <= end,
/// as point extraction takes them).
pub fn windows(session: &Session, tracer_id: &str) -> Vec<Window> {
    let samples = session
        .tracers
        .get(tracer_id)
        .map(Vec::as_slice)
        .unwrap_or(&[]);
    windows_with(&session.events, |begin, end| {
        let begin_ns = session.events[begin].log_time_ns;
        let end_ns = session.events[end].log_time_ns;
        let from = samples.partition_point(|x| x.log_time_ns < begin_ns);
        let to = samples
            .partition_point(|x| x.log_time_ns <= end_ns)
            .max(from);
        let inside = &samples[from..to];
        (
            inside.len(),
            inside.first().map(|x| x.msg.seq),
            inside.last().map(|x| x.msg.seq),
        )
    })
}

/// `windows` of a streamed session: its events with their marks among the tracer's samples
/// (`stream::EventMarks`).
pub fn windows_marked(events: &[Stamped<RunEvent>], marks: &[Mark]) -> Vec<Window> {
    windows_with(events, |begin, end| {
        let (b, e) = (marks[begin], marks[end]);
        let (from, to) = (b.before, e.at_or_before.max(b.before));
        if to == from {
            (0, None, None)
        } else {
            (to - from, b.first_seq_from, e.last_seq_to)
        }
    })
}

/// The windows of `events`; `inside(begin, end)` counts the samples between the events at
/// these indices and gives the first and last one's seq.
fn windows_with(
    events: &[Stamped<RunEvent>],
    inside: impl Fn(usize, usize) -> (usize, Option<u64>, Option<u64>),
) -> Vec<Window> {
    let mut out = Vec::new();
    let mut open: Option<(usize, &RunEvent)> = None;
    for (k, event) in events.iter().enumerate() {
        match &event.msg {
            RunEvent::PointBegin { .. } => open = Some((k, &event.msg)),
            RunEvent::Rehome { .. } => open = None,
            RunEvent::PointEnd {
                station,
                point,
                pass,
            } => {
                let Some((
                    begin,
                    RunEvent::PointBegin {
                        station: s,
                        point: p,
                        pass: q,
                        target,
                        ..
                    },
                )) = open.take()
                else {
                    continue;
                };
                if (s, p, q) != (station, point, pass) {
                    continue;
                }
                let (samples, first_seq, last_seq) = inside(begin, k);
                out.push(Window {
                    station: station.to_string(),
                    point: *point,
                    pass: *pass,
                    target: target.to_string(),
                    samples,
                    first_seq,
                    last_seq,
                });
            }
            _ => {}
        }
    }
    out
}

/// Count of `fault` events by code, and of `rehome` events under "rehome".
pub fn event_counts(session: &Session) -> BTreeMap<String, usize> {
    event_counts_of(&session.events)
}

/// `event_counts` of a list of events.
pub fn event_counts_of(events: &[Stamped<RunEvent>]) -> BTreeMap<String, usize> {
    let mut counts = BTreeMap::new();
    for event in events {
        let key = match &event.msg {
            RunEvent::Fault { code, .. } => format!("fault:{code}"),
            RunEvent::Rehome { .. } => "rehome".to_string(),
            _ => continue,
        };
        *counts.entry(key).or_insert(0) += 1;
    }
    counts
}

#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct WindowComparison {
    pub recorded: usize,
    pub replayed: usize,
    /// Windows equal in order: same station, point, pass, target and the same samples.
    pub identical: usize,
    /// The first window that differs (or is missing on one side), described.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub first_difference: Option<String>,
}

pub fn compare_windows(recorded: &[Window], replayed: &[Window]) -> WindowComparison {
    let identical = recorded
        .iter()
        .zip(replayed)
        .filter(|(a, b)| a == b)
        .count();
    let first_difference = recorded
        .iter()
        .zip(replayed)
        .enumerate()
        .find(|(_, (a, b))| a != b)
        .map(|(i, (a, b))| format!("window {i}: recorded {a}; replayed {b}"))
        .or_else(|| match recorded.len().cmp(&replayed.len()) {
            std::cmp::Ordering::Greater => Some(format!(
                "window {}: recorded {}; not replayed",
                replayed.len(),
                recorded[replayed.len()]
            )),
            std::cmp::Ordering::Less => Some(format!(
                "window {}: replayed {}; not in the recording",
                recorded.len(),
                replayed[recorded.len()]
            )),
            std::cmp::Ordering::Equal => None,
        });
    WindowComparison {
        recorded: recorded.len(),
        replayed: replayed.len(),
        identical,
        first_difference,
    }
}

/// The difference between two results objects (geocal-results/1 JSON).
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct ResultsDifference {
    /// The two results are equal (apart from `session_id`).
    pub identical: bool,
    /// Numbers compared at equal paths.
    pub values_compared: usize,
    /// Numbers that differ, and paths present on one side only or of another type.
    pub values_differing: usize,
    /// Largest |difference| over numbers whose key ends in `_m` (metres).
    pub max_abs_difference_m: f64,
    /// Path of that largest difference.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_at: Option<String>,
}

/// `session_id` is left out: a replay's is the recording's with `-replay` appended.
pub fn results_difference(a: &serde_json::Value, b: &serde_json::Value) -> ResultsDifference {
    let without_id = |v: &serde_json::Value| {
        let mut v = v.clone();
        if let Some(o) = v.as_object_mut() {
            o.remove("session_id");
        }
        v
    };
    let (a, b) = (without_id(a), without_id(b));
    let mut d = ResultsDifference {
        identical: a == b,
        ..Default::default()
    };
    walk(&a, &b, "", false, &mut d);
    d
}

fn walk(
    a: &serde_json::Value,
    b: &serde_json::Value,
    path: &str,
    metres: bool,
    d: &mut ResultsDifference,
) {
    use serde_json::Value;
    match (a, b) {
        (Value::Object(x), Value::Object(y)) => {
            for (k, v) in x {
                let p = format!("{path}/{k}");
                match y.get(k) {
                    Some(w) => walk(v, w, &p, k.ends_with("_m"), d),
                    None => d.values_differing += 1,
                }
            }
            d.values_differing += y.keys().filter(|k| !x.contains_key(*k)).count();
        }
        (Value::Array(x), Value::Array(y)) => {
            for (i, (v, w)) in x.iter().zip(y).enumerate() {
                walk(v, w, &format!("{path}/{i}"), metres, d);
            }
            d.values_differing += x.len().abs_diff(y.len());
        }
        (Value::Number(x), Value::Number(y)) => {
            d.values_compared += 1;
            let (x, y) = (
                x.as_f64().unwrap_or(f64::NAN),
                y.as_f64().unwrap_or(f64::NAN),
            );
            if x != y {
                d.values_differing += 1;
                let diff = (x - y).abs();
                // A NaN difference counts as the largest.
                if metres && (diff.is_nan() || diff > d.max_abs_difference_m) {
                    d.max_abs_difference_m = diff;
                    d.max_at = Some(path.to_string());
                }
            }
        }
        (x, y) if x == y => {}
        _ => d.values_differing += 1,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn differences_are_found_by_path() {
        let a = json!({"points": [{"actual_m": [1.0, 2.0, 3.0], "samples": 5}], "kind": "x"});
        let b = json!({"points": [{"actual_m": [1.0, 2.5, 3.0], "samples": 6}], "kind": "x"});
        let d = results_difference(&a, &b);
        assert!(!d.identical);
        assert_eq!(d.values_compared, 4);
        assert_eq!(d.values_differing, 2);
        assert_eq!(d.max_abs_difference_m, 0.5);
        assert_eq!(d.max_at.as_deref(), Some("/points/0/actual_m/1"));
        let same = results_difference(&a, &a);
        assert!(same.identical);
        assert_eq!(same.values_differing, 0);
    }

    #[test]
    fn a_missing_window_is_named() {
        let w = |point| Window {
            station: "s1".into(),
            point,
            pass: 0,
            target: "t0".into(),
            samples: 10,
            first_seq: Some(1),
            last_seq: Some(10),
        };
        let c = compare_windows(&[w(0), w(1)], &[w(0)]);
        assert_eq!((c.recorded, c.replayed, c.identical), (2, 1, 1));
        assert!(c
            .first_difference
            .is_some_and(|s| s.contains("window 1") && s.contains("not replayed")));
    }
}
