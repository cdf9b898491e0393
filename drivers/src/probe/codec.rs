//! ASCII probe codec, sans-I/O: the request line, parsing of reply lines with configurable
//! patterns and scale (device units -> metres), and formatting of replies for the emulator.

use regex::Regex;

pub use crate::grbl::codec::{Framed, LineFramer};

/// Longest reply line kept; sensors answer in a few dozen bytes.
pub const MAX_REPLY_BYTES: usize = 128;

/// One decoded reply line.
#[derive(Debug, Clone, PartialEq)]
pub enum ProbeReply {
    /// A measurement: the number as sent (device units) and in metres.
    Value { raw: f64, value_m: f64 },
    /// An error reply; `code` is the captured code, or the whole line without a capture.
    Error { code: String, line: String },
    /// Matches neither pattern (noise, a reply to something else, an out-of-range marker).
    Unrecognised(String),
}

/// Why a protocol description is unusable.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ProtocolError {
    #[error("bad {which} pattern: {message}")]
    Pattern {
        which: &'static str,
        message: String,
    },
    #[error("value pattern must have a capture group (named `value`, or the first group)")]
    NoCapture,
    #[error("scale to metres must be finite and non-zero, got {0}")]
    Scale(f64),
}

/// The request/response protocol of one sensor model.
#[derive(Debug, Clone)]
pub struct ProbeProtocol {
    command: String,
    value: Regex,
    error: Option<Regex>,
    scale_to_m: f64,
}

impl ProbeProtocol {
    /// `command` is sent as is (terminator included); `value_pattern` must capture the
    /// number (group `value`, else group 1); `error_pattern` may capture a code (group
    /// `code`, else group 1); a number times `scale_to_m` is metres.
    pub fn new(
        command: &str,
        value_pattern: &str,
        error_pattern: Option<&str>,
        scale_to_m: f64,
    ) -> Result<Self, ProtocolError> {
        let value = Regex::new(value_pattern).map_err(|e| ProtocolError::Pattern {
            which: "value",
            message: e.to_string(),
        })?;
        if value.captures_len() < 2 {
            return Err(ProtocolError::NoCapture);
        }
        let error =
            error_pattern
                .map(Regex::new)
                .transpose()
                .map_err(|e| ProtocolError::Pattern {
                    which: "error",
                    message: e.to_string(),
                })?;
        if !scale_to_m.is_finite() || scale_to_m == 0.0 {
            return Err(ProtocolError::Scale(scale_to_m));
        }
        Ok(Self {
            command: command.to_string(),
            value,
            error,
            scale_to_m,
        })
    }

    /// Bytes of one request.
    pub fn request(&self) -> &[u8] {
        self.command.as_bytes()
    }

    /// The request without its terminator, for messages.
    pub fn command_shown(&self) -> &str {
        self.command.trim_end()
    }

    pub fn scale_to_m(&self) -> f64 {
        self.scale_to_m
    }

    /// Decode one reply line (without terminator). Error replies are tried first, so a
    /// lenient value pattern cannot swallow them.
    pub fn parse_line(&self, line: &str) -> ProbeReply {
        let t = line.trim();
        if let Some(re) = &self.error {
            if let Some(c) = re.captures(t) {
                let code = c
                    .name("code")
                    .or_else(|| c.get(1))
                    .map_or(t, |m| m.as_str())
                    .to_string();
                return ProbeReply::Error {
                    code,
                    line: t.to_string(),
                };
            }
        }
        let Some(c) = self.value.captures(t) else {
            return ProbeReply::Unrecognised(t.to_string());
        };
        let Some(m) = c.name("value").or_else(|| c.get(1)) else {
            return ProbeReply::Unrecognised(t.to_string());
        };
        match m.as_str().trim().parse::<f64>() {
            Ok(raw) if raw.is_finite() => ProbeReply::Value {
                raw,
                value_m: raw * self.scale_to_m,
            },
            _ => ProbeReply::Unrecognised(t.to_string()),
        }
    }
}

