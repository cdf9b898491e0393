//! The parameters of a run that its history follows: every estimate of a results document that
//! carries a standard uncertainty, found by the shape of the JSON (a value beside its σ), so
//! every plan kind's parameters are found without the history naming a kind.
//!
//! Pairing: beside `sigma<S>` the value is `value<S>`, `values<S>`, `error<S>` or `errors<S>`;
//! beside `<name>_sigma<S>` it is `<name><S>`. Arrays pair element by element. Left out: the
//! set-up of the measurement rather than the machine (tracer stations, the measured points and
//! sphere centres, the tracer's radius on a table), diagnostics (validation, solver traces),
//! and σ that are null (not identifiable) or 0 (a reference fixed by definition).

use serde::Serialize;

/// Blocks of a results document that describe the set-up or the solver, not the machine.
const SET_UP_OR_SOLVER: &[&str] = &[
    "stations",
    "points",
    "spheres",
    "validation",
    "misfit",
    "extraction",
    "robust",
    "effects",
    "lm",
    "ga",
    "two_stage",
    "harmonics",
    "rigid_motion",
    "elastic_net",
    "radius_m",
    "radius_sigma_m",
];

/// Keys of an object in an array that give the object's position along a curve.
const ABSCISSA_KEYS: &[(&str, &str)] = &[
    ("commanded_rad", "rad"),
    ("position_m", "m"),
    ("angle_rad", "rad"),
];

/// Keys that name an object in an array (used in its id instead of its index).
const NAME_KEYS: &[&str] = &["name", "id", "station"];

/// One estimate with its standard uncertainty.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Parameter {
    /// Stable id: its name as people read it and the fleet export names it (`names`:
    /// `EC0Y`, `ECY@y=1.200`), else its JSON path.
    pub id: String,
    /// The JSON path of the value, array elements by name where they have one.
    pub path: String,
    /// The curve it belongs to (its id with the curve's index as `[*]`); a lone figure is
    /// its own curve.
    pub curve: String,
    /// Its position along the curve (an axis position, a commanded angle, an index).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub x: Option<f64>,
    /// Unit of `x`: "m", "rad" or "" (an index).
    #[serde(skip_serializing_if = "String::is_empty")]
    pub x_unit: String,
    /// "m", "rad" or "" when the results do not say.
    pub unit: String,
    pub value: f64,
    /// Standard uncertainty, scaled by √(χ²/dof) when the results flag a misfit.
    pub sigma: f64,
}

/// What a results document gives: its parameters and how many estimates were left out.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct Parameters {
    pub parameters: Vec<Parameter>,
    /// Estimates whose σ is null or 0 (not identifiable, or a reference).
    pub without_sigma: usize,
    /// The σ scale applied (results with `misfit`), 1 otherwise.
    pub sigma_scale: f64,
}

impl Parameters {
    pub fn get(&self, id: &str) -> Option<&Parameter> {
        self.parameters.iter().find(|p| p.id == id)
    }

    pub fn at_path(&self, path: &str) -> Option<&Parameter> {
        self.parameters.iter().find(|p| p.path == path)
    }
}

/// Every parameter of a results document, in document order.
pub fn parameters(results: &serde_json::Value) -> Parameters {
    let sigma_scale = results
        .pointer("/misfit/sigma_scale")
        .and_then(|s| s.as_f64())
        .filter(|s| s.is_finite() && *s > 1.0)
        .unwrap_or(1.0);
    let mut out = Parameters {
        sigma_scale,
        ..Default::default()
    };
    let mut walker = Walker {
        results,
        out: &mut out,
        sigma_scale,
        positions: Vec::new(),
    };
    walker.object_or_array(results, &Path::default(), 0);
    out
}

