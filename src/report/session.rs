//! The session a report reads: a clean multilateration file is streamed, so its tracer samples
//! are never held; the report keeps everything else (header, environment, run events) and the
//! settled windows its ISO 230-2 section solves from.

use std::path::Path;

use crate::extract::{SettledSession, WindowStream};
use crate::session::reader::{read_session, KeepingEvents, ReadError, Session};

/// A report's session: `session` holds every stream but, when `settled` is there (a streamed
/// multilateration file), the tracer samples (`tracers` is then empty).
pub struct ReportSession {
    pub session: Session,
    pub settled: Option<SettledSession>,
}

/// Reads the session at `path` for the report: streamed when it is a clean multilateration
/// file, else read whole.
pub fn read(path: &Path) -> Result<ReportSession, ReadError> {
    // The report lists what every run event says.
    let mut sink = KeepingEvents::new(
        WindowStream::new(crate::method::multilateration::is_multilateration),
        |_| true,
    );
    if let Some(streamed) = crate::session::reader::stream_session(path, &mut sink) {
        let mut session = streamed.session.clone();
        if let Some(settled) = sink.inner.finish(streamed) {
            session.tracers.clear();
            session.events = sink.kept;
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
