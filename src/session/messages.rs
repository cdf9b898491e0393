//! The geocal-session/1 message types (../docs/session-format.md) and their JSON Schemas.
//! Readers ignore unknown fields and default missing optional ones, as the contract says.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

pub use super::axis_map::{AxisMap, Name};

pub const SESSION_FORMAT: &str = "geocal-session/1";

pub const TOPIC_SESSION: &str = "/geocal/session";
pub const TOPIC_EVENT: &str = "/run/event";
pub fn tracer_topic(id: &str) -> String {
    format!("/tracer/{id}/range")
}
pub fn env_topic(id: &str) -> String {
    format!("/env/{id}")
}
pub fn rotary_topic(id: &str) -> String {
    format!("/rotary/{id}/state")
}
/// Raw readings of a displacement probe (plan kind `rotary_sphere`).
pub fn machine_state_topic(id: &str) -> String {
    format!("/machine/{id}/state")
}
pub fn probe_topic(id: &str) -> String {
    format!("/probe/{id}/reading")
}

pub const SCHEMA_SESSION: &str = "geocal.Session";
pub const SCHEMA_TRACER: &str = "geocal.TracerSample";
pub const SCHEMA_ENV: &str = "geocal.EnvSample";
pub const SCHEMA_EVENT: &str = "geocal.RunEvent";
pub const SCHEMA_ROTARY: &str = "geocal.RotaryState";
pub const SCHEMA_MACHINE: &str = "geocal.MachineState";
pub const SCHEMA_PROBE: &str = "geocal.ProbeReading";

/// `/geocal/session`: exactly one, first in the file.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct SessionHeader {
    pub format: String,
    pub session_id: String,
    pub started_at: String,
    pub kind: String,
    pub machine: MachineInfo,
    #[serde(default)]
    pub devices: Vec<DeviceInfo>,
    #[serde(default)]
    pub plan: serde_json::Value,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct MachineInfo {
    #[serde(default)]
    pub name: String,
    pub structure: String,
    pub axes: Vec<String>,
    #[serde(default)]
    pub travel_m: BTreeMap<String, [f64; 2]>,
    #[serde(default)]
    pub targets: Vec<TargetInfo>,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct TargetInfo {
    pub id: String,
    pub offset_m: [f64; 3],
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct DeviceInfo {
    pub id: String,
    pub kind: String,
    pub driver: String,
    /// Per-sample sigma = noise_m + noise_ppm * 1e-6 * (|station - target| + dead_path_m):
    /// the ppm term is of the absolute optical path, dead path included.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub noise_m: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub noise_ppm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dead_path_m: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub wavelength_m: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub compensated: Option<bool>,
    /// Anything else the device declares (sample rate, port, ...).
    #[serde(flatten)]
    pub extra: BTreeMap<String, serde_json::Value>,
}

/// `/tracer/<id>/range`.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
pub struct TracerSample {
    pub seq: u64,
    pub t_s: f64,
    pub length_m: f64,
    #[serde(default = "default_signal")]
    pub signal: f64,
    #[serde(default = "default_true")]
    pub tracking: bool,
    #[serde(default)]
    pub beam_segment: u32,
}

fn default_signal() -> f64 {
    1.0
}
fn default_true() -> bool {
    true
}

/// `/env/<id>`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct EnvSample {
    pub t_s: f64,
    pub air_temp_k: f64,
    pub pressure_pa: f64,
    pub humidity_pct: f64,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub material_temp_k: Vec<f64>,
}

/// `/rotary/<id>/state`: the table's state as the sequencer saw it while commanding it.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
pub struct RotaryStateSample {
    /// Seconds since the run started (the table reports no time of its own).
    pub t_s: f64,
    /// The absolute angle last commanded, radians.
    pub commanded_rad: f64,
    /// The encoder angle once in position, radians; null while moving.
    #[serde(default)]
    pub encoder_rad: Option<f64>,
    pub in_position: bool,
}

/// `/machine/<id>/state`: a machine controller's status as polled (GRBL `?`; `geocal monitor`).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct MachineStateSample {
    /// Host time of the report, seconds since recording started.
    pub t_s: f64,
    /// The controller's state as it names it (`Idle`, `Run`, `Hold`, `Alarm`, ...).
    pub state: String,
    /// Reported X, Y, Z position, metres.
    pub position_m: [f64; 3],
    /// `machine` (GRBL `MPos`) or `work` (`WPos`) coordinates.
    pub frame: String,
    /// Current feed if reported, m/s.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub feed_m_s: Option<f64>,
}

