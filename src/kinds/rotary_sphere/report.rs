//! Text report of the rotary_sphere results: what an engineer reads at the end of a run.

use super::config::HeightRole;
use super::solve::RotarySphereResults;

/// Arcseconds per radian.
const ARCSEC_PER_RAD: f64 = 180.0 * 3600.0 / std::f64::consts::PI;

/// The text report section of a rotary_sphere result.
pub fn text(r: &RotarySphereResults) -> String {
    use std::fmt::Write;
    let mut s = String::new();
    let fit = r
        .spheres
        .iter()
        .filter(|s| s.role == HeightRole::Fit)
        .count();
    let _ = writeln!(
        s,
        "rotary axis {} from a reference sphere (r = {:.4} mm, probe σ {:.1} µm): {} spheres, {} at fit heights",
        r.table,
        r.sphere_radius_m * 1e3,
        r.probe_noise_m * 1e6,
        r.spheres.len(),
        fit
    );
    let _ = writeln!(s, "  location (position-independent) errors:");
    for v in &r.location {
        if v.name.starts_with("EX") || v.name.starts_with("EY") {
            let _ = writeln!(
                s,
                "    {:5} {:9.2} µm   σ {:.2} µm",
                v.name,
                v.value * 1e6,
                v.sigma * 1e6
            );
        } else {
            let _ = writeln!(
                s,
                "    {:5} {:9.2} µrad σ {:.2} µrad",
                v.name,
                v.value * 1e6,
                v.sigma * 1e6
            );
        }
    }
    let _ = writeln!(
        s,
        "  motion errors over {} angles (peak |value| and median σ; harmonic order by BIC):",
        r.motion.len()
    );
    for (k, name) in r.motion_names.iter().enumerate() {
        let peak = r
            .motion
            .iter()
            .map(|m| m.errors[k].abs())
            .fold(0.0, f64::max);
        let mut sig: Vec<f64> = r.motion.iter().map(|m| m.sigma[k]).collect();
        sig.sort_by(f64::total_cmp);
        let med = sig.get(sig.len() / 2).copied().unwrap_or(0.0);
        let order = r.harmonics.get(k).map_or(0, |h| h.order);
        if k < 3 {
            let _ = writeln!(
                s,
                "    {name:4} peak {:8.2} µm     σ {:6.2} µm     order {order}",
                peak * 1e6,
                med * 1e6
            );
        } else {
            let _ = writeln!(
                s,
                "    {name:4} peak {:8.2} arcsec σ {:6.2} arcsec order {order}",
                peak * ARCSEC_PER_RAD,
                med * ARCSEC_PER_RAD
            );
        }
    }
    if r.dof > 0 {
        let _ = writeln!(
            s,
            "  per-angle model χ²/dof {:.2} ({} dof)",
            r.chi2 / r.dof as f64,
            r.dof
        );
    }
    for v in &r.validation {
        let _ = writeln!(
            s,
            "  prediction at validation height {} ({} angles): {:.0} % of residuals within 10 µm \
             ({:.0} % of coordinates; published ~80 %), {:.0} % of coordinates within 3 predicted σ, χ²/n {:.2}",
            v.height_index,
            v.angles_rad.len(),
            100.0 * v.share_norm_within_10um,
            100.0 * v.share_coordinates_within_10um,
            100.0 * v.share_within_3_sigma,
            v.chi2 / v.count.max(1) as f64
        );
    }
    for n in &r.notes {
        let _ = writeln!(s, "  note: {n}");
    }
    s
}

impl crate::method::KindResults for RotarySphereResults {
    fn report(&self) -> String {
        text(self)
    }
}

/// The part of the results.json the report shows (`RotarySphereResults` as written).
#[derive(Debug, serde::Deserialize)]
struct ReportView {
    table: String,
    sphere_radius_m: f64,
    probe_noise_m: f64,
    location: Vec<NamedView>,
    motion_names: Vec<String>,
    motion: Vec<MotionView>,
    harmonics: Vec<HarmonicView>,
    #[serde(default)]
    validation: Vec<ValidationView>,
    #[serde(default)]
    notes: Vec<String>,
}

