//! GUM uncertainty budgets (ISO 230-9 style): the solve's statistical σ plus every declared
//! contributor through its sensitivity coefficient, combined, expanded (k = 2) and tabulated.

use serde::Serialize;

use crate::config::uncertainty::UncertaintyConfig;
use crate::sim::effects::{
    edlen_dn, REFERENCE_AIR_TEMP_K, REFERENCE_HUMIDITY_PCT, REFERENCE_PRESSURE_PA,
};

/// Coverage factor of the expanded uncertainty (about 95 % for a normal distribution).
pub const COVERAGE_FACTOR: f64 = 2.0;

/// One input quantity of a budget: its standard uncertainty and its sensitivity coefficient.
#[derive(Debug, Clone, PartialEq)]
pub struct Input {
    pub name: String,
    /// u(x_i), in `unit`.
    pub standard_uncertainty: f64,
    pub unit: String,
    /// c_i = ∂y/∂x_i, in (quantity unit)/(`unit`).
    pub sensitivity: f64,
    pub sensitivity_unit: String,
}

impl Input {
    pub fn new(name: &str, u: f64, unit: &str, c: f64, c_unit: &str) -> Input {
        Input {
            name: name.to_string(),
            standard_uncertainty: u,
            unit: unit.to_string(),
            sensitivity: c,
            sensitivity_unit: c_unit.to_string(),
        }
    }
}

/// A row of the table of contributors.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Contributor {
    pub name: String,
    pub standard_uncertainty: f64,
    pub unit: String,
    pub sensitivity: f64,
    pub sensitivity_unit: String,
    /// u_i(y) = |c_i| u(x_i), in the quantity's unit.
    pub contribution: f64,
    /// u_i(y)² / u_c(y)²: the shares add up to 1.
    pub share: f64,
}

/// The budget of one reported quantity.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Budget {
    pub quantity: String,
    /// "m" or "rad".
    pub unit: String,
    pub value: f64,
    pub combined_standard_uncertainty: f64,
    pub coverage_factor: f64,
    pub expanded_uncertainty: f64,
    pub contributors: Vec<Contributor>,
}

impl Budget {
    /// The GUM law of propagation for uncorrelated inputs: u_c² = Σ (c_i u(x_i))², U = k u_c.
    pub fn combine(quantity: &str, unit: &str, value: f64, inputs: &[Input]) -> Budget {
        let contributions: Vec<f64> = inputs
            .iter()
            .map(|i| (i.sensitivity * i.standard_uncertainty).abs())
            .collect();
        let variance: f64 = contributions.iter().map(|u| u * u).sum();
        let u_c = variance.sqrt();
        let contributors = inputs
            .iter()
            .zip(&contributions)
            .map(|(i, &u)| Contributor {
                name: i.name.clone(),
                standard_uncertainty: i.standard_uncertainty,
                unit: i.unit.clone(),
                sensitivity: i.sensitivity,
                sensitivity_unit: i.sensitivity_unit.clone(),
                contribution: u,
                share: if variance > 0.0 {
                    u * u / variance
                } else {
                    0.0
                },
            })
            .collect();
        Budget {
            quantity: quantity.to_string(),
            unit: unit.to_string(),
            value,
            combined_standard_uncertainty: u_c,
            coverage_factor: COVERAGE_FACTOR,
            expanded_uncertainty: COVERAGE_FACTOR * u_c,
            contributors,
        }
    }
}

/// Sensitivities of the air's refractive index (Edlén) at the reference air.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct EdlenSensitivities {
    pub dn_dt_per_k: f64,
    pub dn_dp_per_pa: f64,
    pub dn_drh_per_pct: f64,
}