/// `/probe/<id>/reading`: one raw reading of a displacement probe, as the driver reported it.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
pub struct ProbeSample {
    /// Readings counted from 1 by the sequencer.
    pub seq: u64,
    /// Device (driver) time of the reading, seconds.
    pub t_s: f64,
    /// Displacement along the probing direction, metres; null when the probe reported out of
    /// range (the reading is kept so the count shows it; a `fault` event says so too).
    pub value_m: Option<f64>,
}

/// `/run/event`: what the sequencer did, in order. Unknown kinds are kept as `Other`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(tag = "kind", rename_all = "snake_case", try_from = "WireEvent")]
pub enum RunEvent {
    StationBegin {
        station: Name,
        station_index: usize,
        #[serde(default)]
        hint_m: Option<[f64; 3]>,
    },
    PointBegin {
        station: Name,
        point: usize,
        pass: usize,
        #[serde(default)]
        target: Name,
        nominal_m: [f64; 3],
        #[serde(default)]
        axes: AxisMap<f64>,
        #[serde(default)]
        approach: AxisMap<i8>,
    },
    PointEnd {
        station: Name,
        point: usize,
        pass: usize,
    },
    StationEnd {
        station: Name,
    },
    Rehome {
        station: Name,
        beam_segment: u32,
    },
    Rotation {
        table: String,
        commanded_rad: f64,
        /// The table was sent here first, so that it approached `commanded_rad` from this side.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        via_rad: Option<f64>,
    },
    Fault {
        device: String,
        code: String,
        message: String,
    },
    /// Plan kind `rotary_sphere`: the sphere at height `height_index` is probed with the table
    /// in position at `commanded_rad` (the `angle_index`-th commanded angle).
    SphereBegin {
        height_index: usize,
        angle_index: usize,
        commanded_rad: f64,
    },
    /// One probed point: the probe approaches `nominal_m` (the nominal surface point) along
    /// −`direction` (the outward nominal normal); the readings until `probe_point_end` belong
    /// to it (the measured point is nominal_m − value_m · direction).
    ProbePointBegin {
        height_index: usize,
        angle_index: usize,
        point: usize,
        nominal_m: [f64; 3],
        direction: [f64; 3],
    },
    ProbePointEnd {
        height_index: usize,
        angle_index: usize,
        point: usize,
    },
    SphereEnd {
        height_index: usize,
        angle_index: usize,
    },
    /// `geocal run --resume`: the run was interrupted and continues here (src/run/resume.rs).
    /// Everything before this event was copied from the interrupted file; a window left open
    /// by the interruption is not used. `point` is where the run continues (None: nothing
    /// was left to measure).
    Resume {
        resume_index: u32,
        messages_kept: u64,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        station: Option<Name>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        target: Option<Name>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        pass: Option<usize>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        point: Option<usize>,
        /// Where a `rotary_sphere` run continues: the first unfinished sphere.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        height_index: Option<usize>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        angle_index: Option<usize>,
        /// Where a run measured posture by posture continues: the first unfinished posture,
        /// measured again in full.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        posture: Option<usize>,
        /// Where a run measured pose by pose continues: the first unfinished pose.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        pose: Option<usize>,
    },
    /// Passive mode: the machine stopped where no point was expected, or left before its
    /// dwell was complete (src/sequencer/passive.rs). `point`/`pass` name the stop that was
    /// expected; a window open at this event is not used.
    UnplannedStop {
        station: Name,
        target: Name,
        pass: usize,
        point: usize,
        message: String,
    },
    /// Plan kind `probe_install`: the machine takes rotary posture `posture` (A, B).
    PostureBegin {
        posture: usize,
        a_rad: f64,
        b_rad: f64,
    },
    PostureEnd {
        posture: usize,
    },
    /// Plan kind `probe_install`: the machine is at sphere point `point` of `posture`
    /// (commanded `axes`); the probe readings until `probe_end` belong to it.
    ProbeBegin {
        posture: usize,
        point: usize,
        axes: AxisMap<f64>,
    },
    ProbeEnd {
        posture: usize,
        point: usize,
    },
    /// Plan kind `hexapod`: the platform is commanded to pose `pose` (`axes`: x, y, z in
    /// metres and rx, ry, rz, the rotation vector in radians); its leg readings and measured
    /// pose until `pose_end` belong to it.
    PoseBegin {
        pose: usize,
        axes: AxisMap<f64>,
    },
    PoseEnd {
        pose: usize,
    },
    /// The controller's compensation trims at the end of a point's dwell (a real controller
    /// that exposes them: LinuxCNC in a real-controller HIL run), after its `point_end`.
    ControllerTrims {
        station: Name,
        point: usize,
        pass: usize,
        joints: Vec<geocal_drivers::ControllerTrim>,
    },
    /// A span of the original recording that `geocal repair` could not copy (a damaged or
    /// truncated part): a window that touches it is dropped, as in the damaged file.
    DataLost {
        lost: super::damage::DamagedChunk,
    },
    #[serde(other)]
    Other,
}

