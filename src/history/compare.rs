//! `geocal compare A B`: has the machine changed between two runs? Per parameter the
//! difference B − A, its combined standard uncertainty, z, and its significance after the
//! Holm–Bonferroni correction for the number of parameters compared; tolerance exceedance;
//! text, JSON (geocal-compare/1) and a report section with the difference curves.

use serde::Serialize;

use super::load::{MachineIdentity, Run};
use super::parameters::{parameters, Parameter, Parameters};
use super::stats::{holm, two_sided_p};

/// The JSON format of a comparison.
pub const COMPARE_FORMAT: &str = "geocal-compare/1";

/// Positions along a curve closer than this are the same position (metres or radians).
const SAME_POSITION: f64 = 1e-9;

/// Allowed change of a parameter, by its unit.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Tolerances {
    /// Parameters in metres.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub m: Option<f64>,
    /// Parameters in radians.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rad: Option<f64>,
    /// Parameters whose results state no unit.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub other: Option<f64>,
}

impl Tolerances {
    pub fn of(&self, unit: &str) -> Option<f64> {
        match unit {
            "m" => self.m,
            "rad" => self.rad,
            _ => self.other,
        }
    }

    pub fn check(&self) -> anyhow::Result<()> {
        for (name, t) in [("m", self.m), ("rad", self.rad), ("other", self.other)] {
            if let Some(t) = t {
                if !(t.is_finite() && t > 0.0) {
                    anyhow::bail!("tolerance ({name}): expected a positive number, found {t}");
                }
            }
        }
        Ok(())
    }
}

/// The choices of a comparison.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct CompareOptions {
    /// Family-wise significance level (the probability of calling any unchanged parameter
    /// changed).
    pub alpha: f64,
    pub tolerances: Tolerances,
}

impl Default for CompareOptions {
    fn default() -> Self {
        CompareOptions {
            alpha: 0.05,
            tolerances: Tolerances::default(),
        }
    }
}

impl CompareOptions {
    pub fn check(&self) -> anyhow::Result<()> {
        if !(self.alpha > 0.0 && self.alpha < 1.0) {
            anyhow::bail!(
                "significance level: expected a number between 0 and 1, found {}",
                self.alpha
            );
        }
        self.tolerances.check()
    }
}

/// A run as a comparison names it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RunRef {
    pub label: String,
    pub session_id: String,
    pub started_at: String,
    pub results: String,
}

impl RunRef {
    pub fn of(run: &Run) -> RunRef {
        RunRef {
            label: run.label.clone(),
            session_id: run.session_id.clone(),
            started_at: run.started_text(),
            results: run.results_path.display().to_string(),
        }
    }
}

/// One parameter in both runs.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ParameterChange {
    /// Its name (docs/history.md, "Which parameters").
    pub id: String,
    /// Its JSON path in the results.
    pub path: String,
    pub curve: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub x: Option<f64>,
    #[serde(skip_serializing_if = "String::is_empty")]
    pub x_unit: String,
    pub unit: String,
    pub a: f64,
    pub sigma_a: f64,
    pub b: f64,
    pub sigma_b: f64,
    /// b − a.
    pub difference: f64,
    /// √(σ_a² + σ_b²): the runs' noise is independent.
    pub sigma: f64,
    pub z: f64,
    /// Two-sided p of |z| for one parameter alone.
    pub p: f64,
    /// p adjusted by Holm–Bonferroni over every parameter compared.
    pub p_adjusted: f64,
    pub significant: bool,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tolerance: Option<f64>,
    /// |difference| > tolerance (None without a tolerance for its unit).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub exceeds_tolerance: Option<bool>,
}

/// geocal-compare/1.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Comparison {
    pub format: String,
    pub kind: String,
    pub machine: MachineIdentity,
    pub a: RunRef,
    pub b: RunRef,
    /// "holm-bonferroni".
    pub correction: String,
    pub alpha: f64,
    pub tolerances: Tolerances,
    /// Parameters compared (the size of the family the correction is over).
    pub compared: usize,
    /// Ids of the parameters that changed significantly, largest |z| first.
    pub significant: Vec<String>,
    /// Ids of the parameters whose change exceeds their tolerance.
    pub exceeding_tolerance: Vec<String>,
    /// Parameters with a σ in one run only (not identifiable in the other), not compared.
    pub only_in_a: Vec<String>,
    pub only_in_b: Vec<String>,
    pub notes: Vec<String>,
    pub parameters: Vec<ParameterChange>,
}

impl Comparison {
    /// Whether anything calls for attention: a significant change or a tolerance breach.
    pub fn changed(&self) -> bool {
        !self.significant.is_empty() || !self.exceeding_tolerance.is_empty()
    }
}