#[derive(Debug, serde::Deserialize)]
struct NamedView {
    name: String,
    value: f64,
    sigma: f64,
}

#[derive(Debug, serde::Deserialize)]
struct MotionView {
    commanded_rad: f64,
    errors: [f64; 6],
    sigma: [f64; 6],
}

#[derive(Debug, serde::Deserialize)]
struct HarmonicView {
    name: String,
    order: usize,
    coefficients: Vec<f64>,
    residual_rms: f64,
}

#[derive(Debug, serde::Deserialize)]
struct ValidationView {
    height_index: usize,
    share_norm_within_10um: f64,
    share_within_3_sigma: f64,
    count: usize,
}

/// Whether an error name is a rotation (EA*, EB*, EC*: rad) rather than a displacement (m).
fn is_angular(name: &str) -> bool {
    ["EA", "EB", "EC"].iter().any(|p| name.starts_with(p))
}

/// A value in display units: µm for displacements, arcsec for rotations.
fn shown(name: &str, value: f64) -> f64 {
    if is_angular(name) {
        value * ARCSEC_PER_RAD
    } else {
        value * 1e6
    }
}

fn unit(name: &str) -> &'static str {
    if is_angular(name) {
        "arcsec"
    } else {
        "µm"
    }
}

/// The report's rotary_sphere sections: the PIGE (location) table, the six motion errors
/// against angle with ±2σ bands and their harmonic fits, and the held-out validation.
pub fn document(results: &serde_json::Value) -> anyhow::Result<crate::document::KindReport> {
    use crate::document::plots::{panels_svg, Panel, Series, Style};
    use crate::document::{cell, KindReport, Plot, Section, Table};
    let r: ReportView = crate::document::results_of(super::config::KIND, results)?;
    let mut pige = Table::new(
        "Location errors (position-independent, PIGE)",
        &["error", "value", "σ", "unit"],
    );
    for v in &r.location {
        pige.row(vec![
            v.name.clone(),
            cell(Some(shown(&v.name, v.value)), 2),
            cell(Some(shown(&v.name, v.sigma)), 2),
            unit(&v.name).to_string(),
        ]);
    }
    let mut harmonics = Table::new(
        "Harmonic fits of the motion errors (order chosen by BIC)",
        &["error", "order", "mean", "RMS of fit residual", "unit"],
    );
    let mut panels = Vec::new();
    for (k, name) in r.motion_names.iter().enumerate().take(6) {
        let points: Vec<(f64, f64)> = r
            .motion
            .iter()
            .map(|m| (m.commanded_rad.to_degrees(), shown(name, m.errors[k])))
            .collect();
        let band: Vec<f64> = r
            .motion
            .iter()
            .map(|m| 2.0 * shown(name, m.sigma[k]).abs())
            .collect();
        let mut series = vec![Series::points("measured ±2σ", points)
            .with_band(band)
            .with_style(Style::Points)];
        if let Some(h) = r.harmonics.iter().find(|h| &h.name == name) {
            let curve: Vec<(f64, f64)> = (0..=360)
                .map(|d| {
                    let theta = f64::from(d).to_radians();
                    let value: f64 = crate::model::rotary_sphere::harmonic_basis(theta, h.order)
                        .iter()
                        .zip(&h.coefficients)
                        .map(|(b, c)| b * c)
                        .sum();
                    (f64::from(d), shown(name, value))
                })
                .collect();
            series.push(
                Series::line(&format!("harmonic fit, order {}", h.order), curve)
                    .with_style(Style::Line),
            );
            harmonics.row(vec![
                name.clone(),
                h.order.to_string(),
                cell(h.coefficients.first().map(|c| shown(name, *c)), 2),
                cell(Some(shown(name, h.residual_rms)), 2),
                unit(name).to_string(),
            ]);
        }
        panels.push(Panel {
            title: name.clone(),
            x_label: "table angle [°]".into(),
            y_label: format!("{name} [{}]", unit(name)),
            series,
        });
    }
    let motion_svg = panels_svg(
        &format!(
            "table {}: motion errors against angle (±2σ band, harmonic fit)",
            r.table
        ),
        &panels,
        2,
    )?;
    let mut validation = Table::new(
        "Held-out heights: centres predicted from the identified errors",
        &["height", "spheres", "within 10 µm (3-D)", "within 3σ"],
    );
    for v in &r.validation {
        validation.row(vec![
            v.height_index.to_string(),
            v.count.to_string(),
            format!("{:.0} %", 100.0 * v.share_norm_within_10um),
            format!("{:.0} %", 100.0 * v.share_within_3_sigma),
        ]);
    }
    let max_motion = |k: usize| {
        r.motion
            .iter()
            .map(|m| shown(&r.motion_names[k], m.errors[k]).abs())
            .fold(0.0, f64::max)
    };
    let mut summary = vec![
        ("table".to_string(), r.table.clone()),
        (
            "reference sphere radius".to_string(),
            format!("{:.4} mm", r.sphere_radius_m * 1e3),
        ),
        (
            "probe σ".to_string(),
            format!("{:.1} µm", r.probe_noise_m * 1e6),
        ),
        ("angles measured".to_string(), r.motion.len().to_string()),
    ];
    for k in 0..r.motion_names.len().min(6) {
        summary.push((
            format!("max |{}|", r.motion_names[k]),
            format!("{:.2} {}", max_motion(k), unit(&r.motion_names[k])),
        ));
    }
    let mut motion =
        Section::new("rotary-sphere-motion", "Motion errors against angle").plot(Plot {
            id: "motion-errors".into(),
            caption:
                "The six motion errors of the table at each commanded angle (points, shaded ±2σ) \
                  and their harmonic fits (lines)."
                    .into(),
            svg: motion_svg,
        });
    motion = motion.table(harmonics);
    let mut sections = vec![
        Section::new("rotary-sphere-location", "Location errors (PIGE)").table(pige),
        motion,
    ];
    if !r.validation.is_empty() {
        sections.push(Section::new("rotary-sphere-validation", "Validation").table(validation));
    }
    if !r.notes.is_empty() {
        sections
            .push(Section::new("rotary-sphere-notes", "Notes").preformatted(r.notes.join("\n")));
    }
    Ok(KindReport { summary, sections })
}

