//! Message decoding: which topic a channel carries, and one message's JSON into its type.

use serde::de::DeserializeOwned;
use serde::Deserialize;

use super::decoder::{Decoder, Failure, Slot};
use super::{event_json, tracer_json};
use super::{ReadError, Stamped};
use crate::session::messages::{
    EnvSample, MachineStateSample, ProbeSample, RotaryStateSample, RunEvent, SessionHeader,
    TracerSample, SESSION_FORMAT, TOPIC_EVENT, TOPIC_SESSION,
};

/// Warnings about unparsable messages stop after this many (the count is still reported).
const MAX_SKIP_WARNINGS: u64 = 20;

impl Decoder {
    pub(super) fn define_channel(&mut self, id: u16, topic: &str, encoding: &str) {
        let mut slot = if topic == TOPIC_SESSION {
            Slot::Session
        } else if topic == TOPIC_EVENT {
            Slot::Event
        } else if let Some(tid) = tracer_id(topic) {
            Slot::Tracer(self.tracers.index(tid))
        } else if let Some(eid) = env_id(topic) {
            Slot::Env(self.env.index(eid))
        } else if let Some(rid) = rotary_id(topic) {
            Slot::Rotary(self.rotary.index(rid))
        } else if let Some(mid) = machine_id(topic) {
            Slot::Machine(self.machines.index(mid))
        } else if let Some(pid) = probe_id(topic) {
            Slot::Probe(self.probes.index(pid))
        } else if KIND_TOPIC_PREFIXES.iter().any(|p| topic.starts_with(p)) {
            Slot::Json(self.json.index(topic))
        } else {
            Slot::Other
        };
        if !matches!(slot, Slot::Other) && encoding != "json" {
            tracing::warn!(
                "{}: channel {id} ({topic}) has message encoding {encoding:?}, not \"json\": \
                 its messages are skipped",
                self.file
            );
            slot = Slot::NotJson;
        }
        let i = usize::from(id);
        if self.slots.len() <= i {
            self.slots.resize(i + 1, Slot::Undefined);
        }
        self.slots[i] = slot;
    }

    /// The first `/geocal/session` message is the header; later ones are ignored.
    pub(super) fn session_message(
        &mut self,
        log_time_ns: u64,
        publish_time_ns: u64,
        data: &[u8],
    ) -> Result<(), Failure> {
        if let Some(first) = &self.header {
            tracing::warn!(
                "{}: another {TOPIC_SESSION} message at log_time {log_time_ns} ns; \
                 keeping the one at {} ns",
                self.file,
                first.log_time_ns
            );
            self.ignored += 1;
            return Ok(());
        }
        let msg = parse_header(&self.file, log_time_ns, data).map_err(Failure::Fatal)?;
        self.header = Some(Stamped {
            log_time_ns,
            publish_time_ns,
            msg,
        });
        Ok(())
    }

    pub(super) fn on_message(
        &mut self,
        channel_id: u16,
        log_time_ns: u64,
        publish_time_ns: u64,
        data: &[u8],
    ) -> Result<(), Failure> {
        self.messages += 1;
        self.span_ns = Some(match self.span_ns {
            None => (log_time_ns, log_time_ns),
            Some((a, b)) => (a.min(log_time_ns), b.max(log_time_ns)),
        });
        if self.raw_only {
            return Ok(());
        }
        let slot = self
            .slots
            .get(usize::from(channel_id))
            .copied()
            .unwrap_or(Slot::Undefined);
        match slot {
            Slot::Tracer(i) => {
                let msg = tracer_json::parse_compact(data)
                    .or_else(|| self.parse::<TracerSample>(channel_id, log_time_ns, data));
                if let Some(msg) = msg {
                    self.tracers.push(i, log_time_ns, publish_time_ns, msg);
                }
            }
            Slot::Env(i) => {
                if let Some(msg) = self.parse::<EnvSample>(channel_id, log_time_ns, data) {
                    self.env.push(i, log_time_ns, publish_time_ns, msg);
                }
            }
            Slot::Rotary(i) => {
                if let Some(msg) = self.parse::<RotaryStateSample>(channel_id, log_time_ns, data) {
                    self.rotary.push(i, log_time_ns, publish_time_ns, msg);
                }
            }
            Slot::Machine(i) => {
                if let Some(msg) = self.parse::<MachineStateSample>(channel_id, log_time_ns, data) {
                    self.machines.push(i, log_time_ns, publish_time_ns, msg);
                }
            }
            Slot::Probe(i) => {
                if let Some(msg) = self.parse::<ProbeSample>(channel_id, log_time_ns, data) {
                    self.probes.push(i, log_time_ns, publish_time_ns, msg);
                }
            }
            Slot::Json(i) => {
                if let Some(msg) = self.parse::<serde_json::Value>(channel_id, log_time_ns, data) {
                    self.json.push(i, log_time_ns, publish_time_ns, msg);
                }
            }
            Slot::Event => {
                let msg = event_json::parse_compact(data)
                    .or_else(|| self.parse::<RunEvent>(channel_id, log_time_ns, data));
                if let Some(msg) = msg {
                    self.events.push(Stamped {
                        log_time_ns,
                        publish_time_ns,
                        msg,
                    });
                }
            }
            Slot::Session if self.lazy_header => {
                self.raw_headers
                    .push((log_time_ns, publish_time_ns, data.to_vec()));
            }
            Slot::Session => self.session_message(log_time_ns, publish_time_ns, data)?,
            Slot::NotJson => self.skip(channel_id, log_time_ns, "message encoding is not json"),
            Slot::Other => self.ignored += 1,
            Slot::Undefined if self.lazy_header => {
                self.saw_undefined = true;
                self.ignored += 1;
            }
            Slot::Undefined => {
                if self.ignored == 0 {
                    tracing::warn!(
                        "{}: message at log_time {log_time_ns} ns on channel {channel_id}, \
                         which was never declared: ignored",
                        self.file
                    );
                }
                self.ignored += 1;
            }
        }
        Ok(())
    }

