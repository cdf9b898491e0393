//! Fault handling shared by every sequencer: a timeout or protocol error is recorded as a
//! `fault` event and retried `DEVICE_RETRIES` times (`retry_decision`); `EventLog` for kinds.

use std::sync::Arc;

use geocal_drivers::DeviceError;

use super::{SequencerError, DEVICE_RETRIES};
use crate::clock::Clock;
use crate::session::messages::RunEvent;
use crate::session::recorder::RecorderHandle;

/// Records events (counting faults) for a kind's sequencer.
pub struct EventLog {
    pub recorder: RecorderHandle,
    pub clock: Arc<dyn Clock>,
    pub faults: u64,
    /// Clock reading at the start of the run: the kind's topics count `t_s` from here.
    pub start_ns: u64,
}

impl EventLog {
    pub fn new(recorder: RecorderHandle, clock: Arc<dyn Clock>) -> Self {
        let start_ns = clock.now_ns();
        Self {
            recorder,
            clock,
            faults: 0,
            start_ns,
        }
    }

    /// Seconds since the run started.
    pub fn elapsed_s(&self) -> f64 {
        self.clock.now_ns().saturating_sub(self.start_ns) as f64 * 1e-9
    }

    pub fn event(&mut self, event: RunEvent) {
        if matches!(event, RunEvent::Fault { .. }) {
            self.faults += 1;
        }
        self.recorder.event(&event, self.clock.now_ns());
    }

    pub fn fault(&mut self, device: &str, code: &str, message: String) {
        self.event(RunEvent::Fault {
            device: device.to_string(),
            code: code.to_string(),
            message,
        });
    }

    /// Record a failed device call as a `fault` event; Ok if it may be retried (a timeout or a
    /// protocol error, at most `DEVICE_RETRIES` times), else the error.
    pub fn retry_or_fail(
        &mut self,
        error: DeviceError,
        attempt: &mut u32,
    ) -> Result<(), SequencerError> {
        match retry_decision(&error, attempt) {
            Some((event, true)) => {
                self.event(event);
                Ok(())
            }
            Some((event, false)) => {
                self.event(event);
                Err(error.into())
            }
            None => Err(error.into()),
        }
    }
}

/// The `fault` event of a failed device call that may be retried (a timeout or a protocol
/// error) and whether to retry it (at most `DEVICE_RETRIES` times); None for other errors.
pub(crate) fn retry_decision(error: &DeviceError, attempt: &mut u32) -> Option<(RunEvent, bool)> {
    let (device, code) = match error {
        DeviceError::Timeout { device, .. } => (device.clone(), "timeout"),
        DeviceError::Protocol { device, .. } => (device.clone(), "protocol"),
        _ => return None,
    };
    *attempt += 1;
    let retry = *attempt <= DEVICE_RETRIES;
    let message = if retry {
        format!("{error} (retry {attempt} of {DEVICE_RETRIES})")
    } else {
        format!("{error} (giving up after {DEVICE_RETRIES} retries)")
    };
    Some((
        RunEvent::Fault {
            device,
            code: code.into(),
            message,
        },
        retry,
    ))
}

/// Call a device method, retrying timeouts and protocol errors with `fault` events.
macro_rules! retried {
    ($log:expr, $call:expr) => {{
        let mut attempt = 0;
        loop {
            match $call.await {
                Ok(v) => break v,
                Err(e) => $log.retry_or_fail(e, &mut attempt)?,
            }
        }
    }};
}
pub(crate) use retried;
