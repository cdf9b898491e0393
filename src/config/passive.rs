//! `[devices.machine.passive]`.

use serde::{Deserialize, Serialize};

/// `[devices.machine.passive]`: how the program dwells and how stops are matched to points.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct PassiveConfig {
    /// Extra dwell beyond what the sequencer needs (stillstand window + `plan.dwell_s`), s.
    pub dwell_margin_s: f64,
    /// How far a true station may lie from its hint, metres: the tolerance of the predicted
    /// length change between stops (src/sequencer/passive.rs).
    pub hint_tolerance_m: f64,
}

impl Default for PassiveConfig {
    fn default() -> Self {
        Self {
            dwell_margin_s: 1.0,
            hint_tolerance_m: 0.1,
        }
    }
}