/// A JSON path being walked, as id text and with the innermost array of objects remembered.
#[derive(Debug, Clone, Default)]
struct Path {
    text: String,
    /// The text with the innermost array-of-objects index as `[*]`, and that object's
    /// position along its curve.
    curve: Option<(String, Option<(f64, &'static str)>)>,
}

impl Path {
    fn key(&self, key: &str) -> Path {
        let join = |base: &str| {
            if base.is_empty() {
                key.to_owned()
            } else {
                format!("{base}.{key}")
            }
        };
        Path {
            text: join(&self.text),
            curve: self.curve.as_ref().map(|(c, x)| (join(c), *x)),
        }
    }

    fn index(&self, label: &str) -> Path {
        Path {
            text: format!("{}[{label}]", self.text),
            curve: self
                .curve
                .as_ref()
                .map(|(c, x)| (format!("{c}[{label}]"), *x)),
        }
    }

    /// The path into element `i` of an array of objects: by name when it has one (then its
    /// own curve), else by index along a curve whose abscissa the object gives.
    fn element(&self, i: usize, item: &serde_json::Map<String, serde_json::Value>) -> Path {
        let name = NAME_KEYS
            .iter()
            .find_map(|k| item.get(*k).and_then(|v| v.as_str()));
        let x = ABSCISSA_KEYS
            .iter()
            .find_map(|(k, unit)| item.get(*k).and_then(|v| v.as_f64()).map(|x| (x, *unit)));
        let text = match name {
            Some(name) => format!("{}[{name}]", self.text),
            None => format!("{}[{i}]", self.text),
        };
        // Named objects without a position (a named figure) are each their own curve.
        let curve = match (name, x) {
            (Some(_), None) => None,
            (_, x) => Some((
                format!("{}[*]", self.text),
                Some(x.unwrap_or((i as f64, ""))),
            )),
        };
        Path { text, curve }
    }
}

struct Walker<'a> {
    results: &'a serde_json::Value,
    out: &'a mut Parameters,
    sigma_scale: f64,
    /// `positions_m` of the enclosing objects, innermost last (an axis's grid positions).
    positions: Vec<Vec<f64>>,
}

fn is_sigma_key(key: &str) -> bool {
    key.starts_with("sigma") || key.contains("_sigma")
}

/// The value keys that may stand beside the σ key `key`, most likely first.
fn value_keys(key: &str) -> Vec<String> {
    if let Some(suffix) = key.strip_prefix("sigma") {
        return ["value", "values", "error", "errors"]
            .iter()
            .map(|v| format!("{v}{suffix}"))
            .collect();
    }
    match key.split_once("_sigma") {
        Some((name, suffix)) => vec![format!("{name}{suffix}")],
        None => Vec::new(),
    }
}

fn unit_of(key: &str, object: &serde_json::Map<String, serde_json::Value>) -> String {
    if let Some(unit) = object.get("unit").and_then(|u| u.as_str()) {
        return unit.to_owned();
    }
    if key.ends_with("_m") {
        "m".into()
    } else if key.ends_with("_rad") {
        "rad".into()
    } else {
        String::new()
    }
}

impl Walker<'_> {
    fn object_or_array(&mut self, value: &serde_json::Value, path: &Path, depth: usize) {
        match value {
            serde_json::Value::Object(fields) => self.object(fields, path, depth),
            serde_json::Value::Array(items) => {
                for (i, item) in items.iter().enumerate() {
                    match item {
                        serde_json::Value::Object(fields) => {
                            self.object(fields, &path.element(i, fields), depth + 1)
                        }
                        other => self.object_or_array(other, &path.index(&i.to_string()), depth),
                    }
                }
            }
            _ => {}
        }
    }

    fn object(
        &mut self,
        fields: &serde_json::Map<String, serde_json::Value>,
        path: &Path,
        depth: usize,
    ) {
        let positions = fields.get("positions_m").and_then(|p| {
            p.as_array()
                .map(|a| a.iter().filter_map(|v| v.as_f64()).collect::<Vec<_>>())
        });
        if let Some(p) = &positions {
            self.positions.push(p.clone());
        }
        let mut paired: Vec<&str> = Vec::new();
        for (key, sigma) in fields {
            if !is_sigma_key(key) || SET_UP_OR_SOLVER.contains(&key.as_str()) {
                continue;
            }
            let Some((value_key, value)) = value_keys(key)
                .into_iter()
                .find_map(|k| fields.get(&k).map(|v| (k, v)))
            else {
                continue;
            };
            let unit = unit_of(&value_key, fields);
            self.pair(value, sigma, &path.key(&value_key), &unit, false);
            paired.push(key.as_str());
            paired.push(
                fields
                    .get_key_value(&value_key)
                    .map_or("", |(k, _)| k.as_str()),
            );
        }
        for (key, item) in fields {
            if paired.contains(&key.as_str())
                || (SET_UP_OR_SOLVER.contains(&key.as_str()))
                || key.contains("covariance")
            {
                continue;
            }
            if item.is_object() || item.is_array() {
                self.object_or_array(item, &path.key(key), depth + 1);
            }
        }
        if positions.is_some() {
            self.positions.pop();
        }
    }

