//! A run's results (geocal-results/1), its ISO 230-2 figures and its diagnosis as rows of the
//! export's tables. Sections are recognised by their shape in the results contract
//! (docs/session-format.md), never by the plan kind's name.

use serde_json::Value;

use super::schema::{DIAGNOSES, ERROR_FUNCTIONS, ISO230_2, PARAMETERS, POINTS};
use super::table::{Cell, RunCells, Table};
use crate::diagnose::Diagnosis;
use crate::evaluate::deviations::Iso230_2;
use crate::history::names;

const XYZ: [&str; 3] = ["x", "y", "z"];

/// The SI unit of an ISO 230-1 error name: E<direction><axis>, the direction X, Y, Z a
/// displacement (m), A, B, C a rotation (rad).
fn unit_of_iso_name(name: &str) -> &'static str {
    match name.as_bytes().get(1) {
        Some(b'A' | b'B' | b'C') => "rad",
        _ => "m",
    }
}

/// The SI unit of a parameter named with its unit as suffix (`_m`, `_rad`); "1" otherwise.
fn unit_of_suffix(name: &str) -> &'static str {
    if name.ends_with("_rad") {
        "rad"
    } else if name.ends_with("_m") {
        "m"
    } else {
        "1"
    }
}

/// A position as the plan gave it: a value within float rounding of a whole number of
/// nanometres (or nanoradians) is that number, so `0.9999999999999999` is `1`; any other value
/// (an angle such as π/6) is kept as it is.
pub fn as_planned(x: f64) -> f64 {
    let snapped = (x * 1e9).round() / 1e9;
    if (snapped - x).abs() <= 4.0 * f64::EPSILON * x.abs().max(1.0) {
        snapped
    } else {
        x
    }
}

fn f64_at(v: &Value, key: &str) -> Option<f64> {
    v.get(key).and_then(Value::as_f64)
}

fn array3(v: Option<&Value>) -> Option<[Option<f64>; 3]> {
    let a = v?.as_array()?;
    (a.len() == 3).then(|| [a[0].as_f64(), a[1].as_f64(), a[2].as_f64()])
}

/// One parameter row.
struct Param<'a> {
    category: &'a str,
    name: String,
    value: Option<f64>,
    sigma: Option<f64>,
    unit: &'a str,
    identifiable: bool,
}

fn parameter(table: &mut Table, p: Param<'_>) {
    table.push(vec![
        ("category", p.category.into()),
        ("name", p.name.into()),
        ("value", p.value.into()),
        ("sigma", p.sigma.into()),
        ("unit", p.unit.into()),
        ("identifiable", p.identifiable.into()),
    ]);
}

