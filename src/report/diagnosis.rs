//! The report's diagnosis section (when diagnosis.json is beside the results): the verdict
//! first, where and how far in two lines, the table of candidate effects, then the residual
//! plot of `geocal diagnose --plot`, recomputed from the session with the default options.

use crate::diagnose::{Candidate, Diagnosis};
use crate::document::{KindReport, Plot, Section, Table, Tone};

use super::Inputs;

/// The candidates table's column heads.
pub const COLUMNS: [&str; 8] = [
    "effect",
    "parameters",
    "round",
    "χ² drop",
    "p",
    "ΔBIC",
    "held-out RMS after [nm]",
    "outcome",
];

pub fn section(inputs: &Inputs, _: &KindReport) -> anyhow::Result<Vec<Section>> {
    let Some(d) = &inputs.diagnosis else {
        return Ok(Vec::new());
    };
    let mut section = document(d);
    match &inputs.session_path {
        Some(path) => {
            let (_, residuals) =
                crate::kinds::diagnosis::diagnose_file_detailed(path, &Default::default())?;
            section = section.plot(Plot {
                id: "diagnosis-residuals".into(),
                caption: crate::diagnose::plot::title(&d.session_id, &residuals),
                svg: crate::diagnose::plot::svg(&d.session_id, &residuals)?,
            });
        }
        None => {
            section = section.paragraph("No session.mcap beside the results: no residual plot.");
        }
    }
    Ok(vec![section])
}

/// The verdict's tone: consistent with the noise is good, an unexplained gap bad, an effect
/// that explains it (or a noise model off by a factor) neither.
pub fn tone(d: &Diagnosis) -> Tone {
    if d.unexplained {
        Tone::Bad
    } else if d.selected.is_empty()
        && d.noise_scale.is_none()
        && !d.candidates.iter().any(|c| c.status == "confounded")
    {
        Tone::Good
    } else {
        Tone::Neutral
    }
}

/// The verdict in words, without the "verdict: " of the text report.
pub fn verdict(d: &Diagnosis) -> String {
    let line = crate::diagnose::verdict(d);
    line.strip_prefix("verdict: ").unwrap_or(&line).to_owned()
}

/// Everything but the plot: verdict badge, where and how far, the candidates, the notes.
pub fn document(d: &Diagnosis) -> Section {
    let summary = crate::diagnose::summary(d);
    let line = |prefix: &str| summary.iter().find(|l| l.starts_with(prefix)).cloned();
    let mut section = Section::new("diagnosis", "Diagnosis")
        .badge(tone(d), verdict(d))
        .paragraph(match &d.model {
            Some(m) => format!(
                "{} session {}, {} residuals ({}); noise floor {:.1} nm (the fitted RMS of \
                 its length residuals the noise model alone would give).",
                m.kind,
                d.session_id,
                d.observations,
                m.coordinates.join(", "),
                d.noise_floor_m * 1e9
            ),
            None => format!(
                "Session {}, {} lengths; noise floor {:.1} nm (the fitted RMS the noise model \
                 alone would give).",
                d.session_id,
                d.observations,
                d.noise_floor_m * 1e9
            ),
        });
    for prefix in ["where: ", "how far: ", "noise: ", "corrected calibration: "] {
        if let Some(text) = line(prefix) {
            section = section.paragraph(text);
        }
    }
    let rows = shown_candidates(d);
    if rows.is_empty() {
        section = section.paragraph("No candidate effect was tested.");
    } else {
        let mut table = Table::new(
            "Candidate effects: each tested against the model of its round (round 0: the \
             nominal model), its χ² drop, p-value and ΔBIC (negative: the data prefer the \
             effect), and the held-out RMS with it",
            &COLUMNS,
        );
        for c in rows {
            table.row(candidate_row(c, d));
        }
        section = section.table(table);
    }
    section
}

/// One row of the candidates table.
pub fn candidate_row(c: &Candidate, d: &Diagnosis) -> Vec<String> {
    let mut outcome = c.status.clone();
    if !c.confounded_with.is_empty() {
        outcome = format!("{outcome} (with {})", c.confounded_with.join(", "));
    }
    vec![
        c.effect.clone(),
        crate::diagnose::key_parameters(c, d),
        c.round.to_string(),
        format!("{:.1}", c.chi2_drop),
        format!("{:.1e}", c.p_value),
        format!("{:.1}", c.bic_delta),
        // A kind's residual model holds residuals of several units: its held-out RMS is in
        // units of each residual's σ.
        if d.model.is_some() {
            format!("{:.3} σ", c.heldout_rms_after_m)
        } else {
            format!("{:.1}", c.heldout_rms_after_m * 1e9)
        },
        outcome,
    ]
}

/// Each effect once: its selection if it was selected, else its last evaluation.
pub fn shown_candidates(d: &Diagnosis) -> Vec<&Candidate> {
    let mut out: Vec<&Candidate> = Vec::new();
    for c in &d.candidates {
        match out.iter_mut().find(|o| o.effect == c.effect) {
            Some(o) => {
                let selected = |x: &Candidate| x.status.starts_with("selected");
                if !selected(o) && (selected(c) || c.round >= o.round) {
                    *o = c;
                }
            }
            None => out.push(c),
        }
    }
    // Selected first (in their order of selection), then by the data's preference.
    out.sort_by(|a, b| {
        let rank = |c: &Candidate| d.selected.iter().position(|s| *s == c.effect);
        match (rank(a), rank(b)) {
            (Some(x), Some(y)) => x.cmp(&y),
            (Some(_), None) => std::cmp::Ordering::Less,
            (None, Some(_)) => std::cmp::Ordering::Greater,
            (None, None) => a.bic_delta.total_cmp(&b.bic_delta),
        }
    });
    out
}
