//! Normalisation to 20 °C (ISO 1): the positioning errors (EXX, EYY, EZZ) with the scales'
//! expansion at the logged material temperature taken out, raw values kept beside them.

use serde::Serialize;
use serde_json::Value;

use crate::config::uncertainty::NormalisationConfig;
use crate::session::reader::Session;
use crate::sim::effects::REFERENCE_MATERIAL_TEMP_K;

/// A `geometric_errors` value that does not have the expected shape.
#[derive(Debug, thiserror::Error)]
#[error("geometric_errors: `{key}`: {message}")]
pub struct EvaluateError {
    pub key: String,
    pub message: String,
}

fn bad(key: &str, message: impl Into<String>) -> EvaluateError {
    EvaluateError {
        key: key.to_string(),
        message: message.into(),
    }
}

/// The material temperatures logged during the run, over every sensor and sample.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct MaterialTemperature {
    pub mean_k: f64,
    pub min_k: f64,
    pub max_k: f64,
    /// Sensor values averaged (samples × sensors).
    pub readings: usize,
}

impl MaterialTemperature {
    /// From `material_temp_k` of every `/env/<id>` sample; None when the session logged none.
    pub fn from_session(session: &Session) -> Option<MaterialTemperature> {
        let values = session
            .env
            .values()
            .flatten()
            .flat_map(|s| s.msg.material_temp_k.iter().copied())
            .filter(|t| t.is_finite());
        Self::from_values(values)
    }

    pub fn from_values(values: impl IntoIterator<Item = f64>) -> Option<MaterialTemperature> {
        let (mut sum, mut n) = (0.0, 0usize);
        let (mut min_k, mut max_k) = (f64::INFINITY, f64::NEG_INFINITY);
        for t in values {
            sum += t;
            n += 1;
            min_k = min_k.min(t);
            max_k = max_k.max(t);
        }
        (n > 0).then(|| MaterialTemperature {
            mean_k: sum / n as f64,
            min_k,
            max_k,
            readings: n,
        })
    }

    /// Mean deviation from 20 °C, K.
    pub fn dt_k(&self) -> f64 {
        self.mean_k - REFERENCE_MATERIAL_TEMP_K
    }
}

/// One axis's positioning error curve as the solve reported it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PositioningCurve {
    pub axis: String,
    /// "EXX", "EYY" or "EZZ".
    pub error: String,
    pub positions_m: Vec<f64>,
    pub values_m: Vec<Option<f64>>,
    pub sigma_m: Vec<Option<f64>>,
}

pub(super) fn numbers(v: &Value, key: &str) -> Result<Vec<Option<f64>>, EvaluateError> {
    let list = v
        .as_array()
        .ok_or_else(|| bad(key, "expected an array of numbers or nulls"))?;
    list.iter()
        .enumerate()
        .map(|(i, x)| match x {
            Value::Null => Ok(None),
            _ => x.as_f64().map(Some).ok_or_else(|| {
                bad(
                    &format!("{key}[{i}]"),
                    format!("expected a number, found {x}"),
                )
            }),
        })
        .collect()
}

/// The positioning error curves (EXX along x, ...) of a results' `geometric_errors`.
pub fn positioning_curves(
    geometric_errors: &Value,
) -> Result<Vec<PositioningCurve>, EvaluateError> {
    let axes = geometric_errors
        .get("axes")
        .and_then(Value::as_object)
        .ok_or_else(|| bad("axes", "expected an object of axes"))?;
    let mut out = Vec::new();
    for (axis, result) in axes {
        let error = format!("E{}{}", axis.to_uppercase(), axis.to_uppercase());
        let key = format!("axes.{axis}");
        let positions_m = numbers(&result["positions_m"], &format!("{key}.positions_m"))?
            .into_iter()
            .enumerate()
            .map(|(i, p)| {
                p.ok_or_else(|| {
                    bad(
                        &format!("{key}.positions_m[{i}]"),
                        "expected a number, found null",
                    )
                })
            })
            .collect::<Result<Vec<f64>, _>>()?;
        let Some(function) = result.get("errors").and_then(|e| e.get(&error)) else {
            continue;
        };
        let fkey = format!("{key}.errors.{error}");
        let values_m = numbers(&function["values"], &format!("{fkey}.values"))?;
        let sigma_m = numbers(&function["sigma"], &format!("{fkey}.sigma"))?;
        if values_m.len() != positions_m.len() || sigma_m.len() != positions_m.len() {
            return Err(bad(
                &fkey,
                format!(
                    "expected {} values and sigmas (one per position), found {} and {}",
                    positions_m.len(),
                    values_m.len(),
                    sigma_m.len()
                ),
            ));
        }
        out.push(PositioningCurve {
            axis: axis.clone(),
            error,
            positions_m,
            values_m,
            sigma_m,
        });
    }
    Ok(out)
}