/// Every estimate with its σ the results hold: tracer stations, squareness, a kind's
/// `parameters` and `location` lists, a rotary axis, hexapod hinges, fitted effects.
pub fn parameters(results: &Value, run: &RunCells) -> Table {
    let mut t = Table::of_run(&PARAMETERS, run);
    for station in results["stations"].as_array().into_iter().flatten() {
        let id = station["id"].as_str().unwrap_or("?");
        if let (Some(p), s) = (
            array3(station.get("position_m")),
            array3(station.get("sigma_m")),
        ) {
            for k in 0..3 {
                let sigma = s.and_then(|s| s[k]);
                let name = format!("station.{id}.{}", XYZ[k]);
                parameter(
                    &mut t,
                    Param {
                        category: "station",
                        name,
                        value: p[k],
                        sigma,
                        unit: "m",
                        identifiable: true,
                    },
                );
            }
        }
    }
    if let Some(squareness) = results["geometric_errors"]["squareness"].as_object() {
        for (name, e) in squareness {
            let identifiable = e["identifiable"].as_bool().unwrap_or(false);
            parameter(
                &mut t,
                Param {
                    category: "squareness",
                    name: name.clone(),
                    value: f64_at(e, "value_rad"),
                    sigma: f64_at(e, "sigma_rad"),
                    unit: "rad",
                    identifiable,
                },
            );
        }
    }
    for p in results["parameters"].as_array().into_iter().flatten() {
        let Some(name) = p["name"].as_str() else {
            continue;
        };
        let sigma = f64_at(p, "sigma");
        parameter(
            &mut t,
            Param {
                category: "parameter",
                name: name.to_owned(),
                value: f64_at(p, "value"),
                sigma,
                unit: unit_of_suffix(name),
                identifiable: sigma.is_some(),
            },
        );
    }
    for p in results["location"].as_array().into_iter().flatten() {
        let Some(name) = p["name"].as_str() else {
            continue;
        };
        let sigma = f64_at(p, "sigma");
        parameter(
            &mut t,
            Param {
                category: "location",
                name: name.to_owned(),
                value: f64_at(p, "value"),
                sigma,
                unit: unit_of_iso_name(name),
                identifiable: sigma.is_some(),
            },
        );
    }
    let rotary = &results["rotary"];
    if rotary.is_object() {
        let table = rotary["table"].as_str().unwrap_or("table");
        for (key, sigma_key, unit) in [
            ("axis_point_m", "axis_point_sigma_m", "m"),
            ("axis_direction", "axis_direction_sigma", "1"),
        ] {
            if let Some(v) = array3(rotary.get(key)) {
                let s = array3(rotary.get(sigma_key));
                for k in 0..3 {
                    let name = names::rotary_axis(table, key, k);
                    let sigma = s.and_then(|s| s[k]);
                    parameter(
                        &mut t,
                        Param {
                            category: "rotary_axis",
                            name,
                            value: v[k],
                            sigma,
                            unit,
                            identifiable: true,
                        },
                    );
                }
            }
        }
        if let Some(r) = f64_at(rotary, "radius_m") {
            let name = format!("rotary_axis.{table}.radius_m");
            let sigma = f64_at(rotary, "radius_sigma_m");
            parameter(
                &mut t,
                Param {
                    category: "rotary_axis",
                    name,
                    value: Some(r),
                    sigma,
                    unit: "m",
                    identifiable: true,
                },
            );
        }
    }
    for hinge in results["hinges"].as_array().into_iter().flatten() {
        let leg = hinge["leg"].as_u64().unwrap_or(0);
        for (key, sigma_key, side) in [
            ("base_m", "base_sigma_m", "base"),
            ("platform_m", "platform_sigma_m", "platform"),
        ] {
            if let Some(v) = array3(hinge.get(key)) {
                let s = array3(hinge.get(sigma_key));
                for k in 0..3 {
                    let name = names::hinge(leg, side, k);
                    let sigma = s.and_then(|s| s[k]);
                    parameter(
                        &mut t,
                        Param {
                            category: "hinge",
                            name,
                            value: v[k],
                            sigma,
                            unit: "m",
                            identifiable: true,
                        },
                    );
                }
            }
        }
    }
    if let Some(effects) = results["effects"].as_object() {
        for (effect, params) in effects {
            let Some(params) = params.as_object() else {
                continue;
            };
            for (name, value) in params {
                if name.ends_with(".sigma") {
                    continue;
                }
                let sigma = params.get(&format!("{name}.sigma")).and_then(Value::as_f64);
                parameter(
                    &mut t,
                    Param {
                        category: "effect",
                        name: format!("effect.{effect}.{name}"),
                        value: value.as_f64(),
                        sigma,
                        unit: unit_of_suffix(name),
                        identifiable: true,
                    },
                );
            }
        }
    }
    t
}

/// One error function row.
struct ErrorRow<'a> {
    axis: &'a str,
    function: &'a str,
    position: f64,
    position_unit: &'a str,
    value: Option<f64>,
    sigma: Option<f64>,
    unit: &'a str,
    identifiable: bool,
}

fn error_row(t: &mut Table, e: ErrorRow<'_>) {
    t.push(vec![
        ("axis", e.axis.into()),
        ("error_function", e.function.into()),
        (
            "parameter",
            names::at_position(e.function, e.axis, as_planned(e.position), e.position_unit).into(),
        ),
        ("position", as_planned(e.position).into()),
        ("position_unit", e.position_unit.into()),
        ("value", e.value.into()),
        ("sigma", e.sigma.into()),
        ("unit", e.unit.into()),
        ("identifiable", e.identifiable.into()),
    ]);
}