/// Why two runs cannot be compared (or a series not trended), said plainly.
pub fn check_comparable(a: &Run, b: &Run) -> anyhow::Result<Vec<String>> {
    let mut notes = Vec::new();
    if a.kind != b.kind {
        anyhow::bail!(
            "{} is a {} run and {} a {} run: runs of different kinds measure different \
             parameters and cannot be compared",
            a.label,
            a.kind,
            b.label,
            b.kind
        );
    }
    match (a.machine.is_known(), b.machine.is_known()) {
        (true, true) if !a.machine.same_machine(&b.machine) => anyhow::bail!(
            "{} calibrated \"{}\" (key {}) and {} calibrated \"{}\" (key {}): runs of \
             different machines cannot be compared (a machine is its [machine] id, else its \
             name and serial together)",
            a.label,
            a.machine.label(),
            a.machine.key(),
            b.label,
            b.machine.label(),
            b.machine.key()
        ),
        (true, true) => {}
        _ => notes.push(format!(
            "the machine of {} is not known (no configuration or session beside its \
             results): taken to be the same machine",
            if a.machine.is_known() {
                &b.label
            } else {
                &a.label
            }
        )),
    }
    if let (Some(pa), Some(pb)) = (&a.plan, &b.plan) {
        if pa.source == pb.source && pa.sha256 != pb.sha256 {
            notes.push(
                "the plans differ: compared only because they measure the same parameters \
                 at the same positions"
                    .into(),
            );
        }
    }
    Ok(notes)
}

/// Check that a parameter's position is the same in both runs: a different plan grid or
/// table angle is a different parameter.
pub fn check_positions(a: &Run, pa: &Parameter, b: &Run, pb: &Parameter) -> anyhow::Result<()> {
    match (pa.x, pb.x) {
        (Some(xa), Some(xb)) if (xa - xb).abs() > SAME_POSITION => anyhow::bail!(
            "incompatible plans: `{}` lies at {xa} {} in {} and at {xb} {} in {}: the runs \
             measured at different positions",
            pa.id,
            pa.x_unit,
            a.label,
            pb.x_unit,
            b.label
        ),
        _ => Ok(()),
    }
}

/// Compare run `a` (before) with run `b` (after).
pub fn compare(a: &Run, b: &Run, options: &CompareOptions) -> anyhow::Result<Comparison> {
    options.check()?;
    let mut notes = check_comparable(a, b)?;
    let params_a = parameters(&a.results);
    let params_b = parameters(&b.results);
    for (run, p) in [(a, &params_a), (b, &params_b)] {
        if p.sigma_scale > 1.0 {
            notes.push(format!(
                "{}: the fit is flagged as a misfit: its σ are scaled by {:.2}",
                run.label, p.sigma_scale
            ));
        }
    }
    let mut changes = Vec::new();
    for pa in &params_a.parameters {
        // Matched by path: a parameter at another position is an incompatible plan.
        let Some(pb) = params_b.at_path(&pa.path) else {
            continue;
        };
        check_positions(a, pa, b, pb)?;
        changes.push(change(pa, pb, &options.tolerances));
    }
    let only = |x: &Parameters, y: &Parameters| -> Vec<String> {
        x.parameters
            .iter()
            .filter(|p| y.at_path(&p.path).is_none())
            .map(|p| p.id.clone())
            .collect()
    };
    let (only_in_a, only_in_b) = (only(&params_a, &params_b), only(&params_b, &params_a));
    if changes.is_empty() {
        anyhow::bail!(
            "{} and {} have no parameter with a standard uncertainty in common: nothing to \
             compare",
            a.label,
            b.label
        );
    }
    if !(only_in_a.is_empty() && only_in_b.is_empty()) {
        notes.push(format!(
            "{} parameters have a σ in one run only (not identifiable in the other) and are \
             not compared",
            only_in_a.len() + only_in_b.len()
        ));
    }
    let p: Vec<f64> = changes.iter().map(|c| c.p).collect();
    for (c, adjusted) in changes.iter_mut().zip(holm(&p)) {
        c.p_adjusted = adjusted;
        c.significant = adjusted <= options.alpha;
    }
    let mut significant: Vec<&ParameterChange> = changes.iter().filter(|c| c.significant).collect();
    significant.sort_by(|x, y| y.z.abs().total_cmp(&x.z.abs()));
    let significant = significant.iter().map(|c| c.id.clone()).collect();
    let exceeding_tolerance = changes
        .iter()
        .filter(|c| c.exceeds_tolerance == Some(true))
        .map(|c| c.id.clone())
        .collect();
    let machine = if a.machine.is_known() {
        a.machine.clone()
    } else {
        b.machine.clone()
    };
    Ok(Comparison {
        format: COMPARE_FORMAT.into(),
        kind: a.kind.clone(),
        machine,
        a: RunRef::of(a),
        b: RunRef::of(b),
        correction: "holm-bonferroni".into(),
        alpha: options.alpha,
        tolerances: options.tolerances,
        compared: changes.len(),
        significant,
        exceeding_tolerance,
        only_in_a,
        only_in_b,
        notes,
        parameters: changes,
    })
}

