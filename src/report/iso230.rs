//! The report's ISO 230-2 section: one table per axis (rows ↑, ↓, ↕; columns E, M, R, B, A
//! in µm or arcsec) with the standard's verdict as a badge, and the plan's departures from the
//! standard and how the deviations were obtained as footnotes, each stated once.

use crate::document::{note_mark, KindReport, Section, Table, Tone};
use crate::evaluate::iso230_2::{AxisType, Evaluation};
use crate::evaluate::Iso230_2;

use super::Inputs;

/// The column heads after the direction: the figures' symbols, each with the unit.
pub const FIGURES: [&str; 5] = ["E", "M", "R", "B", "A"];

/// ISO 230-2 figures of every positioning curve the session holds (docs/iso230-2.md). The
/// per-run deviations need the network solve: the session is solved again with the default
/// settings (as `geocal solve` does).
pub fn section(inputs: &Inputs, _: &KindReport) -> anyhow::Result<Vec<Section>> {
    let Some(session) = &inputs.session else {
        return Ok(Vec::new());
    };
    let by_network = crate::kinds::registry::Registry::standard()
        .named(inputs.kind()?)
        .is_some_and(|k| k.reports_iso230_2());
    if !by_network {
        return Ok(Vec::new());
    }
    let iso = match &inputs.settled {
        // A streamed session: its settled windows, solved as `solve_session` solves them.
        Some(settled) => {
            let (results, _) =
                crate::method::multilateration::solve_settled(settled, &Default::default())?;
            let results = crate::method::Results::new(results);
            crate::evaluate::of_results_extracted(&results, Some(&settled.extraction))?
        }
        None => {
            let results = crate::kinds::registry::solve_session(session, &Default::default())?;
            crate::evaluate::of_results(&results, session)?
        }
    };
    Ok(vec![document(&iso)])
}

/// The section of an evaluation: per axis its verdict badge and its table, then the notes.
pub fn document(iso: &Iso230_2) -> Section {
    let mut notes = Footnotes::default();
    let mut section = Section::new("iso230-2", "ISO 230-2 positioning").paragraph(
        "Unidirectional (↑, ↓) and bidirectional (↕) positioning figures of ISO 230-2 from each \
         pass of the plan (one pass = one run, its direction from the approach; for a rotary \
         table, a run is consecutive table stations approached from one side): E systematic \
         positioning error, M mean bidirectional positioning error, R repeatability, B \
         reversal value, A accuracy (docs/iso230-2.md).",
    );
    // A note names the axes it was given for (by letter when every axis has one target),
    // unless it holds for every axis.
    let one_target = iso.axes.windows(2).all(|w| w[0].target == w[1].target);
    let label = |a: &crate::evaluate::AxisIso| {
        if one_target {
            a.axis.clone()
        } else {
            axis_name(a)
        }
    };
    let every_axis: Vec<String> = iso.axes.iter().map(label).collect();
    for a in &iso.axes {
        let name = axis_name(a);
        let short = label(a);
        let e = &a.evaluation;
        let departures: Vec<usize> = e
            .not_per_iso_230_2
            .iter()
            .map(|why| notes.mark(&format!("not per ISO 230-2: {why}"), &short))
            .collect();
        let how: Vec<usize> = a.notes.iter().map(|n| notes.mark(n, &short)).collect();
        let (tone, verdict) = if departures.is_empty() {
            (Tone::Good, "per ISO 230-2".to_owned())
        } else {
            (
                Tone::Neutral,
                format!("not per ISO 230-2 {}", marks(&departures)),
            )
        };
        section = section
            .badge(tone, format!("axis {name}: {verdict}"))
            .table(table(&name, e, &how));
    }
    for n in &iso.notes {
        notes.mark(&format!("ISO 230-2: {n}"), "");
    }
    section.notes(notes.texts(&every_axis))
}

/// "x (target t0)", or the rotary table's id.
pub fn axis_name(a: &crate::evaluate::AxisIso) -> String {
    match &a.target {
        Some(t) => format!("{} (target {t})", a.axis),
        None => a.axis.clone(),
    }
}

/// The figures' display unit and factor from SI: µm for a linear axis, arcsec for a rotary one.
pub fn display_unit(axis_type: AxisType) -> (f64, &'static str) {
    match axis_type {
        AxisType::Linear => (1e6, "µm"),
        AxisType::Rotary => (180.0 / std::f64::consts::PI * 3600.0, "arcsec"),
    }
}

/// A figure for a cell: three decimals in the display unit, "—" where the standard gives
/// none (s with one run, B and M of one direction).
pub fn figure(value: Option<f64>, factor: f64) -> String {
    crate::document::cell(value.map(|v| v * factor), 3)
}

