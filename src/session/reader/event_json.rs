//! A typed fast path for the run events a dwell plan records once per point, `point_begin`
//! and `point_end`, in the exact form geocal's recorder writes them (serde_json's compact
//! output, fields in declaration order, strings without escapes). Anything else returns None
//! and goes through serde_json (`WireEvent`), so the result is always the one serde_json
//! gives; only the common case is faster (no struct of thirty optional fields per event).

use super::tracer_json::Cursor;
use crate::session::messages::{AxisMap, Name, RunEvent};

/// The event, when `data` is exactly
/// `{"kind":"point_begin","station":S,"point":U,"pass":U,"target":S,"nominal_m":[F,F,F],
/// "axes":{S:F,...},"approach":{S:I,...}}` or `{"kind":"point_end","station":S,"point":U,
/// "pass":U}`.
pub(super) fn parse_compact(data: &[u8]) -> Option<RunEvent> {
    let mut p = Cursor { data, at: 0 };
    p.literal(b"{\"kind\":\"point_")?;
    let begin = if p.literal(b"begin\"").is_some() {
        true
    } else {
        p.literal(b"end\"")?;
        false
    };
    p.literal(b",\"station\":")?;
    let station = string(&mut p)?;
    p.literal(b",\"point\":")?;
    let point = usize::try_from(p.unsigned()?).ok()?;
    p.literal(b",\"pass\":")?;
    let pass = usize::try_from(p.unsigned()?).ok()?;
    let event = if begin {
        p.literal(b",\"target\":")?;
        let target = string(&mut p)?;
        p.literal(b",\"nominal_m\":[")?;
        let x = p.float()?;
        p.literal(b",")?;
        let y = p.float()?;
        p.literal(b",")?;
        let z = p.float()?;
        p.literal(b"],\"axes\":")?;
        let axes = map(&mut p, |p| p.float())?;
        p.literal(b",\"approach\":")?;
        let approach = map(&mut p, small_integer)?;
        RunEvent::PointBegin {
            station,
            point,
            pass,
            target,
            nominal_m: [x, y, z],
            axes,
            approach,
        }
    } else {
        RunEvent::PointEnd {
            station,
            point,
            pass,
        }
    };
    p.literal(b"}")?;
    (p.at == data.len()).then_some(event)
}

/// A JSON string without escapes or control characters, valid UTF-8.
fn string(p: &mut Cursor<'_>) -> Option<Name> {
    p.literal(b"\"")?;
    let rest = p.data.get(p.at..)?;
    let len = rest
        .iter()
        .position(|&b| b == b'"' || b == b'\\' || b < 0x20)?;
    if rest[len] != b'"' {
        return None;
    }
    let text = std::str::from_utf8(&rest[..len]).ok()?;
    p.at += len + 1;
    Some(Name::new(text))
}

/// A JSON object of such strings to values read by `value` (a repeated key keeps its last
/// value, as serde_json's map does).
fn map<'a, T>(
    p: &mut Cursor<'a>,
    value: impl Fn(&mut Cursor<'a>) -> Option<T>,
) -> Option<AxisMap<T>> {
    p.literal(b"{")?;
    let mut entries = AxisMap::new();
    if p.literal(b"}").is_some() {
        return Some(entries);
    }
    loop {
        let key = string(p)?;
        p.literal(b":")?;
        entries.insert(key, value(p)?);
        if p.literal(b"}").is_some() {
            return Some(entries);
        }
        p.literal(b",")?;
    }
}

/// A JSON integer that fits an i8 (serde_json reads "-0" as a float, which an i8 refuses).
fn small_integer(p: &mut Cursor<'_>) -> Option<i8> {
    let negative = p.literal(b"-").is_some();
    let magnitude = i64::try_from(p.unsigned()?).ok()?;
    match (negative, magnitude) {
        (true, 0) => None,
        (true, m) => i8::try_from(-m).ok(),
        (false, m) => i8::try_from(m).ok(),
    }
}

#[cfg(test)]
mod tests {
    use proptest::prelude::*;

    use super::*;

    fn serde(data: &[u8]) -> Option<RunEvent> {
        serde_json::from_slice(data).ok()
    }

