//! The report's summary box: the verdict against the tolerances the user declared (`[report]`
//! of the run's configuration), the largest errors with their expanded uncertainty U (k = 2),
//! the diagnosis's verdict, then the few numbers the kind chose.
//!
//! The decision rule is ISO 14253-1's: an error function conforms to ±T when |e| + U ≤ T at
//! every position, does not conform when |e| − U > T at some position, and is undecided
//! otherwise (the limit lies within the uncertainty).

use std::path::Path;

use anyhow::Context;

use crate::config::report::ReportConfig;
use crate::document::{arcsec, KindReport, Section, Table, Tone};
use crate::evaluate::tracer::TracerEvaluation;
use crate::evaluate::uncertainty::Budget;

use super::Inputs;

/// Rows of each unit (lengths, angles) the box lists.
pub const LARGEST_SHOWN: usize = 3;

/// The column heads of the largest-errors table.
pub const COLUMNS: [&str; 6] = [
    "error",
    "where",
    "value",
    "U (k = 2)",
    "tolerance",
    "conformance",
];

/// Where an error function stands against its tolerance.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Conformance {
    Conforms,
    Undecided,
    DoesNotConform,
}

impl Conformance {
    pub fn text(self) -> &'static str {
        match self {
            Conformance::Conforms => "conforms",
            Conformance::Undecided => "undecided (within U)",
            Conformance::DoesNotConform => "does not conform",
        }
    }

    /// |e| + U ≤ T conforms, |e| − U > T does not, else undecided.
    pub fn of(value: f64, expanded: f64, tolerance: f64) -> Conformance {
        if value.abs() + expanded <= tolerance {
            Conformance::Conforms
        } else if value.abs() - expanded > tolerance {
            Conformance::DoesNotConform
        } else {
            Conformance::Undecided
        }
    }
}

/// One error function: its value with U at each position where the solve gave one.
#[derive(Debug, Clone, PartialEq)]
pub struct ErrorFunction {
    /// EXX, EYX, …, or a squareness (EC0Y …).
    pub name: String,
    /// The axis it varies along; None for a squareness.
    pub axis: Option<String>,
    /// Radians (true) or metres.
    pub angular: bool,
    /// (position m, value, U) in SI units.
    pub values: Vec<(f64, f64, f64)>,
}

impl ErrorFunction {
    /// The entry of largest |value|.
    pub fn largest(&self) -> Option<(f64, f64, f64)> {
        self.values
            .iter()
            .copied()
            .max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))
    }

    /// The worst conformance over every position.
    pub fn conformance(&self, tolerance: f64) -> Option<Conformance> {
        self.values
            .iter()
            .map(|(_, v, u)| Conformance::of(*v, *u, tolerance))
            .max()
    }

    /// The value in its display unit (µm or arcsec) and the unit's name.
    fn shown(&self, si: f64) -> (f64, &'static str) {
        if self.angular {
            (arcsec(si), "″")
        } else {
            (si * 1e6, "µm")
        }
    }
}

pub fn section(inputs: &Inputs, kind: &KindReport) -> anyhow::Result<Vec<Section>> {
    let tolerances = declared_tolerances(inputs)?;
    let functions = error_functions(inputs)?;
    let plan_kind = crate::kinds::registry::Registry::standard().named(inputs.kind()?);
    let mut section = Section::new("summary", "Summary");
    let (tone, verdict) = match &functions {
        None if plan_kind.is_some_and(|k| k.has_error_functions()) => (
            Tone::Neutral,
            "tolerances: not checked (the error functions and the session.mcap beside the \
             results are needed for their uncertainty budget)"
                .to_owned(),
        ),
        None => (
            Tone::Neutral,
            format!(
                "tolerances: not checked for {} results (they have no error functions to \
                 check against [report] tolerance_um and tolerance_arcsec)",
                inputs.kind()?
            ),
        ),
        Some(_) => tolerance_verdict(&functions, &tolerances),
    };
    section = section.badge(tone, verdict);
    let mut facts = kind.summary.clone();
    if let Some(functions) = &functions {
        // The table gives the largest errors with their U: the kind's per-function maxima
        // would repeat it.
        facts.retain(|(name, _)| !name.starts_with("max |E") && !name.starts_with("squareness E"));
        let mut table = Table::new(
            &format!(
                "The largest errors (up to {LARGEST_SHOWN} of lengths and {LARGEST_SHOWN} of \
                 angles), each at the position of its largest |value|, with U (k = 2) from \
                 the uncertainty budget"
            ),
            &COLUMNS,
        );
        for row in largest_rows(functions, &tolerances) {
            table.row(row);
        }
        if !table.rows.is_empty() {
            section = section.table(table);
        }
    }
    section = match &inputs.diagnosis {
        Some(d) => section.badge(
            super::diagnosis::tone(d),
            format!("diagnosis: {}", super::diagnosis::verdict(d)),
        ),
        None if plan_kind.is_some_and(|k| k.diagnosable() || k.has_residual_model()) => section
            .paragraph(
                "Diagnosis: not made (write it beside the results with `geocal diagnose \
             DIR/session.mcap --json > DIR/diagnosis.json`).",
            ),
        None => section,
    };
    Ok(vec![section.facts(facts)])
}

