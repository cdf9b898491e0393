//! The report's figures as SVG (plotters' SVG backend: text as `<text>`, no font files):
//! panels of curves with optional ±kσ bands, and arrow maps of error vectors.

use anyhow::Context;
use plotters::coord::Shift;
use plotters::prelude::*;

const PANEL_WIDTH_PX: u32 = 460;
const PANEL_HEIGHT_PX: u32 = 260;
const TITLE_HEIGHT_PX: u32 = 34;
const COLOURS: [RGBColor; 6] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(148, 103, 189),
    RGBColor(255, 127, 14),
    RGBColor(23, 190, 207),
];

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Style {
    Line,
    Points,
    LinePoints,
}

/// One curve: (x, y) points in display units, and optionally the half-width of a band around
/// it at each point (e.g. 2σ), drawn shaded.
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    pub name: String,
    pub points: Vec<(f64, f64)>,
    pub band: Option<Vec<f64>>,
    pub style: Style,
}

impl Series {
    pub fn line(name: &str, points: Vec<(f64, f64)>) -> Series {
        Series {
            name: name.to_string(),
            points,
            band: None,
            style: Style::LinePoints,
        }
    }

    pub fn points(name: &str, points: Vec<(f64, f64)>) -> Series {
        Series {
            name: name.to_string(),
            points,
            band: None,
            style: Style::Points,
        }
    }

    pub fn with_band(mut self, half_width: Vec<f64>) -> Series {
        self.band = Some(half_width);
        self
    }

    pub fn with_style(mut self, style: Style) -> Series {
        self.style = style;
        self
    }

    fn finite(&self) -> impl Iterator<Item = (usize, (f64, f64))> + '_ {
        self.points
            .iter()
            .copied()
            .enumerate()
            .filter(|(_, (x, y))| x.is_finite() && y.is_finite())
    }
}

/// One panel: axes, labels and its series.
#[derive(Debug, Clone, PartialEq)]
pub struct Panel {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub series: Vec<Series>,
}

/// Panels side by side, `columns` to a row, under one title. Fails when no panel has data.
pub fn panels_svg(title: &str, panels: &[Panel], columns: usize) -> anyhow::Result<String> {
    let columns = columns.clamp(1, panels.len().max(1));
    let rows = panels.len().div_ceil(columns);
    if panels
        .iter()
        .all(|p| p.series.iter().all(|s| s.finite().next().is_none()))
    {
        anyhow::bail!("{title}: no data to plot");
    }
    let size = (
        PANEL_WIDTH_PX * columns as u32,
        TITLE_HEIGHT_PX + PANEL_HEIGHT_PX * rows as u32,
    );
    let mut document = String::new();
    {
        let root = SVGBackend::with_string(&mut document, size).into_drawing_area();
        root.fill(&WHITE).map_err(drawing)?;
        let body = root.titled(title, ("sans-serif", 16)).map_err(drawing)?;
        for (area, panel) in body.split_evenly((rows, columns)).iter().zip(panels) {
            draw_panel(area, panel).with_context(|| format!("{title}: {}", panel.title))?;
        }
        root.present().map_err(drawing)?;
    }
    Ok(document)
}

/// The range of values, padded, never empty.
fn range(values: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) = values
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
            (lo.min(v), hi.max(v))
        });
    if lo > hi {
        return (-1.0, 1.0);
    }
    let pad = 0.06 * (hi - lo);
    if pad > 0.0 {
        (lo - pad, hi + pad)
    } else {
        let w = (lo.abs() * 0.1).max(1e-3);
        (lo - w, hi + w)
    }
}