fn change(pa: &Parameter, pb: &Parameter, tolerances: &Tolerances) -> ParameterChange {
    let difference = pb.value - pa.value;
    let sigma = pa.sigma.hypot(pb.sigma);
    let z = difference / sigma;
    let tolerance = tolerances.of(&pa.unit);
    ParameterChange {
        id: pa.id.clone(),
        path: pa.path.clone(),
        curve: pa.curve.clone(),
        x: pa.x,
        x_unit: pa.x_unit.clone(),
        unit: pa.unit.clone(),
        a: pa.value,
        sigma_a: pa.sigma,
        b: pb.value,
        sigma_b: pb.sigma,
        difference,
        sigma,
        z,
        p: two_sided_p(z),
        p_adjusted: 1.0,
        significant: false,
        tolerance,
        exceeds_tolerance: tolerance.map(|t| difference.abs() > t),
    }
}

/// A value in display units: µm for metres, µrad for radians.
pub fn display(value: f64, unit: &str) -> (f64, &'static str) {
    match unit {
        "m" => (value * 1e6, "µm"),
        "rad" => (value * 1e6, "µrad"),
        _ => (value, ""),
    }
}

fn shown(value: f64, unit: &str) -> String {
    let (v, u) = display(value, unit);
    if u.is_empty() {
        format!("{v:.4e}")
    } else {
        format!("{v:.3} {u}")
    }
}

/// How many changed parameters the text lists.
const TEXT_ROWS: usize = 30;

/// The comparison as people read it.
pub fn text(c: &Comparison) -> String {
    let mut out = format!(
        "Comparison of {} runs of {}\n  A: {} (session {}, {})\n  B: {} (session {}, {})\n",
        c.kind,
        c.machine.label(),
        c.a.label,
        c.a.session_id,
        c.a.started_at,
        c.b.label,
        c.b.session_id,
        c.b.started_at
    );
    out += &format!(
        "  {} parameters compared; significance at {} after the Holm–Bonferroni correction \
         for {} parameters\n",
        c.compared, c.alpha, c.compared
    );
    for note in &c.notes {
        out += &format!("  note: {note}\n");
    }
    let row = |p: &ParameterChange| {
        format!(
            "  {:<52} {:>14} ± {:<14} z {:>6.2}  p_adj {:.2e}{}\n",
            p.id,
            shown(p.difference, &p.unit),
            shown(p.sigma, &p.unit),
            p.z,
            p.p_adjusted,
            match p.exceeds_tolerance {
                Some(true) => "  beyond tolerance",
                _ => "",
            }
        )
    };
    if c.significant.is_empty() {
        out += "\nNo significant change.\n";
    } else {
        out += &format!(
            "\nSignificant changes (B − A ± combined σ), {}:\n",
            c.significant.len()
        );
        for id in c.significant.iter().take(TEXT_ROWS) {
            if let Some(p) = c.parameters.iter().find(|p| &p.id == id) {
                out += &row(p);
            }
        }
        if c.significant.len() > TEXT_ROWS {
            out += &format!("  … {} more in the JSON\n", c.significant.len() - TEXT_ROWS);
        }
    }
    if c.tolerances != Tolerances::default() {
        if c.exceeding_tolerance.is_empty() {
            out += "No change beyond its tolerance.\n";
        } else {
            out += &format!(
                "Changes beyond their tolerance, {}:\n",
                c.exceeding_tolerance.len()
            );
            for id in c.exceeding_tolerance.iter().take(TEXT_ROWS) {
                if let Some(p) = c.parameters.iter().find(|p| &p.id == id) {
                    out += &row(p);
                }
            }
        }
    }
    let largest = c
        .parameters
        .iter()
        .max_by(|x, y| x.z.abs().total_cmp(&y.z.abs()));
    if let Some(p) = largest {
        out += &format!("Largest |z|: {} (z = {:.2})\n", p.id, p.z);
    }
    out
}

