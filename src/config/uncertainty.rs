//! `[uncertainty]` and `[normalisation]`: the declared standard uncertainties (k = 1) of the
//! inputs a result depends on, and the machine scales' CTE used to refer positions to 20 °C.

use serde::{Deserialize, Serialize};

/// Declared standard uncertainties (k = 1), each in the unit its name ends with. A missing
/// section or key takes the default documented in docs/uncertainty.md.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct UncertaintyConfig {
    /// Tracer/interferometer length calibration, length-proportional part, ppm (1e-6).
    pub tracer_scale_ppm: f64,
    /// Tracer/interferometer length calibration, constant part, m.
    pub tracer_offset_m: f64,
    /// Air temperature sensor, K.
    pub air_temp_k: f64,
    /// Air pressure sensor, Pa.
    pub pressure_pa: f64,
    /// Relative humidity sensor, %RH.
    pub humidity_pct: f64,
    /// Material (machine scale) temperature sensors, K.
    pub material_temp_k: f64,
    /// The scales' coefficient of thermal expansion, 1/K.
    pub cte_per_k: f64,
    /// The reflector's (or probe's) own uncertainty: centring, form, m.
    pub reflector_m: f64,
}

impl Default for UncertaintyConfig {
    fn default() -> Self {
        UncertaintyConfig {
            tracer_scale_ppm: 0.2,
            tracer_offset_m: 0.0,
            air_temp_k: 0.1,
            pressure_pa: 20.0,
            humidity_pct: 3.0,
            material_temp_k: 0.1,
            cte_per_k: 1.0e-6,
            reflector_m: 2.0e-7,
        }
    }
}

impl UncertaintyConfig {
    /// Every value finite and >= 0; the error names `section.key`.
    pub fn validate(&self, section: &str) -> Result<(), (String, String)> {
        let keys = [
            ("tracer_scale_ppm", self.tracer_scale_ppm),
            ("tracer_offset_m", self.tracer_offset_m),
            ("air_temp_k", self.air_temp_k),
            ("pressure_pa", self.pressure_pa),
            ("humidity_pct", self.humidity_pct),
            ("material_temp_k", self.material_temp_k),
            ("cte_per_k", self.cte_per_k),
            ("reflector_m", self.reflector_m),
        ];
        for (key, value) in keys {
            if !(value.is_finite() && value >= 0.0) {
                return Err((
                    format!("{section}.{key}"),
                    format!("expected a standard uncertainty >= 0, found {value}"),
                ));
            }
        }
        Ok(())
    }
}

/// Steel scales (glass-ceramic scales are near 0, aluminium near 23e-6).
pub const DEFAULT_SCALE_CTE_PER_K: f64 = 11.5e-6;

/// How measured positions are referred to 20 °C (ISO 1).
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct NormalisationConfig {
    /// The machine scales' coefficient of thermal expansion, 1/K.
    pub scale_cte_per_k: f64,
}

impl Default for NormalisationConfig {
    fn default() -> Self {
        NormalisationConfig {
            scale_cte_per_k: DEFAULT_SCALE_CTE_PER_K,
        }
    }
}

impl NormalisationConfig {
    /// A finite CTE in (-1e-4, 1e-4) 1/K (every engineering material); names `section.key`.
    pub fn validate(&self, section: &str) -> Result<(), (String, String)> {
        let a = self.scale_cte_per_k;
        if a.is_finite() && a.abs() < 1e-4 {
            Ok(())
        } else {
            Err((
                format!("{section}.scale_cte_per_k"),
                format!("expected a CTE in 1/K with |value| < 1e-4 (steel: 11.5e-6), found {a}"),
            ))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn missing_keys_take_the_defaults_and_unknown_keys_are_named() {
        let c: UncertaintyConfig = toml::from_str("air_temp_k = 0.05").expect("parse");
        assert_eq!(c.air_temp_k, 0.05);
        assert_eq!(c.pressure_pa, UncertaintyConfig::default().pressure_pa);
        let e = toml::from_str::<UncertaintyConfig>("air_temp = 0.05").expect_err("unknown");
        assert!(e.to_string().contains("air_temp"), "{e}");
    }

    #[test]
    fn negative_or_nan_values_name_the_key() {
        let c = UncertaintyConfig {
            pressure_pa: -1.0,
            ..Default::default()
        };
        let (key, message) = c.validate("uncertainty").expect_err("negative");
        assert_eq!(key, "uncertainty.pressure_pa");
        assert!(message.contains(">= 0"), "{message}");
        let n = NormalisationConfig {
            scale_cte_per_k: 11.5,
        };
        let (key, _) = n.validate("normalisation").expect_err("per K, not ppm");
        assert_eq!(key, "normalisation.scale_cte_per_k");
    }
}
