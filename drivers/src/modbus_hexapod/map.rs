//! Modbus hexapod register map from config: the commanded pose (x, y, z, rx, ry, rz), the six
//! leg encoders, the handshake; pure pose/lengths <-> register conversions.

use serde::{Deserialize, Serialize};

use crate::modbus::registers::{
    default_holding, default_true, default_unit_id, default_width, scale_of, Acknowledge,
    CommandRegister, Handshake, RegisterKind, RegisterRef, StatusRegister, WordLayout, WordOrder,
};
use crate::traits::PlatformPose;

/// The commanded pose: six consecutive values from `address` (each one or two words):
/// x, y, z (metres) then rx, ry, rz, the rotation vector's components (radians).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PoseRegisters {
    /// Protocol (0-based) address of x; a holding register block.
    pub address: u16,
    #[serde(default = "default_width")]
    pub width_bits: u8,
    #[serde(default)]
    pub word_order: WordOrder,
    #[serde(default = "default_true")]
    pub signed: bool,
    /// Scale of x, y, z: give exactly one of `counts_per_m` and `m_per_count`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub counts_per_m: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub m_per_count: Option<f64>,
    /// Scale of rx, ry, rz: give exactly one of `counts_per_rad` and `rad_per_count`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub counts_per_rad: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rad_per_count: Option<f64>,
}

/// The six leg encoders: consecutive values from `address`, leg 1 first, in metres.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LegRegisters {
    pub address: u16,
    #[serde(default = "default_holding")]
    pub kind: RegisterKind,
    #[serde(default = "default_width")]
    pub width_bits: u8,
    #[serde(default)]
    pub word_order: WordOrder,
    #[serde(default = "default_true")]
    pub signed: bool,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub counts_per_m: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub m_per_count: Option<f64>,
}

/// The whole register map of one hexapod controller; lives in the TOML config.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HexapodRegisterMap {
    #[serde(default = "default_unit_id")]
    pub unit_id: u8,
    pub pose_target: PoseRegisters,
    pub legs: LegRegisters,
    pub status: StatusRegister,
    pub command: CommandRegister,
    pub ack: Acknowledge,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fault_code: Option<RegisterRef>,
}

macro_rules! layout {
    ($t:ty) => {
        impl WordLayout for $t {
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
    };
}
layout!(PoseRegisters);
layout!(LegRegisters);

/// Words of `n` values of `layout`, or None if the count is wrong.
fn chunks<'a>(layout: &impl WordLayout, words: &'a [u16], n: usize) -> Option<Vec<&'a [u16]>> {
    let w = usize::from(layout.words());
    (words.len() == w * n).then(|| words.chunks(w).collect())
}

impl PoseRegisters {
    /// Words of the whole block (six values).
    pub fn block_words(&self) -> u16 {
        6 * self.words()
    }

    fn scales(&self) -> Result<(f64, f64), String> {
        Ok((
            scale_of("pose_target", self.counts_per_m, self.m_per_count, "m")?,
            scale_of(
                "pose_target",
                self.counts_per_rad,
                self.rad_per_count,
                "rad",
            )?,
        ))
    }

    /// The block's words for `pose` (rounded to the nearest count), or why it does not fit.
    pub fn encode(&self, pose: &PlatformPose) -> Result<Vec<u16>, String> {
        let (m, rad) = self.scales()?;
        let mut out = Vec::with_capacity(usize::from(self.block_words()));
        for (name, v) in ["x", "y", "z"].iter().zip(pose.translation_m) {
            out.extend(
                self.encode_scaled(v, m, "m")
                    .map_err(|e| format!("{name}: {e}"))?,
            );
        }
        for (name, v) in ["rx", "ry", "rz"].iter().zip(pose.rotation_vector_rad) {
            out.extend(
                self.encode_scaled(v, rad, "rad")
                    .map_err(|e| format!("{name}: {e}"))?,
            );
        }
        Ok(out)
    }

    /// The pose in the block's words (address order).
    pub fn decode(&self, words: &[u16]) -> Option<PlatformPose> {
        let (m, rad) = self.scales().ok()?;
        let c = chunks(self, words, 6)?;
        let v = |k: usize, s: f64| self.decode_scaled(c[k], s);
        Some(PlatformPose {
            translation_m: [v(0, m)?, v(1, m)?, v(2, m)?],
            rotation_vector_rad: [v(3, rad)?, v(4, rad)?, v(5, rad)?],
        })
    }
}

impl LegRegisters {
    pub fn block_words(&self) -> u16 {
        6 * self.words()
    }

    fn scale(&self) -> Result<f64, String> {
        scale_of("legs", self.counts_per_m, self.m_per_count, "m")
    }

    /// The block's words for six leg lengths; a length out of range reads as count 0.
    pub fn encode(&self, lengths_m: &[f64; 6]) -> Result<Vec<u16>, String> {
        let s = self.scale()?;
        let mut out = Vec::with_capacity(usize::from(self.block_words()));
        for (i, v) in lengths_m.iter().enumerate() {
            out.extend(
                self.encode_scaled(*v, s, "m")
                    .map_err(|e| format!("leg {}: {e}", i + 1))?,
            );
        }
        Ok(out)
    }

