//! Register layouts (kind, width, word order, sign, scale) and the go/acknowledge handshake
//! (status bits, command register, ack) of Modbus devices: pure conversions and checks.

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

pub(crate) fn default_holding() -> RegisterKind {
    RegisterKind::Holding
}
pub(crate) fn default_width() -> u8 {
    32
}
pub(crate) fn default_true() -> bool {
    true
}
pub(crate) fn default_unit_id() -> u8 {
    1
}

/// How a count sits in one (16 bit) or two (32 bit) registers. Implemented by every value
/// register of a map; the conversions are the defaults.
pub trait WordLayout {
    fn width_bits(&self) -> u8;
    fn word_order(&self) -> WordOrder;
    fn signed(&self) -> bool;

    /// Words one value occupies.
    fn words(&self) -> u16 {
        if self.width_bits() == 32 {
            2
        } else {
            1
        }
    }

    /// The counts the register can hold.
    fn count_range(&self) -> (i64, i64) {
        match (self.width_bits(), self.signed()) {
            (16, true) => (i64::from(i16::MIN), i64::from(i16::MAX)),
            (16, false) => (0, i64::from(u16::MAX)),
            (_, true) => (i64::from(i32::MIN), i64::from(i32::MAX)),
            (_, false) => (0, i64::from(u32::MAX)),
        }
    }

    /// Register words for `counts` (already inside the range), in address order.
    fn encode_counts(&self, counts: i64) -> Vec<u16> {
        if self.width_bits() == 16 {
            vec![(counts as u64 & 0xFFFF) as u16]
        } else {
            let raw = counts as u64 & 0xFFFF_FFFF;
            let high = (raw >> 16) as u16;
            let low = (raw & 0xFFFF) as u16;
            match self.word_order() {
                WordOrder::Big => vec![high, low],
                WordOrder::Little => vec![low, high],
            }
        }
    }

    /// Counts from register words in address order; `None` if the count of words is wrong.
    fn decode_counts(&self, words: &[u16]) -> Option<i64> {
        if words.len() != usize::from(self.words()) {
            return None;
        }
        if self.width_bits() == 16 {
            let w = words[0];
            return Some(if self.signed() {
                i64::from(w as i16)
            } else {
                i64::from(w)
            });
        }
        let (high, low) = match self.word_order() {
            WordOrder::Big => (words[0], words[1]),
            WordOrder::Little => (words[1], words[0]),
        };
        let raw = (u32::from(high) << 16) | u32::from(low);
        Some(if self.signed() {
            i64::from(raw as i32)
        } else {
            i64::from(raw)
        })
    }

    /// Encode `value` (SI units) at `counts_per_unit`, rounding to the nearest count; a value
    /// outside the register's range is an error naming `unit`.
    fn encode_scaled(
        &self,
        value: f64,
        counts_per_unit: f64,
        unit: &str,
    ) -> Result<Vec<u16>, String> {
        let counts_f = (value * counts_per_unit).round();
        let (lo, hi) = self.count_range();
        if !counts_f.is_finite() || counts_f < lo as f64 || counts_f > hi as f64 {
            return Err(format!(
                "{value} {unit} is {counts_f} counts, outside {lo}..={hi} of a {}-bit {} register",
                self.width_bits(),
                if self.signed() { "signed" } else { "unsigned" }
            ));
        }
        Ok(self.encode_counts(counts_f as i64))
    }

    /// `value` in SI units from register words at `counts_per_unit`.
    fn decode_scaled(&self, words: &[u16], counts_per_unit: f64) -> Option<f64> {
        self.decode_counts(words)
            .map(|c| c as f64 / counts_per_unit)
    }

    /// Width 16 or 32, and `values` consecutive values from `address` inside the address space.
    fn check_layout(&self, name: &str, address: u16, values: u16) -> Result<(), String> {
        if self.width_bits() != 16 && self.width_bits() != 32 {
            return Err(format!(
                "{name}: width_bits must be 16 or 32, got {}",
                self.width_bits()
            ));
        }
        let words = u32::from(self.words()) * u32::from(values);
        if u32::from(address) + words > 0x1_0000 {
            return Err(format!(
                "{name}: address {address} + {words} words runs past 65535"
            ));
        }
        Ok(())
    }
}

/// The scale from a pair of optional settings `counts_per_<unit>` / `<unit>_per_count`:
/// exactly one, finite and non-zero.
pub fn scale_of(
    name: &str,
    counts_per: Option<f64>,
    per_count: Option<f64>,
    unit: &str,
) -> Result<f64, String> {
    let scale = match (counts_per, per_count) {
        (Some(c), None) => c,
        (None, Some(r)) => 1.0 / r,
        _ => {
            return Err(format!(
                "{name}: give exactly one of counts_per_{unit} and {unit}_per_count"
            ))
        }
    };
    if !(scale.is_finite() && scale != 0.0) {
        return Err(format!("{name}: scale must be finite and non-zero"));
    }
    Ok(scale)
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
    /// If given, the device counts as moving while this bit is set, even with in_position.
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

/// The handshake part of a register map (status, go command, acknowledge, fault code),
/// shared by the driver and the emulator of every commanded Modbus device.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Handshake {
    pub unit_id: u8,
    pub status: StatusRegister,
    pub command: CommandRegister,
    pub ack: Acknowledge,
    pub fault_code: Option<RegisterRef>,
}

impl Handshake {
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

    /// The status word a device shows (and the ack register's word when it has its own).
    pub fn device_words(&self, in_position: bool, fault: bool, acked: bool) -> (u16, Option<u16>) {
        let st = &self.status;
        let mut status = 0u16;
        if in_position {
            status |= 1 << st.in_position_bit;
        }
        if let Some(b) = st.moving_bit {
            if !in_position {
                status |= 1 << b;
            }
        }
        if fault {
            status |= 1 << st.fault_bit;
        }
        match self.ack.register {
            None => {
                if let (Some(b), true) = (self.ack.bit, acked) {
                    status |= 1 << b;
                }
                (status, None)
            }
            Some(_) => {
                let w = match (self.ack.bit, self.ack.value, acked) {
                    (_, _, false) => 0,
                    (Some(b), _, true) => 1 << b,
                    (None, Some(v), true) => v,
                    (None, None, true) => 0,
                };
                (status, Some(w))
            }
        }
    }

    /// Reject handshakes the driver cannot work with (bits, collisions, ack form).
    pub fn validate(&self) -> Result<(), String> {
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
        Ok(())
    }
}
