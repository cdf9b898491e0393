//! Text report of the probe_install results: what an engineer reads at the end of a run.

use std::fmt::Write;

use super::solve::ProbeInstallResults;
use crate::method::report::um;

pub fn text(r: &ProbeInstallResults) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "probe installation ({}): {} points ({} readings, {} out of range) at {} postures, \
         sphere r = {:.4} mm",
        r.session_id,
        r.points,
        r.readings,
        r.readings_out_of_range,
        r.postures_rad.len(),
        r.sphere_radius_m * 1e3
    );
    let _ = writeln!(
        s,
        "  LM: residual rms {:.3} µm, chi²/dof {} ({} dof), {} iterations{}",
        um(r.residual_rms_m),
        chi2_text(r.chi2_per_dof),
        r.dof,
        r.lm.iterations,
        if r.lm.converged {
            ""
        } else {
            " (NOT converged)"
        }
    );
    if !r.not_identifiable.is_empty() {
        let _ = writeln!(
            s,
            "  NOT identifiable by these postures (no σ): {}; held at nominal: {}; unseen: {}",
            r.not_identifiable.join(", "),
            r.held_at_nominal.join(", "),
            r.unseen_directions.join("; ")
        );
    }
    let _ = writeln!(
        s,
        "  {:<20} {:>16} {:>12} {:>16} {:>16}",
        "parameter", "LM value", "σ", "GA value", "nominal"
    );
    for (k, p) in r.parameters.iter().enumerate() {
        let ga = r.ga.values.get(k).copied().unwrap_or(f64::NAN);
        let _ = writeln!(
            s,
            "  {:<20} {:>16.9e} {:>12} {:>16.9e} {:>16.9e}",
            p.name,
            p.value,
            p.sigma
                .map_or("not seen".to_string(), |v| format!("{v:.3e}")),
            ga,
            p.nominal
        );
    }
    let _ = writeln!(
        s,
        "  objective G (M = 1e4): LM {:.4e} (h {:.1e}), GA {:.4e} (h {:.1e}; N = {}, {} generations, {} evaluations)",
        r.lm.objective,
        r.lm.unit_norm_violation,
        r.ga.objective,
        r.ga.unit_norm_violation,
        r.ga.population,
        r.ga.generations,
        r.ga.evaluations
    );
    let _ = writeln!(
        s,
        "  sphere radius measured: before {:.4} mm, after LM {:.4} mm, after GA {:.4} mm",
        r.radius_before_m * 1e3,
        r.radius_after_m * 1e3,
        r.radius_after_ga_m * 1e3
    );
    s
}

impl crate::method::KindResults for ProbeInstallResults {
    fn report(&self) -> String {
        text(self)
    }
}

/// A parameter's display scale and unit from its name: lengths (`_m`) in mm, angles (`_rad`)
/// in arcsec, the rest (direction cosines) as they are.
fn display(name: &str) -> (f64, &'static str) {
    if name.ends_with("_m") {
        (1e3, "mm")
    } else if name.ends_with("_rad") {
        (crate::document::arcsec(1.0), "arcsec")
    } else {
        (1.0, "1")
    }
}

