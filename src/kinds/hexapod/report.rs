//! Text report of the hexapod results: what an engineer reads at the end of a run.

use std::fmt::Write;

use super::solve::HexapodResults;
use crate::method::report::um;

/// χ²/dof to 3 decimals, or why there is none.
fn chi2_text(v: Option<f64>) -> String {
    v.map_or("none (no redundancy)".into(), |v| format!("{v:.3}"))
}

pub fn text(r: &HexapodResults) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "hexapod hinges ({}): {} poses ({} poses {}), {} leg readings, σ per change {:.3} µm",
        r.session_id,
        r.poses,
        r.pose_source,
        if r.pose_source == "measured" {
            "by the sensor"
        } else {
            "as commanded"
        },
        r.readings,
        um(r.sigma_change_m)
    );
    let _ = writeln!(
        s,
        "  two-stage: objective {:.4e} m² (start {:.4e}, stage 1 {:.4e}), residual rms {:.3} µm, \
         weighted chi²/dof {} ({} dof), {} grid rounds, {} leg solves",
        r.two_stage.objective_m2,
        r.two_stage.objective_initial_m2,
        r.two_stage.objective_stage1_m2,
        um(r.residual_rms_m),
        chi2_text(r.chi2_per_dof),
        r.dof,
        r.two_stage.rounds.len(),
        r.two_stage.leg_solves
    );
    let _ = writeln!(
        s,
        "  plain LM: objective {:.4e} m², {} iterations, largest difference from two-stage {:.3} µm",
        r.lm.objective_m2,
        r.lm.iterations,
        um(r.lm.max_difference_m)
    );
    let _ = writeln!(
        s,
        "  leg  base hinge B (m)                          σ (µm)                  platform hinge P (m)                       σ (µm)"
    );
    for h in &r.hinges {
        let _ = writeln!(
            s,
            "  {:>3}  [{:+.6}, {:+.6}, {:+.6}]  [{:6.1}, {:6.1}, {:6.1}]  [{:+.6}, {:+.6}, {:+.6}]  [{:6.1}, {:6.1}, {:6.1}]",
            h.leg,
            h.base_m[0],
            h.base_m[1],
            h.base_m[2],
            um(h.base_sigma_m[0]),
            um(h.base_sigma_m[1]),
            um(h.base_sigma_m[2]),
            h.platform_m[0],
            h.platform_m[1],
            h.platform_m[2],
            um(h.platform_sigma_m[0]),
            um(h.platform_sigma_m[1]),
            um(h.platform_sigma_m[2])
        );
    }
    s
}

impl crate::method::KindResults for HexapodResults {
    fn report(&self) -> String {
        text(self)
    }
}

