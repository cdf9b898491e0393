//! Modbus rotary-table register map from config (addresses, widths, word order, scaling,
//! status bits, command/acknowledge handshake) and the pure angle <-> register conversions.

use serde::{Deserialize, Serialize};

/// Which Modbus table a register lives in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RegisterKind {
    /// Read with function 0x03, written with 0x06 / 0x10.
    Holding,
    /// Read-only, read with function 0x04.
    Input,
}

impl RegisterKind {
    pub fn name(self) -> &'static str {
        match self {
            RegisterKind::Holding => "holding",
            RegisterKind::Input => "input",
        }
    }
}

/// Order of the two 16-bit words of a 32-bit value.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum WordOrder {
    /// High word at the lower address (Modicon convention, "ABCD").
    #[default]
    Big,
    /// Low word at the lower address ("CDAB").
    Little,
}

/// A register holding an angle, in counts, at one address (16 bit) or two (32 bit).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AngleRegister {
    /// Protocol (0-based) address of the first word.
    pub address: u16,
    #[serde(default = "default_holding")]
    pub kind: RegisterKind,
    /// 16 or 32.
    #[serde(default = "default_width")]
    pub width_bits: u8,
    #[serde(default)]
    pub word_order: WordOrder,
    /// Two's complement (true) or unsigned counts.
    #[serde(default = "default_true")]
    pub signed: bool,
    /// Scale: counts per radian (1000 counts per degree = 57295.78 counts per radian).
    /// Give exactly one of `counts_per_rad` and `rad_per_count`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub counts_per_rad: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rad_per_count: Option<f64>,
}

/// A plain register reference (one word).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RegisterRef {
    pub address: u16,
    #[serde(default = "default_holding")]
    pub kind: RegisterKind,
}

/// The status word and the meaning of its bits (bit 0 = least significant).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StatusRegister {
    pub address: u16,
    #[serde(default = "default_holding")]
    pub kind: RegisterKind,
    pub in_position_bit: u8,
    /// If given, the table counts as moving while this bit is set, even with in_position.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub moving_bit: Option<u8>,
    pub fault_bit: u8,
}

/// The command register: the driver writes `go_value` after the target to start a move,
/// and `clear_value` (if given) once the device acknowledged.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CommandRegister {
    /// A holding register.
    pub address: u16,
    pub go_value: u16,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub clear_value: Option<u16>,
}

/// How the device acknowledges a go command: a bit set (`bit`) or a value shown (`value`)
/// in `register`, or in the status register if no register is given. Give one of the two.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Acknowledge {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub register: Option<RegisterRef>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bit: Option<u8>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub value: Option<u16>,
}

/// The whole register map of one table; lives in the table's TOML config.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RegisterMap {
    /// Modbus unit (slave) id.
    #[serde(default = "default_unit_id")]
    pub unit_id: u8,
    /// Commanded angle; a holding register.
    pub target: AngleRegister,
    /// Encoder angle; input or holding.
    pub actual: AngleRegister,
    pub status: StatusRegister,
    pub command: CommandRegister,
    pub ack: Acknowledge,
    /// Optional register with the device's fault code, read when the fault bit is set.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fault_code: Option<RegisterRef>,
}

fn default_holding() -> RegisterKind {
    RegisterKind::Holding
}
fn default_width() -> u8 {
    32
}
fn default_true() -> bool {
    true
}
fn default_unit_id() -> u8 {
    1
}

impl AngleRegister {
    /// Words the value occupies.
    pub fn words(&self) -> u16 {
        if self.width_bits == 32 {
            2
        } else {
            1
        }
    }

    /// Counts per radian, from whichever scale was given (validated first).
    pub fn scale_counts_per_rad(&self) -> f64 {
        match (self.counts_per_rad, self.rad_per_count) {
            (Some(c), _) => c,
            (None, Some(r)) => 1.0 / r,
            (None, None) => f64::NAN,
        }
    }

