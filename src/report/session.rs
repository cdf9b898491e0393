//! The session a report reads: a clean multilateration file is streamed, so its tracer samples
//! are never held; the report keeps everything else (header, environment, run events) and the
//! settled windows its ISO 230-2 section solves from.

use std::path::Path;

use crate::extract::{SettledSession, WindowStream};
use crate::session::messages::{RunEvent, SessionHeader, TracerSample};
use crate::session::reader::{read_session, ReadError, Session, SessionSink, Stamped};

/// A report's session: `session` holds every stream but, when `settled` is there (a streamed
/// multilateration file), the tracer samples (`tracers` is then empty).
pub struct ReportSession {
    pub session: Session,
    pub settled: Option<SettledSession>,
}

/// Reads the session at `path` for the report: streamed when it is a clean multilateration
/// file, else read whole.
pub fn read(path: &Path) -> Result<ReportSession, ReadError> {
    let mut sink = EventsAndWindows {
        windows: WindowStream::new(crate::method::multilateration::is_multilateration),
        events: Vec::new(),
    };
    if let Some(streamed) = crate::session::reader::stream_session(path, &mut sink) {
        let mut session = streamed.session.clone();
        if let Some(settled) = sink.windows.finish(streamed) {
            session.tracers.clear();
            session.events = sink.events;
            return Ok(ReportSession {
                session,
                settled: Some(settled),
            });
        }
    }
    Ok(ReportSession {
        session: read_session(path)?,
        settled: None,
    })
}

/// The settled windows of the stream, and its run events (the report lists what they say).
struct EventsAndWindows {
    windows: WindowStream,
    events: Vec<Stamped<RunEvent>>,
}

impl SessionSink for EventsAndWindows {
    fn begin(&mut self, header: &SessionHeader, tracers: &[String], run_events: usize) -> bool {
        self.events.reserve(run_events);
        self.windows.begin(header, tracers, run_events)
    }

    fn batch(
        &mut self,
        tracers: &mut [Vec<Stamped<TracerSample>>],
        events: &mut Vec<Stamped<RunEvent>>,
    ) -> bool {
        self.events.extend(events.iter().cloned());
        self.windows.batch(tracers, events)
    }
}