/// A positioning error curve raw and referred to 20 °C.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct NormalisedCurve {
    pub axis: String,
    pub error: String,
    pub positions_m: Vec<f64>,
    /// Where the scale's expansion is zero: the first grid position, m.
    pub reference_position_m: f64,
    pub scale_cte_per_k: f64,
    /// Mean logged material temperature, K; None: nothing logged, normalised = raw.
    pub material_temp_k: Option<f64>,
    pub raw_m: Vec<Option<f64>>,
    /// raw − α (T − 293.15 K)(x − x_ref).
    pub normalised_m: Vec<Option<f64>>,
    pub sigma_m: Vec<Option<f64>>,
}

/// Refer a positioning curve to 20 °C: a scale at T reads short by α (T − 20 °C) per metre,
/// so the machine's positions carry α ΔT (x − x_ref), which is taken out.
pub fn normalise_curve(
    curve: &PositioningCurve,
    material: Option<&MaterialTemperature>,
    config: &NormalisationConfig,
) -> NormalisedCurve {
    let reference_position_m = curve.positions_m.first().copied().unwrap_or(0.0);
    let dt_k = material.map_or(0.0, MaterialTemperature::dt_k);
    let normalised_m = curve
        .positions_m
        .iter()
        .zip(&curve.values_m)
        .map(|(x, v)| {
            v.map(|v| v - correction_m(config.scale_cte_per_k, dt_k, x - reference_position_m))
        })
        .collect();
    NormalisedCurve {
        axis: curve.axis.clone(),
        error: curve.error.clone(),
        positions_m: curve.positions_m.clone(),
        reference_position_m,
        scale_cte_per_k: config.scale_cte_per_k,
        material_temp_k: material.map(|m| m.mean_k),
        raw_m: curve.values_m.clone(),
        normalised_m,
        sigma_m: curve.sigma_m.clone(),
    }
}

/// The scales' expansion at distance `from_reference_m`: α ΔT d, m.
pub fn correction_m(scale_cte_per_k: f64, dt_k: f64, from_reference_m: f64) -> f64 {
    scale_cte_per_k * dt_k * from_reference_m
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn geometric_errors() -> Value {
        json!({"axes": {"x": {"positions_m": [0.1, 0.6, 1.1],
            "errors": {"EXX": {"unit": "m", "values": [1e-6, null, 3e-6], "sigma": [1e-7, null, 2e-7]},
                       "EYX": {"unit": "m", "values": [0, 0, 0], "sigma": [0, 0, 0]}}}}})
    }

    #[test]
    fn normalisation_takes_out_the_scale_expansion() {
        let curves = positioning_curves(&geometric_errors()).expect("curves");
        assert_eq!(curves.len(), 1);
        assert_eq!(curves[0].error, "EXX");
        // 0.5 K warm, α = 11.5e-6: at 1 m from the reference the scale adds 5.75 µm.
        let m = MaterialTemperature::from_values([293.4, 293.9]).expect("logged");
        assert!((m.dt_k() - 0.5).abs() < 1e-9);
        let n = normalise_curve(&curves[0], Some(&m), &NormalisationConfig::default());
        assert_eq!(n.reference_position_m, 0.1);
        assert_eq!(n.normalised_m[0], Some(1e-6));
        assert_eq!(n.normalised_m[1], None);
        let v = n.normalised_m[2].expect("value");
        assert!((v - (3e-6 - 5.75e-6)).abs() < 1e-12, "{v}");
        assert_eq!(n.raw_m[2], Some(3e-6));
    }

    #[test]
    fn no_material_temperature_leaves_the_curve_raw() {
        let curves = positioning_curves(&geometric_errors()).expect("curves");
        let n = normalise_curve(&curves[0], None, &NormalisationConfig::default());
        assert_eq!(n.normalised_m, n.raw_m);
        assert_eq!(n.material_temp_k, None);
    }

    #[test]
    fn malformed_curves_name_the_key() {
        let mut g = geometric_errors();
        g["axes"]["x"]["errors"]["EXX"]["values"] = json!([1e-6, "a", 3e-6]);
        let e = positioning_curves(&g).expect_err("string");
        assert_eq!(e.key, "axes.x.errors.EXX.values[1]");
        g["axes"]["x"]["errors"]["EXX"]["values"] = json!([1e-6]);
        let e = positioning_curves(&g).expect_err("short");
        assert!(e.to_string().contains("expected 3 values"), "{e}");
        assert!(positioning_curves(&json!({})).is_err());
    }
}