    pub(super) fn parse<T: DeserializeOwned>(
        &mut self,
        channel_id: u16,
        log_time_ns: u64,
        data: &[u8],
    ) -> Option<T> {
        match serde_json::from_slice(data) {
            Ok(msg) => Some(msg),
            Err(err) => {
                self.skip(channel_id, log_time_ns, &err.to_string());
                None
            }
        }
    }

    pub(super) fn skip(&mut self, channel_id: u16, log_time_ns: u64, why: &str) {
        self.skipped += 1;
        if self.skipped <= MAX_SKIP_WARNINGS {
            tracing::warn!(
                "{}: skipping the message on {} at log_time {log_time_ns} ns: {why}",
                self.file,
                self.topic_of(channel_id)
            );
        }
    }

    pub(super) fn topic_of(&self, channel_id: u16) -> String {
        match self.slots.get(usize::from(channel_id)) {
            Some(Slot::Tracer(i)) => format!("/tracer/{}/range", self.tracers.streams[*i].0),
            Some(Slot::Env(i)) => format!("/env/{}", self.env.streams[*i].0),
            Some(Slot::Rotary(i)) => format!("/rotary/{}/state", self.rotary.streams[*i].0),
            Some(Slot::Machine(i)) => format!("/machine/{}/state", self.machines.streams[*i].0),
            Some(Slot::Probe(i)) => format!("/probe/{}/reading", self.probes.streams[*i].0),
            Some(Slot::Json(i)) => self.json.streams[*i].0.clone(),
            Some(Slot::Event) => TOPIC_EVENT.to_owned(),
            Some(Slot::Session) => TOPIC_SESSION.to_owned(),
            _ => match self.raw.as_ref().and_then(|r| r.channels.get(&channel_id)) {
                Some(channel) => channel.topic.clone(),
                None => format!("channel {channel_id}"),
            },
        }
    }
}

/// Topics of plan kinds that the reader keeps as JSON for the kind's method.
pub(super) const KIND_TOPIC_PREFIXES: [&str; 3] = ["/probe/", "/machine/", "/hexapod/"];

pub(super) fn tracer_id(topic: &str) -> Option<&str> {
    let id = topic.strip_prefix("/tracer/")?.strip_suffix("/range")?;
    (!id.is_empty() && !id.contains('/')).then_some(id)
}

pub(super) fn env_id(topic: &str) -> Option<&str> {
    let id = topic.strip_prefix("/env/")?;
    (!id.is_empty() && !id.contains('/')).then_some(id)
}

pub(super) fn rotary_id(topic: &str) -> Option<&str> {
    let id = topic.strip_prefix("/rotary/")?.strip_suffix("/state")?;
    (!id.is_empty() && !id.contains('/')).then_some(id)
}

pub(super) fn machine_id(topic: &str) -> Option<&str> {
    let id = topic.strip_prefix("/machine/")?.strip_suffix("/state")?;
    (!id.is_empty() && !id.contains('/')).then_some(id)
}

pub(super) fn probe_id(topic: &str) -> Option<&str> {
    let id = topic.strip_prefix("/probe/")?.strip_suffix("/reading")?;
    (!id.is_empty() && !id.contains('/')).then_some(id)
}

pub(super) fn parse_header(
    file: &str,
    log_time_ns: u64,
    data: &[u8],
) -> Result<SessionHeader, ReadError> {
    #[derive(Deserialize)]
    struct FormatOnly {
        format: Option<String>,
    }
    let wrong_format = |found: String| ReadError::WrongFormat {
        file: file.to_owned(),
        found,
    };
    match serde_json::from_slice::<SessionHeader>(data) {
        Ok(h) if h.format == SESSION_FORMAT => Ok(h),
        Ok(h) => Err(wrong_format(h.format)),
        Err(error) => match serde_json::from_slice::<FormatOnly>(data) {
            // A header of another format version fails for that reason first.
            Ok(FormatOnly {
                format: Some(found),
            }) if found != SESSION_FORMAT => Err(wrong_format(found)),
            _ => Err(ReadError::BadHeader {
                file: file.to_owned(),
                log_time_ns,
                error,
            }),
        },
    }
}
