//! The evaluation of a tracer network's results (multilateration, rotary_tracer): positioning
//! errors raw and at 20 °C with their budgets, squareness and point-coordinate budgets.

use serde::Serialize;
use serde_json::Value;

use super::normalise::{
    normalise_curve, positioning_curves, EvaluateError, MaterialTemperature, NormalisedCurve,
};
use super::uncertainty::{angle_budget, length_budget, Budget, EdlenSensitivities, LengthContext};
use crate::config::uncertainty::{NormalisationConfig, UncertaintyConfig};
use crate::config::Config;
use crate::method::multilateration::{MultilaterationResults, PointResult};
use crate::session::reader::Session;

/// One positioning error curve with a budget per position where it has a value.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PositioningEvaluation {
    pub curve: NormalisedCurve,
    /// Parallel to `curve.positions_m`; None where the solve gave no value.
    pub budgets: Vec<Option<Budget>>,
}

/// Budgets of one of the other error functions (straightness, roll, pitch, yaw) of an axis.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FunctionEvaluation {
    pub axis: String,
    pub error: String,
    /// "m" or "rad".
    pub unit: String,
    pub positions_m: Vec<f64>,
    /// Parallel to `positions_m`; None where the solve gave no value.
    pub budgets: Vec<Option<Budget>>,
}

/// Everything the report shows of the budget and the normalisation of a tracer run.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TracerEvaluation {
    pub declared: UncertaintyConfig,
    pub scale_cte_per_k: f64,
    pub material_temperature: Option<MaterialTemperature>,
    pub edlen: EdlenSensitivities,
    pub positioning: Vec<PositioningEvaluation>,
    /// The other 15 error functions: straightness (m), roll, pitch and yaw (rad).
    pub functions: Vec<FunctionEvaluation>,
    pub squareness: Vec<Budget>,
    /// Three per point (x, y, z), in the order of the results' points.
    pub points: Vec<Budget>,
    pub notes: Vec<String>,
}

/// The budgets of a positioning curve: value = the normalised error, length = x − x_ref.
pub fn positioning_budgets(
    curve: &NormalisedCurve,
    material: Option<&MaterialTemperature>,
    declared: &UncertaintyConfig,
) -> Vec<Option<Budget>> {
    let dt_k = material.map_or(0.0, MaterialTemperature::dt_k);
    curve
        .positions_m
        .iter()
        .zip(curve.normalised_m.iter().zip(&curve.sigma_m))
        .map(|(x, (v, s))| {
            let v = (*v)?;
            let ctx = LengthContext {
                length_m: x - curve.reference_position_m,
                material_dt_k: dt_k,
                scale_cte_per_k: curve.scale_cte_per_k,
            };
            let name = format!("{} at {} = {:.4} m", curve.error, curve.axis, x);
            Some(length_budget(&name, v, s.unwrap_or(0.0), &ctx, declared))
        })
        .collect()
}

/// Point coordinates: scale-like errors act from the gauge centre (the nominal points'
/// centroid, where the inner constraints hold the network).
pub fn point_budgets(
    points: &[PointResult],
    material: Option<&MaterialTemperature>,
    scale_cte_per_k: f64,
    declared: &UncertaintyConfig,
) -> Vec<Budget> {
    let n = points.len().max(1) as f64;
    let centre: [f64; 3] =
        std::array::from_fn(|k| points.iter().map(|p| p.nominal_m[k]).sum::<f64>() / n);
    let dt_k = material.map_or(0.0, MaterialTemperature::dt_k);
    let mut out = Vec::with_capacity(3 * points.len());
    for p in points {
        for (k, axis) in ["x", "y", "z"].iter().enumerate() {
            let ctx = LengthContext {
                length_m: p.nominal_m[k] - centre[k],
                material_dt_k: dt_k,
                scale_cte_per_k,
            };
            let name = format!("point {} ({}) {axis}", p.point, p.target);
            out.push(length_budget(
                &name,
                p.actual_m[k],
                p.sigma_m[k],
                &ctx,
                declared,
            ));
        }
    }
    out
}