fn draw_panel(area: &DrawingArea<SVGBackend, Shift>, panel: &Panel) -> anyhow::Result<()> {
    let xs = panel
        .series
        .iter()
        .flat_map(|s| s.finite().map(|(_, p)| p.0).collect::<Vec<_>>());
    let (x_min, x_max) = range(xs);
    let ys = panel.series.iter().flat_map(|s| {
        s.finite()
            .flat_map(|(i, (_, y))| {
                let w = band_at(s, i);
                [y - w, y + w]
            })
            .collect::<Vec<_>>()
    });
    let (y_min, y_max) = range(ys);
    let mut chart = ChartBuilder::on(area)
        .margin(6)
        .caption(&panel.title, ("sans-serif", 13))
        .x_label_area_size(34)
        .y_label_area_size(52)
        .build_cartesian_2d(x_min..x_max, y_min..y_max)
        .map_err(drawing)?;
    chart
        .configure_mesh()
        .x_desc(panel.x_label.as_str())
        .y_desc(panel.y_label.as_str())
        .x_labels(6)
        .y_labels(6)
        .x_label_formatter(&|v| short(*v))
        .y_label_formatter(&|v| short(*v))
        .light_line_style(WHITE)
        .label_style(("sans-serif", 11))
        .draw()
        .map_err(drawing)?;
    let mut labelled = false;
    for (n, series) in panel.series.iter().enumerate() {
        let colour = COLOURS[n % COLOURS.len()];
        let finite: Vec<(usize, (f64, f64))> = series.finite().collect();
        if series.band.is_some() && finite.len() >= 2 {
            let upper = finite
                .iter()
                .map(|&(i, (x, y))| (x, y + band_at(series, i)));
            let lower = finite
                .iter()
                .rev()
                .map(|&(i, (x, y))| (x, y - band_at(series, i)));
            let outline: Vec<(f64, f64)> = upper.chain(lower).collect();
            chart
                .draw_series(std::iter::once(Polygon::new(outline, colour.mix(0.18))))
                .map_err(drawing)?;
        }
        let xy = finite.iter().map(|&(_, p)| p);
        let drawn = match series.style {
            Style::Line | Style::LinePoints => chart
                .draw_series(LineSeries::new(xy.clone(), colour.stroke_width(2)))
                .map_err(drawing)?,
            Style::Points => chart
                .draw_series(xy.clone().map(|p| Circle::new(p, 3, colour.filled())))
                .map_err(drawing)?,
        };
        if !series.name.is_empty() {
            labelled = true;
            drawn.label(series.name.as_str()).legend(move |(x, y)| {
                Rectangle::new([(x, y - 3), (x + 12, y + 3)], colour.filled())
            });
        }
        if series.style == Style::LinePoints {
            chart
                .draw_series(xy.map(|p| Circle::new(p, 2, colour.filled())))
                .map_err(drawing)?;
        }
        if series.band.is_some() && finite.len() == 1 {
            let (i, (x, y)) = finite[0];
            let w = band_at(series, i);
            chart
                .draw_series(std::iter::once(PathElement::new(
                    vec![(x, y - w), (x, y + w)],
                    colour.stroke_width(1),
                )))
                .map_err(drawing)?;
        }
    }
    if labelled && panel.series.len() > 1 {
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperRight)
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK.mix(0.3))
            .label_font(("sans-serif", 11))
            .draw()
            .map_err(drawing)?;
    }
    Ok(())
}

fn band_at(series: &Series, i: usize) -> f64 {
    series
        .band
        .as_ref()
        .and_then(|b| b.get(i))
        .copied()
        .filter(|w| w.is_finite())
        .unwrap_or(0.0)
}

/// An error vector at a position: the arrow from `at` to `at + scale · error`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Arrow {
    pub at: (f64, f64),
    pub error: (f64, f64),
}

