//! What every kind's replay shares (`geocal replay`): the clock that follows the recorded log
//! times, how a replayed sequencer ended, the recorded streams and device ids read from a
//! session, and a probe that hands out its recorded readings.

use std::collections::VecDeque;
use std::sync::{Arc, Mutex};

use anyhow::Context;
use async_trait::async_trait;
use geocal_drivers::{DeviceError, Probe, ProbeReading};

use crate::clock::Clock;
use crate::session::messages::SessionHeader;
use crate::session::reader::Session;

/// How a kind's replayed sequencer ended: Ok (the plan completed), the recording of a device
/// ended first (`Err((Some(device), _))`), or it stopped otherwise (`Err((None, why))`).
pub type SequenceEnd = Result<(), (Option<String>, String)>;

/// A kind's replay: its sequencer re-run against a session, recording into a handle.
pub type ReplaySequence =
    fn(&Session, crate::session::recorder::RecorderHandle) -> anyhow::Result<SequenceEnd>;

/// A device's end of stream as where the recording ended; any other error as a divergence.
pub fn sequence_end(
    device_error: Option<&DeviceError>,
    message: String,
) -> (Option<String>, String) {
    match device_error {
        Some(DeviceError::EndOfStream { device }) => (Some(device.clone()), String::new()),
        _ => (None, message),
    }
}

/// The single-threaded runtime a replayed sequencer runs on.
pub fn replay_runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")
}

/// Log times that follow the recording. With k samples delivered, the clock reads sample
/// k-1's recorded log time; where the recording stamped the messages after that sample later
/// (a wall clock), each further reading is 1 ns later, staying before sample k's log time, so
/// that a window opened there excludes sample k-1 exactly as the recorded one does.
#[derive(Debug, Default)]
pub struct ReplayClock {
    pub(crate) state: Mutex<ClockState>,
}

#[derive(Debug, Default)]
pub(crate) struct ClockState {
    pub(crate) base_ns: u64,
    pub(crate) limit_ns: u64,
    pub(crate) strict: bool,
    pub(crate) calls: u64,
}

impl ReplayClock {
    /// Read `ns` until the cursor next moves.
    pub fn set_fixed(&self, ns: u64) {
        let mut c = self.state.lock().unwrap_or_else(|e| e.into_inner());
        *c = ClockState {
            base_ns: ns,
            limit_ns: ns,
            strict: false,
            calls: 0,
        };
    }
}

impl Clock for ReplayClock {
    fn now_ns(&self) -> u64 {
        let mut c = self.state.lock().unwrap_or_else(|e| e.into_inner());
        if !c.strict {
            return c.base_ns;
        }
        let t = c.base_ns.saturating_add(c.calls).min(c.limit_ns);
        c.calls += 1;
        t
    }
}

pub fn device_id(session: &Session, kind: &str) -> anyhow::Result<String> {
    session
        .header
        .devices
        .iter()
        .find(|d| d.kind == kind)
        .map(|d| d.id.clone())
        .ok_or_else(|| anyhow::anyhow!("session header: no device of kind `{kind}`"))
}

/// A topic's recorded JSON messages parsed, with their log times.
pub fn stream<T: serde::de::DeserializeOwned>(
    session: &Session,
    topic: &str,
) -> anyhow::Result<VecDeque<(u64, T)>> {
    session
        .topics
        .get(topic)
        .map(Vec::as_slice)
        .unwrap_or(&[])
        .iter()
        .map(|m| {
            T::deserialize(&m.msg)
                .map(|v| (m.log_time_ns, v))
                .with_context(|| format!("message on {topic} at log time {} ns", m.log_time_ns))
        })
        .collect()
}

pub fn ended(device: &str) -> DeviceError {
    DeviceError::EndOfStream {
        device: device.to_string(),
    }
}

/// A kind's configuration with the recorded plan: only `plan` matters to expanding it, the
/// rest is taken from the header or is a placeholder.
pub fn config_from_header<T: serde::de::DeserializeOwned>(
    session: &Session,
    mut rest: serde_json::Value,
) -> anyhow::Result<T> {
    rest["kind"] = session.header.kind.clone().into();
    rest["plan"] = session.header.plan.clone();
    serde_path_to_error::deserialize(rest).map_err(|e| {
        anyhow::anyhow!(
            "the session header cannot be replayed: key `{}`: {}",
            e.path(),
            e.inner()
        )
    })
}

/// The laser probe of a probe_install recording: every raw reading, out-of-range ones again
/// as the driver's out-of-range rejection.
pub struct ReplayLaserProbe {
    pub id: String,
    pub clock: Arc<ReplayClock>,
    /// Log time, recorded `t_s` and value (None: out of range) of every reading.
    pub readings: VecDeque<(u64, f64, Option<f64>)>,
    /// The recorded `out_of_range` fault messages, one per null reading, in order.
    pub out_of_range: VecDeque<String>,
}

#[async_trait]
impl Probe for ReplayLaserProbe {
    fn id(&self) -> &str {
        &self.id
    }
    async fn read(&mut self) -> Result<ProbeReading, DeviceError> {
        let (t, t_s, value) = self.readings.pop_front().ok_or_else(|| ended(&self.id))?;
        self.clock.set_fixed(t);
        match value {
            Some(value_m) => Ok(ProbeReading { t_s, value_m }),
            None => Err(DeviceError::Rejected {
                device: self.id.clone(),
                message: self
                    .out_of_range
                    .pop_front()
                    .unwrap_or_else(|| "out of range".into()),
            }),
        }
    }
}

/// The recording's header, marked as a replay: `<id>-replay`, every driver `replay` (the
/// recorded one kept as `replayed_driver`).
pub fn replay_header(original: &SessionHeader) -> SessionHeader {
    let mut header = original.clone();
    header.session_id = format!("{}-replay", original.session_id);
    header.started_at = time::OffsetDateTime::now_utc()
        .format(&time::format_description::well_known::Rfc3339)
        .unwrap_or_default();
    for device in &mut header.devices {
        device
            .extra
            .insert("replayed_driver".into(), device.driver.clone().into());
        device.driver = "replay".into();
    }
    header
}
