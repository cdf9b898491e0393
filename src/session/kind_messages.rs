//! Messages of the `probe_install` and `hexapod` plan kinds (docs/session-format.md): machine
//! axis positions, leg encoder readings and measured platform poses (probe readings are the
//! core `/probe/<id>/reading` stream, `messages::ProbeSample`).
//!
//! They are written and read as plain JSON topics (`RecorderHandle::json`,
//! `Session::topics`); each topic's schema is here beside its type.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use super::recorder::TopicSchema;

/// `/machine/pose`: the commanded and reported axis positions of a multi-axis machine.
pub const TOPIC_MACHINE_POSE: &str = "/machine/pose";
/// `/hexapod/<id>/legs`: the six leg encoder readings.
pub fn hexapod_legs_topic(id: &str) -> String {
    format!("/hexapod/{id}/legs")
}
/// `/hexapod/<id>/pose`: the measured platform pose.
pub fn hexapod_pose_topic(id: &str) -> String {
    format!("/hexapod/{id}/pose")
}

/// `/machine/pose`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct MachinePoseSample {
    /// Seconds since the run started.
    pub t_s: f64,
    /// Commanded axis positions: linear axes in metres, rotary axes (`a`, `b`) in radians.
    pub commanded: BTreeMap<String, f64>,
    /// Positions the machine reported at rest (same units); empty if it reports none.
    #[serde(default)]
    pub reported: BTreeMap<String, f64>,
}

/// `/hexapod/<id>/legs`.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
pub struct LegSample {
    pub t_s: f64,
    /// Encoder leg lengths (relative: an unknown constant per leg), metres.
    pub lengths_m: [f64; 6],
}

/// `/hexapod/<id>/pose`.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
pub struct PlatformPoseSample {
    pub t_s: f64,
    /// x_fixed = R(rotation_vector_rad) · x_platform + translation_m.
    pub rotation_vector_rad: [f64; 3],
    pub translation_m: [f64; 3],
}

pub const SCHEMA_MACHINE_POSE: TopicSchema = TopicSchema {
    name: "geocal.MachinePose",
    text: r#"{
  "$schema": "https://json-schema.org/draft/2020-12/schema",
  "title": "geocal.MachinePose",
  "type": "object",
  "required": ["t_s", "commanded"],
  "properties": {
    "t_s": {"type": "number"},
    "commanded": {"type": "object", "additionalProperties": {"type": "number"}},
    "reported": {"type": "object", "additionalProperties": {"type": "number"}}
  }
}"#,
};

pub const SCHEMA_LEGS: TopicSchema = TopicSchema {
    name: "geocal.HexapodLegs",
    text: r#"{
  "$schema": "https://json-schema.org/draft/2020-12/schema",
  "title": "geocal.HexapodLegs",
  "type": "object",
  "required": ["t_s", "lengths_m"],
  "properties": {
    "t_s": {"type": "number"},
    "lengths_m": {"type": "array", "items": {"type": "number"}, "minItems": 6, "maxItems": 6}
  }
}"#,
};

pub const SCHEMA_PLATFORM_POSE: TopicSchema = TopicSchema {
    name: "geocal.PlatformPose",
    text: r#"{
  "$schema": "https://json-schema.org/draft/2020-12/schema",
  "title": "geocal.PlatformPose",
  "type": "object",
  "required": ["t_s", "rotation_vector_rad", "translation_m"],
  "properties": {
    "t_s": {"type": "number"},
    "rotation_vector_rad": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3},
    "translation_m": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3}
  }
}"#,
};

/// Serialise a message for `RecorderHandle::json` (these types hold only numbers and
/// strings, so this cannot fail except on non-finite numbers, which become `null`).
pub fn to_value<T: Serialize>(msg: &T) -> serde_json::Value {
    serde_json::to_value(msg).unwrap_or(serde_json::Value::Null)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn schemas_are_json_and_messages_round_trip() {
        for s in [SCHEMA_MACHINE_POSE, SCHEMA_LEGS, SCHEMA_PLATFORM_POSE] {
            let v: serde_json::Value = serde_json::from_str(s.text).expect(s.name);
            assert_eq!(v["title"], s.name);
        }
        let r = LegSample {
            t_s: 1.5,
            lengths_m: [0.1, 0.2, 0.3, 0.4, 0.5, 0.6],
        };
        let back: LegSample = serde_json::from_value(to_value(&r)).expect("legs");
        assert_eq!(back, r);
        assert_eq!(hexapod_legs_topic("h"), "/hexapod/h/legs");
        assert_eq!(hexapod_pose_topic("h"), "/hexapod/h/pose");
    }
}