impl EdlenSensitivities {
    /// Central differences of the code's own Edlén function, so the budget and the
    /// simulated air can never disagree.
    pub fn at_reference() -> EdlenSensitivities {
        let (t, p, rh) = (
            REFERENCE_AIR_TEMP_K,
            REFERENCE_PRESSURE_PA,
            REFERENCE_HUMIDITY_PCT,
        );
        let (dt, dp, drh) = (0.5, 50.0, 5.0);
        EdlenSensitivities {
            dn_dt_per_k: (edlen_dn(t + dt, p, rh) - edlen_dn(t - dt, p, rh)) / (2.0 * dt),
            dn_dp_per_pa: (edlen_dn(t, p + dp, rh) - edlen_dn(t, p - dp, rh)) / (2.0 * dp),
            dn_drh_per_pct: (edlen_dn(t, p, rh + drh) - edlen_dn(t, p, rh - drh)) / (2.0 * drh),
        }
    }
}

/// Where a length-type quantity sits: the length over which scale-like errors act and the
/// material's deviation from 20 °C during the measurement.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LengthContext {
    /// Distance from the quantity's reference (the axis's reference position, the gauge
    /// centre for a point coordinate), m.
    pub length_m: f64,
    /// Mean material temperature minus 293.15 K, K.
    pub material_dt_k: f64,
    /// The scales' CTE used for the normalisation, 1/K.
    pub scale_cte_per_k: f64,
}

/// The inputs of a length-type quantity (a positioning error at a position, a point
/// coordinate, a straightness value): every scale-like contributor acts over `length_m`.
pub fn length_inputs(
    sigma_stat_m: f64,
    ctx: &LengthContext,
    declared: &UncertaintyConfig,
) -> Vec<Input> {
    let l = ctx.length_m.abs();
    let e = EdlenSensitivities::at_reference();
    vec![
        Input::new("statistical (solve)", sigma_stat_m, "m", 1.0, "1"),
        Input::new(
            "tracer calibration (scale)",
            declared.tracer_scale_ppm,
            "ppm",
            1e-6 * l,
            "m/ppm",
        ),
        Input::new(
            "tracer calibration (offset)",
            declared.tracer_offset_m,
            "m",
            1.0,
            "1",
        ),
        Input::new(
            "air temperature sensor",
            declared.air_temp_k,
            "K",
            e.dn_dt_per_k * l,
            "m/K",
        ),
        Input::new(
            "air pressure sensor",
            declared.pressure_pa,
            "Pa",
            e.dn_dp_per_pa * l,
            "m/Pa",
        ),
        Input::new(
            "humidity sensor",
            declared.humidity_pct,
            "%RH",
            e.dn_drh_per_pct * l,
            "m/%RH",
        ),
        Input::new(
            "material temperature sensor",
            declared.material_temp_k,
            "K",
            ctx.scale_cte_per_k * l,
            "m/K",
        ),
        Input::new(
            "scale CTE",
            declared.cte_per_k,
            "1/K",
            ctx.material_dt_k * l,
            "m·K",
        ),
        Input::new("reflector/probe", declared.reflector_m, "m", 1.0, "1"),
    ]
}

/// The budget of a length-type quantity.
pub fn length_budget(
    quantity: &str,
    value_m: f64,
    sigma_stat_m: f64,
    ctx: &LengthContext,
    declared: &UncertaintyConfig,
) -> Budget {
    Budget::combine(
        quantity,
        "m",
        value_m,
        &length_inputs(sigma_stat_m, ctx, declared),
    )
}

/// The budget of an angle measured from lengths (a rotary step-angle error, a squareness):
/// a uniform scale (tracer calibration, air index, material expansion) leaves angles
/// unchanged, so besides the statistical σ only the reflector's own uncertainty acts,
/// over the lever `lever_m` (the circle's radius, the axis travel).
pub fn angle_budget(
    quantity: &str,
    value_rad: f64,
    sigma_stat_rad: f64,
    lever_m: f64,
    declared: &UncertaintyConfig,
) -> Budget {
    let c = if lever_m > 0.0 { 1.0 / lever_m } else { 0.0 };
    Budget::combine(
        quantity,
        "rad",
        value_rad,
        &[
            Input::new("statistical (solve)", sigma_stat_rad, "rad", 1.0, "1"),
            Input::new("reflector/probe", declared.reflector_m, "m", c, "rad/m"),
        ],
    )
}