fn table(name: &str, e: &Evaluation, how: &[usize]) -> Table {
    let (factor, unit) = display_unit(e.axis_type);
    let header: Vec<String> = std::iter::once("direction".to_owned())
        .chain(FIGURES.iter().map(|f| format!("{f} [{unit}]")))
        .collect();
    let header: Vec<&str> = header.iter().map(String::as_str).collect();
    let mut table = Table::new(
        format!(
            "Axis {name}: {} targets, runs ↑ {} ↓ {} {}",
            e.targets,
            e.runs_up,
            e.runs_down,
            marks(how)
        )
        .trim_end(),
        &header,
    );
    let f = e.figures();
    for (direction, d) in [("↑", &f.up), ("↓", &f.down)] {
        if let Some(d) = d {
            table.row(vec![
                direction.to_owned(),
                figure(Some(d.systematic_error), factor),
                figure(None, factor),
                figure(d.repeatability, factor),
                figure(None, factor),
                figure(d.accuracy, factor),
            ]);
        }
    }
    if let Some(b) = &f.bidirectional {
        table.row(vec![
            "↕".to_owned(),
            figure(Some(b.systematic_error), factor),
            figure(Some(b.mean_error), factor),
            figure(b.repeatability, factor),
            figure(Some(b.reversal), factor),
            figure(b.accuracy, factor),
        ]);
    }
    table
}

fn marks(notes: &[usize]) -> String {
    notes
        .iter()
        .map(|n| note_mark(*n))
        .collect::<Vec<_>>()
        .join(" ")
}

/// Notes in order of first mention, each with the axes it was given for.
#[derive(Default)]
struct Footnotes {
    notes: Vec<(String, Vec<String>)>,
}

impl Footnotes {
    /// The 1-based number of `text`, new or already given; `axis` joins its axes.
    fn mark(&mut self, text: &str, axis: &str) -> usize {
        let index = match self.notes.iter().position(|(t, _)| t == text) {
            Some(i) => i,
            None => {
                self.notes.push((text.to_owned(), Vec::new()));
                self.notes.len() - 1
            }
        };
        let axes = &mut self.notes[index].1;
        if !axis.is_empty() && !axes.iter().any(|a| a == axis) {
            axes.push(axis.to_owned());
        }
        index + 1
    }

    /// Each note's text, with its axes named unless it holds for every axis.
    fn texts(self, every_axis: &[String]) -> Vec<String> {
        self.notes
            .into_iter()
            .map(|(text, axes)| {
                if axes.is_empty() || axes.len() == every_axis.len() {
                    text
                } else if axes.len() == 1 {
                    format!("{text} (axis {})", axes[0])
                } else {
                    format!("{text} (axes {})", axes.join(", "))
                }
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::document::Block;
    use crate::evaluate::iso230_2::{evaluate, Curves};
    use crate::evaluate::AxisIso;

    fn axis(name: &str, runs: usize) -> AxisIso {
        let targets = vec![0.0, 0.1, 0.2];
        let run = |k: usize, sign: f64| -> Vec<f64> {
            targets
                .iter()
                .map(|t| sign * 1e-6 + 1e-5 * t + 1e-8 * k as f64)
                .collect()
        };
        let curves = Curves {
            axis_type: AxisType::Linear,
            targets: targets.clone(),
            up: (0..runs).map(|k| run(k, 1.0)).collect(),
            down: (0..runs).map(|k| run(k, -1.0)).collect(),
        };
        AxisIso {
            axis: name.into(),
            target: Some("t0".into()),
            source: String::new(),
            deviation_sigma_median_m: None,
            target_sigma_m: None,
            deviation_sigma_median_rad: None,
            target_sigma_rad: None,
            notes: vec!["runs are passes".into()],
            evaluation: evaluate(&curves).expect("evaluate"),
            curves,
        }
    }

    #[test]
    fn one_table_per_axis_and_each_note_once() {
        let iso = Iso230_2 {
            axes: vec![axis("x", 2), axis("y", 2)],
            notes: vec![],
        };
        let s = document(&iso);
        let tables: Vec<&Table> = s
            .blocks
            .iter()
            .filter_map(|b| match b {
                Block::Table(t) => Some(t),
                _ => None,
            })
            .collect();
        assert_eq!(tables.len(), 2);
        assert_eq!(tables[0].header[1], "E [µm]");
        let rows: Vec<&str> = tables[0].rows.iter().map(|r| r[0].as_str()).collect();
        assert_eq!(rows, ["↑", "↓", "↕"]);
        // B = x̄↑ − x̄↓ = 2 µm at every target; M of the mean curve = 1e-5 · 0.2 m = 2 µm.
        assert_eq!(tables[0].rows[2][4], "2.000");
        assert_eq!(tables[0].rows[2][2], "2.000");
        assert_eq!(tables[0].rows[0][2], "—");
        let notes = s
            .blocks
            .iter()
            .find_map(|b| match b {
                Block::Notes(n) => Some(n.clone()),
                _ => None,
            })
            .expect("notes");
        // Fewer than 5 runs (a departure) and the source note: once each, for both axes.
        assert_eq!(
            notes
                .iter()
                .filter(|n| n.contains("runs are passes"))
                .count(),
            1
        );
        assert!(notes.iter().all(|n| !n.contains("(axis")), "{notes:?}");
        assert!(notes.iter().any(|n| n.starts_with("not per ISO 230-2")));
        assert!(!s.blocks.iter().any(|b| matches!(b, Block::Preformatted(_))));
    }
}