    fn point_begin(nominal_m: [f64; 3], approach: i8) -> RunEvent {
        RunEvent::PointBegin {
            station: "s1".into(),
            point: 42,
            pass: 1,
            target: "t0".into(),
            nominal_m,
            axes: AxisMap::from([("x", 0.1), ("y", -2.5), ("z", 1e-3)]),
            approach: AxisMap::from([("x", approach), ("y", 0), ("z", 1)]),
        }
    }

    #[test]
    fn recorder_output_takes_the_fast_path() {
        for event in [
            point_begin([0.0, 1.25, -3.0e-7], -1),
            RunEvent::PointBegin {
                station: "Süd".into(),
                point: 0,
                pass: 0,
                target: Name::default(),
                nominal_m: [0.0; 3],
                axes: AxisMap::new(),
                approach: AxisMap::new(),
            },
            RunEvent::PointEnd {
                station: "s16".into(),
                point: 9999,
                pass: 2,
            },
        ] {
            let data = serde_json::to_vec(&event).unwrap();
            assert_eq!(parse_compact(&data), Some(event));
        }
    }

    #[test]
    fn anything_else_is_left_to_serde_json() {
        for text in [
            r#"{"kind":"station_end","station":"s1"}"#,
            r#"{"kind":"point_end","station":"s1","point":1}"#,
            r#"{"kind":"point_end","point":1,"station":"s1","pass":0}"#,
            r#"{"kind":"point_end","station":"s\"1","point":1,"pass":0}"#,
            r#"{"kind":"point_end","station":"s1","point":1,"pass":0,"extra":1}"#,
            r#"{"kind":"point_end","station":"s1","point":1,"pass":0} "#,
            r#"{"kind":"point_end","station":"s1","point":-1,"pass":0}"#,
            r#"{"kind":"point_begin","station":"s1","point":1,"pass":0,"target":"t0","nominal_m":[0,0.0,0.0],"axes":{},"approach":{}}"#,
            r#"{"kind":"point_begin","station":"s1","point":1,"pass":0,"target":"t0","nominal_m":[0.0,0.0],"axes":{},"approach":{}}"#,
            r#"{"kind":"point_begin","station":"s1","point":1,"pass":0,"target":"t0","nominal_m":[0.0,0.0,0.0],"axes":{"x":1.0},"approach":{"x":128}}"#,
            r#"{"kind":"point_begin","station":"s1","point":1,"pass":0,"target":"t0","nominal_m":[0.0,0.0,0.0],"axes":{"x":1.0,},"approach":{}}"#,
        ] {
            assert_eq!(parse_compact(text.as_bytes()), None, "{text}");
        }
    }

    #[test]
    fn a_repeated_key_keeps_its_last_value_as_serde_json_does() {
        let text = r#"{"kind":"point_begin","station":"s1","point":1,"pass":0,"target":"t0","nominal_m":[0.0,0.0,0.0],"axes":{"x":1.0,"x":2.0},"approach":{"x":-1,"y":-128}}"#;
        let fast = parse_compact(text.as_bytes()).expect("fast path");
        assert_eq!(Some(fast), serde(text.as_bytes()));
        // serde_json reads "-0" as a float: no i8.
        let minus_zero = text.replace("-128", "-0");
        assert_eq!(parse_compact(minus_zero.as_bytes()), None);
        assert_eq!(serde(minus_zero.as_bytes()), None);
    }

    proptest! {
        /// Whenever the fast path answers, serde_json gives the same event.
        #[test]
        fn agrees_with_serde_json(
            x in any::<f64>(),
            y in -10.0f64..10.0,
            approach in any::<i8>(),
            end in any::<bool>(),
            cut in 0usize..300,
            flip in 0usize..300,
            byte in any::<u8>(),
        ) {
            let event = if end {
                RunEvent::PointEnd { station: "s3".into(), point: 17, pass: 0 }
            } else {
                point_begin([x, y, 0.5], approach)
            };
            let data = serde_json::to_vec(&event).unwrap();
            if x.is_finite() || end {
                prop_assert_eq!(parse_compact(&data), Some(event));
            }
            let mut damaged = data.clone();
            damaged.truncate(cut.max(1).min(data.len()));
            if let Some(b) = damaged.get_mut(flip) {
                *b ^= byte;
            }
            if let Some(fast) = parse_compact(&damaged) {
                prop_assert_eq!(Some(fast), serde(&damaged));
            }
        }
    }
}
