//! A kind's budgets as a report section: per group of quantities the largest expanded
//! uncertainty U (k = 2) and its dominant contributor, the contributor table, what was not declared.

use crate::document::{arcsec, cell, um, Section, Table};

use super::uncertainty::{Budget, KindBudgets};

/// A quantity's value in the unit a report shows it in, and that unit's name.
fn shown(unit: &str, v: f64) -> (f64, &'static str) {
    match unit {
        "rad" => (arcsec(v), "arcsec"),
        "1" => (v * 1e6, "1e-6"),
        _ => (um(v), "µm"),
    }
}

/// One row of the summary: a label and the budgets it stands for (its largest U is shown).
pub struct BudgetGroup<'a> {
    pub label: String,
    pub budgets: Vec<&'a Budget>,
}

/// The section: `groups` in the summary table, then the contributor table of the largest U of
/// each unit, then which contributors the configuration did not declare.
pub fn section(id: &str, intro: &str, groups: &[BudgetGroup], all: &KindBudgets) -> Section {
    let mut section = Section::new(id, "Uncertainty budget").paragraph(intro);
    let mut table = Table::new(
        "Largest expanded uncertainty per group (k = 2)",
        &[
            "quantity",
            "at",
            "value",
            "σ (solve)",
            "U",
            "unit",
            "largest contributor",
        ],
    );
    for g in groups {
        let Some(b) = g
            .budgets
            .iter()
            .copied()
            .max_by(|a, b| a.expanded_uncertainty.total_cmp(&b.expanded_uncertainty))
        else {
            continue;
        };
        let sigma = b.contributors.first().map_or(0.0, |c| c.contribution);
        let (value, unit) = shown(&b.unit, b.value);
        table.row(vec![
            g.label.clone(),
            b.quantity.clone(),
            cell(Some(value), 3),
            cell(Some(shown(&b.unit, sigma).0), 3),
            cell(Some(shown(&b.unit, b.expanded_uncertainty).0), 3),
            unit.to_string(),
            dominant(b),
        ]);
    }
    section = section.table(table);
    for unit in ["m", "rad", "1"] {
        let Some(b) = all
            .budgets
            .iter()
            .filter(|b| b.unit == unit)
            .max_by(|a, b| a.expanded_uncertainty.total_cmp(&b.expanded_uncertainty))
        else {
            continue;
        };
        let shown_unit = shown(unit, 0.0).1;
        let mut contributors = Table::new(
            &format!(
                "Contributors at the largest U in {shown_unit}: {}",
                b.quantity
            ),
            &[
                "contributor",
                "u(x)",
                "sensitivity",
                &format!("u(y) [{shown_unit}]"),
                "share",
            ],
        );
        for c in &b.contributors {
            contributors.row(vec![
                c.name.clone(),
                format!("{:.3e} {}", c.standard_uncertainty, c.unit),
                format!("{:.3e} {}", c.sensitivity, c.sensitivity_unit),
                format!("{:.4}", shown(unit, c.contribution).0),
                format!("{:.1} %", 100.0 * c.share),
            ]);
        }
        section = section.table(contributors);
    }
    if all.not_declared.is_empty() {
        section
    } else {
        section.paragraph(format!(
            "Not declared in the configuration, so not in the budget: {}.",
            all.not_declared.join(", ")
        ))
    }
}

/// The section when the budget could not be computed (results or session not as the kind's
/// solver needs them): the report goes on and says why.
pub fn unavailable(id: &str, why: &anyhow::Error) -> Section {
    Section::new(id, "Uncertainty budget")
        .paragraph(format!("No uncertainty budget could be computed: {why:#}."))
}

/// The contributor with the largest share, "name (share %)".
fn dominant(b: &Budget) -> String {
    b.contributors
        .iter()
        .max_by(|x, y| x.share.total_cmp(&y.share))
        .map_or("-".to_owned(), |c| {
            format!("{} ({:.0} %)", c.name, 100.0 * c.share)
        })
}