/// The error functions at their axis positions: the 21 geometric errors' 18 axis functions,
/// a rotary axis's motion errors, a rotary table's step errors.
pub fn error_functions(results: &Value, run: &RunCells) -> Table {
    let mut t = Table::of_run(&ERROR_FUNCTIONS, run);
    if let Some(axes) = results["geometric_errors"]["axes"].as_object() {
        for (axis, a) in axes {
            let positions: Vec<f64> = a["positions_m"]
                .as_array()
                .into_iter()
                .flatten()
                .filter_map(Value::as_f64)
                .collect();
            for (name, f) in a["errors"].as_object().into_iter().flatten() {
                let unit = f["unit"].as_str().unwrap_or_else(|| unit_of_iso_name(name));
                let identifiable = f["identifiable"].as_bool().unwrap_or(false);
                for (i, position) in positions.iter().enumerate() {
                    let value = f["values"].get(i).and_then(Value::as_f64);
                    let sigma = f["sigma"].get(i).and_then(Value::as_f64);
                    error_row(
                        &mut t,
                        ErrorRow {
                            axis,
                            function: name,
                            position: *position,
                            position_unit: "m",
                            value,
                            sigma,
                            unit,
                            identifiable,
                        },
                    );
                }
            }
        }
    }
    if let (Some(names), Some(motion)) = (
        results["motion_names"].as_array(),
        results["motion"].as_array(),
    ) {
        let table = results["table"].as_str().unwrap_or("table");
        for m in motion {
            let Some(position) = f64_at(m, "commanded_rad") else {
                continue;
            };
            for (k, name) in names.iter().enumerate() {
                let name = name.as_str().unwrap_or("?");
                let value = m["errors"].get(k).and_then(Value::as_f64);
                let sigma = m["sigma"].get(k).and_then(Value::as_f64);
                let unit = unit_of_iso_name(name);
                let identifiable = value.is_some();
                error_row(
                    &mut t,
                    ErrorRow {
                        axis: table,
                        function: name,
                        position,
                        position_unit: "rad",
                        value,
                        sigma,
                        unit,
                        identifiable,
                    },
                );
            }
        }
    }
    let rotary = &results["rotary"];
    if let Some(steps) = rotary["steps"].as_array() {
        let table = rotary["table"].as_str().unwrap_or("table");
        for s in steps {
            let Some(position) = f64_at(s, "commanded_rad") else {
                continue;
            };
            let value = f64_at(s, "error_rad");
            error_row(
                &mut t,
                ErrorRow {
                    axis: table,
                    function: "step_error",
                    position,
                    position_unit: "rad",
                    value,
                    sigma: f64_at(s, "sigma_rad"),
                    unit: "rad",
                    identifiable: value.is_some(),
                },
            );
        }
    }
    t
}

/// The measured points of a tracer network.
pub fn points(results: &Value, run: &RunCells) -> Table {
    let mut t = Table::of_run(&POINTS, run);
    for p in results["points"].as_array().into_iter().flatten() {
        let (Some(nominal), Some(error), Some(sigma)) = (
            array3(p.get("nominal_m")),
            array3(p.get("error_m")),
            array3(p.get("sigma_m")),
        ) else {
            continue;
        };
        let (Some(point), Some(target)) = (p["point"].as_u64(), p["target"].as_str()) else {
            continue;
        };
        let mut cells: Vec<(&str, Cell)> = vec![
            ("target", target.into()),
            ("point", Cell::Int(point as i64)),
            (
                "observations",
                Cell::Int(p["observations"].as_i64().unwrap_or(0)),
            ),
        ];
        const NOMINAL: [&str; 3] = ["nominal_x_m", "nominal_y_m", "nominal_z_m"];
        const ERROR: [&str; 3] = ["error_x_m", "error_y_m", "error_z_m"];
        const SIGMA: [&str; 3] = ["sigma_x_m", "sigma_y_m", "sigma_z_m"];
        for k in 0..3 {
            cells.push((NOMINAL[k], nominal[k].into()));
            cells.push((ERROR[k], error[k].into()));
            cells.push((SIGMA[k], sigma[k].into()));
        }
        t.push(cells);
    }
    t
}