    /// A value and its σ: numbers, or arrays of them element by element.
    fn pair(
        &mut self,
        value: &serde_json::Value,
        sigma: &serde_json::Value,
        path: &Path,
        unit: &str,
        inner: bool,
    ) {
        match (value, sigma) {
            (serde_json::Value::Array(values), serde_json::Value::Array(sigmas))
                if values.len() == sigmas.len() =>
            {
                // The first level of an array along an axis's grid positions is that curve.
                let along_axis = !inner
                    && self
                        .positions
                        .last()
                        .is_some_and(|p| p.len() == values.len());
                for (i, (v, s)) in values.iter().zip(sigmas).enumerate() {
                    if along_axis {
                        let x = self.positions.last().map(|p| p[i]);
                        let element = Path {
                            text: format!("{}[{i}]", path.text),
                            curve: Some((path.text.clone(), x.map(|x| (x, "m")))),
                        };
                        self.pair(v, s, &element, unit, true);
                    } else {
                        self.pair(v, s, &path.index(&i.to_string()), unit, true);
                    }
                }
            }
            (value, sigma) if value.is_number() || value.is_null() => {
                let (Some(v), Some(s)) = (value.as_f64(), sigma.as_f64()) else {
                    self.out.without_sigma += 1;
                    return;
                };
                if !(s.is_finite() && s > 0.0 && v.is_finite()) {
                    self.out.without_sigma += 1;
                    return;
                }
                let (curve, x) = match &path.curve {
                    Some((curve, x)) => (curve.clone(), *x),
                    None => (path.text.clone(), None),
                };
                let x_unit = x.map(|(_, u)| u.to_owned()).unwrap_or_default();
                self.out.parameters.push(Parameter {
                    id: super::names::of_path(self.results, &path.text, x.map(|(x, _)| x), &x_unit),
                    path: path.text.clone(),
                    curve,
                    x: x.map(|(x, _)| x),
                    x_unit,
                    unit: unit.to_owned(),
                    value: v,
                    sigma: s * self.sigma_scale,
                });
            }
            _ => {}
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finds_error_functions_squareness_and_named_figures() {
        let results = serde_json::json!({
            "format": "geocal-results/1", "kind": "k",
            "stations": [{"id": "s1", "position_m": [1, 2, 3], "sigma_m": [1e-6, 1e-6, 1e-6]}],
            "geometric_errors": {
                "axes": {"x": {"positions_m": [0.1, 0.5, 0.9], "errors": {
                    "EXX": {"unit": "m", "values": [0.0, 1e-6, null], "sigma": [0.0, 2e-7, null]}}}},
                "squareness": {"EB0Z": {"value_rad": 3e-6, "sigma_rad": 1e-6}}
            },
            "location": [{"name": "EXOC", "value": 1e-5, "sigma": 1e-6}],
            "rotary": {"steps": [
                {"station": "c01", "commanded_rad": 0.0, "error_rad": 0.0, "sigma_rad": 0.0},
                {"station": "c02", "commanded_rad": 0.5, "error_rad": 2e-6, "sigma_rad": 1e-6}]},
            "hinges": [{"leg": 0, "base_m": [1.0, 2.0, 3.0], "base_sigma_m": [1e-5, 1e-5, 1e-5]}],
        });
        let found = parameters(&results);
        let mut paths: Vec<&str> = found.parameters.iter().map(|p| p.path.as_str()).collect();
        paths.sort();
        assert_eq!(
            paths,
            [
                "geometric_errors.axes.x.errors.EXX.values[1]",
                "geometric_errors.squareness.EB0Z.value_rad",
                "hinges[0].base_m[0]",
                "hinges[0].base_m[1]",
                "hinges[0].base_m[2]",
                "location[EXOC].value",
                "rotary.steps[c02].error_rad",
            ]
        );
        let exx = found.get("EXX@x=0.500").expect("EXX");
        assert_eq!(exx.curve, "geometric_errors.axes.x.errors.EXX.values");
        assert_eq!((exx.x, exx.unit.as_str()), (Some(0.5), "m"));
        let step = found.get("step_error@table=0.5000").expect("step");
        assert_eq!(step.curve, "rotary.steps[*].error_rad");
        assert_eq!((step.x, step.x_unit.as_str()), (Some(0.5), "rad"));
        assert_eq!(
            found.get("hinge.0.base.y").map(|p| p.curve.as_str()),
            Some("hinges[*].base_m[1]")
        );
        // EXX at 0.1 (σ 0), at 0.9 (null) and the reference step are not estimates.
        assert_eq!(found.without_sigma, 3);
    }

    #[test]
    fn a_misfit_scales_the_sigma() {
        let results = serde_json::json!({
            "misfit": {"sigma_scale": 2.0},
            "a": {"value_m": 1.0, "sigma_m": 0.5},
        });
        let found = parameters(&results);
        assert_eq!(found.parameters[0].sigma, 1.0);
        assert_eq!(
            found.parameters[0].id, "a.value_m",
            "no known shape: its path"
        );
    }
}