/// A contributor a kind declares under its `[uncertainty]` section: its name in the table,
/// its configuration key, the unit of its standard uncertainty and the value (None: left out
/// of the configuration, so left out of the budget and named as not declared).
#[derive(Debug, Clone, PartialEq)]
pub struct Declared {
    pub name: &'static str,
    pub key: &'static str,
    pub unit: &'static str,
    pub u: Option<f64>,
}

/// A reported quantity of a kind: its name, unit ("m" or "rad"), value and statistical σ.
#[derive(Debug, Clone, PartialEq)]
pub struct Quantity {
    pub name: String,
    pub unit: &'static str,
    pub value: f64,
    pub sigma: f64,
}

/// The budgets of a kind's reported quantities, and the contributors its configuration left out.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct KindBudgets {
    pub budgets: Vec<Budget>,
    /// `uncertainty.<key>` of every contributor that was not declared.
    pub not_declared: Vec<String>,
}

/// Sensitivity coefficients of every quantity to one input by central differences through a
/// solver: `solve(h)` re-solves with the input moved by h and returns the quantities in order.
pub fn central_difference<E>(
    step: f64,
    mut solve: impl FnMut(f64) -> Result<Vec<f64>, E>,
) -> Result<Vec<f64>, E> {
    let plus = solve(step)?;
    let minus = solve(-step)?;
    Ok(plus
        .iter()
        .zip(&minus)
        .map(|(p, m)| (p - m) / (2.0 * step))
        .collect())
}