    fn validate(&self, name: &str) -> Result<(), String> {
        if self.width_bits != 16 && self.width_bits != 32 {
            return Err(format!(
                "{name}: width_bits must be 16 or 32, got {}",
                self.width_bits
            ));
        }
        if u32::from(self.address) + u32::from(self.words()) > 0x1_0000 {
            return Err(format!(
                "{name}: address {} + {} words runs past 65535",
                self.address,
                self.words()
            ));
        }
        let scale = match (self.counts_per_rad, self.rad_per_count) {
            (Some(c), None) => c,
            (None, Some(r)) => 1.0 / r,
            _ => {
                return Err(format!(
                    "{name}: give exactly one of counts_per_rad and rad_per_count"
                ))
            }
        };
        if !(scale.is_finite() && scale != 0.0) {
            return Err(format!("{name}: scale must be finite and non-zero"));
        }
        Ok(())
    }

    fn count_range(&self) -> (i64, i64) {
        match (self.width_bits, self.signed) {
            (16, true) => (i64::from(i16::MIN), i64::from(i16::MAX)),
            (16, false) => (0, i64::from(u16::MAX)),
            (_, true) => (i64::from(i32::MIN), i64::from(i32::MAX)),
            (_, false) => (0, i64::from(u32::MAX)),
        }
    }

    /// Encode an angle into the register words (address order). Rounds to the nearest
    /// count; an angle outside the representable range is an error.
    pub fn encode_rad(&self, angle_rad: f64) -> Result<Vec<u16>, String> {
        let counts_f = (angle_rad * self.scale_counts_per_rad()).round();
        let (lo, hi) = self.count_range();
        if !counts_f.is_finite() || counts_f < lo as f64 || counts_f > hi as f64 {
            return Err(format!(
                "angle {angle_rad} rad is {counts_f} counts, outside {lo}..={hi} of a {}-bit {} register",
                self.width_bits,
                if self.signed { "signed" } else { "unsigned" }
            ));
        }
        let counts = counts_f as i64;
        Ok(self.encode_counts(counts))
    }

    /// Register words for `counts` (already inside the range), in address order.
    pub fn encode_counts(&self, counts: i64) -> Vec<u16> {
        if self.width_bits == 16 {
            vec![(counts as u64 & 0xFFFF) as u16]
        } else {
            let raw = counts as u64 & 0xFFFF_FFFF;
            let high = (raw >> 16) as u16;
            let low = (raw & 0xFFFF) as u16;
            match self.word_order {
                WordOrder::Big => vec![high, low],
                WordOrder::Little => vec![low, high],
            }
        }
    }

    /// Counts from register words in address order; `None` if the count of words is wrong.
    pub fn decode_counts(&self, words: &[u16]) -> Option<i64> {
        if words.len() != usize::from(self.words()) {
            return None;
        }
        if self.width_bits == 16 {
            let w = words[0];
            return Some(if self.signed {
                i64::from(w as i16)
            } else {
                i64::from(w)
            });
        }
        let (high, low) = match self.word_order {
            WordOrder::Big => (words[0], words[1]),
            WordOrder::Little => (words[1], words[0]),
        };
        let raw = (u32::from(high) << 16) | u32::from(low);
        Some(if self.signed {
            i64::from(raw as i32)
        } else {
            i64::from(raw)
        })
    }

    /// Angle from register words in address order.
    pub fn decode_rad(&self, words: &[u16]) -> Option<f64> {
        self.decode_counts(words)
            .map(|c| c as f64 / self.scale_counts_per_rad())
    }
}

fn check_bit(name: &str, bit: u8) -> Result<(), String> {
    if bit < 16 {
        Ok(())
    } else {
        Err(format!("{name} must be 0..=15, got {bit}"))
    }
}

impl StatusRegister {
    pub fn in_position(&self, word: u16) -> bool {
        word & (1 << self.in_position_bit) != 0
    }
    pub fn moving(&self, word: u16) -> bool {
        self.moving_bit.is_some_and(|b| word & (1 << b) != 0)
    }
    pub fn fault(&self, word: u16) -> bool {
        word & (1 << self.fault_bit) != 0
    }
}