/// Format a reply as a device would: `{value}` in `template` becomes the number in device
/// units with `decimals` places, signed (`+`/`-`) when `plus_sign`.
pub fn format_reply(template: &str, value_dev: f64, decimals: usize, plus_sign: bool) -> String {
    let num = if plus_sign {
        format!("{value_dev:+.decimals$}")
    } else {
        format!("{value_dev:.decimals$}")
    };
    template.replace("{value}", &num)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn keyence() -> ProbeProtocol {
        ProbeProtocol::new(
            "M0\r",
            r"^M0,(?P<value>[+-]?\d+(?:\.\d+)?)$",
            Some(r"^ER,\w+,(?P<code>\d+)$"),
            1e-3,
        )
        .expect("protocol")
    }

    #[test]
    fn parses_values_errors_and_noise() {
        let p = keyence();
        let ProbeReply::Value { raw, value_m } = p.parse_line("M0,+00.1234") else {
            panic!("not a value")
        };
        assert_eq!(raw, 0.1234);
        assert!((value_m - 0.1234e-3).abs() < 1e-15);
        assert_eq!(
            p.parse_line("ER,M0,01"),
            ProbeReply::Error {
                code: "01".into(),
                line: "ER,M0,01".into()
            }
        );
        assert!(matches!(
            p.parse_line("M0,+FFFFFFF"),
            ProbeReply::Unrecognised(_)
        ));
        let other =
            ProbeProtocol::new("MEAS?\n", r"MEASURE=\s*(-?[\d.]+)\s*mm", None, 1e-3).expect("p");
        assert!(matches!(
            other.parse_line("MEASURE=-1.234 mm"),
            ProbeReply::Value { raw, .. } if raw == -1.234
        ));
        assert!(matches!(
            other.parse_line("MEASURE=1.2.3 mm"),
            ProbeReply::Unrecognised(_)
        ));
    }

    #[test]
    fn rejects_bad_protocols() {
        assert_eq!(
            ProbeProtocol::new("M0\r", r"^M0,.*$", None, 1e-3).unwrap_err(),
            ProtocolError::NoCapture
        );
        assert!(ProbeProtocol::new("M0\r", r"(", None, 1e-3).is_err());
        assert!(ProbeProtocol::new("M0\r", r"(\d+)", None, 0.0).is_err());
    }

    proptest! {
        #[test]
        fn random_lines_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..200)) {
            let p = keyence();
            let mut f = LineFramer::new(MAX_REPLY_BYTES);
            for fr in f.push(&bytes) {
                if let Framed::Line(l) = fr { let _ = p.parse_line(&l); }
            }
        }

        #[test]
        fn formatted_replies_parse_back(v in -99.9999f64..99.9999, decimals in 1usize..7,
                                        cut in any::<prop::sample::Index>()) {
            let p = keyence();
            let line = format_reply("M0,{value}", v, decimals, true) + "\r";
            let whole = {
                let mut f = LineFramer::new(MAX_REPLY_BYTES);
                f.push(line.as_bytes())
            };
            let k = cut.index(line.len() + 1);
            let mut f = LineFramer::new(MAX_REPLY_BYTES);
            let mut split = f.push(&line.as_bytes()[..k]);
            split.extend(f.push(&line.as_bytes()[k..]));
            prop_assert_eq!(&whole, &split);
            let Some(Framed::Line(l)) = whole.first() else { panic!("no line") };
            let ProbeReply::Value { raw, value_m } = p.parse_line(l) else { panic!("{l}") };
            let half_step = 0.5 * 10f64.powi(-(decimals as i32)) + 1e-12;
            prop_assert!((raw - v).abs() <= half_step);
            prop_assert!((value_m - raw * 1e-3).abs() < 1e-15);
        }
    }
}
