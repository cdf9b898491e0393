//! The tracer network's report sections (both tracer kinds): station layout, the points'
//! volumetric error (RMS, max, arrow maps in two projections) and the network's summary.

use super::multilateration::MultilaterationResults;
use crate::document::plots::{arrows_svg, panels_svg, Arrow, Panel, Series, Style};
use crate::document::{cell, um, Plot, Section, Table};

/// The few numbers of the network solve.
pub fn network_summary(r: &MultilaterationResults) -> Vec<(String, String)> {
    let (rms, max) = volumetric(r);
    vec![
        (
            "stations, points".to_string(),
            format!("{}, {}", r.stations.len(), r.points.len()),
        ),
        (
            "length residual RMS".to_string(),
            format!("{:.3} µm", um(r.residual_rms_m)),
        ),
        (
            "volumetric error RMS / max".to_string(),
            format!("{:.2} µm / {:.2} µm", um(rms), um(max)),
        ),
        ("solve converged".to_string(), r.converged.to_string()),
    ]
}

/// RMS and maximum of the points' 3-D error lengths |actual − nominal|, metres.
pub fn volumetric(r: &MultilaterationResults) -> (f64, f64) {
    let lengths: Vec<f64> = r
        .points
        .iter()
        .map(|p| p.error_m.iter().map(|e| e * e).sum::<f64>().sqrt())
        .collect();
    if lengths.is_empty() {
        return (f64::NAN, f64::NAN);
    }
    let rms = (lengths.iter().map(|l| l * l).sum::<f64>() / lengths.len() as f64).sqrt();
    (rms, lengths.iter().copied().fold(0.0, f64::max))
}

/// Station layout and volumetric error sections.
pub fn network_sections(r: &MultilaterationResults) -> anyhow::Result<Vec<Section>> {
    Ok(vec![volumetric_section(r)?, layout_section(r)?])
}

fn volumetric_section(r: &MultilaterationResults) -> anyhow::Result<Section> {
    let (rms, max) = volumetric(r);
    // Arrows drawn at a scale that makes the largest one a tenth of the measured volume.
    let span = |k: usize| {
        let (lo, hi) = r
            .points
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| {
                (lo.min(p.nominal_m[k]), hi.max(p.nominal_m[k]))
            });
        (hi - lo).max(0.0)
    };
    let extent = span(0).max(span(1)).max(span(2));
    let scale = if max > 0.0 && extent > 0.0 {
        0.1 * extent / max
    } else {
        1.0
    };
    let projection = |a: usize, b: usize| -> Vec<Arrow> {
        r.points
            .iter()
            .map(|p| Arrow {
                at: (p.nominal_m[a], p.nominal_m[b]),
                error: (p.error_m[a], p.error_m[b]),
            })
            .collect()
    };
    let svg = arrows_svg(
        &format!(
            "volumetric error at the measured points (arrows × {:.0}: 1 µm drawn as {:.2} mm)",
            scale,
            scale * 1e-6 * 1e3
        ),
        &[
            (
                "top view (x–y)".into(),
                "x [m]".into(),
                "y [m]".into(),
                projection(0, 1),
            ),
            (
                "front view (x–z)".into(),
                "x [m]".into(),
                "z [m]".into(),
                projection(0, 2),
            ),
        ],
        scale,
    )?;
    Ok(Section::new("volumetric", "Volumetric error")
        .facts(vec![
            ("points".into(), r.points.len().to_string()),
            ("RMS of |error|".into(), format!("{:.2} µm", um(rms))),
            ("max |error|".into(), format!("{:.2} µm", um(max))),
        ])
        .plot(Plot {
            id: "volumetric-arrows".into(),
            caption: "Error of each measured point (actual − nominal, gauge as in the solve) as \
                      arrows from its nominal position, in two projections."
                .into(),
            svg,
        }))
}

fn layout_section(r: &MultilaterationResults) -> anyhow::Result<Section> {
    let mut table = Table::new(
        "Tracer stations",
        &[
            "station",
            "x [m]",
            "y [m]",
            "z [m]",
            "σ (x, y, z) [µm]",
            "lengths",
            "residual RMS [µm]",
        ],
    );
    for s in &r.stations {
        table.row(vec![
            s.id.clone(),
            cell(Some(s.position_m[0]), 4),
            cell(Some(s.position_m[1]), 4),
            cell(Some(s.position_m[2]), 4),
            format!(
                "{:.2}, {:.2}, {:.2}",
                um(s.sigma_m[0]),
                um(s.sigma_m[1]),
                um(s.sigma_m[2])
            ),
            s.observations.to_string(),
            cell(Some(um(s.residual_rms_m)), 3),
        ]);
    }
    let view = |a: usize, b: usize, title: &str, x: &str, y: &str| Panel {
        title: title.into(),
        x_label: x.into(),
        y_label: y.into(),
        series: vec![
            Series::points(
                "points",
                r.points
                    .iter()
                    .map(|p| (p.nominal_m[a], p.nominal_m[b]))
                    .collect(),
            )
            .with_style(Style::Points),
            Series::points(
                "stations",
                r.stations
                    .iter()
                    .map(|s| (s.position_m[a], s.position_m[b]))
                    .collect(),
            )
            .with_style(Style::Points),
        ],
    };
    let svg = panels_svg(
        "station layout",
        &[
            view(0, 1, "top view (x–y)", "x [m]", "y [m]"),
            view(0, 2, "front view (x–z)", "x [m]", "z [m]"),
        ],
        2,
    )?;
    Ok(Section::new("stations", "Station layout")
        .table(table)
        .plot(Plot {
            id: "station-layout".into(),
            caption: "Tracer stations and measured points, machine frame.".into(),
            svg,
        }))
}
