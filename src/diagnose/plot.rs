//! `geocal diagnose --plot`: the lengths' standardised residuals against time, one row per
//! station, before and after the selected effects, as SVG (text as <text>, no font files).

use std::path::Path;

use anyhow::Context;
use plotters::prelude::*;

use super::StandardisedResiduals;

/// Pixels: the plot's width, each station row's height and the title band's.
const WIDTH_PX: u32 = 960;
const ROW_HEIGHT_PX: u32 = 170;
const TITLE_HEIGHT_PX: u32 = 40;
/// The reference lines at ± this many σ.
const REFERENCE_SIGMA: f64 = 3.0;
const BEFORE_COLOUR: RGBColor = RGBColor(120, 120, 120);
const AFTER_COLOUR: RGBColor = RGBColor(214, 39, 40);

/// The plot's title: what the two series are, or that there is only one.
pub fn title(session_id: &str, residuals: &StandardisedResiduals) -> String {
    if residuals.final_effects.is_empty() {
        format!("session {session_id}: residual / sigma, nominal model only (no effect selected)")
    } else {
        format!(
            "session {session_id}: residual / sigma before (grey) and after {} (red)",
            residuals.final_effects.join(", ")
        )
    }
}

/// The plot as an SVG document.
pub fn svg(session_id: &str, residuals: &StandardisedResiduals) -> anyhow::Result<String> {
    let stations = residuals.station_ids.len();
    if stations == 0 || residuals.lengths.is_empty() {
        anyhow::bail!("no lengths to plot");
    }
    let with_after = !residuals.final_effects.is_empty();
    // One symmetric scale for every row, so that the rows compare; the ±3σ lines always show.
    let z_max = residuals
        .lengths
        .iter()
        .flat_map(|r| [r.before, r.after])
        .filter(|z| z.is_finite())
        .fold(REFERENCE_SIGMA + 1.0, |m, z| m.max(1.05 * z.abs()));
    let height = TITLE_HEIGHT_PX + ROW_HEIGHT_PX * stations as u32;
    let mut document = String::new();
    {
        let root = SVGBackend::with_string(&mut document, (WIDTH_PX, height)).into_drawing_area();
        root.fill(&WHITE).map_err(drawing)?;
        let body = root
            .titled(&title(session_id, residuals), ("sans-serif", 16))
            .map_err(drawing)?;
        for (station, (area, id)) in body
            .split_evenly((stations, 1))
            .iter()
            .zip(&residuals.station_ids)
            .enumerate()
        {
            let of_station = || {
                residuals
                    .lengths
                    .iter()
                    .filter(move |r| r.station == station)
            };
            // Each station's own time span: stations are usually measured one after another.
            let (t_min, t_max) = of_station()
                .map(|r| r.t_s)
                .filter(|t| t.is_finite())
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), t| {
                    (lo.min(t), hi.max(t))
                });
            let (t_min, t_max) = if t_min <= t_max {
                // A kind's coordinate may span less than one unit (e.g. a posture index).
                let min_pad = if residuals.x_axis.is_some() { 0.5 } else { 1.0 };
                let pad = (0.02 * (t_max - t_min)).max(min_pad);
                (t_min - pad, t_max + pad)
            } else {
                (0.0, 1.0)
            };
            let mut chart = ChartBuilder::on(area)
                .margin(6)
                .caption(
                    match residuals.x_axis {
                        Some(_) => id.clone(),
                        None => format!("station {id}"),
                    },
                    ("sans-serif", 13),
                )
                .x_label_area_size(40)
                .y_label_area_size(48)
                .build_cartesian_2d(t_min..t_max, -z_max..z_max)
                .map_err(drawing)?;
            chart
                .configure_mesh()
                .x_desc(
                    residuals
                        .x_axis
                        .as_deref()
                        .unwrap_or("time since the first length [s]"),
                )
                .y_desc("residual / sigma")
                .x_label_formatter(&|t| format!("{t:.0}"))
                .y_label_formatter(&|z| format!("{z:.0}"))
                .light_line_style(WHITE)
                .draw()
                .map_err(drawing)?;
            for level in [-REFERENCE_SIGMA, REFERENCE_SIGMA] {
                chart
                    .draw_series(DashedLineSeries::new(
                        [(t_min, level), (t_max, level)],
                        6,
                        4,
                        BLACK.mix(0.5).stroke_width(1),
                    ))
                    .map_err(drawing)?;
            }
            let before = chart
                .draw_series(PointSeries::of_element(
                    of_station().map(|r| (r.t_s, r.before)),
                    2,
                    BEFORE_COLOUR.filled(),
                    &|c, s, st| Circle::new(c, s, st),
                ))
                .map_err(drawing)?;
            if station == 0 {
                before
                    .label("before: nominal model")
                    .legend(|(x, y)| Circle::new((x + 8, y), 3, BEFORE_COLOUR.filled()));
            }
            if with_after {
                let after = chart
                    .draw_series(PointSeries::of_element(
                        of_station().map(|r| (r.t_s, r.after)),
                        2,
                        AFTER_COLOUR.filled(),
                        &|c, s, st| Circle::new(c, s, st),
                    ))
                    .map_err(drawing)?;
                if station == 0 {
                    after
                        .label(format!("after: {}", residuals.final_effects.join(", ")))
                        .legend(|(x, y)| Circle::new((x + 8, y), 3, AFTER_COLOUR.filled()));
                }
            }
            if station == 0 {
                chart
                    .configure_series_labels()
                    .position(SeriesLabelPosition::UpperRight)
                    .background_style(WHITE.mix(0.8))
                    .border_style(BLACK.mix(0.3))
                    .label_font(("sans-serif", 12))
                    .draw()
                    .map_err(drawing)?;
            }
        }
        root.present().map_err(drawing)?;
    }
    Ok(document)
}

/// Write the plot to `path`.
pub fn write_svg(
    path: &Path,
    session_id: &str,
    residuals: &StandardisedResiduals,
) -> anyhow::Result<()> {
    let document = svg(session_id, residuals).context("drawing the residual plot")?;
    std::fs::write(path, document)
        .with_context(|| format!("writing the residual plot to {}", path.display()))
}

fn drawing<E: std::error::Error + Send + Sync>(e: DrawingAreaErrorKind<E>) -> anyhow::Error {
    anyhow::anyhow!("{e}")
}
