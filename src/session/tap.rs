//! A live copy of what the recorder writes: every message, with its channel, handed to an
//! observer on the recorder's thread right after it is written (live view, progress, status).

use std::sync::Arc;

/// The channel a tapped message was written on, as recorded in the file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TapChannel {
    pub id: u16,
    pub topic: String,
    pub message_encoding: String,
    /// (name, encoding, data) of the channel's schema, when it has one.
    pub schema: Option<(String, String, Vec<u8>)>,
}

/// One message exactly as written to the session file.
#[derive(Debug, Clone, Copy)]
pub struct TappedMessage<'a> {
    pub channel: &'a Arc<TapChannel>,
    pub sequence: u32,
    pub log_time_ns: u64,
    pub publish_time_ns: u64,
    pub data: &'a [u8],
    /// Messages sent to the recorder and not yet written when this one was.
    pub queue_depth: u64,
}

/// Called on the recorder's writer thread for every message written: it must return quickly
/// and never block (hand the message on through a bounded or lossy channel).
pub trait MessageTap: Send + Sync {
    fn message(&self, message: &TappedMessage<'_>);

    /// The run whose messages this tap saw has ended (a tap that outlives its runs, such as
    /// the daemon's live view, ends what belonged to it).
    fn run_ended(&self) {}
}

/// An optional tap in `RecorderOptions` (which derives Debug and Clone).
#[derive(Clone, Default)]
pub struct Tap(pub Option<Arc<dyn MessageTap>>);

impl Tap {
    pub fn new(tap: Arc<dyn MessageTap>) -> Tap {
        Tap(Some(tap))
    }
}

impl std::fmt::Debug for Tap {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(if self.0.is_some() {
            "Tap(on)"
        } else {
            "Tap(off)"
        })
    }
}