    pub fn decode(&self, words: &[u16]) -> Option<[f64; 6]> {
        let s = self.scale().ok()?;
        let c = chunks(self, words, 6)?;
        let mut out = [0.0; 6];
        for (o, w) in out.iter_mut().zip(c) {
            *o = self.decode_scaled(w, s)?;
        }
        Some(out)
    }
}

impl HexapodRegisterMap {
    pub fn handshake(&self) -> Handshake {
        Handshake {
            unit_id: self.unit_id,
            status: self.status.clone(),
            command: self.command.clone(),
            ack: self.ack.clone(),
            fault_code: self.fault_code,
        }
    }

    /// Reject maps the driver cannot work with.
    pub fn validate(&self) -> Result<(), String> {
        let p = &self.pose_target;
        p.check_layout("pose_target", p.address, 6)?;
        p.scales()?;
        let l = &self.legs;
        l.check_layout("legs", l.address, 6)?;
        l.scale()?;
        self.handshake().validate()?;
        let span = |a: u16, n: u16| u32::from(a)..u32::from(a) + u32::from(n);
        let target = span(p.address, p.block_words());
        if target.contains(&u32::from(self.command.address)) {
            return Err("command register overlaps the pose_target block".into());
        }
        if l.kind == RegisterKind::Holding {
            let legs = span(l.address, l.block_words());
            if legs.start < target.end && target.start < legs.end {
                return Err("legs and pose_target blocks overlap".into());
            }
            if legs.contains(&u32::from(self.command.address)) {
                return Err("command register overlaps the legs block".into());
            }
        }
        Ok(())
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// The example map of docs/hexapod.md: 32-bit values, 0.1 µm and 0.1 µrad per count.
    pub(crate) fn example_map() -> HexapodRegisterMap {
        serde_json::from_value(serde_json::json!({
            "unit_id": 1,
            "pose_target": {"address": 100, "word_order": "little",
                            "counts_per_m": 1e7, "rad_per_count": 1e-7},
            "legs": {"address": 200, "kind": "input", "m_per_count": 1e-7},
            "status": {"address": 300, "kind": "input", "in_position_bit": 0,
                       "moving_bit": 1, "fault_bit": 2},
            "command": {"address": 120, "go_value": 1, "clear_value": 0},
            "ack": {"bit": 3},
            "fault_code": {"address": 301, "kind": "input"}
        }))
        .expect("example map parses")
    }

    #[test]
    fn example_validates_and_round_trips() {
        let m = example_map();
        assert_eq!(m.validate(), Ok(()));
        let pose = PlatformPose {
            translation_m: [0.0123456, -0.05, -0.7],
            rotation_vector_rad: [0.1, -0.17, 1e-7],
        };
        let w = m.pose_target.encode(&pose).expect("fits");
        assert_eq!(w.len(), 12);
        // x = 123456 counts, little word order: low word first.
        assert_eq!(&w[..2], &[123_456u32 as u16, 1]);
        let back = m.pose_target.decode(&w).expect("decodes");
        for k in 0..3 {
            assert!((back.translation_m[k] - pose.translation_m[k]).abs() <= 0.5e-7);
            assert!((back.rotation_vector_rad[k] - pose.rotation_vector_rad[k]).abs() <= 0.5e-7);
        }
        let legs = [0.7, 0.71, -0.01, 0.0, 0.65, 0.699_999_9];
        let lw = m.legs.encode(&legs).expect("fits");
        let lb = m.legs.decode(&lw).expect("decodes");
        for k in 0..6 {
            assert!((lb[k] - legs[k]).abs() <= 0.5e-7 + 1e-15, "{k}");
        }
        assert_eq!(m.legs.decode(&lw[..11]), None);
    }

    #[test]
    fn bad_maps_and_values_rejected() {
        let mut m = example_map();
        m.pose_target.counts_per_rad = Some(1e7);
        assert!(m
            .validate()
            .unwrap_err()
            .contains("exactly one of counts_per_rad"));
        let mut m = example_map();
        m.legs.m_per_count = None;
        assert!(m.validate().unwrap_err().contains("legs"));
        let mut m = example_map();
        m.command.address = 105;
        assert!(m.validate().unwrap_err().contains("overlaps"));
        let mut m = example_map();
        m.legs.kind = RegisterKind::Holding;
        m.legs.address = 110;
        assert!(m.validate().unwrap_err().contains("overlap"));
        let mut m = example_map();
        m.pose_target.width_bits = 8;
        assert!(m.validate().unwrap_err().contains("width_bits"));
        let mut m = example_map();
        m.ack.bit = Some(0);
        assert!(m.validate().unwrap_err().contains("collides"));
        let mut m = example_map();
        m.pose_target.address = 65_530;
        assert!(m.validate().unwrap_err().contains("runs past"));
        // 16-bit at 0.1 µm: ±3.3 mm only.
        let mut m = example_map();
        m.pose_target.width_bits = 16;
        let far = PlatformPose {
            translation_m: [0.01, 0.0, 0.0],
            rotation_vector_rad: [0.0; 3],
        };
        assert!(m.pose_target.encode(&far).unwrap_err().starts_with("x: "));
        let r: Result<LegRegisters, _> = serde_json::from_value(
            serde_json::json!({"address": 1, "counts_per_m": 1.0, "scale": 2}),
        );
        assert!(r.is_err());
    }
}