/// `[report]` of the stored run configuration beside the results (none: nothing declared).
fn declared_tolerances(inputs: &Inputs) -> anyhow::Result<ReportConfig> {
    let Some(path) = config_beside(&inputs.results_path) else {
        return Ok(ReportConfig::default());
    };
    let text =
        std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    Ok(ReportConfig::of_config_text(&text, &path)?)
}

fn config_beside(results: &Path) -> Option<std::path::PathBuf> {
    results
        .parent()
        .map(|d| d.join(crate::run::resume::CONFIG_FILE))
        .filter(|p| p.is_file())
}

/// The kind's error functions with budgets (the session is needed for the material
/// temperature); None for kinds without them or without the session.
fn error_functions(inputs: &Inputs) -> anyhow::Result<Option<Vec<ErrorFunction>>> {
    let Some(session) = &inputs.session else {
        return Ok(None);
    };
    let Some(kind) = crate::kinds::registry::Registry::standard().named(inputs.kind()?) else {
        return Ok(None);
    };
    if !kind.has_error_functions() {
        return Ok(None);
    }
    let config = match config_beside(&inputs.results_path) {
        Some(path) => Some(crate::config::Config::load(&path)?),
        None => None,
    };
    Ok(kind
        .evaluated_errors(&inputs.results, session, config.as_ref())?
        .map(|e| functions_of(&e.evaluation, &e.geometric)))
}

/// Every identifiable error function of the evaluation, positioning errors at 20 °C.
pub fn functions_of(
    evaluation: &TracerEvaluation,
    geometric: &serde_json::Value,
) -> Vec<ErrorFunction> {
    let identifiable = |axis: &str, name: &str| {
        geometric
            .pointer(&format!("/axes/{axis}/errors/{name}/identifiable"))
            .and_then(|i| i.as_bool())
            .unwrap_or(true)
    };
    let of = |budgets: &[Option<Budget>], positions: &[f64]| -> Vec<(f64, f64, f64)> {
        positions
            .iter()
            .zip(budgets)
            .filter_map(|(x, b)| b.as_ref().map(|b| (*x, b.value, b.expanded_uncertainty)))
            .collect()
    };
    let mut out = Vec::new();
    for p in &evaluation.positioning {
        let c = &p.curve;
        if identifiable(&c.axis, &c.error) {
            out.push(ErrorFunction {
                name: c.error.clone(),
                axis: Some(c.axis.clone()),
                angular: false,
                values: of(&p.budgets, &c.positions_m),
            });
        }
    }
    for f in &evaluation.functions {
        if identifiable(&f.axis, &f.error) {
            out.push(ErrorFunction {
                name: f.error.clone(),
                axis: Some(f.axis.clone()),
                angular: f.unit == "rad",
                values: of(&f.budgets, &f.positions_m),
            });
        }
    }
    for b in &evaluation.squareness {
        out.push(ErrorFunction {
            name: b.quantity.clone(),
            axis: None,
            angular: true,
            values: vec![(0.0, b.value, b.expanded_uncertainty)],
        });
    }
    out.retain(|f| !f.values.is_empty());
    out
}

fn tolerance_of(f: &ErrorFunction, t: &ReportConfig) -> Option<f64> {
    if f.angular {
        t.tolerance_arcsec.map(|a| (a / 3600.0).to_radians())
    } else {
        t.tolerance_um.map(|u| u * 1e-6)
    }
}

/// The box's headline: conformance of every checked function, or what is missing.
pub fn tolerance_verdict(
    functions: &Option<Vec<ErrorFunction>>,
    t: &ReportConfig,
) -> (Tone, String) {
    if t.tolerance_um.is_none() && t.tolerance_arcsec.is_none() {
        return (
            Tone::Neutral,
            "no tolerances declared ([report] tolerance_um, tolerance_arcsec in the \
             configuration)"
                .into(),
        );
    }
    let Some(functions) = functions else {
        return (
            Tone::Neutral,
            "tolerances declared, not checked: these results have no error functions with \
             budgets (a multilateration with its session)"
                .into(),
        );
    };
    let mut zones = Vec::new();
    if let Some(u) = t.tolerance_um {
        zones.push(format!("±{u} µm"));
    }
    if let Some(a) = t.tolerance_arcsec {
        zones.push(format!("±{a}″"));
    }
    let checked: Vec<(&ErrorFunction, Conformance)> = functions
        .iter()
        .filter_map(|f| Some((f, f.conformance(tolerance_of(f, t)?)?)))
        .collect();
    let worst = checked.iter().map(|(_, c)| *c).max();
    let named = |c: Conformance| -> String {
        checked
            .iter()
            .filter(|(_, k)| *k == c)
            .map(|(f, _)| label(f))
            .collect::<Vec<_>>()
            .join(", ")
    };
    let zones = zones.join(", ");
    let n = checked.len();
    match worst {
        None => (
            Tone::Neutral,
            format!("tolerances {zones}: no error function to check"),
        ),
        Some(Conformance::Conforms) => (
            Tone::Good,
            format!("PASS: all {n} error functions within {zones} (|e| + U ≤ T, ISO 14253-1)"),
        ),
        Some(Conformance::Undecided) => (
            Tone::Neutral,
            format!(
                "UNDECIDED against {zones}: {} within U of the limit; the other functions conform",
                named(Conformance::Undecided)
            ),
        ),
        Some(Conformance::DoesNotConform) => (
            Tone::Bad,
            format!(
                "FAIL against {zones}: {} beyond the tolerance by more than U",
                named(Conformance::DoesNotConform)
            ),
        ),
    }
}

