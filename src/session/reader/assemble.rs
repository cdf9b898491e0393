//! The end of a read: completeness, the damage report and the assembled `Session`.

use super::decoder::Decoder;
use super::{Completeness, DamagedChunk, ReadError, Session};
use crate::session::messages::RunEvent;

impl Decoder {
    /// Whether the file was read to its end magic; warns when it was not.
    pub(super) fn completeness(&mut self, file: &str, file_bytes: u64) -> Completeness {
        let Some((bytes_read, reason)) = self.truncation.take() else {
            return Completeness::Complete;
        };
        tracing::warn!(
            "{file} is incomplete: read {bytes_read} of {file_bytes} bytes ({} messages): \
             {reason}; run `geocal repair {file}` for a complete copy, or resume the run with \
             `geocal run --resume DIR`",
            self.messages
        );
        Completeness::Truncated {
            bytes_read,
            file_bytes,
            messages_read: self.messages,
            reason,
        }
    }

    /// The damaged records as reported, each warned about once.
    pub(super) fn damaged_chunks(&mut self, file: &str) -> Vec<DamagedChunk> {
        self.settle_neighbours();
        let damages = std::mem::take(&mut self.damages);
        damages
            .into_iter()
            .map(|d| {
                let chunk = d.finish(|channel| self.topic_of(channel));
                tracing::warn!(
                    "{file}: damaged, skipped {}; run `geocal repair {file}` for a clean copy",
                    chunk.describe()
                );
                chunk
            })
            .collect()
    }

    pub(super) fn into_session(
        mut self,
        file: &str,
        file_bytes: u64,
    ) -> Result<Session, ReadError> {
        let damaged = self.damaged_chunks(file);
        let completeness = self.completeness(file, file_bytes);
        let Some(header) = self.header else {
            let truncated = match &completeness {
                Completeness::Complete => String::new(),
                Completeness::Truncated { bytes_read, .. } => {
                    format!("; the file is cut short after byte {bytes_read}")
                }
            };
            return Err(ReadError::NoHeader {
                file: file.to_owned(),
                messages: self.messages,
                truncated,
            });
        };
        if self.skipped > 0 {
            tracing::warn!(
                "{file}: {} messages on known topics could not be parsed and were skipped",
                self.skipped
            );
        }
        // Stable sorts: equal log times keep file order. Nearly free on already sorted data.
        let tracers = self.tracers.into_sorted_map();
        let env = self.env.into_sorted_map();
        let rotary = self.rotary.into_sorted_map();
        let machines = self.machines.into_sorted_map();
        let probes = self.probes.into_sorted_map();
        let topics = self.json.into_sorted_map();
        let mut events = self.events;
        events.sort_by_key(|s| s.log_time_ns);
        let lost_before_repair = events
            .iter()
            .filter_map(|e| match &e.msg {
                RunEvent::DataLost { lost } => Some(lost.clone()),
                _ => None,
            })
            .collect();
        Ok(Session {
            header: header.msg,
            tracers,
            env,
            rotary,
            machines,
            probes,
            events,
            topics,
            completeness,
            damaged,
            lost_before_repair,
            skipped: self.skipped,
            ignored: self.ignored,
        })
    }
}