/// The ISO 230-2 figures of every evaluated axis.
pub fn iso230_2(iso: &Iso230_2, run: &RunCells) -> Table {
    use crate::evaluate::iso230_2::UnitFigures;
    let mut t = Table::of_run(&ISO230_2, run);
    for a in &iso.axes {
        let e = &a.evaluation;
        let (unit, f) = match &e.figures {
            UnitFigures::Metres(f) => ("m", f),
            UnitFigures::Radians(f) => ("rad", f),
        };
        let up = f.up.as_ref();
        let down = f.down.as_ref();
        let bi = f.bidirectional.as_ref();
        t.push(vec![
            ("axis", a.axis.as_str().into()),
            ("target", a.target.clone().into()),
            ("unit", unit.into()),
            ("targets", e.targets.into()),
            ("runs_up", e.runs_up.into()),
            ("runs_down", e.runs_down.into()),
            ("systematic_error", bi.map(|b| b.systematic_error).into()),
            ("systematic_error_up", up.map(|u| u.systematic_error).into()),
            (
                "systematic_error_down",
                down.map(|u| u.systematic_error).into(),
            ),
            ("mean_error", bi.map(|b| b.mean_error).into()),
            ("reversal", bi.map(|b| b.reversal).into()),
            ("mean_reversal", bi.map(|b| b.mean_reversal).into()),
            ("repeatability", bi.and_then(|b| b.repeatability).into()),
            ("repeatability_up", up.and_then(|u| u.repeatability).into()),
            (
                "repeatability_down",
                down.and_then(|u| u.repeatability).into(),
            ),
            ("accuracy", bi.and_then(|b| b.accuracy).into()),
            ("accuracy_up", up.and_then(|u| u.accuracy).into()),
            ("accuracy_down", down.and_then(|u| u.accuracy).into()),
            (
                "deviation_sigma_median",
                a.deviation_sigma_median_m
                    .or(a.deviation_sigma_median_rad)
                    .into(),
            ),
            ("per_iso_230_2", e.not_per_iso_230_2.is_empty().into()),
            ("not_per_iso_230_2", e.not_per_iso_230_2.clone().into()),
        ]);
    }
    t
}

/// The verdict of a diagnosis as one stable word (the text report's verdict line, coded).
pub fn verdict(d: &Diagnosis) -> &'static str {
    let confounded = d.candidates.iter().any(|c| c.status == "confounded");
    if d.unexplained {
        "unexplained"
    } else if !d.selected.is_empty() {
        "explained"
    } else if confounded {
        "confounded"
    } else if d.noise_scale.is_some() {
        "noise_scale"
    } else {
        "consistent"
    }
}

/// The diagnosis's verdict row.
pub fn diagnosis(d: &Diagnosis, run: &RunCells) -> Table {
    let mut t = Table::of_run(&DIAGNOSES, run);
    t.push(vec![
        ("verdict", verdict(d).into()),
        ("selected", d.selected.clone().into()),
        ("unexplained", d.unexplained.into()),
        ("noise_scale_k", d.noise_scale.as_ref().map(|s| s.k).into()),
        ("noise_floor_m", d.noise_floor_m.into()),
        ("gap_rms_m", d.gap.rms_m.into()),
        ("gap_heldout_ratio", d.gap.heldout_ratio.into()),
        ("gap_after_rms_m", d.gap_after.rms_m.into()),
        ("gap_after_heldout_ratio", d.gap_after.heldout_ratio.into()),
        ("observations", d.observations.into()),
    ]);
    t
}

#[cfg(test)]
mod tests {
    use super::as_planned;

    #[test]
    fn positions_are_as_planned() {
        assert_eq!(as_planned(0.9999999999999999), 1.0);
        assert_eq!(as_planned(0.1 + 0.2), 0.3);
        assert_eq!(as_planned(-0.30000000000000004), -0.3);
        assert_eq!(as_planned(1.2), 1.2);
        let angle = std::f64::consts::FRAC_PI_6;
        assert_eq!(as_planned(angle), angle, "not a grid value: kept");
        assert_eq!(as_planned(0.0), 0.0);
    }
}