/// How a `RunEvent` is read: one flat object with every field optional, checked per kind
/// afterwards. Serde's internally tagged enums buffer each message into a tree first, which
/// cost about a third of the time to read a large session.
#[derive(Deserialize)]
struct WireEvent {
    kind: Name,
    station: Option<Name>,
    station_index: Option<usize>,
    hint_m: Option<[f64; 3]>,
    point: Option<usize>,
    pass: Option<usize>,
    target: Option<Name>,
    nominal_m: Option<[f64; 3]>,
    axes: Option<AxisMap<f64>>,
    approach: Option<AxisMap<i8>>,
    beam_segment: Option<u32>,
    table: Option<String>,
    commanded_rad: Option<f64>,
    via_rad: Option<f64>,
    device: Option<String>,
    code: Option<String>,
    message: Option<String>,
    height_index: Option<usize>,
    angle_index: Option<usize>,
    direction: Option<[f64; 3]>,
    resume_index: Option<u32>,
    messages_kept: Option<u64>,
    posture: Option<usize>,
    a_rad: Option<f64>,
    b_rad: Option<f64>,
    pose: Option<usize>,
    joints: Option<Vec<geocal_drivers::ControllerTrim>>,
    lost: Option<super::damage::DamagedChunk>,
}

impl TryFrom<WireEvent> for RunEvent {
    type Error = String;