/// The report's probe_install sections: the 11 installation parameters before (nominal) and
/// after calibration with σ, their changes in σ, and the sphere radius before/after.
pub fn document(results: &serde_json::Value) -> anyhow::Result<crate::document::KindReport> {
    use crate::document::plots::{panels_svg, Panel, Series, Style};
    use crate::document::{cell, KindReport, Plot, Section, Table};
    let r: ProbeInstallResults = crate::document::results_of(super::config::KIND, results)?;
    let mut table = Table::new(
        "Installation parameters: before (nominal) and after (LM, with σ; GA for comparison)",
        &[
            "parameter",
            "unit",
            "before",
            "after (LM)",
            "σ",
            "after (GA)",
            "change / σ",
        ],
    );
    let mut standardised = Vec::new();
    for (k, p) in r.parameters.iter().enumerate() {
        let (scale, unit) = display(&p.name);
        let ga = r.ga.values.get(k).copied();
        let z = p
            .sigma
            .filter(|s| *s > 0.0)
            .map(|s| (p.value - p.nominal) / s);
        if let Some(z) = z {
            standardised.push((k as f64, z));
        }
        table.row(vec![
            p.name.clone(),
            unit.to_string(),
            cell(Some(p.nominal * scale), 6),
            cell(Some(p.value * scale), 6),
            cell(p.sigma.map(|v| v * scale), 6),
            cell(ga.map(|v| v * scale), 6),
            cell(z, 1),
        ]);
    }
    let mut radius = Table::new(
        "Sphere radius measured from every point",
        &[
            "",
            "radius [mm]",
            "deviation from the calibrated radius [µm]",
        ],
    );
    for (label, value) in [
        ("before (nominal installation)", r.radius_before_m),
        ("after (LM)", r.radius_after_m),
        ("after (GA)", r.radius_after_ga_m),
    ] {
        radius.row(vec![
            label.to_string(),
            cell(Some(value * 1e3), 4),
            cell(Some((value - r.sphere_radius_m) * 1e6), 2),
        ]);
    }
    let plot = panels_svg(
        "installation parameters: (after − before) / σ",
        &[Panel {
            title: "change of each parameter in its σ".into(),
            x_label: "parameter index (table order)".into(),
            y_label: "(after − before) / σ".into(),
            series: vec![Series::points("", standardised).with_style(Style::Points)],
        }],
        1,
    )?;
    let summary = vec![
        (
            "points (readings)".to_string(),
            format!("{} ({})", r.points, r.readings),
        ),
        (
            "residual RMS".to_string(),
            format!("{:.3} µm", r.residual_rms_m * 1e6),
        ),
        ("χ²/dof".to_string(), chi2_text(r.chi2_per_dof)),
        (
            "sphere radius before → after".to_string(),
            format!(
                "{:.4} mm → {:.4} mm (calibrated {:.4} mm)",
                r.radius_before_m * 1e3,
                r.radius_after_m * 1e3,
                r.sphere_radius_m * 1e3
            ),
        ),
        ("LM converged".to_string(), r.lm.converged.to_string()),
    ];
    let mut sections = vec![
        Section::new("probe-install-parameters", "Installation parameters")
            .table(table)
            .plot(Plot {
                id: "parameter-changes".into(),
                caption: "Each parameter's change from its nominal value in units of its σ.".into(),
                svg: plot,
            }),
    ];
    sections.push(Section::new("probe-install-radius", "Sphere radius").table(radius));
    if !r.note.is_empty() {
        sections.push(Section::new("probe-install-notes", "Notes").paragraph(r.note.clone()));
    }
    Ok(KindReport { summary, sections })
}

/// The budget section: per parameter its U (k = 2) and largest contributor, the contributor
/// table, and the contributors the run's configuration did not declare.
pub fn uncertainty(
    results: &serde_json::Value,
    session: &crate::session::reader::Session,
    declared: &super::config::ProbeInstallUncertainty,
) -> anyhow::Result<crate::document::Section> {
    use crate::evaluate::budget_section::{section, BudgetGroup};
    let r: ProbeInstallResults = crate::document::results_of(super::config::KIND, results)?;
    let (_, problem, _, _) = super::solve::problem(session)?;
    use crate::model::probe_install::{InstallParams, N_PARAMS};
    if r.parameters.len() != N_PARAMS {
        anyhow::bail!(
            "results key `parameters`: expected the {N_PARAMS} installation parameters, found {}",
            r.parameters.len()
        );
    }
    let values =
        nalgebra::SVector::<f64, N_PARAMS>::from_iterator(r.parameters.iter().map(|p| p.value));
    let solution = InstallParams::from_vector(&values);
    // A parameter the postures cannot see has no σ to budget.
    let sigma: Vec<f64> = r
        .parameters
        .iter()
        .map(|p| p.sigma.unwrap_or(f64::NAN))
        .collect();
    let all = super::budget::budgets(&problem, &solution, &sigma, declared)?;
    let groups: Vec<BudgetGroup> = [
        ("δB", 0..1),
        ("y32", 1..2),
        ("beam direction l, m, n", 2..5),
        ("probe zero point", 5..8),
        ("sphere centre", 8..11),
        ("sphere radius (after LM)", 11..12),
    ]
    .into_iter()
    .map(|(label, range)| BudgetGroup {
        label: label.to_string(),
        budgets: all.budgets[range].iter().collect(),
    })
    .collect();
    Ok(section(
        "probe-install-uncertainty",
        "Expanded uncertainty U (k = 2) of the LM parameters and of the sphere radius measured \
         with them: the solve's σ and the declared contributors under [uncertainty], each \
         through its sensitivity found by re-solving with the input moved (GUM; \
         docs/uncertainty.md). The beam direction is a unit vector: its U is shown in 1e-6.",
        &groups,
        &all,
    ))
}

/// χ²/dof to 3 decimals, or why there is none.
fn chi2_text(v: Option<f64>) -> String {
    v.map_or("none (no redundancy)".into(), |v| format!("{v:.3}"))
}