/// Arrow maps (one panel per projection) with the same `scale` (display length per unit of
/// error), stated in the title.
pub fn arrows_svg(
    title: &str,
    projections: &[(String, String, String, Vec<Arrow>)],
    scale: f64,
) -> anyhow::Result<String> {
    if projections.iter().all(|p| p.3.is_empty()) {
        anyhow::bail!("{title}: no arrows to draw");
    }
    let columns = projections.len().max(1);
    let size = (
        PANEL_WIDTH_PX * columns as u32,
        TITLE_HEIGHT_PX + 2 * PANEL_HEIGHT_PX,
    );
    let mut document = String::new();
    {
        let root = SVGBackend::with_string(&mut document, size).into_drawing_area();
        root.fill(&WHITE).map_err(drawing)?;
        let body = root.titled(title, ("sans-serif", 16)).map_err(drawing)?;
        for (area, (name, x_label, y_label, arrows)) in
            body.split_evenly((1, columns)).iter().zip(projections)
        {
            let ends = || {
                arrows.iter().flat_map(|a| {
                    [
                        a.at,
                        (a.at.0 + scale * a.error.0, a.at.1 + scale * a.error.1),
                    ]
                })
            };
            let (x_min, x_max) = range(ends().map(|p| p.0));
            let (y_min, y_max) = range(ends().map(|p| p.1));
            let mut chart = ChartBuilder::on(area)
                .margin(8)
                .caption(name, ("sans-serif", 13))
                .x_label_area_size(34)
                .y_label_area_size(52)
                .build_cartesian_2d(x_min..x_max, y_min..y_max)
                .map_err(drawing)?;
            chart
                .configure_mesh()
                .x_desc(x_label.as_str())
                .y_desc(y_label.as_str())
                .x_label_formatter(&|v| short(*v))
                .y_label_formatter(&|v| short(*v))
                .light_line_style(WHITE)
                .label_style(("sans-serif", 11))
                .draw()
                .map_err(drawing)?;
            chart
                .draw_series(arrows.iter().map(|a| Circle::new(a.at, 2, BLACK.filled())))
                .map_err(drawing)?;
            chart
                .draw_series(arrows.iter().map(|a| {
                    PathElement::new(
                        vec![
                            a.at,
                            (a.at.0 + scale * a.error.0, a.at.1 + scale * a.error.1),
                        ],
                        COLOURS[1].stroke_width(2),
                    )
                }))
                .map_err(drawing)?;
        }
        root.present().map_err(drawing)?;
    }
    Ok(document)
}

/// An axis label: few digits, no trailing noise.
fn short(v: f64) -> String {
    let a = v.abs();
    // A tick at zero computed as ±1e-17: rounding, in any display unit.
    if a < 1e-12 {
        return "0".into();
    }
    if !(1e-3..1e5).contains(&a) {
        format!("{v:.1e}")
    } else if a >= 100.0 {
        format!("{v:.0}")
    } else if a >= 1.0 {
        format!("{v:.2}")
    } else {
        format!("{v:.3}")
    }
}

fn drawing<E: std::error::Error + Send + Sync>(e: DrawingAreaErrorKind<E>) -> anyhow::Error {
    anyhow::anyhow!("{e}")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_curve_with_a_band_draws_a_path_and_a_polygon() {
        let panel = Panel {
            title: "p".into(),
            x_label: "x [m]".into(),
            y_label: "y [µm]".into(),
            series: vec![Series::line("y", vec![(0.0, 1.0), (1.0, 2.0), (2.0, 1.5)])
                .with_band(vec![0.2, 0.3, 0.2])],
        };
        let svg = panels_svg("t", &[panel], 1).expect("svg");
        assert!(svg.contains("<polyline") || svg.contains("<path"), "{svg}");
        assert!(svg.contains("<polygon"), "{svg}");
    }

    #[test]
    fn a_rounded_zero_tick_reads_zero() {
        assert_eq!(short(-1.4e-17), "0");
        assert_eq!(short(2e-6), "2.0e-6");
        assert_eq!(short(0.05), "0.050");
    }

    #[test]
    fn panels_without_data_are_an_error() {
        let panel = Panel {
            title: "p".into(),
            x_label: "x".into(),
            y_label: "y".into(),
            series: vec![Series::line("y", vec![(f64::NAN, 1.0)])],
        };
        let e = panels_svg("empty plot", &[panel], 1).expect_err("no data");
        assert!(e.to_string().contains("empty plot: no data"), "{e}");
    }
}
