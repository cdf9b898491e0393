//! What a caller other than the console (the daemon) gives a run: a way to cancel it
//! cleanly, a live copy of what it records, its progress, who answers its prompts, and the
//! device connections it keeps between runs.

use std::future::Future;
use std::sync::Arc;

use tokio_util::sync::CancellationToken;

use crate::progress_sink::ProgressSink;
use crate::sequencer::control::{Cancelled, OperatorSource};
use crate::session::tap::Tap;

#[derive(Clone, Default)]
pub struct RunControl {
    /// Cancelled: the sequencer stops at once, the recorder flushes and closes the file, and
    /// the run can be resumed like a killed one.
    pub cancel: CancellationToken,
    /// Receives every recorded message as it is written.
    pub tap: Tap,
    pub progress: Option<ProgressSink>,
    pub operator: Option<OperatorSource>,
    /// Connections kept open between runs; without it a run opens its devices and closes
    /// them when it ends.
    pub devices: Option<Arc<crate::devices::held::DeviceHolder>>,
}

impl RunControl {
    /// `sequence`, unless the run is cancelled first.
    pub async fn until_cancelled<T, E: From<Cancelled>>(
        &self,
        sequence: impl Future<Output = Result<T, E>>,
    ) -> Result<T, E> {
        tokio::select! {
            biased;
            _ = self.cancel.cancelled() => Err(Cancelled.into()),
            summary = sequence => summary,
        }
    }

    pub fn report_progress(&self, done: u64, total: u64) {
        if let Some(progress) = &self.progress {
            progress.report(done, total);
        }
    }
}

impl std::fmt::Debug for RunControl {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RunControl")
            .field("cancelled", &self.cancel.is_cancelled())
            .field("tap", &self.tap)
            .field("progress", &self.progress.is_some())
            .field("operator", &self.operator.is_some())
            .field("devices_held", &self.devices.is_some())
            .finish()
    }
}
