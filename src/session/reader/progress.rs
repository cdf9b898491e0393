//! How far a read of a session file is: bytes of the file done of its size, reported to a
//! caller's function (a progress bar, the Python package's callback) as the chunks are merged.

use std::sync::{Arc, Mutex, PoisonError};

use crate::progress_sink::ProgressSink;

/// A caller's function of (bytes done, bytes in all). It sees `done` grow and never fall
/// (a read that starts over, whole, after a streamed attempt is not reported again from
/// its start) and ends at `done == total`.
#[derive(Clone)]
pub struct ReadProgress {
    sink: ProgressSink,
    /// The last `done` reported; held while the function runs, so that it sees the reports
    /// in order.
    last: Arc<Mutex<Option<u64>>>,
}

impl std::fmt::Debug for ReadProgress {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ReadProgress")
            .field(
                "last",
                &*self.last.lock().unwrap_or_else(PoisonError::into_inner),
            )
            .finish()
    }
}

impl ReadProgress {
    pub fn new(report: impl Fn(u64, u64) + Send + Sync + 'static) -> ReadProgress {
        ReadProgress {
            sink: ProgressSink::new(report),
            last: Arc::default(),
        }
    }

    /// `done` bytes of `total`: reported when beyond the last report (the first report
    /// always goes out, even at 0).
    pub fn report(&self, done: u64, total: u64) {
        let done = done.min(total);
        let mut last = self.last.lock().unwrap_or_else(PoisonError::into_inner);
        if last.is_some_and(|last| done <= last) {
            return;
        }
        *last = Some(done);
        self.sink.report(done, total);
    }

    /// The read of `total` bytes is over.
    pub fn finish(&self, total: u64) {
        self.report(total, total);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reports_grow_and_repeat_nothing() {
        let seen = Arc::new(Mutex::new(Vec::new()));
        let log = seen.clone();
        let progress =
            ReadProgress::new(move |done, total| log.lock().unwrap().push((done, total)));
        progress.report(0, 100);
        progress.report(40, 100);
        progress.report(30, 100);
        progress.report(40, 100);
        progress.report(250, 100);
        progress.finish(100);
        assert_eq!(*seen.lock().unwrap(), vec![(0, 100), (40, 100), (100, 100)]);
    }
}