/// The report's hexapod sections: each leg's base and platform hinge, the correction from its
/// nominal position with σ, as a table and as a plot of |correction| with 2σ.
pub fn document(results: &serde_json::Value) -> anyhow::Result<crate::document::KindReport> {
    use crate::document::plots::{panels_svg, Panel, Series, Style};
    use crate::document::{cell, KindReport, Plot, Section, Table};
    let r: HexapodResults = crate::document::results_of(super::config::KIND, results)?;
    let mut table = Table::new(
        "Hinge corrections (calibrated − nominal), µm, with σ",
        &["leg", "hinge", "Δx", "Δy", "Δz", "σx", "σy", "σz", "|Δ|"],
    );
    let norm = |v: [f64; 3]| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    let mut panels = Vec::new();
    for (hinge, pick) in [("base", 0usize), ("platform", 1)] {
        let mut components: [Vec<(f64, f64)>; 3] = Default::default();
        let mut bands: [Vec<f64>; 3] = Default::default();
        for h in &r.hinges {
            let (value, nominal, sigma) = if pick == 0 {
                (h.base_m, h.nominal_base_m, h.base_sigma_m)
            } else {
                (h.platform_m, h.nominal_platform_m, h.platform_sigma_m)
            };
            let d = [0, 1, 2].map(|k| value[k] - nominal[k]);
            let mut row = vec![h.leg.to_string(), hinge.to_string()];
            row.extend(d.iter().map(|v| cell(Some(um(*v)), 2)));
            row.extend(sigma.iter().map(|v| cell(Some(um(*v)), 2)));
            row.push(cell(Some(um(norm(d))), 2));
            table.row(row);
            for k in 0..3 {
                components[k].push((h.leg as f64, um(d[k])));
                bands[k].push(2.0 * um(sigma[k]));
            }
        }
        let [cx, cy, cz] = components;
        let [bx, by, bz] = bands;
        panels.push(Panel {
            title: format!("{hinge} hinges"),
            x_label: "leg".into(),
            y_label: "correction [µm]".into(),
            series: vec![
                Series::points("Δx ±2σ", cx)
                    .with_band(bx)
                    .with_style(Style::Points),
                Series::points("Δy ±2σ", cy)
                    .with_band(by)
                    .with_style(Style::Points),
                Series::points("Δz ±2σ", cz)
                    .with_band(bz)
                    .with_style(Style::Points),
            ],
        });
    }
    let plot = panels_svg("hinge corrections (calibrated − nominal)", &panels, 2)?;
    let largest = r
        .hinges
        .iter()
        .flat_map(|h| {
            [
                norm([0, 1, 2].map(|k| h.base_m[k] - h.nominal_base_m[k])),
                norm([0, 1, 2].map(|k| h.platform_m[k] - h.nominal_platform_m[k])),
            ]
        })
        .fold(0.0, f64::max);
    let summary = vec![
        (
            "poses (leg readings)".to_string(),
            format!("{} ({})", r.poses, r.readings),
        ),
        ("poses from".to_string(), r.pose_source.clone()),
        (
            "residual RMS".to_string(),
            format!("{:.3} µm", um(r.residual_rms_m)),
        ),
        (
            "weighted χ²/dof".to_string(),
            format!("{} ({} dof)", chi2_text(r.chi2_per_dof), r.dof),
        ),
        (
            "largest hinge correction".to_string(),
            format!("{:.2} µm", um(largest)),
        ),
    ];
    let mut sections = vec![Section::new("hexapod-hinges", "Hinge corrections")
        .table(table)
        .plot(Plot {
            id: "hinge-corrections".into(),
            caption: "Each hinge's correction per coordinate, with its ±2σ interval, by leg."
                .into(),
            svg: plot,
        })];
    if !r.note.is_empty() {
        sections.push(Section::new("hexapod-notes", "Notes").paragraph(r.note.clone()));
    }
    Ok(KindReport { summary, sections })
}

/// The budget section: per hinge set and coordinate the largest U (k = 2) and its largest
/// contributor, the contributor table, and the contributors the configuration did not declare.
pub fn uncertainty(
    results: &serde_json::Value,
    session: &crate::session::reader::Session,
    declared: &super::config::HexapodUncertainty,
) -> anyhow::Result<crate::document::Section> {
    use crate::evaluate::budget_section::{section, BudgetGroup};
    use crate::model::hexapod::{HexapodGeometry, LEGS};
    let r: HexapodResults = crate::document::results_of(super::config::KIND, results)?;
    if r.hinges.len() != LEGS {
        anyhow::bail!(
            "results key `hinges`: expected {LEGS} legs, found {}",
            r.hinges.len()
        );
    }
    let prepared = super::solve::prepare(session)?;
    let mut values = Vec::with_capacity(6 * LEGS);
    let mut sigma = Vec::with_capacity(6 * LEGS);
    for platform in [false, true] {
        for h in &r.hinges {
            let (v, s) = if platform {
                (h.platform_m, h.platform_sigma_m)
            } else {
                (h.base_m, h.base_sigma_m)
            };
            values.extend(v);
            sigma.extend(s);
        }
    }
    let solution = HexapodGeometry::from_slice(&values);
    let all = super::budget::budgets(
        &prepared.observations,
        &prepared.noise,
        &solution,
        &sigma,
        declared,
    )?;
    let mut groups = Vec::new();
    for (set, offset) in [("base hinges", 0), ("platform hinges", 3 * LEGS)] {
        for (c, axis) in ["x", "y", "z"].iter().enumerate() {
            groups.push(BudgetGroup {
                label: format!("{set}, {axis}"),
                budgets: (0..LEGS)
                    .map(|leg| &all.budgets[offset + 3 * leg + c])
                    .collect(),
            });
        }
    }
    Ok(section(
        "hexapod-uncertainty",
        "Expanded uncertainty U (k = 2) of the hinge coordinates (and so of their corrections): \
         the weighted fit's σ and the declared contributors under [uncertainty], each through \
         its sensitivity found by re-fitting with the input moved (GUM; docs/uncertainty.md).",
        &groups,
        &all,
    ))
}
