//! A typed fast path for the one high-rate message, `geocal.TracerSample`, in the exact form
//! geocal's recorder writes it (serde_json's compact output, fields in declaration order).
//! Anything else — other writers' field order, whitespace, extra fields, integers for floats,
//! errors — returns None and goes through serde_json, so the result is always the one
//! serde_json gives; only the common case is faster (no visitor, no field matching).

use crate::session::messages::TracerSample;

/// The sample, when `data` is exactly
/// `{"seq":U,"t_s":F,"length_m":F,"signal":F,"tracking":B,"beam_segment":U}`.
pub(super) fn parse_compact(data: &[u8]) -> Option<TracerSample> {
    let mut p = Cursor { data, at: 0 };
    p.literal(b"{\"seq\":")?;
    let seq = p.unsigned()?;
    p.literal(b",\"t_s\":")?;
    let t_s = p.float()?;
    p.literal(b",\"length_m\":")?;
    let length_m = p.float()?;
    p.literal(b",\"signal\":")?;
    let signal = p.float()?;
    p.literal(b",\"tracking\":")?;
    let tracking = if p.literal(b"true").is_some() {
        true
    } else {
        p.literal(b"false")?;
        false
    };
    p.literal(b",\"beam_segment\":")?;
    let beam_segment = u32::try_from(p.unsigned()?).ok()?;
    p.literal(b"}")?;
    (p.at == data.len()).then_some(TracerSample {
        seq,
        t_s,
        length_m,
        signal,
        tracking,
        beam_segment,
    })
}

/// Reads the compact JSON that serde_json writes, byte by byte; every method returns None
/// (and may leave `at` anywhere) at anything else.
pub(super) struct Cursor<'a> {
    pub(super) data: &'a [u8],
    pub(super) at: usize,
}

impl Cursor<'_> {
    // Inlined, each call compares a constant number of bytes without a call to memcmp.
    #[inline]
    pub(super) fn literal(&mut self, text: &[u8]) -> Option<()> {
        let rest = self.data.get(self.at..)?;
        rest.starts_with(text).then(|| self.at += text.len())
    }

    /// The bytes of the digits starting here.
    fn digits(&mut self) -> usize {
        let start = self.at;
        while self.data.get(self.at).is_some_and(u8::is_ascii_digit) {
            self.at += 1;
        }
        self.at - start
    }

    /// A JSON integer without sign or leading zeros that fits a u64.
    pub(super) fn unsigned(&mut self) -> Option<u64> {
        let start = self.at;
        let n = self.digits();
        if n == 0 || (n > 1 && self.data[start] == b'0') {
            return None;
        }
        // Digits only: what `u64::from_str` reads, without its UTF-8 check.
        self.data[start..self.at].iter().try_fold(0u64, |value, d| {
            value.checked_mul(10)?.checked_add(u64::from(d - b'0'))
        })
    }

    /// A JSON number with a fraction or an exponent (how serde_json writes every finite f64),
    /// parsed with correct rounding as serde_json's `float_roundtrip` does. Integers are left
    /// to serde_json, which reads "-0" as +0.0.
    pub(super) fn float(&mut self) -> Option<f64> {
        let start = self.at;
        if self.data.get(self.at) == Some(&b'-') {
            self.at += 1;
        }
        let int_start = self.at;
        let n = self.digits();
        if n == 0 || (n > 1 && self.data[int_start] == b'0') {
            return None;
        }
        let mut real = false;
        if self.data.get(self.at) == Some(&b'.') {
            self.at += 1;
            if self.digits() == 0 {
                return None;
            }
            real = true;
        }
        if matches!(self.data.get(self.at), Some(b'e' | b'E')) {
            self.at += 1;
            if matches!(self.data.get(self.at), Some(b'+' | b'-')) {
                self.at += 1;
            }
            if self.digits() == 0 {
                return None;
            }
            real = true;
        }
        if !real {
            return None;
        }
        // The bytes are a JSON number (checked above), which lexical reads exactly as
        // `str::parse` does, without the UTF-8 check and ~30 % faster.
        let value: f64 = lexical_core::parse(&self.data[start..self.at]).ok()?;
        // serde_json refuses numbers beyond f64's range.
        value.is_finite().then_some(value)
    }
}

#[cfg(test)]
mod tests {
    use proptest::prelude::*;

    use super::*;

    fn serde(data: &[u8]) -> Option<TracerSample> {
        serde_json::from_slice(data).ok()
    }

    #[test]
    fn recorder_output_takes_the_fast_path() {
        let s = TracerSample {
            seq: 17,
            t_s: 1234.05,
            length_m: -0.123456789012345,
            signal: 0.95,
            tracking: false,
            beam_segment: 2,
        };
        let data = serde_json::to_vec(&s).unwrap();
        assert_eq!(parse_compact(&data), Some(s));
    }

