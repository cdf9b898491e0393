//! The text report of a kind's residual-model diagnosis: the same summary lines as the
//! multilateration diagnosis (verdict, where, which, how far, corrected calibration), then the
//! details (failing groups, candidates, parameters with the effects fitted, notes).

use std::fmt::Write;

use super::super::{verdict, Diagnosis, WhereEntry, TABLE_MAX_ROWS};

/// A residual in its unit: nm for metres, µrad for radians.
fn value(v: f64, unit: &str) -> String {
    match unit {
        "rad" => format!("{:.2} µrad", v * 1e6),
        _ => format!("{:.1} nm", v * 1e9),
    }
}

fn unit_of<'a>(d: &'a Diagnosis, w: &WhereEntry) -> &'a str {
    // A group's unit: that of its key's row when the key names one, else metres.
    d.model
        .as_ref()
        .and_then(|m| m.residual_units.get(&w.key))
        .map_or("m", String::as_str)
}

fn group(d: &Diagnosis, w: &WhereEntry) -> String {
    let label = if w.key.starts_with(&w.group) {
        w.key.clone()
    } else {
        format!("{} {}", w.group, w.key)
    };
    format!(
        "{label} ({:.0} % of the residual, RMS {})",
        100.0 * w.share,
        value(w.rms_m, unit_of(d, w))
    )
}

pub fn summary(d: &Diagnosis) -> Vec<String> {
    let kind = d.model.as_ref().map_or("", |m| m.kind.as_str());
    let mut lines = vec![
        format!(
            "Diagnosis of {kind} session {} ({} residuals)",
            d.session_id, d.observations
        ),
        verdict(d),
    ];
    lines.push(match d.where_.first() {
        None => "where: no group departs from the noise model".into(),
        Some(first) => {
            let mut s = format!("where: {}", group(d, first));
            if let Some(second) = d.where_.iter().find(|w| w.group != first.group) {
                let _ = write!(s, ", {}", group(d, second));
            }
            if d.where_.len() > 1 {
                let _ = write!(s, "; {} groups fail the noise model", d.where_.len());
            }
            s
        }
    });
    if d.selected.is_empty() {
        lines.push(if d.unexplained {
            "which: none: unexplained".into()
        } else {
            "which: none (no effect needed)".into()
        });
    } else {
        for (k, name) in d.selected.iter().enumerate() {
            let params = d
                .candidates
                .iter()
                .find(|c| &c.effect == name)
                .map(|c| {
                    c.params
                        .iter()
                        .filter(|(k, _)| !k.ends_with(".sigma"))
                        .take(6)
                        .map(|(k, v)| {
                            let s = c.params.get(&format!("{k}.sigma"));
                            match (v.as_f64(), s.and_then(|s| s.as_f64())) {
                                (Some(v), Some(s)) => format!("{k} {v:.3e} ± {s:.1e}"),
                                _ => format!("{k} n/a"),
                            }
                        })
                        .collect::<Vec<_>>()
                        .join(", ")
                })
                .unwrap_or_default();
            let prefix = if k == 0 { "which: " } else { "       " };
            lines.push(format!("{prefix}{name}: {params}"));
        }
    }
    lines.push(format!(
        "how far: gap {:.2} → {:.2} × noise (held-out, standardised); RMS {} → {} (floor {}); chi²/dof {:.2} → {:.2}",
        d.gap.heldout_ratio,
        d.gap_after.heldout_ratio,
        value(d.gap.rms_m, "m"),
        value(d.gap_after.rms_m, "m"),
        value(d.noise_floor_m, "m"),
        d.gap.chi2_per_dof,
        d.gap_after.chi2_per_dof
    ));
    if let Some(c) = &d.corrected {
        lines.push(format!(
            "corrected calibration: `{}` (parameters move {:.2} σ RMS)",
            c.command, c.points_moved_rms_sigma
        ));
    }
    lines.truncate(super::super::SUMMARY_MAX_LINES);
    lines
}

pub fn details(d: &Diagnosis) -> String {
    let mut s = String::from("Details\n");
    let _ = writeln!(
        s,
        "  noise floor (fitted RMS of the length residuals expected from noise alone): {}",
        value(d.noise_floor_m, "m")
    );
    for (label, g) in [("nominal model", &d.gap), ("final model", &d.gap_after)] {
        let _ = writeln!(
            s,
            "  {label}: RMS {}, held-out {:.2} × noise, chi2/dof {:.3}",
            value(g.rms_m, "m"),
            g.heldout_ratio,
            g.chi2_per_dof
        );
    }
    if let Some(m) = &d.model {
        let _ = writeln!(
            s,
            "  coordinates tested: {}; library: {}",
            m.coordinates.join(", "),
            m.library.join(", ")
        );
    }
    if !d.where_.is_empty() {
        let _ = writeln!(s, "  groups failing the noise model (nominal model):");
        for w in d.where_.iter().take(TABLE_MAX_ROWS) {
            let _ = writeln!(s, "    {} p {:.1e}", group(d, w), w.p_value);
        }
        if d.where_.len() > TABLE_MAX_ROWS {
            let _ = writeln!(s, "    and {} more", d.where_.len() - TABLE_MAX_ROWS);
        }
    }
    let _ = writeln!(s, "  candidates:");
    for c in &d.candidates {
        let _ = writeln!(
            s,
            "    {:<16} round {} df {:>2} chi2 drop {:>10.2} p {:.1e} dBIC {:>9.1} held-out after {:.3}: {}",
            c.effect, c.round, c.df, c.chi2_drop, c.p_value, c.bic_delta, c.heldout_rms_after_m, c.status
        );
    }
    if let Some(m) = &d.model {
        if !m.parameters_after.is_empty() {
            let _ = writeln!(
                s,
                "  parameters with the selected effects fitted (nominal → corrected):"
            );
            for p in m.parameters_after.iter().take(3 * TABLE_MAX_ROWS) {
                let _ = writeln!(
                    s,
                    "    {:<20} {:.9} ± {:.2e} → {:.9} ± {:.2e}",
                    p.name, p.nominal, p.nominal_sigma, p.corrected, p.sigma
                );
            }
            if m.parameters_after.len() > 3 * TABLE_MAX_ROWS {
                let _ = writeln!(
                    s,
                    "    and {} more",
                    m.parameters_after.len() - 3 * TABLE_MAX_ROWS
                );
            }
        }
    }
    for note in &d.notes {
        let _ = writeln!(s, "  note: {note}");
    }
    s
}
