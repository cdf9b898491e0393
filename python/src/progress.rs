//! A Python progress callback `progress(done, total)` called from the Rust core's threads: it
//! takes the GIL for each call; what it raises (Ctrl-C's KeyboardInterrupt included, checked
//! at each call) is kept, cancels a run, and is raised when the call returns.

use std::sync::{Arc, Mutex};

use pyo3::prelude::*;
use tokio_util::sync::CancellationToken;

#[derive(Clone, Default)]
pub struct Callback {
    function: Option<Arc<Py<PyAny>>>,
    raised: Arc<Mutex<Option<PyErr>>>,
}

impl Callback {
    pub fn new(function: Option<Py<PyAny>>) -> Callback {
        Callback {
            function: function.map(Arc::new),
            raised: Arc::default(),
        }
    }

    /// Calls the function unless it (or a signal) has raised already; false once it has.
    pub fn report(&self, done: u64, total: u64) -> bool {
        let Some(function) = &self.function else {
            return true;
        };
        let Ok(mut raised) = self.raised.lock() else {
            return false;
        };
        if raised.is_some() {
            return false;
        }
        let result = Python::attach(|py| {
            py.check_signals()?;
            function.call1(py, (done, total)).map(drop)
        });
        match result {
            Ok(()) => true,
            Err(e) => {
                *raised = Some(e);
                false
            }
        }
    }

    /// A run's progress sink: a callback that raised cancels the run.
    pub fn sink(&self, cancel: CancellationToken) -> geocal::progress_sink::ProgressSink {
        let callback = self.clone();
        geocal::progress_sink::ProgressSink::new(move |done, total| {
            if !callback.report(done, total) {
                cancel.cancel();
            }
        })
    }

    /// What the callback raised, if it did.
    pub fn raised(&self) -> PyResult<()> {
        match self.raised.lock().ok().and_then(|mut r| r.take()) {
            Some(e) => Err(e),
            None => Ok(()),
        }
    }
}
