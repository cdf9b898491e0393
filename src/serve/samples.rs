//! The live samples stream: every reading the running job's devices record, gathered per
//! device and sent at most `MESSAGES_PER_SECOND` times a second as one message, so a tablet
//! keeps up with a 1 kHz tracer. Messages go through a bounded broadcast: a client that reads
//! too slowly loses the oldest ones (and is told how many), never holds up the run or others.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use serde::Serialize;
use tokio::sync::broadcast;
use tokio_util::sync::CancellationToken;
use utoipa::ToSchema;

use super::status::device_of_topic;

/// Messages per device and second, at most.
pub const MESSAGES_PER_SECOND: u64 = 20;
const INTERVAL: Duration = Duration::from_millis(1000 / MESSAGES_PER_SECOND);
/// Samples one message carries at most (4 kHz per device at 20 messages a second); more in
/// one interval are thinned evenly.
pub const MAX_SAMPLES_PER_MESSAGE: usize = 200;
/// Readings kept per device between two messages; more are counted, not kept.
const MAX_PENDING: usize = 4096;
/// Messages a client may fall behind before it loses the oldest (about 1.5 s of two devices).
const BACKLOG: usize = 64;

/// One device's readings since its previous message, column by column.
#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize, ToSchema)]
pub struct SampleBatch {
    pub device: String,
    /// tracer, environment, rotary_table, machine, probe.
    pub kind: String,
    /// The readings' log times (s), oldest first.
    pub t_s: Vec<f64>,
    /// Each numeric field of the readings (`length_m`, `signal`, `air_temp_k`, …; not `seq`
    /// or the device's own `t_s`): one value per sample, null where a reading lacks it.
    pub fields: BTreeMap<String, Vec<Option<f64>>>,
    /// Readings of this interval not carried: thinned beyond `MAX_SAMPLES_PER_MESSAGE`, or
    /// beyond what the daemon keeps between two messages.
    pub skipped: u64,
}

struct Pending {
    kind: &'static str,
    /// (log time in ns, the reading as recorded)
    readings: Vec<(u64, Vec<u8>)>,
    overflow: u64,
}

/// Fed by the recorder's tap; read by the `/v1/devices/samples` streams.
pub struct SampleFeed {
    pending: Mutex<BTreeMap<String, Pending>>,
    sender: broadcast::Sender<Arc<SampleBatch>>,
}

impl Default for SampleFeed {
    fn default() -> Self {
        SampleFeed {
            pending: Mutex::default(),
            sender: broadcast::channel(BACKLOG).0,
        }
    }
}

impl SampleFeed {
    /// Take in one recorded message (on the recorder's thread: a copy, nothing decoded).
    /// Nothing is kept while no client listens.
    pub fn observe(&self, topic: &str, log_time_ns: u64, data: &[u8]) {
        let Some((kind, id)) = device_of_topic(topic) else {
            return;
        };
        if self.sender.receiver_count() == 0 {
            return;
        }
        let Ok(mut pending) = self.pending.lock() else {
            return;
        };
        let entry = pending.entry(id.to_owned()).or_insert_with(|| Pending {
            kind,
            readings: Vec::new(),
            overflow: 0,
        });
        if entry.readings.len() < MAX_PENDING {
            entry.readings.push((log_time_ns, data.to_vec()));
        } else {
            entry.overflow += 1;
        }
    }

    pub fn subscribe(&self) -> broadcast::Receiver<Arc<SampleBatch>> {
        self.sender.subscribe()
    }

    /// Send each device's readings since the last flush as one message; how many were sent.
    pub fn flush(&self) -> usize {
        let taken = match self.pending.lock() {
            Ok(mut pending) => std::mem::take(&mut *pending),
            Err(_) => return 0,
        };
        let mut sent = 0;
        for (device, pending) in taken {
            if pending.readings.is_empty() && pending.overflow == 0 {
                continue;
            }
            let batch = batch(device, pending);
            // No receiver left: nothing to do (the next reading is not kept either).
            if self.sender.send(Arc::new(batch)).is_ok() {
                sent += 1;
            }
        }
        sent
    }

    /// Flush every `INTERVAL` until `stop`.
    pub async fn run(self: Arc<Self>, stop: CancellationToken) {
        let mut tick = tokio::time::interval(INTERVAL);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
        loop {
            tokio::select! {
                _ = tick.tick() => { self.flush(); }
                _ = stop.cancelled() => return,
            }
        }
    }
}