/// Budgets of the error functions other than positioning. A uniform scale (tracer
/// calibration, air index, material expansion) changes a straightness only by a constant
/// along the axis, which the straightness's datum takes out, and changes no angle: a
/// straightness keeps the statistical σ, the tracer's offset and the reflector (length
/// model with L = 0), an angular error the statistical σ and the reflector over the axis
/// travel.
pub fn function_budgets(
    geometric_errors: &Value,
    declared: &UncertaintyConfig,
) -> Result<Vec<FunctionEvaluation>, EvaluateError> {
    let axes = geometric_errors
        .get("axes")
        .and_then(Value::as_object)
        .ok_or_else(|| EvaluateError {
            key: "axes".into(),
            message: "expected an object of axes".into(),
        })?;
    let curves = positioning_curves(geometric_errors)?;
    let mut out = Vec::new();
    for curve in &curves {
        let positioning = curve.error.clone();
        let travel_m = span_m(&curve.positions_m);
        let Some(errors) = axes
            .get(&curve.axis)
            .and_then(|a| a.get("errors"))
            .and_then(Value::as_object)
        else {
            continue;
        };
        for (name, function) in errors {
            if *name == positioning {
                continue;
            }
            let key = format!("axes.{}.errors.{name}", curve.axis);
            let unit = function.get("unit").and_then(Value::as_str).unwrap_or("m");
            let values = super::normalise::numbers(&function["values"], &format!("{key}.values"))?;
            let sigma = super::normalise::numbers(&function["sigma"], &format!("{key}.sigma"))?;
            if values.len() != curve.positions_m.len() || sigma.len() != values.len() {
                return Err(EvaluateError {
                    key,
                    message: format!(
                        "expected {} values and sigmas (one per position), found {} and {}",
                        curve.positions_m.len(),
                        values.len(),
                        sigma.len()
                    ),
                });
            }
            let budgets = curve
                .positions_m
                .iter()
                .zip(values.iter().zip(&sigma))
                .map(|(x, (v, s))| {
                    let v = (*v)?;
                    let s = s.unwrap_or(0.0);
                    let q = format!("{name} at {} = {x:.4} m", curve.axis);
                    Some(if unit == "rad" {
                        angle_budget(&q, v, s, travel_m, declared)
                    } else {
                        let ctx = LengthContext {
                            length_m: 0.0,
                            material_dt_k: 0.0,
                            scale_cte_per_k: 0.0,
                        };
                        length_budget(&q, v, s, &ctx, declared)
                    })
                })
                .collect();
            out.push(FunctionEvaluation {
                axis: curve.axis.clone(),
                error: name.clone(),
                unit: unit.to_string(),
                positions_m: curve.positions_m.clone(),
                budgets,
            });
        }
    }
    Ok(out)
}

fn span_m(positions_m: &[f64]) -> f64 {
    let lo = positions_m.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = positions_m
        .iter()
        .copied()
        .fold(f64::NEG_INFINITY, f64::max);
    if hi > lo {
        hi - lo
    } else {
        0.0
    }
}

/// Squareness budgets; the lever of the reflector's uncertainty is the shortest axis travel
/// in the grid (the conservative choice).
pub fn squareness_budgets(
    geometric_errors: &Value,
    declared: &UncertaintyConfig,
) -> Result<Vec<Budget>, EvaluateError> {
    let curves = positioning_curves(geometric_errors)?;
    let lever_m = curves
        .iter()
        .map(|c| span_m(&c.positions_m))
        .filter(|&s| s > 0.0)
        .fold(f64::INFINITY, f64::min);
    let lever_m = if lever_m.is_finite() { lever_m } else { 0.0 };
    let Some(map) = geometric_errors
        .get("squareness")
        .and_then(Value::as_object)
    else {
        return Ok(Vec::new());
    };
    let mut out = Vec::new();
    for (name, s) in map {
        let value = s.get("value_rad").and_then(Value::as_f64);
        let sigma = s.get("sigma_rad").and_then(Value::as_f64);
        if let Some(value) = value {
            out.push(angle_budget(
                name,
                value,
                sigma.unwrap_or(0.0),
                lever_m,
                declared,
            ));
        }
    }
    Ok(out)
}

