//! The rotary_tracer report: the tracer network, then the table's axis and step errors.

use std::fmt::Write;

use super::solve::{RotaryResult, RotaryTracerResults};
use crate::method::multilateration::MultilaterationResults;
use crate::method::report::{multilateration_text, um};
use crate::method::KindResults;

impl KindResults for RotaryTracerResults {
    fn report(&self) -> String {
        multilateration_text(&self.multilateration) + &rotary_text(&self.rotary)
    }

    fn tracer_network(&self) -> Option<&MultilaterationResults> {
        Some(&self.multilateration)
    }
}

/// Arcseconds per radian.
const ARCSEC_PER_RAD: f64 = 180.0 * 3600.0 / std::f64::consts::PI;

fn rotary_text(r: &RotaryResult) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "\n  rotary table {} (circle through the table stations):",
        r.table
    );
    let _ = writeln!(
        s,
        "    axis point  [{:.6}, {:.6}, {:.6}] m  σ [{:.2}, {:.2}, {:.2}] µm",
        r.axis_point_m[0],
        r.axis_point_m[1],
        r.axis_point_m[2],
        um(r.axis_point_sigma_m[0]),
        um(r.axis_point_sigma_m[1]),
        um(r.axis_point_sigma_m[2])
    );
    let _ = writeln!(
        s,
        "    axis dir.   [{:.7}, {:.7}, {:.7}]  σ [{:.2}, {:.2}, {:.2}] µrad",
        r.axis_direction[0],
        r.axis_direction[1],
        r.axis_direction[2],
        um(r.axis_direction_sigma[0]),
        um(r.axis_direction_sigma[1]),
        um(r.axis_direction_sigma[2])
    );
    let _ = writeln!(
        s,
        "    radius {:.6} m (σ {:.2} µm), stations off the circle: RMS {:.3} µm",
        r.radius_m,
        um(r.radius_sigma_m),
        um(r.circle_residual_rms_m)
    );
    let _ = writeln!(
        s,
        "    station   commanded [°]   measured [°]   error [\"]    σ [\"]   (from {})",
        r.reference_station
    );
    for step in &r.steps {
        let _ = writeln!(
            s,
            "    {:<8} {:>13.4} {:>14.6} {:>10.3} {:>8.3}",
            step.station,
            step.commanded_rad.to_degrees(),
            step.measured_rad.to_degrees(),
            step.error_rad * ARCSEC_PER_RAD,
            step.sigma_rad * ARCSEC_PER_RAD
        );
    }
    s
}

