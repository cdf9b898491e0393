//! What the daemon knows of the job that runs now and of the devices, fed by the recorder's
//! tap: progress, current station, last faults, each device's last reading and last error.

use std::collections::{BTreeMap, VecDeque};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde::Serialize;
use utoipa::ToSchema;

use crate::session::tap::{MessageTap, TappedMessage};

/// The last faults kept per running job.
const FAULTS_KEPT: usize = 10;
/// A device whose last reading is older than this is shown as not connected.
const CONNECTED_WITHIN: Duration = Duration::from_secs(5);

/// Live progress of the running job.
#[derive(Debug, Clone, Default, PartialEq, Serialize, serde::Deserialize, ToSchema)]
pub struct Progress {
    /// Points (postures, poses, sphere points) done.
    pub done: u64,
    pub total: u64,
    /// The station the tracer stands on now.
    pub station: Option<String>,
    /// Estimated seconds to the end, from the rate so far.
    pub eta_s: Option<f64>,
    /// The last faults, newest last.
    pub last_faults: Vec<String>,
}

/// One device as the daemon sees it.
#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize, ToSchema)]
pub struct DeviceStatus {
    pub id: String,
    /// tracer, environment, rotary_table, machine, probe.
    pub kind: String,
    /// A reading came within the last few seconds.
    pub connected: bool,
    /// The last reading as recorded.
    #[schema(value_type = Object)]
    pub last_reading: Option<serde_json::Value>,
    /// Seconds since the last reading (wall clock).
    pub last_reading_age_s: Option<f64>,
    /// The tracer's signal level (0..1) in its last reading.
    pub signal_level: Option<f64>,
    pub last_error: Option<String>,
    pub readings: u64,
    /// The connection the daemon keeps open between jobs, if it holds one for this device.
    pub connection: Option<crate::devices::held::HeldStatus>,
}

struct DeviceEntry {
    kind: String,
    /// The last reading's recorded bytes, decoded only when asked for (readings come at up to
    /// kHz rates on the recorder's thread).
    last_reading: Option<Vec<u8>>,
    last_at: Option<Instant>,
    last_error: Option<String>,
    readings: u64,
}

#[derive(Default)]
struct Board {
    progress: Progress,
    started: Option<Instant>,
    faults: VecDeque<String>,
    devices: BTreeMap<String, DeviceEntry>,
    counters: Counters,
}

/// Totals since the daemon started, for the metrics.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Counters {
    pub samples: u64,
    pub faults_by_kind: BTreeMap<String, u64>,
    /// Messages waiting for the recorder's writer when the last one was written.
    pub recorder_queue_depth: u64,
    pub recorder_queue_depth_max: u64,
}

/// Shared between the recorder's tap, the job's progress callback and the API.
#[derive(Clone, Default)]
pub struct StatusBoard {
    inner: Arc<Mutex<Board>>,
}

/// A change worth telling the event stream about.
#[derive(Debug, Clone)]
pub enum Change {
    Station(String),
    Fault { device: String, message: String },
}

impl StatusBoard {
    /// A job starts: progress from zero.
    pub fn job_started(&self) {
        if let Ok(mut board) = self.inner.lock() {
            board.progress = Progress::default();
            board.faults.clear();
            board.started = Some(Instant::now());
        }
    }

    pub fn set_progress(&self, done: u64, total: u64) -> Progress {
        let Ok(mut board) = self.inner.lock() else {
            return Progress::default();
        };
        board.progress.done = done;
        board.progress.total = total;
        board.progress.eta_s = board.started.and_then(|started| {
            let elapsed = started.elapsed().as_secs_f64();
            (done > 0 && total >= done).then(|| elapsed / done as f64 * (total - done) as f64)
        });
        board.progress.clone()
    }

    pub fn progress(&self) -> Progress {
        self.inner
            .lock()
            .map(|b| {
                let mut p = b.progress.clone();
                p.last_faults = b.faults.iter().cloned().collect();
                p
            })
            .unwrap_or_default()
    }

    pub fn devices(&self) -> Vec<DeviceStatus> {
        let Ok(board) = self.inner.lock() else {
            return Vec::new();
        };
        board
            .devices
            .iter()
            .map(|(id, d)| {
                let age = d.last_at.map(|t| t.elapsed());
                let last_reading: Option<serde_json::Value> = d
                    .last_reading
                    .as_ref()
                    .and_then(|bytes| serde_json::from_slice(bytes).ok());
                DeviceStatus {
                    id: id.clone(),
                    kind: d.kind.clone(),
                    connected: age.is_some_and(|a| a < CONNECTED_WITHIN),
                    signal_level: last_reading
                        .as_ref()
                        .and_then(|r| r.get("signal"))
                        .and_then(|s| s.as_f64()),
                    last_reading,
                    last_reading_age_s: age.map(|a| a.as_secs_f64()),
                    last_error: d.last_error.clone(),
                    readings: d.readings,
                    connection: None,
                }
            })
            .collect()
    }

