//! The diagnosis by the session's kind (`geocal diagnose`, `geocal solve --effects`): a kind
//! with a residual model is diagnosed through `diagnose::residual_model` with its own effect
//! library, the tracer kinds through the tracer network's (`tracer_plan::diagnosis`); any
//! other kind is refused by name.

use std::path::Path;

use anyhow::Context;

use super::tracer_plan;
use crate::diagnose::{residual_model, DiagnoseOptions, Diagnosis, StandardisedResiduals};

/// Read a session file and diagnose it.
pub fn diagnose_file(path: &Path, options: &DiagnoseOptions) -> anyhow::Result<Diagnosis> {
    Ok(diagnose_file_detailed(path, options)?.0)
}

/// [`diagnose_file`] with the standardised residuals of every residual (the plot's).
pub fn diagnose_file_detailed(
    path: &Path,
    options: &DiagnoseOptions,
) -> anyhow::Result<(Diagnosis, StandardisedResiduals)> {
    if let Some(diagnosed) = diagnose_residual_model_file(path, options)? {
        return Ok(diagnosed);
    }
    tracer_plan::diagnosis::diagnose_file_detailed(path, options)
}

/// Whether the session at `path` is of a kind with a residual model; then its diagnosis and
/// standardised residuals (None: another diagnosis applies).
fn diagnose_residual_model_file(
    path: &Path,
    options: &DiagnoseOptions,
) -> anyhow::Result<Option<(Diagnosis, StandardisedResiduals)>> {
    let Ok(header) = crate::session::file_stream::read_header(path) else {
        return Ok(None);
    };
    let Some(kind) = crate::kinds::kind_named(&header.kind) else {
        return Ok(None);
    };
    if !kind.has_residual_model() {
        return Ok(None);
    }
    let session = crate::session::reader::read_session(path)
        .with_context(|| format!("reading {}", path.display()))?;
    let model = kind
        .residual_model(&session)
        .with_context(|| format!("diagnosing {}", path.display()))?;
    let (mut diagnosis, residuals) = residual_model::diagnose(model.as_ref(), options);
    if let Some(c) = &mut diagnosis.corrected {
        c.command = format!(
            "geocal solve {} --effects {}",
            path.display(),
            c.effects.join(",")
        );
    }
    Ok(Some((diagnosis, residuals)))
}

/// The settings of `geocal solve SESSION --effects NAMES`: the names of a kind with a residual
/// model go to its own solve (which checks them against its library); the multilateration
/// effects are parsed as before.
pub fn solve_settings(
    session: &Path,
    names: &[String],
    base: crate::method::SolveSettings,
) -> anyhow::Result<crate::method::SolveSettings> {
    let own_library = crate::session::file_stream::read_header(session)
        .ok()
        .and_then(|h| crate::kinds::kind_named(&h.kind))
        .is_some_and(|k| k.has_residual_model());
    Ok(if own_library {
        crate::method::SolveSettings {
            effect_names: names
                .iter()
                .flat_map(|n| n.split(','))
                .map(|n| n.trim().to_string())
                .filter(|n| !n.is_empty())
                .collect(),
            ..base
        }
    } else {
        crate::method::SolveSettings {
            effects: tracer_plan::diagnosis::correct::parse_effects(names)?,
            ..base
        }
    })
}

/// `--twin` compares a tracer session with its twin's lengths; a session of a kind with a
/// residual model is diagnosed without it (a clear error, not the tracer kinds' refusal).
pub fn refuse_twin(session: &Path) -> anyhow::Result<()> {
    let kind = crate::session::file_stream::read_header(session)
        .ok()
        .and_then(|h| crate::kinds::kind_named(&h.kind))
        .filter(|k| k.has_residual_model());
    match kind {
        Some(k) => anyhow::bail!(
            "{}: --twin compares tracer lengths with a twin's; a {} session is diagnosed \
             against its own model: run `geocal diagnose {}` without --twin",
            session.display(),
            k.name(),
            session.display()
        ),
        None => Ok(()),
    }
}