fn batch(device: String, pending: Pending) -> SampleBatch {
    let n = pending.readings.len();
    let kept: Vec<&(u64, Vec<u8>)> = if n > MAX_SAMPLES_PER_MESSAGE {
        (0..MAX_SAMPLES_PER_MESSAGE)
            .map(|i| &pending.readings[i * n / MAX_SAMPLES_PER_MESSAGE])
            .collect()
    } else {
        pending.readings.iter().collect()
    };
    let mut fields: BTreeMap<String, Vec<Option<f64>>> = BTreeMap::new();
    let mut t_s = Vec::with_capacity(kept.len());
    for (index, (log_time_ns, data)) in kept.iter().enumerate() {
        t_s.push(*log_time_ns as f64 * 1e-9);
        let Ok(serde_json::Value::Object(reading)) = serde_json::from_slice(data) else {
            continue;
        };
        for (name, value) in reading {
            if name == "seq" || name == "t_s" {
                continue;
            }
            let Some(value) = value.as_f64() else {
                continue;
            };
            let column = fields.entry(name).or_insert_with(|| vec![None; kept.len()]);
            column[index] = Some(value);
        }
    }
    SampleBatch {
        device,
        kind: pending.kind.to_owned(),
        t_s,
        fields,
        skipped: (n - kept.len()) as u64 + pending.overflow,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn reading(seq: u64, length: f64) -> Vec<u8> {
        format!(r#"{{"seq":{seq},"t_s":0.1,"length_m":{length},"signal":0.9,"tracking":true}}"#)
            .into_bytes()
    }

    #[test]
    fn readings_are_batched_per_device_only_while_someone_listens() {
        let feed = SampleFeed::default();
        feed.observe("/tracer/t0/range", 1_000_000_000, &reading(0, 0.5));
        let mut listener = feed.subscribe();
        assert_eq!(feed.flush(), 0, "nothing kept before a client listened");
        for i in 0..3 {
            feed.observe(
                "/tracer/t0/range",
                2_000_000_000 + i,
                &reading(i, 0.5 + i as f64),
            );
        }
        feed.observe(
            "/env/air",
            2_500_000_000,
            br#"{"t_s":1.0,"air_temp_k":293.15,"pressure_pa":101325.0,"humidity_pct":45.0,"material_temp_k":[293.2]}"#,
        );
        feed.observe("/run/event", 2_600_000_000, br#"{"kind":"point_end"}"#);
        assert_eq!(feed.flush(), 2);
        let first = listener.try_recv().unwrap();
        let second = listener.try_recv().unwrap();
        let (env, tracer) = if first.device == "air" {
            (first, second)
        } else {
            (second, first)
        };
        assert_eq!(tracer.kind, "tracer");
        assert_eq!(tracer.t_s.len(), 3);
        assert_eq!(tracer.t_s[0], 2.0);
        assert_eq!(
            tracer.fields["length_m"],
            vec![Some(0.5), Some(1.5), Some(2.5)]
        );
        assert_eq!(
            tracer.fields.keys().collect::<Vec<_>>(),
            ["length_m", "signal"]
        );
        assert_eq!(env.kind, "environment");
        assert_eq!(env.fields["air_temp_k"], vec![Some(293.15)]);
        assert!(!env.fields.contains_key("material_temp_k"));
        assert_eq!(feed.flush(), 0, "each reading is sent once");
    }

    #[test]
    fn a_fast_device_is_thinned_and_a_slow_client_loses_old_messages() {
        let feed = SampleFeed::default();
        let mut slow = feed.subscribe();
        let n = MAX_PENDING + 10;
        for i in 0..n as u64 {
            feed.observe("/tracer/t0/range", i, &reading(i, i as f64));
        }
        feed.flush();
        let batch = slow.try_recv().unwrap();
        assert_eq!(batch.t_s.len(), MAX_SAMPLES_PER_MESSAGE);
        assert_eq!(batch.skipped, (n - MAX_SAMPLES_PER_MESSAGE) as u64);
        // Evenly thinned over the interval, oldest first.
        let lengths: Vec<f64> = batch.fields["length_m"].iter().flatten().copied().collect();
        assert_eq!(lengths[0], 0.0);
        assert!(lengths.windows(2).all(|w| w[1] > w[0]));
        assert!(lengths[MAX_SAMPLES_PER_MESSAGE - 1] > 0.9 * MAX_PENDING as f64);
        // A client that does not read: the feed never waits for it, and it is told what it
        // lost once it reads again.
        for i in 0..(3 * BACKLOG) as u64 {
            feed.observe("/tracer/t0/range", i, &reading(i, 0.0));
            assert_eq!(feed.flush(), 1);
        }
        match slow.try_recv() {
            Err(broadcast::error::TryRecvError::Lagged(lost)) => {
                assert_eq!(lost, 2 * BACKLOG as u64)
            }
            other => panic!("expected a lag, got {other:?}"),
        }
        assert_eq!(
            slow.try_recv().unwrap().t_s,
            vec![(2 * BACKLOG) as f64 * 1e-9]
        );
    }
}