    #[test]
    fn anything_else_is_left_to_serde_json() {
        for text in [
            r#"{"seq":1,"t_s":1.0,"length_m":2.0,"signal":1.0,"tracking":true}"#,
            r#"{"seq":1,"t_s":1,"length_m":2.0,"signal":1.0,"tracking":true,"beam_segment":0}"#,
            r#"{"seq":1,"t_s":-0,"length_m":2.0,"signal":1.0,"tracking":true,"beam_segment":0}"#,
            r#"{"seq":01,"t_s":1.0,"length_m":2.0,"signal":1.0,"tracking":true,"beam_segment":0}"#,
            r#"{"seq":1,"t_s":1.,"length_m":2.0,"signal":1.0,"tracking":true,"beam_segment":0}"#,
            r#"{"seq":1,"t_s":1e999,"length_m":2.0,"signal":1.0,"tracking":true,"beam_segment":0}"#,
            r#"{"seq":1,"t_s":1.0,"length_m":2.0,"signal":1.0,"tracking":true,"beam_segment":4294967296}"#,
            r#"{"seq":1,"t_s":1.0,"length_m":2.0,"signal":1.0,"tracking":true,"beam_segment":0} "#,
            r#"{"seq": 1,"t_s":1.0,"length_m":2.0,"signal":1.0,"tracking":true,"beam_segment":0}"#,
            r#"{"seq":1,"t_s":1.0,"length_m":null,"signal":1.0,"tracking":true,"beam_segment":0}"#,
        ] {
            assert_eq!(parse_compact(text.as_bytes()), None, "{text}");
        }
    }

    proptest! {
        /// Numbers as other writers may print them (long mantissas, exponents up to f64's
        /// limits and beyond, halfway cases): the fast path reads serde_json's value or none.
        #[test]
        fn numbers_read_as_serde_json_reads_them(
            negative in any::<bool>(),
            int in "[1-9][0-9]{0,25}|0",
            frac in "[0-9]{1,30}",
            exp in proptest::option::of(-340i32..320),
        ) {
            let number = format!(
                "{}{int}.{frac}{}",
                if negative { "-" } else { "" },
                exp.map_or(String::new(), |e| format!("e{e}"))
            );
            let text = format!(
                r#"{{"seq":1,"t_s":{number},"length_m":2.0,"signal":1.0,"tracking":true,"beam_segment":0}}"#
            );
            let fast = parse_compact(text.as_bytes());
            match serde(text.as_bytes()) {
                Some(slow) => prop_assert_eq!(fast.map(|f| f.t_s.to_bits()), Some(slow.t_s.to_bits())),
                None => prop_assert!(fast.is_none()),
            }
        }

        /// Whenever the fast path answers, serde_json gives the same sample, bit for bit.
        #[test]
        fn agrees_with_serde_json(
            seq in any::<u64>(),
            t_s in any::<f64>(),
            length_m in any::<f64>(),
            signal in any::<f64>(),
            tracking in any::<bool>(),
            beam_segment in any::<u32>(),
            cut in 0usize..200,
            flip in 0usize..200,
            byte in any::<u8>(),
        ) {
            let s = TracerSample { seq, t_s, length_m, signal, tracking, beam_segment };
            let data = serde_json::to_vec(&s).unwrap();
            if s.t_s.is_finite() && s.length_m.is_finite() && s.signal.is_finite() {
                let fast = parse_compact(&data).expect("fast path");
                prop_assert_eq!(fast.seq, s.seq);
                for (a, b) in [(fast.t_s, s.t_s), (fast.length_m, s.length_m), (fast.signal, s.signal)] {
                    prop_assert_eq!(a.to_bits(), b.to_bits());
                }
                prop_assert_eq!((fast.tracking, fast.beam_segment), (s.tracking, s.beam_segment));
            }
            let mut damaged = data.clone();
            damaged.truncate(cut.max(1).min(data.len()));
            if let Some(b) = damaged.get_mut(flip) {
                *b ^= byte;
            }
            if let Some(fast) = parse_compact(&damaged) {
                let slow = serde(&damaged).expect("serde_json reads what the fast path reads");
                prop_assert_eq!(fast.seq, slow.seq);
                for (a, b) in [(fast.t_s, slow.t_s), (fast.length_m, slow.length_m), (fast.signal, slow.signal)] {
                    prop_assert_eq!(a.to_bits(), b.to_bits());
                }
                prop_assert_eq!((fast.tracking, fast.beam_segment), (slow.tracking, slow.beam_segment));
            }
        }
    }
}