/// The report: a summary, the changed parameters and the difference curves with ±2σ bands.
pub fn document(c: &Comparison) -> anyhow::Result<crate::document::Document> {
    use crate::document::{Document, Section, Table};
    let mut facts = vec![
        ("machine".into(), c.machine.label()),
        ("kind".into(), c.kind.clone()),
        (
            "A (before)".into(),
            format!(
                "{} — session {}, {}",
                c.a.label, c.a.session_id, c.a.started_at
            ),
        ),
        (
            "B (after)".into(),
            format!(
                "{} — session {}, {}",
                c.b.label, c.b.session_id, c.b.started_at
            ),
        ),
        ("parameters compared".into(), c.compared.to_string()),
        (
            "significance".into(),
            format!(
                "{} family-wise, Holm–Bonferroni over {} parameters",
                c.alpha, c.compared
            ),
        ),
        (
            "significant changes".into(),
            c.significant.len().to_string(),
        ),
    ];
    if c.tolerances != Tolerances::default() {
        facts.push((
            "beyond tolerance".into(),
            c.exceeding_tolerance.len().to_string(),
        ));
    }
    let mut summary = Section::new("comparison", "Comparison").facts(facts);
    for note in &c.notes {
        summary = summary.paragraph(format!("Note: {note}"));
    }
    let mut table = Table::new(
        "Changed parameters: B − A with its combined standard uncertainty",
        &["parameter", "B − A", "σ", "z", "p (Holm)", "tolerance"],
    );
    for p in c
        .parameters
        .iter()
        .filter(|p| p.significant || p.exceeds_tolerance == Some(true))
    {
        table.row(vec![
            p.id.clone(),
            shown(p.difference, &p.unit),
            shown(p.sigma, &p.unit),
            format!("{:.2}", p.z),
            format!("{:.2e}", p.p_adjusted),
            match (p.tolerance, p.exceeds_tolerance) {
                (Some(t), Some(true)) => format!("beyond {}", shown(t, &p.unit)),
                (Some(t), _) => format!("within {}", shown(t, &p.unit)),
                _ => "—".into(),
            },
        ]);
    }
    summary = if table.rows.is_empty() {
        summary.paragraph("No parameter changed significantly or beyond its tolerance.")
    } else {
        summary.table(table)
    };
    let mut sections = vec![summary];
    if let Some(plot) = difference_plot(c)? {
        sections.push(
            Section::new("differences", "Differences B − A with ±2σ")
                .paragraph(
                    "Each curve is the difference of one parameter along its positions, with \
                     the band of twice its combined standard uncertainty: a change is real \
                     where the curve leaves the band (by more than the correction for the \
                     number of parameters allows).",
                )
                .plot(plot),
        );
    }
    Ok(Document {
        title: format!(
            "geocal comparison: {}, {} vs {}",
            c.machine.label(),
            c.a.label,
            c.b.label
        ),
        sections,
    })
}

/// One panel per curve (lone figures gathered in one panel by index), difference ± 2σ.
fn difference_plot(c: &Comparison) -> anyhow::Result<Option<crate::document::Plot>> {
    use crate::document::plots::{panels_svg, Panel, Series, Style};
    let mut curves: Vec<(String, Vec<&ParameterChange>)> = Vec::new();
    for p in &c.parameters {
        match curves.iter_mut().find(|(name, _)| name == &p.curve) {
            Some((_, members)) => members.push(p),
            None => curves.push((p.curve.clone(), vec![p])),
        }
    }
    let mut panels = Vec::new();
    let mut lone: Vec<&ParameterChange> = Vec::new();
    for (curve, members) in &curves {
        if members.len() < 2 {
            lone.extend(members.iter().copied());
            continue;
        }
        let unit = display(1.0, &members[0].unit).1;
        let x_unit = &members[0].x_unit;
        let (xs, scale_x) = match x_unit.as_str() {
            "m" => ("position / m", 1.0),
            "rad" => ("angle / °", 180.0 / std::f64::consts::PI),
            _ => ("index", 1.0),
        };
        let points: Vec<(f64, f64)> = members
            .iter()
            .map(|p| {
                (
                    p.x.unwrap_or(0.0) * scale_x,
                    display(p.difference, &p.unit).0,
                )
            })
            .collect();
        let band = members
            .iter()
            .map(|p| 2.0 * display(p.sigma, &p.unit).0)
            .collect();
        panels.push(Panel {
            title: short(curve),
            x_label: xs.into(),
            y_label: format!("B − A / {unit}"),
            series: vec![Series::line("B − A", points).with_band(band)],
        });
    }
    // Lone figures by unit, one panel each, against their index.
    for unit in ["m", "rad", ""] {
        let members: Vec<&&ParameterChange> = lone.iter().filter(|p| p.unit == unit).collect();
        if members.is_empty() {
            continue;
        }
        let points = members
            .iter()
            .enumerate()
            .map(|(i, p)| (i as f64, display(p.difference, unit).0))
            .collect();
        let band = members
            .iter()
            .map(|p| 2.0 * display(p.sigma, unit).0)
            .collect();
        let names: Vec<String> = members
            .iter()
            .enumerate()
            .map(|(i, p)| format!("{i}: {}", short(&p.id)))
            .collect();
        panels.push(Panel {
            title: format!("single figures ({})", names.join(", ")),
            x_label: "figure".into(),
            y_label: format!("B − A / {}", display(1.0, unit).1),
            series: vec![Series::line("B − A", points)
                .with_band(band)
                .with_style(Style::Points)],
        });
    }
    if panels.is_empty() {
        return Ok(None);
    }
    let svg = panels_svg("Differences B − A with ±2σ bands", &panels, 3)?;
    Ok(Some(crate::document::Plot {
        id: "compare-differences".into(),
        caption: format!("{} parameters in {} panels", c.compared, panels.len()),
        svg,
    }))
}

