//! `geocal report`: the report people read, built from a run's results.json, the session
//! beside it (the one session reader) and, when present, its diagnosis.json, as a list of
//! sections each made by its own function, rendered to HTML or Markdown (src/document).

pub mod diagnosis;
pub mod header;
pub mod iso230;
pub mod session;
pub mod standards;
pub mod summary;
pub mod verification;

use std::path::{Path, PathBuf};

use anyhow::Context;

use crate::diagnose::Diagnosis;
use crate::document::{Document, KindReport, Section, Table};
use crate::extract::SettledSession;
use crate::kinds::registry::Registry;
use crate::session::reader::Session;
use crate::solve::misfit::{sigma_rows, Misfit};

/// What the report is made from: the results, and what lies beside them.
pub struct Inputs {
    pub results_path: PathBuf,
    pub results: serde_json::Value,
    /// The recorded session (`session.mcap` beside the results), when it is there. A clean
    /// multilateration file is streamed: `session` then holds every stream but the tracer
    /// samples (`tracers` empty) and `settled` its settled windows (`session::read`).
    pub session_path: Option<PathBuf>,
    pub session: Option<Session>,
    pub settled: Option<SettledSession>,
    /// `diagnosis.json` beside the results (geocal-diagnosis/1), when it is there.
    pub diagnosis_path: Option<PathBuf>,
    pub diagnosis: Option<Diagnosis>,
    /// A verification run's "before" results given by hand (`geocal report --before`).
    pub before_results: Option<PathBuf>,
}

/// One part of the report, built from the inputs and the kind's contribution. A builder whose
/// input is absent (no diagnosis.json, no session) returns no section or says what is missing.
pub type SectionBuilder = fn(&Inputs, &KindReport) -> anyhow::Result<Vec<Section>>;

/// The report's parts in order.
pub const SECTIONS: &[(&str, SectionBuilder)] = &[
    ("summary", summary::section),
    ("header", header::sections),
    ("misfit", misfit),
    ("kind", kind_sections),
    ("iso230-2", iso230::section),
    ("uncertainty", standards::uncertainty),
    ("verification", verification::sections),
    ("diagnosis", diagnosis::section),
];

/// Output formats of `geocal report`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    Html,
    Markdown,
}

impl Inputs {
    /// Read the inputs from a run directory (results.json inside) or a results file.
    pub fn read(path: &Path) -> anyhow::Result<Inputs> {
        let results_path = if path.is_dir() {
            path.join("results.json")
        } else {
            path.to_path_buf()
        };
        let dir = results_path
            .parent()
            .unwrap_or(Path::new("."))
            .to_path_buf();
        let text = std::fs::read_to_string(&results_path).with_context(|| {
            format!(
                "reading {} (geocal report takes a run directory with results.json, or a \
                 results file)",
                results_path.display()
            )
        })?;
        let results: serde_json::Value = serde_json::from_str(&text).with_context(|| {
            format!(
                "{}: not JSON (expected geocal-results/1)",
                results_path.display()
            )
        })?;
        let format = results.get("format").and_then(|f| f.as_str());
        if format != Some("geocal-results/1") {
            anyhow::bail!(
                "{}: key `format` is {}, expected \"geocal-results/1\"",
                results_path.display(),
                format.map_or("missing".to_string(), |f| format!("\"{f}\""))
            );
        }
        let session_path = Some(dir.join("session.mcap")).filter(|p| p.is_file());
        let (session, settled) = match &session_path {
            Some(p) => {
                let read = session::read(p).with_context(|| format!("reading {}", p.display()))?;
                (Some(read.session), read.settled)
            }
            None => (None, None),
        };
        let diagnosis_path = Some(dir.join("diagnosis.json")).filter(|p| p.is_file());
        let diagnosis = match &diagnosis_path {
            Some(p) => {
                let text = std::fs::read_to_string(p)
                    .with_context(|| format!("reading {}", p.display()))?;
                Some(serde_json::from_str(&text).with_context(|| {
                    format!("{}: not a geocal-diagnosis/1 document", p.display())
                })?)
            }
            None => None,
        };
        Ok(Inputs {
            results_path,
            results,
            session_path,
            session,
            settled,
            diagnosis_path,
            diagnosis,
            before_results: None,
        })
    }