/// One budget per quantity: its statistical σ (c = 1) and every declared contributor with
/// its sensitivity to that quantity (`sensitivities[j][q]` for `declared[j]`; entries of
/// undeclared contributors are not read).
pub fn kind_budgets(
    quantities: &[Quantity],
    declared: &[Declared],
    sensitivities: &[Vec<f64>],
) -> KindBudgets {
    let budgets = quantities
        .iter()
        .enumerate()
        .map(|(q, quantity)| {
            let mut inputs = vec![Input::new(
                "statistical (solve)",
                quantity.sigma,
                quantity.unit,
                1.0,
                "1",
            )];
            for (d, c) in declared.iter().zip(sensitivities) {
                if let Some(u) = d.u {
                    let unit = format!("{}/{}", quantity.unit, d.unit);
                    inputs.push(Input::new(d.name, u, d.unit, c[q], &unit));
                }
            }
            Budget::combine(&quantity.name, quantity.unit, quantity.value, &inputs)
        })
        .collect();
    // A key may stand for several rows (one scale per axis): named once.
    let mut not_declared: Vec<String> = Vec::new();
    for d in declared.iter().filter(|d| d.u.is_none()) {
        let key = format!("uncertainty.{}", d.key);
        if !not_declared.contains(&key) {
            not_declared.push(key);
        }
    }
    KindBudgets {
        budgets,
        not_declared,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn combination_follows_the_law_of_propagation() {
        // u = sqrt((1·3)² + (2·2)²) = 5; U = 10; shares 9/25 and 16/25.
        let b = Budget::combine(
            "q",
            "m",
            1.0,
            &[
                Input::new("a", 3.0, "m", 1.0, "1"),
                Input::new("b", 2.0, "K", -2.0, "m/K"),
            ],
        );
        assert!((b.combined_standard_uncertainty - 5.0).abs() < 1e-12);
        assert!((b.expanded_uncertainty - 10.0).abs() < 1e-12);
        assert!((b.contributors[0].share - 0.36).abs() < 1e-12);
        assert!((b.contributors[1].share - 0.64).abs() < 1e-12);
        assert!((b.contributors[1].contribution - 4.0).abs() < 1e-12);
    }

    #[test]
    fn edlen_sensitivities_are_those_of_the_code() {
        let e = EdlenSensitivities::at_reference();
        assert!((e.dn_dt_per_k + 0.93e-6).abs() < 1e-12, "{e:?}");
        assert!((e.dn_dp_per_pa - 0.27e-8).abs() < 1e-15, "{e:?}");
        assert!((e.dn_drh_per_pct + 0.008e-6).abs() < 1e-14, "{e:?}");
    }

    #[test]
    fn length_budget_against_hand_computed_values() {
        // L = 1 m, ΔT = 0.5 K, α = 11.5e-6 /K; contributions in m:
        // stat 1e-7; scale 0.2e-6; offset 0; T 0.1·0.93e-6 = 0.93e-7;
        // p 20·0.27e-8 = 0.54e-7; RH 3·0.008e-6 = 0.24e-7; material 0.1·11.5e-6 = 1.15e-6;
        // CTE 1e-6·0.5 = 0.5e-6; reflector 2e-7.
        let ctx = LengthContext {
            length_m: 1.0,
            material_dt_k: 0.5,
            scale_cte_per_k: 11.5e-6,
        };
        let b = length_budget("EXX", 0.0, 1e-7, &ctx, &UncertaintyConfig::default());
        let parts: [f64; 9] = [
            1e-7, 0.2e-6, 0.0, 0.93e-7, 0.54e-7, 0.24e-7, 1.15e-6, 0.5e-6, 2e-7,
        ];
        // Σ u_i² = (1 + 4 + 0 + 0.8649 + 0.2916 + 0.0576 + 132.25 + 25 + 4)e-14
        //       = 167.4641e-14, u_c = 1.29408e-6 m.
        let hand = 167.4641e-14f64.sqrt();
        assert!((hand - 1.29408e-6).abs() < 1e-10, "{hand}");
        assert!((b.combined_standard_uncertainty - hand).abs() < 1e-12);
        for (c, p) in b.contributors.iter().zip(parts) {
            assert!(
                (c.contribution - p).abs() < 1e-13,
                "{}: {}",
                c.name,
                c.contribution
            );
        }
        let shares: f64 = b.contributors.iter().map(|c| c.share).sum();
        assert!((shares - 1.0).abs() < 1e-12);
        assert_eq!(b.contributors[6].name, "material temperature sensor");
    }

    #[test]
    fn angles_ignore_uniform_scale() {
        // u = sqrt((2e-6)² + (2e-7 / 0.1)²) = sqrt(4e-12 + 4e-12).
        let b = angle_budget("step", 0.0, 2e-6, 0.1, &UncertaintyConfig::default());
        assert!((b.combined_standard_uncertainty - 8e-12f64.sqrt()).abs() < 1e-15);
        assert_eq!(b.unit, "rad");
    }

    #[test]
    fn budget_serialises_with_its_table() {
        let b = angle_budget("step", 0.0, 2e-6, 0.1, &UncertaintyConfig::default());
        let v = serde_json::to_value(&b).expect("json");
        assert_eq!(v["coverage_factor"], 2.0);
        assert_eq!(v["contributors"][1]["name"], "reflector/probe");
    }

    #[test]
    fn kind_budgets_take_declared_contributors_and_name_the_others() {
        let quantities = [Quantity {
            name: "q".into(),
            unit: "m",
            value: 0.0,
            sigma: 3.0,
        }];
        let declared = [
            Declared {
                name: "a",
                key: "a_m",
                unit: "m",
                u: Some(2.0),
            },
            Declared {
                name: "b",
                key: "b_ppm",
                unit: "ppm",
                u: None,
            },
        ];
        let b = kind_budgets(&quantities, &declared, &[vec![2.0], vec![100.0]]);
        // u = sqrt(3² + (2·2)²) = 5: the undeclared contributor does not enter.
        assert!((b.budgets[0].combined_standard_uncertainty - 5.0).abs() < 1e-12);
        assert_eq!(b.budgets[0].contributors.len(), 2);
        assert_eq!(b.not_declared, vec!["uncertainty.b_ppm".to_string()]);
    }

    #[test]
    fn central_differences_are_exact_on_a_line() {
        let c = central_difference(0.5, |h| Ok::<_, ()>(vec![3.0 * h + 1.0, -h])).expect("ok");
        assert_eq!(c, vec![3.0, -1.0]);
    }
}