/// A curve's name without the results' block names that say nothing to a reader.
pub fn short(id: &str) -> String {
    id.replace("geometric_errors.axes.", "")
        .replace("geometric_errors.", "")
        .replace(".errors.", " ")
        .replace(".values", "")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run(label: &str, machine: &str, squareness: f64, exx: [f64; 2]) -> Run {
        let results = serde_json::json!({
            "format": "geocal-results/1", "kind": "multilateration", "session_id": label,
            "geometric_errors": {
                "axes": {"x": {"positions_m": [0.1, 0.5, 0.9], "errors": {
                    "EXX": {"unit": "m", "values": [0.0, exx[0], exx[1]],
                            "sigma": [0.0, 1e-7, 1e-7]}}}},
                "squareness": {"EB0Z": {"value_rad": squareness, "sigma_rad": 1e-6}}
            }
        });
        Run::from_results(
            label,
            results,
            MachineIdentity {
                name: Some(machine.into()),
                serial: None,
                id: None,
            },
            None,
        )
        .expect("run")
    }

    #[test]
    fn names_only_the_changed_parameter() {
        let a = run("a", "M", 1e-6, [1e-6, 2e-6]);
        let b = run("b", "M", 9e-6, [1.05e-6, 2.02e-6]);
        let c = compare(&a, &b, &CompareOptions::default()).expect("compare");
        assert_eq!(c.compared, 3);
        assert_eq!(c.significant, ["EB0Z"]);
        let sq = &c.parameters[2];
        assert!((sq.z - 8e-6 / 2f64.sqrt() / 1e-6).abs() < 1e-9, "{sq:?}");
        assert!(text(&c).contains("EB0Z"));
        let doc = document(&c).expect("document");
        assert_eq!(doc.plots().count(), 1);
    }

    #[test]
    fn tolerance_is_on_the_difference() {
        let a = run("a", "M", 1e-6, [1e-6, 2e-6]);
        let b = run("b", "M", 1e-6, [1.05e-6, 2.5e-6]);
        let options = CompareOptions {
            tolerances: Tolerances {
                m: Some(3e-7),
                ..Default::default()
            },
            ..Default::default()
        };
        let c = compare(&a, &b, &options).expect("compare");
        assert_eq!(c.exceeding_tolerance, ["EXX@x=0.900"]);
    }

    #[test]
    fn refuses_other_machines_and_kinds() {
        let a = run("a", "M", 1e-6, [1e-6, 2e-6]);
        let b = run("b", "N", 1e-6, [1e-6, 2e-6]);
        let e = compare(&a, &b, &CompareOptions::default()).expect_err("refused");
        assert!(e.to_string().contains("different machines"), "{e}");
        let mut h = run("h", "M", 1e-6, [1e-6, 2e-6]);
        h.kind = "hexapod".into();
        let e = compare(&a, &h, &CompareOptions::default()).expect_err("refused");
        assert!(e.to_string().contains("different kinds"), "{e}");
    }

    #[test]
    fn refuses_a_plan_with_other_positions() {
        let a = run("a", "M", 1e-6, [1e-6, 2e-6]);
        let mut b = run("b", "M", 1e-6, [1e-6, 2e-6]);
        b.results["geometric_errors"]["axes"]["x"]["positions_m"] =
            serde_json::json!([0.1, 0.6, 0.9]);
        let e = compare(&a, &b, &CompareOptions::default()).expect_err("refused");
        assert!(e.to_string().contains("incompatible plans"), "{e}");
    }
}