    fn try_from(w: WireEvent) -> Result<Self, Self::Error> {
        let kind = w.kind.as_str();
        let need = |field: &'static str| format!("missing field `{field}` in a `{kind}` event");
        Ok(match kind {
            "station_begin" => RunEvent::StationBegin {
                station: w.station.ok_or_else(|| need("station"))?,
                station_index: w.station_index.ok_or_else(|| need("station_index"))?,
                hint_m: w.hint_m,
            },
            "point_begin" => RunEvent::PointBegin {
                station: w.station.ok_or_else(|| need("station"))?,
                point: w.point.ok_or_else(|| need("point"))?,
                pass: w.pass.ok_or_else(|| need("pass"))?,
                target: w.target.unwrap_or_default(),
                nominal_m: w.nominal_m.ok_or_else(|| need("nominal_m"))?,
                axes: w.axes.unwrap_or_default(),
                approach: w.approach.unwrap_or_default(),
            },
            "point_end" => RunEvent::PointEnd {
                station: w.station.ok_or_else(|| need("station"))?,
                point: w.point.ok_or_else(|| need("point"))?,
                pass: w.pass.ok_or_else(|| need("pass"))?,
            },
            "controller_trims" => RunEvent::ControllerTrims {
                station: w.station.ok_or_else(|| need("station"))?,
                point: w.point.ok_or_else(|| need("point"))?,
                pass: w.pass.ok_or_else(|| need("pass"))?,
                joints: w.joints.ok_or_else(|| need("joints"))?,
            },
            "data_lost" => RunEvent::DataLost {
                lost: w.lost.ok_or_else(|| need("lost"))?,
            },
            "station_end" => RunEvent::StationEnd {
                station: w.station.ok_or_else(|| need("station"))?,
            },
            "rehome" => RunEvent::Rehome {
                station: w.station.ok_or_else(|| need("station"))?,
                beam_segment: w.beam_segment.ok_or_else(|| need("beam_segment"))?,
            },
            "rotation" => RunEvent::Rotation {
                table: w.table.ok_or_else(|| need("table"))?,
                commanded_rad: w.commanded_rad.ok_or_else(|| need("commanded_rad"))?,
                via_rad: w.via_rad,
            },
            "fault" => RunEvent::Fault {
                device: w.device.ok_or_else(|| need("device"))?,
                code: w.code.ok_or_else(|| need("code"))?,
                message: w.message.ok_or_else(|| need("message"))?,
            },
            "sphere_begin" => RunEvent::SphereBegin {
                height_index: w.height_index.ok_or_else(|| need("height_index"))?,
                angle_index: w.angle_index.ok_or_else(|| need("angle_index"))?,
                commanded_rad: w.commanded_rad.ok_or_else(|| need("commanded_rad"))?,
            },
            "probe_point_begin" => RunEvent::ProbePointBegin {
                height_index: w.height_index.ok_or_else(|| need("height_index"))?,
                angle_index: w.angle_index.ok_or_else(|| need("angle_index"))?,
                point: w.point.ok_or_else(|| need("point"))?,
                nominal_m: w.nominal_m.ok_or_else(|| need("nominal_m"))?,
                direction: w.direction.ok_or_else(|| need("direction"))?,
            },
            "probe_point_end" => RunEvent::ProbePointEnd {
                height_index: w.height_index.ok_or_else(|| need("height_index"))?,
                angle_index: w.angle_index.ok_or_else(|| need("angle_index"))?,
                point: w.point.ok_or_else(|| need("point"))?,
            },
            "sphere_end" => RunEvent::SphereEnd {
                height_index: w.height_index.ok_or_else(|| need("height_index"))?,
                angle_index: w.angle_index.ok_or_else(|| need("angle_index"))?,
            },
            "resume" => RunEvent::Resume {
                resume_index: w.resume_index.ok_or_else(|| need("resume_index"))?,
                messages_kept: w.messages_kept.ok_or_else(|| need("messages_kept"))?,
                station: w.station,
                target: w.target,
                pass: w.pass,
                point: w.point,
                height_index: w.height_index,
                angle_index: w.angle_index,
                posture: w.posture,
                pose: w.pose,
            },
            "unplanned_stop" => RunEvent::UnplannedStop {
                station: w.station.ok_or_else(|| need("station"))?,
                target: w.target.unwrap_or_default(),
                pass: w.pass.ok_or_else(|| need("pass"))?,
                point: w.point.ok_or_else(|| need("point"))?,
                message: w.message.unwrap_or_default(),
            },
            "posture_begin" => RunEvent::PostureBegin {
                posture: w.posture.ok_or_else(|| need("posture"))?,
                a_rad: w.a_rad.ok_or_else(|| need("a_rad"))?,
                b_rad: w.b_rad.ok_or_else(|| need("b_rad"))?,
            },
            "posture_end" => RunEvent::PostureEnd {
                posture: w.posture.ok_or_else(|| need("posture"))?,
            },
            "probe_begin" => RunEvent::ProbeBegin {
                posture: w.posture.ok_or_else(|| need("posture"))?,
                point: w.point.ok_or_else(|| need("point"))?,
                axes: w.axes.unwrap_or_default(),
            },
            "probe_end" => RunEvent::ProbeEnd {
                posture: w.posture.ok_or_else(|| need("posture"))?,
                point: w.point.ok_or_else(|| need("point"))?,
            },
            "pose_begin" => RunEvent::PoseBegin {
                pose: w.pose.ok_or_else(|| need("pose"))?,
                axes: w.axes.unwrap_or_default(),
            },
            "pose_end" => RunEvent::PoseEnd {
                pose: w.pose.ok_or_else(|| need("pose"))?,
            },
            _ => RunEvent::Other,
        })
    }
}