/// The report's rotary_tracer sections: the table's step-angle errors against angle with ±2σ,
/// its axis, then the network's volumetric error and station layout.
pub fn document(results: &serde_json::Value) -> anyhow::Result<crate::document::KindReport> {
    use crate::document::plots::{panels_svg, Panel, Series};
    use crate::document::{cell, KindReport, Plot, Section, Table};
    use crate::method::report_document::{network_sections, network_summary};
    let r: RotaryTracerResults = crate::document::results_of("rotary_tracer", results)?;
    let t = &r.rotary;
    let mut table = Table::new(
        &format!("Step-angle errors (from station {})", t.reference_station),
        &[
            "station",
            "commanded [°]",
            "approach",
            "measured [°]",
            "error [arcsec]",
            "σ [arcsec]",
        ],
    );
    let mut points = Vec::new();
    let mut band = Vec::new();
    for s in &t.steps {
        table.row(vec![
            s.station.clone(),
            cell(Some(s.commanded_rad.to_degrees()), 4),
            s.approach.map_or_else(String::new, |a| {
                String::from(if a > 0 { "↑" } else { "↓" })
            }),
            cell(Some(s.measured_rad.to_degrees()), 6),
            cell(Some(s.error_rad * ARCSEC_PER_RAD), 3),
            cell(Some(s.sigma_rad * ARCSEC_PER_RAD), 3),
        ]);
        points.push((s.commanded_rad.to_degrees(), s.error_rad * ARCSEC_PER_RAD));
        band.push(2.0 * s.sigma_rad * ARCSEC_PER_RAD);
    }
    let runs = crate::evaluate::deviations::rotary_axis(&results["rotary"])?;
    let curves = &runs.curves;
    let (series, caption) = if curves.up.len() + curves.down.len() <= 1 {
        (
            vec![Series::line("", points).with_band(band)],
            "Measured minus commanded table angle at each station, shaded ±2σ.",
        )
    } else {
        let sigma = runs.target_sigma_rad.clone().unwrap_or_default();
        let mut series = Vec::new();
        let figures = runs.evaluation.figures();
        for (name, direction, means) in [
            ("↑", &curves.up, &figures.up),
            ("↓", &curves.down, &figures.down),
        ] {
            let Some(means) = means else {
                continue;
            };
            let at = |i: usize, v: f64| (curves.targets[i].to_degrees(), v * ARCSEC_PER_RAD);
            let each = direction
                .iter()
                .flat_map(|run| run.iter().enumerate().map(|(i, &v)| at(i, v)))
                .collect();
            let mean = means
                .mean_deviation_i
                .iter()
                .enumerate()
                .map(|(i, &v)| at(i, v))
                .collect();
            let band = sigma.iter().map(|s| 2.0 * s * ARCSEC_PER_RAD).collect();
            series.push(Series::line(&format!("mean {name}"), mean).with_band(band));
            series.push(Series::points(&format!("runs {name}"), each));
        }
        (
            series,
            "Measured minus commanded table angle: every run's station as a point, the mean of \
             each approach direction as a line, shaded ±2σ of one station.",
        )
    };
    let svg = panels_svg(
        &format!("table {}: step-angle error against angle (±2σ)", t.table),
        &[Panel {
            title: "angular positioning error".into(),
            x_label: "commanded angle [°]".into(),
            y_label: "error [arcsec]".into(),
            series,
        }],
        1,
    )?;
    let peak = t
        .steps
        .iter()
        .map(|s| (s.error_rad * ARCSEC_PER_RAD).abs())
        .fold(0.0, f64::max);
    let mut summary = network_summary(&r.multilateration);
    summary.push(("table".into(), t.table.clone()));
    summary.push(("max |step-angle error|".into(), format!("{peak:.3} arcsec")));
    summary.push((
        "axis point (σ)".into(),
        format!(
            "[{:.6}, {:.6}, {:.6}] m ({:.2}, {:.2}, {:.2} µm)",
            t.axis_point_m[0],
            t.axis_point_m[1],
            t.axis_point_m[2],
            um(t.axis_point_sigma_m[0]),
            um(t.axis_point_sigma_m[1]),
            um(t.axis_point_sigma_m[2])
        ),
    ));
    let mut sections = vec![
        Section::new("rotary-steps", "Rotary table: step-angle errors")
            .facts(vec![
                (
                    "axis direction".into(),
                    format!(
                        "[{:.7}, {:.7}, {:.7}]",
                        t.axis_direction[0], t.axis_direction[1], t.axis_direction[2]
                    ),
                ),
                (
                    "radius of the station circle".into(),
                    format!("{:.6} m (σ {:.2} µm)", t.radius_m, um(t.radius_sigma_m)),
                ),
                (
                    "stations off the circle (RMS)".into(),
                    format!("{:.3} µm", um(t.circle_residual_rms_m)),
                ),
            ])
            .plot(Plot {
                id: "step-angle-errors".into(),
                caption: caption.into(),
                svg,
            })
            .table(table),
    ];
    if !t.note.is_empty() {
        sections[0] = sections[0].clone().paragraph(t.note.clone());
    }
    sections.extend(network_sections(&r.multilateration)?);
    Ok(KindReport { summary, sections })
}

/// The uncertainty budget of every step-angle error (k = 2): the solve's σ and the reflector's
/// own uncertainty over the lever of the two stations (docs/uncertainty.md, "Angles"), from the
/// `[uncertainty]` of the run's configuration (the documented defaults without it).
pub fn uncertainty(
    results: &serde_json::Value,
    declared: Option<crate::config::uncertainty::UncertaintyConfig>,
) -> anyhow::Result<crate::document::Section> {
    use crate::evaluate::budget_section::{section, BudgetGroup};
    use crate::evaluate::uncertainty::KindBudgets;
    let r: RotaryTracerResults = crate::document::results_of("rotary_tracer", results)?;
    let all = KindBudgets {
        budgets: super::budget::step_angle_budgets(&r.rotary, &declared.unwrap_or_default()),
        not_declared: Vec::new(),
    };
    let groups = [BudgetGroup {
        label: format!(
            "step-angle error of table {} (over the steps)",
            r.rotary.table
        ),
        budgets: all.budgets.iter().collect(),
    }];
    let mut out = section(
        "rotary-tracer-uncertainty",
        "Expanded uncertainty U (k = 2) of the table's step-angle errors: the solve's σ and the \
         reflector's own uncertainty acting over the lever of the two stations an angle is \
         taken between; a uniform scale (tracer calibration, air index, thermal expansion) \
         changes no angle (GUM; docs/uncertainty.md).",
        &groups,
        &all,
    );
    if declared.is_none() {
        out = out.paragraph(
            "No [uncertainty] in the run's configuration: the documented default uncertainties are used.",
        );
    }
    Ok(out)
}