impl RegisterMap {
    /// The register the acknowledge is read from.
    pub fn ack_register(&self) -> RegisterRef {
        self.ack.register.unwrap_or(RegisterRef {
            address: self.status.address,
            kind: self.status.kind,
        })
    }

    /// Whether the acknowledge register's word shows the acknowledge.
    pub fn acknowledged(&self, word: u16) -> bool {
        match (self.ack.bit, self.ack.value) {
            (Some(b), _) => word & (1 << b) != 0,
            (None, Some(v)) => word == v,
            (None, None) => false,
        }
    }

    /// Reject maps the driver cannot work with.
    pub fn validate(&self) -> Result<(), String> {
        self.target.validate("target")?;
        self.actual.validate("actual")?;
        if self.target.kind != RegisterKind::Holding {
            return Err("target must be a holding register (it is written)".into());
        }
        check_bit("status.in_position_bit", self.status.in_position_bit)?;
        check_bit("status.fault_bit", self.status.fault_bit)?;
        if let Some(b) = self.status.moving_bit {
            check_bit("status.moving_bit", b)?;
        }
        if self.status.in_position_bit == self.status.fault_bit
            || self.status.moving_bit == Some(self.status.in_position_bit)
            || self.status.moving_bit == Some(self.status.fault_bit)
        {
            return Err("status bits in_position, moving and fault must differ".into());
        }
        match (self.ack.bit, self.ack.value) {
            (Some(b), None) => {
                check_bit("ack.bit", b)?;
                if self.ack.register.is_none()
                    && (b == self.status.in_position_bit
                        || b == self.status.fault_bit
                        || self.status.moving_bit == Some(b))
                {
                    return Err(format!(
                        "ack.bit {b} in the status register collides with a status bit"
                    ));
                }
            }
            (None, Some(_)) => {
                if self.ack.register.is_none() {
                    return Err("ack.value needs ack.register (the status word is bits)".into());
                }
            }
            _ => return Err("ack: give exactly one of bit and value".into()),
        }
        if self.command.clear_value == Some(self.command.go_value) {
            return Err("command.clear_value must differ from command.go_value".into());
        }
        let target_span = self.target.address..self.target.address + self.target.words();
        if target_span.contains(&self.command.address) {
            return Err("command register overlaps the target register".into());
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn reg(width_bits: u8, word_order: WordOrder, signed: bool) -> AngleRegister {
        AngleRegister {
            address: 10,
            kind: RegisterKind::Holding,
            width_bits,
            word_order,
            signed,
            counts_per_rad: Some(1000.0 * 180.0 / std::f64::consts::PI),
            rad_per_count: None,
        }
    }

    pub(crate) fn example_map() -> RegisterMap {
        toml_example()
    }

    fn toml_example() -> RegisterMap {
        serde_json::from_value(serde_json::json!({
            "unit_id": 1,
            "target": {"address": 100, "width_bits": 32, "word_order": "little",
                        "counts_per_rad": 57_295.779_513_082_32},
            "actual": {"address": 200, "kind": "input", "width_bits": 32,
                        "rad_per_count": 1.7453292519943296e-5},
            "status": {"address": 300, "kind": "input", "in_position_bit": 0,
                        "moving_bit": 1, "fault_bit": 2},
            "command": {"address": 110, "go_value": 1, "clear_value": 0},
            "ack": {"bit": 3},
            "fault_code": {"address": 301, "kind": "input"}
        }))
        .expect("example map parses")
    }

    #[test]
    fn example_validates() {
        assert_eq!(example_map().validate(), Ok(()));
    }

    #[test]
    fn unknown_fields_rejected() {
        let r: Result<AngleRegister, _> = serde_json::from_value(serde_json::json!({
            "address": 1, "counts_per_rad": 1.0, "scale": 2.0
        }));
        assert!(r.is_err());
    }

    #[test]
    fn bad_maps_rejected() {
        let mut m = example_map();
        m.target.width_bits = 24;
        assert!(m.validate().unwrap_err().contains("width_bits"));
        let mut m = example_map();
        m.target.rad_per_count = Some(1.0);
        assert!(m.validate().unwrap_err().contains("exactly one"));
        let mut m = example_map();
        m.target.kind = RegisterKind::Input;
        assert!(m.validate().is_err());
        let mut m = example_map();
        m.ack.bit = Some(0);
        assert!(m.validate().unwrap_err().contains("collides"));
        let mut m = example_map();
        m.status.fault_bit = 16;
        assert!(m.validate().is_err());
    }

    #[test]
    fn negative_16_bit() {
        let r = reg(16, WordOrder::Big, true);
        let w = r.encode_rad((-1.5f64).to_radians()).unwrap();
        assert_eq!(w, vec![(-1500i16) as u16]);
        assert_eq!(w, vec![0xFA24]);
        let back = r.decode_rad(&w).unwrap();
        assert!((back - (-1.5f64).to_radians()).abs() < 1e-12);
        // Out of range for 16 bits: 40 degrees = 40000 counts.
        assert!(r.encode_rad(40f64.to_radians()).is_err());
        // Unsigned rejects negatives.
        assert!(reg(16, WordOrder::Big, false).encode_rad(-0.01).is_err());
    }

    #[test]
    fn word_order_32_bit_both_ways() {
        // -90 degrees = -90000 counts = 0xFFFE_A070.
        let angle = (-90f64).to_radians();
        let big = reg(32, WordOrder::Big, true);
        let little = reg(32, WordOrder::Little, true);
        assert_eq!(big.encode_rad(angle).unwrap(), vec![0xFFFE, 0xA070]);
        assert_eq!(little.encode_rad(angle).unwrap(), vec![0xA070, 0xFFFE]);
        assert!((big.decode_rad(&[0xFFFE, 0xA070]).unwrap() - angle).abs() < 1e-12);
        assert!((little.decode_rad(&[0xA070, 0xFFFE]).unwrap() - angle).abs() < 1e-12);
        // 200 degrees = 200000 counts = 0x0003_0D40.
        let a = 200f64.to_radians();
        assert_eq!(big.encode_rad(a).unwrap(), vec![0x0003, 0x0D40]);
        assert_eq!(little.encode_rad(a).unwrap(), vec![0x0D40, 0x0003]);
        // Unsigned 32 bit reads the high bit as a magnitude.
        let u = reg(32, WordOrder::Big, false);
        assert_eq!(
            u.decode_counts(&[0xFFFF, 0xFFFF]),
            Some(i64::from(u32::MAX))
        );
        assert_eq!(big.decode_counts(&[0xFFFF, 0xFFFF]), Some(-1));
        // Wrong word count is refused, not a panic.
        assert_eq!(big.decode_counts(&[1]), None);
    }

    #[test]
    fn flags() {
        let m = example_map();
        assert!(m.status.in_position(0b0001));
        assert!(m.status.moving(0b0010));
        assert!(m.status.fault(0b0100));
        assert!(m.acknowledged(0b1000));
        assert!(!m.acknowledged(0b0111));
        assert_eq!(m.ack_register().address, 300);
    }

    proptest! {
        #[test]
        fn round_trip(
            angle_deg in -2000.0f64..2000.0,
            w32 in any::<bool>(),
            little in any::<bool>(),
            signed in any::<bool>(),
        ) {
            let order = if little { WordOrder::Little } else { WordOrder::Big };
            let r = reg(if w32 { 32 } else { 16 }, order, signed);
            let a = angle_deg.to_radians();
            match r.encode_rad(a) {
                Ok(w) => {
                    prop_assert_eq!(w.len(), usize::from(r.words()));
                    let back = r.decode_rad(&w).unwrap();
                    // Within half a count.
                    prop_assert!((back - a).abs() <= 0.5 / r.scale_counts_per_rad() + 1e-12);
                }
                Err(_) => {
                    let c = (a * r.scale_counts_per_rad()).round();
                    let (lo, hi) = r.count_range();
                    prop_assert!(c < lo as f64 || c > hi as f64);
                }
            }
        }
    }
}
