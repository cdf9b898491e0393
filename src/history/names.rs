//! The names of a machine's parameters as people read them, one naming for the history
//! (`compare`, `trend`, the daemon) and the fleet export: `EC0Y`, `ECY@y=1.200`,
//! `EXC@c=0.5236`, `hinge.3.base.x`. A parameter the history finds by the shape of the results
//! (its JSON path) is named from that path; one the results do not describe in a known shape
//! keeps its path as its name.

use serde_json::Value;

const XYZ: [&str; 3] = ["x", "y", "z"];

/// An error function at a position along its axis: `<function>@<axis>=<position>`, metres
/// with 3 decimals (`ECY@y=1.200`), radians with 4 (`EXC@c=0.5236`).
pub fn at_position(function: &str, axis: &str, position: f64, unit: &str) -> String {
    let text = if unit == "rad" {
        format!("{position:.4}")
    } else {
        format!("{position:.3}")
    };
    // No `-0.000`.
    let text = if text.bytes().all(|b| matches!(b, b'-' | b'0' | b'.')) {
        text.trim_start_matches('-').to_owned()
    } else {
        text
    };
    format!("{function}@{axis}={text}")
}

/// A hexapod hinge coordinate: `hinge.<leg>.<base|platform>.<x|y|z>`.
pub fn hinge(leg: u64, side: &str, k: usize) -> String {
    format!("hinge.{leg}.{side}.{}", XYZ.get(k).unwrap_or(&"?"))
}

/// A rotary table axis coordinate: `rotary_axis.<table>.<key>.<x|y|z>`.
pub fn rotary_axis(table: &str, key: &str, k: usize) -> String {
    format!("rotary_axis.{table}.{key}.{}", XYZ.get(k).unwrap_or(&"?"))
}

/// The rotary table's id in the results (`rotary.table`, or a sphere run's `table`).
fn table_of(block: &Value) -> &str {
    block["table"].as_str().unwrap_or("table")
}

/// `name[inner]rest` → (`inner`, `rest`) when `text` starts with `name[`.
fn bracket<'a>(text: &'a str, name: &str) -> Option<(&'a str, &'a str)> {
    let rest = text.strip_prefix(name)?.strip_prefix('[')?;
    let (inner, rest) = rest.split_once(']')?;
    Some((inner, rest))
}

/// The name of the parameter at JSON `path` of `results`, at position `x` (its unit
/// `x_unit`) along its curve; the path itself when it is of no known shape.
pub fn of_path(results: &Value, path: &str, x: Option<f64>, x_unit: &str) -> String {
    named(results, path, x, x_unit).unwrap_or_else(|| path.to_owned())
}

fn named(results: &Value, path: &str, x: Option<f64>, x_unit: &str) -> Option<String> {
    if let Some(rest) = path.strip_prefix("geometric_errors.axes.") {
        // <axis>.errors.<function>.values[i]
        let (axis, rest) = rest.split_once(".errors.")?;
        let (function, _) = rest.split_once(".values[")?;
        return Some(at_position(function, axis, x?, "m"));
    }
    if let Some(rest) = path.strip_prefix("geometric_errors.squareness.") {
        return rest.strip_suffix(".value_rad").map(str::to_owned);
    }
    if let Some((name, ".value")) = bracket(path, "location") {
        return Some(name.to_owned());
    }
    if let Some((name, ".value")) = bracket(path, "parameters") {
        return Some(name.to_owned());
    }
    if let Some((i, rest)) = bracket(path, "hinges") {
        let leg = results["hinges"].get(i.parse::<usize>().ok()?)?["leg"].as_u64()?;
        let (side, k) = rest.strip_prefix('.')?.split_once("_m[")?;
        let k: usize = k.strip_suffix(']')?.parse().ok()?;
        return Some(hinge(leg, side, k));
    }
    if let Some((_, rest)) = bracket(path, "motion") {
        // motion[i].errors[k]: the k-th of `motion_names` at angle x.
        let Some((k, "")) = bracket(rest.strip_prefix('.')?, "errors") else {
            return None;
        };
        let function = results["motion_names"]
            .get(k.parse::<usize>().ok()?)?
            .as_str()?;
        return Some(at_position(function, table_of(results), x?, x_unit));
    }
    if let Some(rest) = path.strip_prefix("rotary.") {
        let table = table_of(&results["rotary"]);
        if let Some((_, ".error_rad")) = bracket(rest, "steps") {
            return Some(at_position("step_error", table, x?, "rad"));
        }
        for key in ["axis_point_m", "axis_direction"] {
            if let Some((k, "")) = bracket(rest, key) {
                return Some(rotary_axis(table, key, k.parse().ok()?));
            }
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn positions_are_named_as_planned() {
        assert_eq!(at_position("ECY", "y", 1.2, "m"), "ECY@y=1.200");
        assert_eq!(
            at_position("EXX", "x", 0.9999999999999999, "m"),
            "EXX@x=1.000"
        );
        assert_eq!(at_position("EXX", "x", -1e-12, "m"), "EXX@x=0.000");
        assert_eq!(
            at_position("EXC", "c", std::f64::consts::FRAC_PI_6, "rad"),
            "EXC@c=0.5236"
        );
    }

    #[test]
    fn paths_of_every_shape_are_named() {
        let results = serde_json::json!({
            "hinges": [{"leg": 3}], "table": "c", "motion_names": ["EXC", "EYC"],
            "rotary": {"table": "b"},
        });
        let name = |path: &str, x: Option<f64>, unit: &str| of_path(&results, path, x, unit);
        assert_eq!(
            name(
                "geometric_errors.axes.y.errors.ECY.values[2]",
                Some(1.2),
                "m"
            ),
            "ECY@y=1.200"
        );
        assert_eq!(
            name("geometric_errors.squareness.EB0Z.value_rad", None, ""),
            "EB0Z"
        );
        assert_eq!(name("location[EXOC].value", None, ""), "EXOC");
        assert_eq!(name("parameters[probe_x_m].value", None, ""), "probe_x_m");
        assert_eq!(name("hinges[0].base_m[1]", None, ""), "hinge.3.base.y");
        assert_eq!(
            name("motion[4].errors[1]", Some(0.5), "rad"),
            "EYC@c=0.5000"
        );
        assert_eq!(
            name("rotary.steps[c02].error_rad", Some(0.5), "rad"),
            "step_error@b=0.5000"
        );
        assert_eq!(
            name("rotary.axis_direction[2]", None, ""),
            "rotary_axis.b.axis_direction.z"
        );
        assert_eq!(name("something.else[1]", None, ""), "something.else[1]");
    }
}
