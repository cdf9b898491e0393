//! The multilateration's uncertainty budget in `geocal report` (GUM, docs/uncertainty.md):
//! the positioning errors' expanded uncertainty and their values referred to 20 °C.

use std::path::Path;

use crate::document::{cell, um, Section, Table};
use crate::method::multilateration::MultilaterationResults;
use crate::session::reader::Session;

/// The uncertainty budget of the positioning errors (k = 2) and their values referred to
/// 20 °C, from the declared uncertainties of the run's configuration (`config`: the
/// documented defaults without it).
pub fn section(
    results: &serde_json::Value,
    session: &Session,
    config_path: Option<&Path>,
) -> anyhow::Result<Vec<Section>> {
    let results: MultilaterationResults =
        crate::document::results_of(crate::config::PlanKind::Multilateration.as_str(), results)?;
    let config = match config_path {
        Some(path) => Some(crate::config::Config::load(path)?),
        None => None,
    };
    let evaluation = crate::evaluate::tracer::evaluate_session(session, &results, config.as_ref())?;
    let mut section = Section::new("uncertainty", "Uncertainty budget and 20 °C").paragraph(
        "Expanded uncertainty U (k = 2) of the positioning errors from the solve's σ and the \
         declared contributors (GUM; docs/uncertainty.md); the values referred to 20 °C with \
         the scales' CTE and the logged material temperature (ISO 1).",
    );
    let mut table = Table::new(
        "Positioning errors",
        &[
            "error",
            "positions",
            "max |raw| [µm]",
            "max |at 20 °C| [µm]",
            "max U [µm]",
            "largest contributor",
        ],
    );
    let mut worst: Option<&crate::evaluate::uncertainty::Budget> = None;
    for positioning in &evaluation.positioning {
        let curve = &positioning.curve;
        let max_abs = |values: &[Option<f64>]| {
            values
                .iter()
                .flatten()
                .map(|v| v.abs())
                .fold(None, |m: Option<f64>, v| Some(m.map_or(v, |m| m.max(v))))
        };
        let budgets: Vec<_> = positioning.budgets.iter().flatten().collect();
        let largest = budgets
            .iter()
            .copied()
            .max_by(|a, b| a.expanded_uncertainty.total_cmp(&b.expanded_uncertainty));
        if let Some(b) = largest {
            if worst.is_none_or(|w| b.expanded_uncertainty > w.expanded_uncertainty) {
                worst = Some(b);
            }
        }
        let contributor = largest
            .and_then(|b| {
                b.contributors
                    .iter()
                    .max_by(|x, y| x.share.total_cmp(&y.share))
            })
            .map_or("-".to_owned(), |c| {
                format!("{} ({:.0} %)", c.name, 100.0 * c.share)
            });
        table.row(vec![
            format!("{} along {}", curve.error, curve.axis),
            curve.positions_m.len().to_string(),
            cell(max_abs(&curve.raw_m).map(um), 3),
            cell(max_abs(&curve.normalised_m).map(um), 3),
            cell(largest.map(|b| um(b.expanded_uncertainty)), 3),
            contributor,
        ]);
    }
    section = section.table(table);
    if let Some(budget) = worst {
        let mut contributors = Table::new(
            &format!("Contributors at the largest U: {}", budget.quantity),
            &["contributor", "u(x)", "sensitivity", "u(y) [µm]", "share"],
        );
        for c in &budget.contributors {
            contributors.row(vec![
                c.name.clone(),
                format!("{:.3e} {}", c.standard_uncertainty, c.unit),
                format!("{:.3e} {}", c.sensitivity, c.sensitivity_unit),
                format!("{:.4}", um(c.contribution)),
                format!("{:.1} %", 100.0 * c.share),
            ]);
        }
        section = section.table(contributors);
    }
    let mut notes: Vec<String> = evaluation.notes.clone();
    if config.is_none() {
        notes.push(
            "no run-config.toml beside the results: the default declared uncertainties".into(),
        );
    }
    for note in notes {
        section = section.paragraph(note);
    }
    Ok(vec![section])
}