    /// The recorded session the results came from, when it is not beside them.
    pub fn with_session(mut self, path: &Path) -> anyhow::Result<Inputs> {
        let read = session::read(path).with_context(|| format!("reading {}", path.display()))?;
        self.session = Some(read.session);
        self.settled = read.settled;
        self.session_path = Some(path.to_path_buf());
        Ok(self)
    }

    /// The results' plan kind (key `kind`).
    pub fn kind(&self) -> anyhow::Result<&str> {
        self.results
            .get("kind")
            .and_then(|k| k.as_str())
            .ok_or_else(|| {
                anyhow::anyhow!(
                    "{}: key `kind` missing or not a string",
                    self.results_path.display()
                )
            })
    }
}

/// The report's document, every section of `SECTIONS` in order.
pub fn build(inputs: &Inputs, registry: &Registry) -> anyhow::Result<Document> {
    let kind_name = inputs.kind()?;
    let kind = registry.named(kind_name).ok_or_else(|| {
        anyhow::anyhow!(
            "{}: kind `{kind_name}` is not known (known: {})",
            inputs.results_path.display(),
            registry.names()
        )
    })?;
    let contribution = kind.report(&inputs.results).with_context(|| {
        format!(
            "{}: the {kind_name} sections",
            inputs.results_path.display()
        )
    })?;
    let mut sections = Vec::new();
    for (name, builder) in SECTIONS {
        sections.extend(
            builder(inputs, &contribution).with_context(|| format!("report section `{name}`"))?,
        );
    }
    let session_id = inputs
        .results
        .get("session_id")
        .and_then(|s| s.as_str())
        .unwrap_or("?");
    Ok(Document {
        title: format!("geocal calibration report: {kind_name}, session {session_id}"),
        sections,
    })
}

/// Write the document to `out`: one HTML file, or Markdown with its plots as SVG files beside
/// it (`<stem>-<plot>.svg`). Returns every file written.
pub fn write(doc: &Document, out: &Path, format: Format) -> anyhow::Result<Vec<PathBuf>> {
    let write = |path: &Path, text: &str| {
        std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))
    };
    match format {
        Format::Html => {
            write(out, &crate::document::html::render(doc))?;
            Ok(vec![out.to_path_buf()])
        }
        Format::Markdown => {
            let stem = out
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_else(|| "report".into());
            let (text, plots) = crate::document::markdown::render(doc, &format!("{stem}-"));
            let dir = out.parent().unwrap_or(Path::new("."));
            let mut written = vec![out.to_path_buf()];
            write(out, &text)?;
            for (name, svg) in plots {
                let path = dir.join(name);
                write(&path, &svg)?;
                written.push(path);
            }
            Ok(written)
        }
    }
}

/// How many σ the report lists, scaled, beside the misfit warning.
const MISFIT_REPORT_ROWS: usize = 60;

/// A warning when the fit's χ²/dof is improbable: the σ scaled by √(χ²/dof) beside the model's.
fn misfit(inputs: &Inputs, _: &KindReport) -> anyhow::Result<Vec<Section>> {
    let Some(misfit) = inputs.results.get("misfit") else {
        return Ok(Vec::new());
    };
    let misfit: Misfit = serde_json::from_value(misfit.clone())
        .with_context(|| format!("{}: `misfit`", inputs.results_path.display()))?;
    let rows = sigma_rows(&inputs.results);
    let scaled = format!("σ × {:.2}", misfit.sigma_scale);
    let mut table = Table::new(
        "The results' σ: the model's, and scaled by √(χ²/dof)",
        &["quantity", "σ (model)", &scaled],
    );
    for (path, sigma) in rows.iter().take(MISFIT_REPORT_ROWS) {
        table.row(vec![
            path.clone(),
            format!("{sigma:.4e}"),
            format!("{:.4e}", sigma * misfit.sigma_scale),
        ]);
    }
    let mut section =
        Section::new("misfit", "Misfit: the σ are not trustworthy").paragraph(misfit.warning());
    if rows.len() > MISFIT_REPORT_ROWS {
        section = section.paragraph(format!(
            "{} more σ in results.json: multiply each by {:.2}.",
            rows.len() - MISFIT_REPORT_ROWS,
            misfit.sigma_scale
        ));
    }
    if !rows.is_empty() {
        section = section.table(table);
    }
    Ok(vec![section])
}

fn kind_sections(_: &Inputs, kind: &KindReport) -> anyhow::Result<Vec<Section>> {
    Ok(kind.sections.clone())
}
