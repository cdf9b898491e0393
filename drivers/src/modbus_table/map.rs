//! Modbus rotary-table register map from config (addresses, widths, word order, scaling,
//! status bits, command/acknowledge handshake) and the pure angle <-> register conversions.

use serde::{Deserialize, Serialize};

use crate::modbus::registers::{
    default_holding, default_true, default_unit_id, default_width, scale_of,
};
pub use crate::modbus::registers::{
    Acknowledge, CommandRegister, Handshake, RegisterKind, RegisterRef, StatusRegister, WordLayout,
    WordOrder,
};

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

impl WordLayout for AngleRegister {
    fn width_bits(&self) -> u8 {
        self.width_bits
    }
    fn word_order(&self) -> WordOrder {
        self.word_order
    }
    fn signed(&self) -> bool {
        self.signed
    }
}

impl AngleRegister {
    /// Words the value occupies.
    pub fn words(&self) -> u16 {
        WordLayout::words(self)
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
        self.check_layout(name, self.address, 1)?;
        scale_of(name, self.counts_per_rad, self.rad_per_count, "rad").map(|_| ())
    }

    /// Encode an angle into the register words (address order). Rounds to the nearest
    /// count; an angle outside the representable range is an error.
    pub fn encode_rad(&self, angle_rad: f64) -> Result<Vec<u16>, String> {
        self.encode_scaled(angle_rad, self.scale_counts_per_rad(), "rad")
            .map_err(|m| format!("angle {m}"))
    }

    /// Register words for `counts` (already inside the range), in address order.
    pub fn encode_counts(&self, counts: i64) -> Vec<u16> {
        WordLayout::encode_counts(self, counts)
    }

    /// Counts from register words in address order; `None` if the count of words is wrong.
    pub fn decode_counts(&self, words: &[u16]) -> Option<i64> {
        WordLayout::decode_counts(self, words)
    }

    /// Angle from register words in address order.
    pub fn decode_rad(&self, words: &[u16]) -> Option<f64> {
        self.decode_scaled(words, self.scale_counts_per_rad())
    }
}

impl RegisterMap {
    /// The status / go / ack / fault-code part, shared with the Modbus client and server.
    pub fn handshake(&self) -> Handshake {
        Handshake {
            unit_id: self.unit_id,
            status: self.status.clone(),
            command: self.command.clone(),
            ack: self.ack.clone(),
            fault_code: self.fault_code,
        }
    }

    /// The register the acknowledge is read from.
    pub fn ack_register(&self) -> RegisterRef {
        self.handshake().ack_register()
    }

    /// Whether the acknowledge register's word shows the acknowledge.
    pub fn acknowledged(&self, word: u16) -> bool {
        self.handshake().acknowledged(word)
    }

    /// Reject maps the driver cannot work with.
    pub fn validate(&self) -> Result<(), String> {
        self.target.validate("target")?;
        self.actual.validate("actual")?;
        if self.target.kind != RegisterKind::Holding {
            return Err("target must be a holding register (it is written)".into());
        }
        self.handshake().validate()?;
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