/// "EXX along x", or the squareness's name.
fn label(f: &ErrorFunction) -> String {
    match &f.axis {
        Some(axis) => format!("{} along {axis}", f.name),
        None => f.name.clone(),
    }
}

/// The rows of the largest errors: up to `LARGEST_SHOWN` lengths, then angles.
pub fn largest_rows(functions: &[ErrorFunction], t: &ReportConfig) -> Vec<Vec<String>> {
    let mut rows = Vec::new();
    for angular in [false, true] {
        let mut of_unit: Vec<(&ErrorFunction, (f64, f64, f64))> = functions
            .iter()
            .filter(|f| f.angular == angular)
            .filter_map(|f| Some((f, f.largest()?)))
            .collect();
        of_unit.sort_by(|a, b| b.1 .1.abs().total_cmp(&a.1 .1.abs()));
        for (f, (x, value, expanded)) in of_unit.into_iter().take(LARGEST_SHOWN) {
            let (v, unit) = f.shown(value);
            let (u, _) = f.shown(expanded);
            let tolerance = tolerance_of(f, t);
            rows.push(vec![
                f.name.clone(),
                match &f.axis {
                    Some(axis) => format!("{axis} = {x:.3} m"),
                    None => "squareness".into(),
                },
                format!("{v:.3} {unit}"),
                format!("{u:.3} {unit}"),
                tolerance.map_or("—".into(), |tol| format!("±{:.3} {unit}", f.shown(tol).0)),
                tolerance
                    .and_then(|tol| f.conformance(tol))
                    .map_or("—".into(), |c| c.text().to_owned()),
            ]);
        }
    }
    rows
}

#[cfg(test)]
mod tests {
    use super::*;

    fn function(name: &str, angular: bool, values: &[(f64, f64)]) -> ErrorFunction {
        ErrorFunction {
            name: name.into(),
            axis: Some("x".into()),
            angular,
            values: values
                .iter()
                .enumerate()
                .map(|(k, (v, u))| (0.1 * k as f64, *v, *u))
                .collect(),
        }
    }

    #[test]
    fn the_decision_rule_and_the_largest_errors() {
        assert_eq!(Conformance::of(-4e-6, 1e-6, 5e-6), Conformance::Conforms);
        assert_eq!(Conformance::of(4.5e-6, 1e-6, 5e-6), Conformance::Undecided);
        assert_eq!(
            Conformance::of(7e-6, 1e-6, 5e-6),
            Conformance::DoesNotConform
        );
        let functions = vec![
            function("EXX", false, &[(1e-6, 1e-7), (-6e-6, 2e-7)]),
            function("EYX", false, &[(2e-6, 1e-7)]),
            function("EZX", false, &[(3e-6, 1e-7)]),
            function("EBX", true, &[(1e-6, 1e-7)]),
            function("ECX", false, &[(0.5e-6, 1e-7)]),
        ];
        let t = ReportConfig {
            tolerance_um: Some(5.0),
            tolerance_arcsec: None,
        };
        let rows = largest_rows(&functions, &t);
        let names: Vec<&str> = rows.iter().map(|r| r[0].as_str()).collect();
        assert_eq!(names, ["EXX", "EZX", "EYX", "EBX"]);
        assert_eq!(rows[0][2], "-6.000 µm");
        assert_eq!(rows[0][5], "does not conform");
        assert_eq!(rows[3][4], "—");
        let (tone, text) = tolerance_verdict(&Some(functions.clone()), &t);
        assert_eq!(tone, Tone::Bad);
        assert!(
            text.starts_with("FAIL") && text.contains("EXX along x"),
            "{text}"
        );
        let loose = ReportConfig {
            tolerance_um: Some(10.0),
            tolerance_arcsec: Some(10.0),
        };
        assert_eq!(tolerance_verdict(&Some(functions), &loose).0, Tone::Good);
        assert_eq!(
            tolerance_verdict(&None, &ReportConfig::default()).0,
            Tone::Neutral
        );
    }
}