    pub fn counters(&self) -> Counters {
        self.inner
            .lock()
            .map(|b| b.counters.clone())
            .unwrap_or_default()
    }

    fn note_queue_depth(&self, depth: u64) {
        if let Ok(mut board) = self.inner.lock() {
            board.counters.recorder_queue_depth = depth;
            let max = &mut board.counters.recorder_queue_depth_max;
            *max = (*max).max(depth);
        }
    }

    /// Take in one recorded message; what changed.
    pub fn observe(&self, topic: &str, data: &[u8]) -> Option<Change> {
        if let Some((kind, id)) = device_of_topic(topic) {
            let mut board = self.inner.lock().ok()?;
            board.counters.samples += 1;
            let entry = board
                .devices
                .entry(id.to_owned())
                .or_insert_with(|| DeviceEntry {
                    kind: kind.to_owned(),
                    last_reading: None,
                    last_at: None,
                    last_error: None,
                    readings: 0,
                });
            entry.last_reading = Some(data.to_vec());
            entry.last_at = Some(Instant::now());
            entry.readings += 1;
            return None;
        }
        if topic != crate::session::messages::TOPIC_EVENT {
            return None;
        }
        let value: serde_json::Value = serde_json::from_slice(data).ok()?;
        let mut board = self.inner.lock().ok()?;
        let text = |key: &str| value.get(key).and_then(|v| v.as_str()).map(str::to_owned);
        match value.get("kind").and_then(|k| k.as_str()) {
            Some("station_begin") => {
                let station = text("station")?;
                board.progress.station = Some(station.clone());
                Some(Change::Station(station))
            }
            Some("fault") => {
                let device = text("device").unwrap_or_default();
                let code = text("code").unwrap_or_default();
                let message = format!("{device}: {code}: {}", text("message").unwrap_or_default());
                *board.counters.faults_by_kind.entry(code).or_default() += 1;
                if board.faults.len() == FAULTS_KEPT {
                    board.faults.pop_front();
                }
                board.faults.push_back(message.clone());
                if let Some(entry) = board.devices.get_mut(&device) {
                    entry.last_error = Some(message.clone());
                }
                Some(Change::Fault { device, message })
            }
            _ => None,
        }
    }
}

/// (device kind, id) of a device topic.
pub(super) fn device_of_topic(topic: &str) -> Option<(&'static str, &str)> {
    let parts: Vec<&str> = topic.trim_start_matches('/').split('/').collect();
    match parts.as_slice() {
        ["tracer", id, "range"] => Some(("tracer", id)),
        ["env", id] => Some(("environment", id)),
        ["rotary", id, "state"] => Some(("rotary_table", id)),
        ["machine", id, "state"] => Some(("machine", id)),
        ["probe", id, "reading"] => Some(("probe", id)),
        _ => None,
    }
}

/// The tap a daemon's run records through: the status board, the event stream, the live
/// samples stream, and the live view when there is one.
pub struct DaemonTap {
    pub board: StatusBoard,
    pub on_change: Box<dyn Fn(Change) + Send + Sync>,
    pub samples: Arc<super::samples::SampleFeed>,
    pub live: Option<Arc<dyn MessageTap>>,
}

impl MessageTap for DaemonTap {
    fn message(&self, message: &TappedMessage<'_>) {
        self.board.note_queue_depth(message.queue_depth);
        if let Some(change) = self.board.observe(&message.channel.topic, message.data) {
            (self.on_change)(change);
        }
        self.samples
            .observe(&message.channel.topic, message.log_time_ns, message.data);
        if let Some(live) = &self.live {
            live.message(message);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn readings_faults_and_stations_are_seen() {
        let board = StatusBoard::default();
        board.job_started();
        assert!(board
            .observe(
                "/tracer/t1/range",
                br#"{"seq":1,"length_m":0.5,"signal":0.8}"#
            )
            .is_none());
        let change = board.observe(
            "/run/event",
            br#"{"kind":"station_begin","station":"s2","station_index":1}"#,
        );
        assert!(matches!(change, Some(Change::Station(s)) if s == "s2"));
        board.observe(
            "/run/event",
            br#"{"kind":"fault","device":"t1","code":"beam_break","message":"beam lost"}"#,
        );
        let devices = board.devices();
        assert_eq!(devices.len(), 1);
        assert!(devices[0].connected);
        assert_eq!(devices[0].signal_level, Some(0.8));
        assert_eq!(
            devices[0].last_error.as_deref(),
            Some("t1: beam_break: beam lost")
        );
        let progress = board.set_progress(5, 10);
        assert_eq!(progress.station.as_deref(), Some("s2"));
        assert!(progress.eta_s.is_some());
        assert_eq!(board.progress().last_faults.len(), 1);
        let counters = board.counters();
        assert_eq!(counters.samples, 1);
        assert_eq!(counters.faults_by_kind.get("beam_break"), Some(&1));
        assert!(board.observe("/run/event", b"not json").is_none());
    }
}