/// The budget section: the location errors and, per motion error, the largest U (k = 2) over
/// the angles with its largest contributor, the contributor tables, and the contributors the
/// configuration did not declare.
pub fn uncertainty(
    session: &crate::session::reader::Session,
    declared: &super::config::SphereUncertainty,
) -> anyhow::Result<crate::document::Section> {
    use crate::evaluate::budget_section::{section, BudgetGroup};
    use crate::model::rotary_sphere::{LOCATION_NAMES, MOTION_NAMES};
    let (plan, noise_m, probed) = super::solve::probed(session)?;
    let all = super::budget::budgets(&plan, noise_m, &probed, declared)?;
    let mut groups: Vec<BudgetGroup> = (0..4)
        .map(|k| BudgetGroup {
            label: LOCATION_NAMES[k].to_string(),
            budgets: vec![&all.budgets[k]],
        })
        .collect();
    for (k, name) in MOTION_NAMES.iter().enumerate() {
        groups.push(BudgetGroup {
            label: format!("{name} (over the angles)"),
            budgets: all.budgets[4..].iter().skip(k).step_by(6).collect(),
        });
    }
    Ok(section(
        "rotary-sphere-uncertainty",
        "Expanded uncertainty U (k = 2) of the location errors and of the motion errors: the \
         solve's σ (the probe's repeatability) and the declared contributors under \
         [uncertainty], each through its sensitivity found by re-solving with the input moved \
         (the sphere's form one surface point at a time; GUM; docs/uncertainty.md). The kind \
         logs no temperatures: no thermal contributor.",
        &groups,
        &all,
    ))
}
