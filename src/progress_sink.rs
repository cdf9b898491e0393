//! A caller's function of (done, total): how a run, a read or a diagnosis tells its caller
//! (a progress bar, the daemon's job board, the Python package's callback) how far it is.

use std::sync::Arc;

/// Cheap to clone; two sinks are equal when they are the same function.
#[derive(Clone)]
pub struct ProgressSink(Arc<dyn Fn(u64, u64) + Send + Sync>);

impl ProgressSink {
    pub fn new(report: impl Fn(u64, u64) + Send + Sync + 'static) -> ProgressSink {
        ProgressSink(Arc::new(report))
    }

    /// `done` of `total`.
    pub fn report(&self, done: u64, total: u64) {
        (self.0)(done, total);
    }
}

impl std::fmt::Debug for ProgressSink {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("ProgressSink")
    }
}

impl PartialEq for ProgressSink {
    fn eq(&self, other: &Self) -> bool {
        Arc::ptr_eq(&self.0, &other.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Mutex;

    #[test]
    fn reports_reach_the_function_and_clones_are_equal() {
        let seen = Arc::new(Mutex::new(Vec::new()));
        let log = seen.clone();
        let sink = ProgressSink::new(move |d, t| log.lock().expect("lock").push((d, t)));
        sink.clone().report(1, 2);
        assert_eq!(*seen.lock().expect("lock"), vec![(1, 2)]);
        assert_eq!(sink, sink.clone());
        assert_ne!(sink, ProgressSink::new(|_, _| {}));
    }
}