/// A header's `started_at`: the epoch (ns since 1970, UTC) in RFC 3339.
pub fn started_at(epoch_ns: u64) -> String {
    time::OffsetDateTime::from_unix_timestamp_nanos(epoch_ns as i128)
        .ok()
        .and_then(|t| {
            t.format(&time::format_description::well_known::Rfc3339)
                .ok()
        })
        .unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn events_round_trip_and_unknown_kinds_are_kept_as_other() {
        let events = [
            RunEvent::StationBegin {
                station: "s1".into(),
                station_index: 0,
                hint_m: None,
            },
            RunEvent::PointBegin {
                station: "s1".into(),
                point: 3,
                pass: 1,
                target: "t0".into(),
                nominal_m: [0.1, 0.2, 0.3],
                axes: AxisMap::from([("x", 0.1)]),
                approach: AxisMap::from([("x", -1)]),
            },
            RunEvent::PointEnd {
                station: "s1".into(),
                point: 3,
                pass: 1,
            },
            RunEvent::StationEnd {
                station: "s1".into(),
            },
            RunEvent::Rehome {
                station: "s1".into(),
                beam_segment: 2,
            },
            RunEvent::Rotation {
                table: "c".into(),
                commanded_rad: 0.5,
                via_rad: None,
            },
            RunEvent::Rotation {
                table: "c".into(),
                commanded_rad: 0.5,
                via_rad: Some(0.45),
            },
            RunEvent::Fault {
                device: "tracer0".into(),
                code: "timeout".into(),
                message: "late".into(),
            },
            RunEvent::SphereBegin {
                height_index: 1,
                angle_index: 4,
                commanded_rad: 0.7,
            },
            RunEvent::ProbePointBegin {
                height_index: 1,
                angle_index: 4,
                point: 2,
                nominal_m: [0.07, 0.01, 0.18],
                direction: [0.0, 0.0, 1.0],
            },
            RunEvent::ProbePointEnd {
                height_index: 1,
                angle_index: 4,
                point: 2,
            },
            RunEvent::SphereEnd {
                height_index: 1,
                angle_index: 4,
            },
            RunEvent::Resume {
                resume_index: 1,
                messages_kept: 1234,
                station: Some("s2".into()),
                target: Some("t0".into()),
                pass: Some(1),
                point: Some(7),
                height_index: None,
                angle_index: None,
                posture: None,
                pose: None,
            },
            RunEvent::Resume {
                resume_index: 2,
                messages_kept: 99,
                station: None,
                target: None,
                pass: None,
                point: None,
                height_index: Some(2),
                angle_index: Some(17),
                posture: None,
                pose: None,
            },
            RunEvent::Resume {
                resume_index: 1,
                messages_kept: 7,
                station: None,
                target: None,
                pass: None,
                point: None,
                height_index: None,
                angle_index: None,
                posture: Some(2),
                pose: None,
            },
            RunEvent::Resume {
                resume_index: 1,
                messages_kept: 8,
                station: None,
                target: None,
                pass: None,
                point: None,
                height_index: None,
                angle_index: None,
                posture: None,
                pose: Some(11),
            },
            RunEvent::PostureBegin {
                posture: 1,
                a_rad: 1.5,
                b_rad: 0.0,
            },
            RunEvent::PostureEnd { posture: 1 },
            RunEvent::ProbeBegin {
                posture: 1,
                point: 4,
                axes: AxisMap::from([("a", 1.5)]),
            },
            RunEvent::ProbeEnd {
                posture: 1,
                point: 4,
            },
            RunEvent::PoseBegin {
                pose: 2,
                axes: AxisMap::from([("rz", 0.1)]),
            },
            RunEvent::PoseEnd { pose: 2 },
        ];
        for e in events {
            let json = serde_json::to_string(&e).expect("serialise");
            assert_eq!(serde_json::from_str::<RunEvent>(&json).expect(&json), e);
        }
        let other: RunEvent =
            serde_json::from_str(r#"{"kind":"vendor_marker","n":3}"#).expect("unknown kind");
        assert_eq!(other, RunEvent::Other);
    }

    #[test]
    fn a_missing_required_field_is_named() {
        let err =
            serde_json::from_str::<RunEvent>(r#"{"kind":"point_end","station":"s1","point":2}"#)
                .expect_err("pass is required");
        assert!(
            err.to_string()
                .contains("missing field `pass` in a `point_end` event"),
            "{err}"
        );
        // Defaults of optional fields, null hints and extra fields are accepted.
        let e: RunEvent = serde_json::from_str(
            r#"{"kind":"station_begin","station":"s2","station_index":1,"hint_m":null,"extra":true}"#,
        )
        .expect("valid");
        assert!(matches!(e, RunEvent::StationBegin { hint_m: None, .. }));
    }
}

/// JSON Schema (draft 2020-12) of each channel's messages.
pub mod schema {
    pub const SESSION: &str = r#"{
  "$schema": "https://json-schema.org/draft/2020-12/schema",
  "title": "geocal.Session",
  "type": "object",
  "required": ["format", "session_id", "started_at", "kind", "machine"],
  "properties": {
    "format": {"const": "geocal-session/1"},
    "session_id": {"type": "string"},
    "started_at": {"type": "string"},
    "kind": {"type": "string"},
    "machine": {
      "type": "object",
      "required": ["structure", "axes"],
      "properties": {
        "name": {"type": "string"},
        "structure": {"type": "string"},
        "axes": {"type": "array", "items": {"type": "string"}},
        "travel_m": {"type": "object", "additionalProperties": {"type": "array", "items": {"type": "number"}, "minItems": 2, "maxItems": 2}},
        "targets": {"type": "array", "items": {"type": "object", "required": ["id", "offset_m"],
          "properties": {"id": {"type": "string"}, "offset_m": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3}}}}
      }
    },
    "devices": {"type": "array", "items": {"type": "object", "required": ["id", "kind", "driver"],
      "properties": {"id": {"type": "string"}, "kind": {"type": "string"}, "driver": {"type": "string"},
        "noise_m": {"type": "number"}, "noise_ppm": {"type": "number"}, "dead_path_m": {"type": "number"},
        "wavelength_m": {"type": "number"}, "compensated": {"type": "boolean"}}}},
    "plan": {"type": "object"}
  }
}"#;

    pub const TRACER: &str = r#"{
  "$schema": "https://json-schema.org/draft/2020-12/schema",
  "title": "geocal.TracerSample",
  "type": "object",
  "required": ["seq", "t_s", "length_m"],
  "properties": {
    "seq": {"type": "integer", "minimum": 0},
    "t_s": {"type": "number"},
    "length_m": {"type": "number"},
    "signal": {"type": "number"},
    "tracking": {"type": "boolean"},
    "beam_segment": {"type": "integer", "minimum": 0}
  }
}"#;

    pub const ENV: &str = r#"{
  "$schema": "https://json-schema.org/draft/2020-12/schema",
  "title": "geocal.EnvSample",
  "type": "object",
  "required": ["t_s", "air_temp_k", "pressure_pa", "humidity_pct"],
  "properties": {
    "t_s": {"type": "number"},
    "air_temp_k": {"type": "number"},
    "pressure_pa": {"type": "number"},
    "humidity_pct": {"type": "number"},
    "material_temp_k": {"type": "array", "items": {"type": "number"}}
  }
}"#;

    pub const ROTARY: &str = r#"{
  "$schema": "https://json-schema.org/draft/2020-12/schema",
  "title": "geocal.RotaryState",
  "type": "object",
  "required": ["t_s", "commanded_rad", "in_position"],
  "properties": {
    "t_s": {"type": "number"},
    "commanded_rad": {"type": "number"},
    "encoder_rad": {"type": ["number", "null"]},
    "in_position": {"type": "boolean"}
  }
}"#;

    pub const MACHINE: &str = r#"{
  "$schema": "https://json-schema.org/draft/2020-12/schema",
  "title": "geocal.MachineState",
  "type": "object",
  "required": ["t_s", "state", "position_m", "frame"],
  "properties": {
    "t_s": {"type": "number"},
    "state": {"type": "string"},
    "position_m": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3},
    "frame": {"enum": ["machine", "work"]},
    "feed_m_s": {"type": "number"}
  }
}"#;

    pub const PROBE: &str = r#"{
  "$schema": "https://json-schema.org/draft/2020-12/schema",
  "title": "geocal.ProbeReading",
  "type": "object",
  "required": ["seq", "t_s", "value_m"],
  "properties": {
    "seq": {"type": "integer", "minimum": 0},
    "t_s": {"type": "number"},
    "value_m": {"type": ["number", "null"]}
  }
}"#;

    pub const EVENT: &str = r#"{
  "$schema": "https://json-schema.org/draft/2020-12/schema",
  "title": "geocal.RunEvent",
  "type": "object",
  "required": ["kind"],
  "properties": {
    "kind": {"type": "string"},
    "station": {"type": "string"},
    "station_index": {"type": "integer", "minimum": 0},
    "hint_m": {"anyOf": [{"type": "null"}, {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3}]},
    "point": {"type": "integer", "minimum": 0},
    "pass": {"type": "integer", "minimum": 0},
    "target": {"type": "string"},
    "nominal_m": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3},
    "axes": {"type": "object", "additionalProperties": {"type": "number"}},
    "approach": {"type": "object", "additionalProperties": {"type": "integer", "minimum": -1, "maximum": 1}},
    "beam_segment": {"type": "integer", "minimum": 0},
    "table": {"type": "string"},
    "commanded_rad": {"type": "number"},
    "via_rad": {"type": "number"},
    "device": {"type": "string"},
    "code": {"type": "string"},
    "message": {"type": "string"},
    "height_index": {"type": "integer", "minimum": 0},
    "angle_index": {"type": "integer", "minimum": 0},
    "direction": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3},
    "resume_index": {"type": "integer", "minimum": 1},
    "messages_kept": {"type": "integer", "minimum": 0},
    "posture": {"type": "integer", "minimum": 0},
    "a_rad": {"type": "number"},
    "b_rad": {"type": "number"},
    "pose": {"type": "integer", "minimum": 0}
  },
  "allOf": [
    {"if": {"properties": {"kind": {"const": "point_begin"}}},
     "then": {"required": ["station", "point", "pass", "nominal_m"]}},
    {"if": {"properties": {"kind": {"const": "point_end"}}},
     "then": {"required": ["station", "point", "pass"]}},
    {"if": {"properties": {"kind": {"const": "station_begin"}}},
     "then": {"required": ["station", "station_index"]}},
    {"if": {"properties": {"kind": {"const": "rotation"}}},
     "then": {"required": ["table", "commanded_rad"]}},
    {"if": {"properties": {"kind": {"const": "fault"}}},
     "then": {"required": ["device", "code", "message"]}},
    {"if": {"properties": {"kind": {"const": "sphere_begin"}}},
     "then": {"required": ["height_index", "angle_index", "commanded_rad"]}},
    {"if": {"properties": {"kind": {"const": "probe_point_begin"}}},
     "then": {"required": ["height_index", "angle_index", "point", "nominal_m", "direction"]}},
    {"if": {"properties": {"kind": {"const": "probe_point_end"}}},
     "then": {"required": ["height_index", "angle_index", "point"]}},
    {"if": {"properties": {"kind": {"const": "sphere_end"}}},
     "then": {"required": ["height_index", "angle_index"]}},
    {"if": {"properties": {"kind": {"const": "unplanned_stop"}}},
     "then": {"required": ["station", "pass", "point"]}},
    {"if": {"properties": {"kind": {"const": "resume"}}},
     "then": {"required": ["resume_index", "messages_kept"]}},
    {"if": {"properties": {"kind": {"const": "posture_begin"}}},
     "then": {"required": ["posture", "a_rad", "b_rad"]}},
    {"if": {"properties": {"kind": {"const": "posture_end"}}},
     "then": {"required": ["posture"]}},
    {"if": {"properties": {"kind": {"enum": ["probe_begin", "probe_end"]}}},
     "then": {"required": ["posture", "point"]}},
    {"if": {"properties": {"kind": {"enum": ["pose_begin", "pose_end"]}}},
     "then": {"required": ["pose"]}}
  ]
}"#;
}