/// The whole evaluation of a tracer network's results.
pub fn evaluate_tracer(
    points: &[PointResult],
    geometric_errors: Option<&Value>,
    material: Option<&MaterialTemperature>,
    declared: &UncertaintyConfig,
    normalisation: &NormalisationConfig,
) -> Result<TracerEvaluation, EvaluateError> {
    let mut notes = Vec::new();
    if material.is_none() {
        notes.push(
            "no material temperature logged: positioning errors are not normalised to 20 °C"
                .to_string(),
        );
    }
    let mut positioning = Vec::new();
    let mut squareness = Vec::new();
    let mut functions = Vec::new();
    if let Some(g) = geometric_errors {
        for curve in positioning_curves(g)? {
            let curve = normalise_curve(&curve, material, normalisation);
            let budgets = positioning_budgets(&curve, material, declared);
            positioning.push(PositioningEvaluation { curve, budgets });
        }
        functions = function_budgets(g, declared)?;
        squareness = squareness_budgets(g, declared)?;
    } else {
        notes.push("no geometric errors in the results: points only".to_string());
    }
    Ok(TracerEvaluation {
        declared: *declared,
        scale_cte_per_k: normalisation.scale_cte_per_k,
        material_temperature: material.copied(),
        edlen: EdlenSensitivities::at_reference(),
        positioning,
        functions,
        squareness,
        points: point_budgets(points, material, normalisation.scale_cte_per_k, declared),
        notes,
    })
}

/// The evaluation of a tracer run: material temperatures from the session, the declared
/// uncertainties and the scales' CTE from the configuration (the defaults without one, or
/// without its sections; the evaluation's notes say which).
pub fn evaluate_session(
    session: &Session,
    results: &MultilaterationResults,
    config: Option<&Config>,
) -> Result<TracerEvaluation, EvaluateError> {
    let declared = config.and_then(|c| c.uncertainty);
    let normalisation = config.and_then(|c| c.normalisation);
    let material = MaterialTemperature::from_session(session);
    let mut evaluation = evaluate_tracer(
        &results.points,
        results.geometric_errors.as_ref(),
        material.as_ref(),
        &declared.unwrap_or_default(),
        &normalisation.unwrap_or_default(),
    )?;
    if declared.is_none() {
        evaluation
            .notes
            .push("no [uncertainty] declared: the default uncertainties are used".to_string());
    }
    if normalisation.is_none() {
        evaluation.notes.push(
            "no [normalisation] declared: the scales' CTE is the default (steel, 11.5e-6 /K)"
                .to_string(),
        );
    }
    Ok(evaluation)
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn positioning_budget_grows_with_distance_from_the_reference() {
        let g = json!({"axes": {"x": {"positions_m": [0.0, 0.5, 1.0],
            "errors": {"EXX": {"values": [0.0, 1e-6, 2e-6], "sigma": [1e-7, 1e-7, 1e-7]},
                       "EYX": {"unit": "m", "values": [0.0, 1e-6, null], "sigma": [1e-7, 1e-7, null]},
                       "EAX": {"unit": "rad", "values": [1e-6, 2e-6, 3e-6], "sigma": [1e-6, 1e-6, 1e-6]}}}},
            "squareness": {"C0Y": {"value_rad": 1e-5, "sigma_rad": 1e-6}}});
        let m = MaterialTemperature::from_values([294.15]).expect("logged");
        let e = evaluate_tracer(
            &[],
            Some(&g),
            Some(&m),
            &UncertaintyConfig::default(),
            &NormalisationConfig::default(),
        )
        .expect("evaluation");
        let b: Vec<&Budget> = e.positioning[0].budgets.iter().flatten().collect();
        assert_eq!(b.len(), 3);
        // At the reference only the statistical σ and the reflector remain.
        let at_ref = (1e-7f64.powi(2) + 2e-7f64.powi(2)).sqrt();
        assert!((b[0].combined_standard_uncertainty - at_ref).abs() < 1e-15);
        assert!(b[2].expanded_uncertainty > b[1].expanded_uncertainty);
        // 1 K warm: 11.5 µm taken out at 1 m.
        assert!((b[2].value - (2e-6 - 11.5e-6)).abs() < 1e-12);
        // Straightness: σ, tracer offset (0) and reflector only; roll over the 1 m travel.
        let named = |n: &str| e.functions.iter().find(|f| f.error == n).expect("function");
        let eyx = named("EYX");
        assert_eq!((eyx.error.as_str(), eyx.unit.as_str()), ("EYX", "m"));
        assert!(eyx.budgets[2].is_none());
        let b1 = eyx.budgets[1].as_ref().expect("budget");
        assert!((b1.combined_standard_uncertainty - at_ref).abs() < 1e-15);
        let eax = named("EAX").budgets[0].as_ref().expect("budget");
        assert!((eax.combined_standard_uncertainty - (1e-12f64 + 4e-14).sqrt()).abs() < 1e-15);
        // The squareness lever is the 1 m travel: u = sqrt(1e-6² + (2e-7 / 1)²).
        let s = &e.squareness[0];
        assert!((s.combined_standard_uncertainty - (1e-12f64 + 4e-14).sqrt()).abs() < 1e-15);
    }
}
