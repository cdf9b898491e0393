//! The multilateration report: the tracer network (method::report).

use crate::method::multilateration::MultilaterationResults;
use crate::method::report::multilateration_text;
use crate::method::KindResults;

impl KindResults for MultilaterationResults {
    fn report(&self) -> String {
        multilateration_text(self)
    }

    fn tracer_network(&self) -> Option<&MultilaterationResults> {
        Some(self)
    }
}

/// The report's multilateration sections: the geometric errors (each axis's six error
/// functions with ±2σ bands, the squareness), then the network's volumetric error and station
/// layout.
pub fn document(results: &serde_json::Value) -> anyhow::Result<crate::document::KindReport> {
    use crate::method::report_document::{network_sections, network_summary};
    let r: MultilaterationResults = crate::document::results_of("multilateration", results)?;
    let mut summary = network_summary(&r);
    let mut sections = Vec::new();
    match &r.geometric_errors {
        Some(g) => {
            let (facts, mut own) = geometric_error_sections(g)?;
            summary.extend(facts);
            sections.append(&mut own);
        }
        None => sections.push(
            crate::document::Section::new("geometric-errors", "Geometric errors").paragraph(
                "The plan does not allow the axes' error functions to be separated (no \
                 geometric_errors in the results).",
            ),
        ),
    }
    sections.extend(network_sections(&r)?);
    if !r.notes.is_empty() {
        sections
            .push(crate::document::Section::new("notes", "Notes").preformatted(r.notes.join("\n")));
    }
    Ok(crate::document::KindReport { summary, sections })
}

/// A value of an error function in display units: µm for `m`, arcsec for `rad`.
fn shown(unit: &str, value: f64) -> f64 {
    if unit == "rad" {
        crate::document::arcsec(value)
    } else {
        value * 1e6
    }
}

fn display_unit(unit: &str) -> &'static str {
    if unit == "rad" {
        "arcsec"
    } else {
        "µm"
    }
}

fn numbers(v: &serde_json::Value) -> Vec<Option<f64>> {
    v.as_array()
        .map(|a| a.iter().map(|x| x.as_f64()).collect())
        .unwrap_or_default()
}

/// The `geometric_errors` of the results (as `solve::geometric_errors` writes them): one plot
/// of six panels per axis, a table of the squareness errors, and the summary's maxima.
#[allow(clippy::type_complexity)]
fn geometric_error_sections(
    g: &serde_json::Value,
) -> anyhow::Result<(Vec<(String, String)>, Vec<crate::document::Section>)> {
    use crate::document::plots::{panels_svg, Panel, Series};
    use crate::document::{cell, Plot, Section, Table};
    let axes = g
        .get("axes")
        .and_then(|a| a.as_object())
        .ok_or_else(|| anyhow::anyhow!("results: geometric_errors.axes: expected an object"))?;
    let mut summary = Vec::new();
    let mut section =
        Section::new("geometric-errors", "Geometric errors of the axes").paragraph(format!(
            "Structure {}; each error function with its ±2σ band (shaded). Lines: E_XX…E_ZZ \
             positioning and straightness errors (µm), E_AX…E_CZ angular errors (arcsec).",
            g.get("structure").and_then(|s| s.as_str()).unwrap_or("?")
        ));
    let mut not_identifiable: Vec<String> = Vec::new();
    let mut plots = Vec::new();
    for (axis, a) in axes {
        let positions = numbers(&a["positions_m"]);
        let errors = a.get("errors").and_then(|e| e.as_object()).ok_or_else(|| {
            anyhow::anyhow!("results: geometric_errors.axes.{axis}.errors: expected an object")
        })?;
        let mut panels = Vec::new();
        for (name, f) in errors {
            let unit = f.get("unit").and_then(|u| u.as_str()).unwrap_or("m");
            let values = numbers(&f["values"]);
            let sigma = numbers(&f["sigma"]);
            let mut points = Vec::new();
            let mut band = Vec::new();
            for (k, x) in positions.iter().enumerate() {
                if let (Some(x), Some(Some(v))) = (x, values.get(k)) {
                    points.push((*x, shown(unit, *v)));
                    band.push(2.0 * shown(unit, sigma.get(k).copied().flatten().unwrap_or(0.0)));
                }
            }
            let identifiable = f
                .get("identifiable")
                .and_then(|i| i.as_bool())
                .unwrap_or(true);
            // A function the plan cannot identify is named, not drawn: its zeros are no
            // measurement.
            if !identifiable {
                if !not_identifiable.contains(name) {
                    not_identifiable.push(name.clone());
                }
                continue;
            }
            let peak = points.iter().map(|p| p.1.abs()).fold(0.0, f64::max);
            summary.push((
                format!("max |{name}|"),
                format!("{peak:.2} {}", display_unit(unit)),
            ));
            panels.push(Panel {
                title: name.clone(),
                x_label: format!("{axis} position [m]"),
                y_label: format!("{name} [{}]", display_unit(unit)),
                series: vec![Series::line("", points).with_band(band)],
            });
        }
        if panels.is_empty() {
            continue;
        }
        let svg = panels_svg(&format!("{axis} axis: error functions (±2σ)"), &panels, 3)?;
        plots.push(Plot {
            id: format!("errors-{axis}"),
            caption: format!("The {} error functions of the {axis} axis.", panels.len()),
            svg,
        });
    }
    if !not_identifiable.is_empty() {
        let line = not_identifiable_line(&not_identifiable);
        summary.push(("not identifiable".into(), not_identifiable.join(", ")));
        section = section.paragraph(line);
    }
    for plot in plots {
        section = section.plot(plot);
    }
    let mut squareness = Table::new(
        "Squareness errors",
        &["error", "value [µrad]", "σ [µrad]", "value [arcsec]"],
    );
    if let Some(sq) = g.get("squareness").and_then(|s| s.as_object()) {
        for (name, s) in sq {
            let value = s.get("value_rad").and_then(|v| v.as_f64());
            let sigma = s.get("sigma_rad").and_then(|v| v.as_f64());
            squareness.row(vec![
                name.clone(),
                cell(value.map(|v| v * 1e6), 2),
                cell(sigma.map(|v| v * 1e6), 2),
                cell(value.map(crate::document::arcsec), 2),
            ]);
            summary.push((
                format!("squareness {name}"),
                match (value, sigma) {
                    (Some(v), Some(s)) => format!("{:.2} ± {:.2} µrad", v * 1e6, s * 1e6),
                    (Some(v), None) => format!("{:.2} µrad", v * 1e6),
                    _ => "not identifiable".to_string(),
                },
            ));
        }
    }
    let mut sections = vec![section];
    if !squareness.rows.is_empty() {
        sections.push(Section::new("squareness", "Squareness").table(squareness));
    }
    Ok((summary, sections))
}

/// The one line naming the error functions a plan cannot identify.
pub fn not_identifiable_line(names: &[String]) -> String {
    format!(
        "not identifiable from this plan: {} — see docs/kinematics.md",
        names.join(", ")
    )
}
