//! The text report of a diagnosis: a summary a person reads in ten seconds (verdict, where,
//! which, how far), then the details of the groups and candidates that fail the noise model.

use std::collections::BTreeMap;
use std::fmt::Write;

use serde_json::Value;

use super::{Candidate, Diagnosis, Gap, WhereEntry};

/// The summary's length at most, in lines.
pub const SUMMARY_MAX_LINES: usize = 10;
/// Rows of a detail table before the rest is counted as "and N more".
pub const TABLE_MAX_ROWS: usize = 8;

/// A readable report of a diagnosis: the summary, a blank line, the details.
pub fn text(d: &Diagnosis) -> String {
    let mut s = summary(d).join("\n");
    s.push_str("\n\n");
    s.push_str(&details(d));
    s
}

/// At most [`SUMMARY_MAX_LINES`] lines: session, verdict, where, which, how far, and when
/// present the points level, the noise scale and the corrected calibration.
pub fn summary(d: &Diagnosis) -> Vec<String> {
    if d.model.is_some() {
        return super::residual_model::summary(d);
    }
    let mut head = vec![
        format!(
            "Diagnosis of session {} ({} lengths)",
            d.session_id, d.observations
        ),
        verdict(d),
        where_line(d),
    ];
    let mut tail = vec![how_far(d)];
    tail.extend(points_line(d));
    if let Some(scale) = &d.noise_scale {
        tail.push(format!(
            "noise: {} (k = {:.2}, {:.0} % interval {:.2}-{:.2})",
            scale.statement,
            scale.k,
            100.0 * scale.confidence,
            scale.k_low,
            scale.k_high
        ));
    }
    if let Some(c) = &d.corrected {
        tail.push(format!(
            "corrected calibration: `{}` (points move {:.3} µm RMS, {:.1} σ)",
            c.command,
            c.points_moved_rms_m * 1e6,
            c.points_moved_rms_sigma
        ));
    }
    let budget = SUMMARY_MAX_LINES.saturating_sub(head.len() + tail.len());
    head.extend(which_lines(d, budget.max(1)));
    head.extend(tail);
    head.truncate(SUMMARY_MAX_LINES);
    head
}

pub fn verdict(d: &Diagnosis) -> String {
    let confounded = confounded_names(d);
    if d.unexplained {
        if d.selected.is_empty() {
            "verdict: unexplained: structure remains that no candidate explains".into()
        } else {
            format!(
                "verdict: unexplained: structure remains after {}",
                d.selected.join(" + ")
            )
        }
    } else if !d.selected.is_empty() {
        format!("verdict: explained by {}", d.selected.join(" + "))
    } else if !confounded.is_empty() {
        format!(
            "verdict: explained by a confounded group ({}), none of which can be named",
            confounded.join(", ")
        )
    } else if let Some(scale) = &d.noise_scale {
        format!("verdict: no effect; {}", scale.statement)
    } else {
        "verdict: consistent with the noise model (no effect needed)".into()
    }
}

fn confounded_names(d: &Diagnosis) -> Vec<&str> {
    d.candidates
        .iter()
        .filter(|c| c.status == "confounded")
        .map(|c| c.effect.as_str())
        .collect()
}

/// A held-out station's entry in `where` (the leave-one-station-out test).
fn is_held_out(w: &WhereEntry) -> bool {
    w.key.ends_with(" held out")
}

/// The group in words: "station st2", "time 900-1200 s", "direction x+", "pass 1".
fn group_label(w: &WhereEntry) -> String {
    let label = if w.key.starts_with(&w.group) || w.group == "axis" || w.key.contains(" in ") {
        w.key.clone()
    } else {
        format!("{} {}", w.group, w.key)
    };
    if w.level == "lengths" {
        label
    } else {
        format!("{}-level {label}", w.level)
    }
}

/// The one or two groups that carry the gap: the lengths level's groups first (their shares
/// split the residual the effects are fitted to), ranked by share times concentration (the
/// group's mean square over the overall one, ∝ share·RMS²), so that half of the lengths
/// holding half of the residual (a direction, a pass) does not outrank a group where it
/// concentrates; the second of another kind than the first.
fn where_line(d: &Diagnosis) -> String {
    if d.where_.is_empty() {
        return "where: no group departs from the noise model".into();
    }
    let mut ranked: Vec<&WhereEntry> = d
        .where_
        .iter()
        .filter(|w| w.level == "lengths" && !is_held_out(w))
        .collect();
    if ranked.is_empty() {
        ranked = d.where_.iter().collect();
    }
    let weight = |w: &WhereEntry| w.share * w.rms_m * w.rms_m;
    ranked.sort_by(|a, b| weight(b).total_cmp(&weight(a)));
    let first = ranked[0];
    let second = ranked.iter().find(|w| w.group != first.group);
    let mut s = format!(
        "where: {} ({:.0} % of the residual, RMS {})",
        group_label(first),
        100.0 * first.share,
        nm(first.rms_m)
    );
    if let Some(w) = second {
        let _ = write!(
            s,
            ", {} ({:.0} %, RMS {})",
            group_label(w),
            100.0 * w.share,
            nm(w.rms_m)
        );
    }
    let _ = write!(
        s,
        "; {} group{} fail the noise model",
        d.where_.len(),
        if d.where_.len() == 1 { "" } else { "s" }
    );
    s
}

/// One line per selected effect with its key parameters, at most `budget` lines.
fn which_lines(d: &Diagnosis, budget: usize) -> Vec<String> {
    const INDENT: &str = "       ";
    if d.selected.is_empty() {
        let confounded = confounded_names(d);
        let line = if d.unexplained {
            "which: none: unexplained".to_string()
        } else if !confounded.is_empty() {
            format!(
                "which: none named: {} are confounded; their common signal is fitted",
                confounded.join(", ")
            )
        } else {
            "which: none (no effect needed)".to_string()
        };
        return vec![line];
    }
    let shown = if d.selected.len() > budget {
        budget.saturating_sub(1)
    } else {
        d.selected.len()
    };
    let mut lines: Vec<String> = d
        .selected
        .iter()
        .take(shown)
        .enumerate()
        .map(|(k, name)| {
            let prefix = if k == 0 { "which: " } else { INDENT };
            let record = d
                .candidates
                .iter()
                .filter(|c| c.effect == *name)
                .max_by_key(|c| c.status.starts_with("selected"));
            match record.map(|c| key_parameters(c, d)) {
                Some(params) if !params.is_empty() => format!("{prefix}{name}: {params}"),
                _ => format!("{prefix}{name}"),
            }
        })
        .collect();
    if shown < d.selected.len() {
        let rest = &d.selected[shown..];
        let prefix = if shown == 0 { "which: " } else { INDENT };
        lines.push(format!(
            "{prefix}and {} more: {}",
            rest.len(),
            rest.join(", ")
        ));
    }
    lines
}

/// A fitted parameter: `owner` is the station (or target) of a per-station parameter.
struct Param {
    owner: Option<String>,
    leaf: String,
    value: f64,
    sigma: f64,
}

/// The effect's fitted parameters in readable units with their σ; for per-station effects
/// the station with the largest values.
pub fn key_parameters(c: &Candidate, d: &Diagnosis) -> String {
    let mut params = Vec::new();
    for (name, v) in &c.params {
        if name.ends_with(".sigma") {
            continue;
        }
        if let Some(value) = v.as_f64() {
            if let Some(sigma) = c
                .params
                .get(&format!("{name}.sigma"))
                .and_then(Value::as_f64)
            {
                let (owner, leaf) = match name.rsplit_once('.') {
                    Some((owner, leaf)) => (Some(owner.to_string()), leaf.to_string()),
                    None => (None, name.clone()),
                };
                params.push(Param {
                    owner,
                    leaf,
                    value,
                    sigma,
                });
            }
        } else if let (Some(target), Some(values)) =
            (name.strip_suffix("_offset_error_m"), v.as_array())
        {
            // target_offset: one vector per target, its σ in the points level's test.
            let sigmas = d
                .points_level
                .as_ref()
                .and_then(|p| p.target_offset.as_ref())
                .and_then(|t| t.offsets_sigma_m.get(target));
            for (k, axis) in ["x", "y", "z"].iter().enumerate() {
                if let Some(value) = values.get(k).and_then(Value::as_f64) {
                    params.push(Param {
                        owner: Some(target.to_string()),
                        leaf: format!("{axis}_m"),
                        value,
                        sigma: sigmas.map_or(f64::NAN, |s| s[k]),
                    });
                }
            }
        }
    }
    let mut out = String::new();
    let mut owners: Vec<String> = params.iter().filter_map(|p| p.owner.clone()).collect();
    owners.dedup();
    let size = |owner: &String| -> f64 {
        params
            .iter()
            .filter(|p| p.owner.as_ref() == Some(owner))
            .map(|p| p.value * p.value)
            .sum()
    };
    if let Some(largest) = owners.iter().max_by(|a, b| size(a).total_cmp(&size(b))) {
        if owners.len() > 1 {
            let _ = write!(out, "{largest} (largest of {}): ", owners.len());
        } else {
            let _ = write!(out, "{largest}: ");
        }
        params.retain(|p| p.owner.is_none() || p.owner.as_ref() == Some(largest));
    }
    out.push_str(&format_params(&params));
    // What a parameter is conditional on: where a step is, a settling time constant.
    if let Some(pass) = c.params.get("pass").and_then(Value::as_str) {
        let _ = write!(out, " in {pass}");
        if let Some(t) = c.params.get("after_t_s").and_then(Value::as_f64) {
            let _ = write!(out, " from {t:.1} s");
        }
    }
    if let Some(tau) = c.params.get("tau_s").and_then(Value::as_f64) {
        let _ = write!(out, ", tau {tau:.2} s");
    }
    out
}

#[derive(Clone, Copy, PartialEq)]
enum Unit {
    Metre,
    MetrePerSecond,
    PerKelvin,
    Second,
    Unitless,
}

/// The parameter's symbol and unit from its name's suffix (`bx_m`, `wx_m_s`, `alpha_x_per_k`).
fn symbol_and_unit(leaf: &str) -> (&str, Unit) {
    for (suffix, unit) in [
        ("_m_s", Unit::MetrePerSecond),
        ("_per_k", Unit::PerKelvin),
        ("_m", Unit::Metre),
        ("_s", Unit::Second),
    ] {
        if let Some(symbol) = leaf.strip_suffix(suffix) {
            return (symbol, unit);
        }
    }
    (leaf, Unit::Unitless)
}

/// The factor from SI and the unit's name for values of this size.
fn readable(unit: Unit, magnitude: f64) -> (f64, &'static str) {
    match unit {
        Unit::Metre if magnitude < 1e-6 => (1e9, "nm"),
        Unit::Metre if magnitude < 1e-3 => (1e6, "µm"),
        Unit::Metre if magnitude < 1.0 => (1e3, "mm"),
        Unit::Metre => (1.0, "m"),
        Unit::MetrePerSecond if magnitude < 1e-6 => (1e9, "nm/s"),
        Unit::MetrePerSecond if magnitude < 1e-3 => (1e6, "µm/s"),
        Unit::MetrePerSecond => (1.0, "m/s"),
        Unit::PerKelvin => (1e6, "µm/m/K"),
        Unit::Second => (1.0, "s"),
        Unit::Unitless => (1.0, ""),
    }
}

/// "bx 1.02 ± 0.03, by -0.01 ± 0.03 µm": runs of one unit share its name; two significant
/// digits of σ.
fn format_params(params: &[Param]) -> String {
    let mut runs: Vec<(Unit, Vec<&Param>)> = Vec::new();
    for p in params {
        let unit = symbol_and_unit(&p.leaf).1;
        match runs.last_mut() {
            Some((u, members)) if *u == unit => members.push(p),
            _ => runs.push((unit, vec![p])),
        }
    }
    let parts: Vec<String> = runs
        .iter()
        .map(|(unit, members)| {
            let magnitude = members
                .iter()
                .map(|p| {
                    p.value
                        .abs()
                        .max(if p.sigma.is_finite() { p.sigma } else { 0.0 })
                })
                .fold(0.0, f64::max);
            let (factor, name) = readable(*unit, magnitude);
            let values: Vec<String> = members
                .iter()
                .map(|p| {
                    let symbol = symbol_and_unit(&p.leaf).0;
                    // A σ a millionth of the effect's size is no measurement: the direction is
                    // not identified and its value is the minimum-norm zero.
                    if p.sigma.is_finite() && p.sigma <= 1e-6 * magnitude {
                        format!("{symbol} not identified")
                    } else {
                        format!(
                            "{symbol} {}",
                            value_with_sigma(p.value * factor, p.sigma * factor)
                        )
                    }
                })
                .collect();
            let joined = values.join(", ");
            if name.is_empty() {
                joined
            } else {
                format!("{joined} {name}")
            }
        })
        .collect();
    parts.join("; ")
}

fn value_with_sigma(value: f64, sigma: f64) -> String {
    if sigma.is_finite() && sigma > 0.0 {
        let decimals = (1.0 - sigma.log10().floor()).clamp(0.0, 6.0) as usize;
        format!("{value:.decimals$} ± {sigma:.decimals$}")
    } else {
        format!("{value:.3e}")
    }
}

fn ratio(v: f64) -> String {
    if v.is_finite() {
        format!("{v:.2}")
    } else {
        "n/a".into()
    }
}

fn nm(v: f64) -> String {
    format!("{:.1} nm", v * 1e9)
}

/// The gap before and after in units of the noise: the held-out residuals standardised by
/// their predicted σ (1 = noise), the RMS against the noise floor, χ²/dof.
fn how_far(d: &Diagnosis) -> String {
    format!(
        "how far: gap {} → {} × noise (held-out, standardised); RMS {} → {} (floor {}); chi²/dof {} → {}",
        ratio(d.gap.heldout_ratio),
        ratio(d.gap_after.heldout_ratio),
        nm(d.gap.rms_m),
        nm(d.gap_after.rms_m),
        nm(d.noise_floor_m),
        ratio(d.gap.chi2_per_dof),
        ratio(d.gap_after.chi2_per_dof)
    )
}

/// The points level (and the twin's points) before → after, when tested.
fn points_line(d: &Diagnosis) -> Option<String> {
    let mut parts = Vec::new();
    if let Some(p) = &d.points_level {
        let after = d.points_level_after.as_ref().map_or_else(
            || "n/a".to_string(),
            |g| format!("{} (p {:.1e})", ratio(g.chi2_per_dof), g.p_value),
        );
        parts.push(format!(
            "chi²/dof {} → {after}, solved points against the 21-error model",
            ratio(p.gap.chi2_per_dof),
        ));
    }
    if let Some(t) = &d.twin {
        let of = |g: &Option<super::lengths::TwinPointsGap>| {
            g.as_ref()
                .map_or_else(|| "n/a".to_string(), |g| ratio(g.chi2_per_dof))
        };
        parts.push(format!(
            "the twin's points: chi²/dof {} → {}",
            of(&t.points_before),
            of(&t.points_after)
        ));
    }
    (!parts.is_empty()).then(|| format!("points level: {}", parts.join("; ")))
}

/// `rows` formatted one a line, at most [`TABLE_MAX_ROWS`], then "and N more".
fn capped<T>(s: &mut String, rows: &[T], row: impl Fn(&T) -> String) {
    for r in rows.iter().take(TABLE_MAX_ROWS) {
        let _ = writeln!(s, "{}", row(r));
    }
    if rows.len() > TABLE_MAX_ROWS {
        let _ = writeln!(s, "    and {} more", rows.len() - TABLE_MAX_ROWS);
    }
}

/// Everything behind the summary: the gaps in full, the failing groups, points and stations,
/// every candidate's statistics, the selected effects' parameters, the notes.
pub fn details(d: &Diagnosis) -> String {
    if d.model.is_some() {
        return super::residual_model::details(d);
    }
    let mut s = String::from("Details\n");
    let _ = writeln!(
        s,
        "  noise floor (fitted RMS expected from noise alone): {}",
        nm(d.noise_floor_m)
    );
    let gap = |s: &mut String, label: &str, g: &Gap| {
        let _ = writeln!(
            s,
            "  {label}: RMS {}, held-out RMS {} (floor {}, standardised {}), chi2/dof {}",
            nm(g.rms_m),
            nm(g.heldout_rms_m),
            nm(g.heldout_floor_m),
            ratio(g.heldout_ratio),
            ratio(g.chi2_per_dof)
        );
    };
    gap(&mut s, "gap (nominal model)", &d.gap);
    gap(&mut s, "gap after the selected effects", &d.gap_after);
    if let Some(p) = &d.points_level {
        let g = &p.gap;
        let _ = writeln!(
            s,
            "  points level ({} points per pass against the 21-error model, rank {}): chi2/dof {:.2} (chi2 {:.1}, dof {}, p {:.1e}), RMS {} (floor {})",
            g.points,
            g.rank,
            g.chi2_per_dof,
            g.chi2,
            g.dof,
            g.p_value,
            nm(g.rms_m),
            nm(g.floor_m)
        );
        let before = Some(g);
        if let Some(g) = d.points_level_after.as_ref().filter(|g| Some(*g) != before) {
            let _ = writeln!(
                s,
                "  points level after the selected effects: chi2/dof {:.2} (chi2 {:.1}, dof {}, p {:.1e})",
                g.chi2_per_dof, g.chi2, g.dof, g.p_value
            );
        }
        if !p.departures.is_empty() {
            let _ = writeln!(
                s,
                "  points failing the noise model ({}), largest chi2 first:",
                p.departures.len()
            );
            capped(&mut s, &p.departures, |dep| {
                format!(
                    "    point {} {} pass {} at [{:.3}, {:.3}, {:.3}] m: residual [{}, {}, {}] chi2 {:.1} p {:.1e}",
                    dep.target,
                    dep.point,
                    dep.pass,
                    dep.nominal_m[0],
                    dep.nominal_m[1],
                    dep.nominal_m[2],
                    nm(dep.residual_m[0]),
                    nm(dep.residual_m[1]),
                    nm(dep.residual_m[2]),
                    dep.chi2,
                    dep.p_value
                )
            });
        }
    }
    if let Some(t) = &d.twin {
        let _ = writeln!(
            s,
            "  twin {} ({}): {} lengths matched, {} not",
            t.session_id, t.source, t.matched_lengths, t.unmatched_lengths
        );
        for (label, g) in [
            ("before", &t.points_before),
            ("after the selected effects", &t.points_after),
        ] {
            if let Some(g) = g {
                let _ = writeln!(
                    s,
                    "    points minus the twin's, {label}: chi2/dof {:.2} (dof {}, p {:.1e}), RMS {} (floor {})",
                    g.chi2_per_dof,
                    g.dof,
                    g.p_value,
                    nm(g.rms_m),
                    nm(g.floor_m)
                );
            }
        }
        capped(&mut s, &t.departures, |dep| {
            format!(
                "    point {} {} pass {}: recording minus twin [{}, {}, {}] chi2 {:.1} p {:.1e}",
                dep.target,
                dep.point,
                dep.pass,
                nm(dep.residual_m[0]),
                nm(dep.residual_m[1]),
                nm(dep.residual_m[2]),
                dep.chi2,
                dep.p_value
            )
        });
    }
    held_out_stations(&mut s, d);
    let groups: Vec<&WhereEntry> = d.where_.iter().filter(|w| !is_held_out(w)).collect();
    let mut levels: Vec<&str> = groups.iter().map(|w| w.level.as_str()).collect();
    levels.dedup();
    if groups.is_empty() {
        let _ = writeln!(s, "  where: no group departs from the noise model");
    }
    for level in levels {
        let rows: Vec<&&WhereEntry> = groups.iter().filter(|w| w.level == level).collect();
        let _ = writeln!(
            s,
            "  where, {level} level ({} groups failing the noise model, largest share first):",
            rows.len()
        );
        capped(&mut s, &rows, |w| {
            format!(
                "    {:<9} {:<40} share {:5.1} %  RMS {}  p {:.1e}",
                w.group,
                w.key,
                100.0 * w.share,
                nm(w.rms_m),
                w.p_value
            )
        });
    }
    let _ = writeln!(s, "  candidates:");
    for c in &d.candidates {
        let status = if c.confounded_with.is_empty() {
            c.status.clone()
        } else {
            format!("{} with {}", c.status, c.confounded_with.join(", "))
        };
        let _ = writeln!(
            s,
            "    {:<20} round {} df {:>2}  chi2 drop {:>9.1}  p {:.1e}  BIC {:>+9.1}  RMS after {}  held-out {}  {}",
            c.effect,
            c.round,
            c.df,
            c.chi2_drop,
            c.p_value,
            c.bic_delta,
            nm(c.rms_after_m),
            nm(c.heldout_rms_after_m),
            status
        );
    }
    selected_parameters(&mut s, d);
    for n in &d.notes {
        let _ = writeln!(s, "  note: {n}");
    }
    s
}

/// Leave-one-station-out: the stations that fail (in `where`), and the range of the rest.
fn held_out_stations(s: &mut String, d: &Diagnosis) {
    if d.leave_one_station_out.is_empty() {
        return;
    }
    let failing_share = |station: &str| {
        d.where_
            .iter()
            .find(|w| is_held_out(w) && w.key == format!("{station} held out"))
            .map(|w| w.share)
    };
    let (failing, passing): (Vec<_>, Vec<_>) = d
        .leave_one_station_out
        .iter()
        .partition(|h| failing_share(&h.station).is_some());
    let _ = write!(
        s,
        "  leave-one-station-out (lengths predicted from the other stations' points): {} of {} stations fail the noise model",
        failing.len(),
        d.leave_one_station_out.len()
    );
    if !passing.is_empty() {
        let (lo, hi) = passing
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |a, h| {
                (a.0.min(h.ratio), a.1.max(h.ratio))
            });
        let which = if failing.is_empty() {
            "all"
        } else {
            "the others"
        };
        let _ = write!(s, "; {which} standardised {lo:.2}-{hi:.2}");
    }
    let _ = writeln!(s);
    capped(s, &failing, |h| {
        format!(
            "    {:<9} {:>4} lengths  held-out RMS {} (floor {})  standardised {:.2}  p {:.1e}  share {:.1} %",
            h.station,
            h.lengths,
            nm(h.heldout_rms_m),
            nm(h.floor_m),
            h.ratio,
            h.p_value,
            100.0 * failing_share(&h.station).unwrap_or(0.0)
        )
    });
}

/// Every parameter of the selected effects, one row per station (or target, or the effect's
/// own), largest first.
fn selected_parameters(s: &mut String, d: &Diagnosis) {
    for name in &d.selected {
        let Some(c) = d.candidates.iter().find(|c| c.effect == *name) else {
            continue;
        };
        let mut by_owner: BTreeMap<String, BTreeMap<String, Value>> = BTreeMap::new();
        for (key, v) in &c.params {
            let (param, sigma_suffix) = match key.strip_suffix(".sigma") {
                Some(p) => (p, ".sigma"),
                None => (key.as_str(), ""),
            };
            let (owner, leaf) = match param.rsplit_once('.') {
                Some((owner, leaf)) => (owner.to_string(), leaf.to_string()),
                None => (String::new(), param.to_string()),
            };
            by_owner
                .entry(owner)
                .or_default()
                .insert(format!("{leaf}{sigma_suffix}"), v.clone());
        }
        let rows: Vec<(String, String)> = by_owner
            .into_iter()
            .map(|(owner, params)| {
                let record = Candidate {
                    params,
                    ..c.clone()
                };
                (owner, key_parameters(&record, d))
            })
            .collect();
        let _ = writeln!(s, "  {name} parameters:");
        capped(s, &rows, |(owner, params)| {
            if owner.is_empty() {
                format!("    {params}")
            } else {
                format!("    {owner:<9} {params}")
            }
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::diagnose::lengths::HeldOutStation;

    fn gap(ratio: f64) -> Gap {
        Gap {
            rms_m: 2e-8 * ratio,
            heldout_rms_m: 2.1e-8 * ratio,
            chi2_per_dof: ratio * ratio,
            heldout_floor_m: 2.1e-8,
            heldout_ratio: ratio,
        }
    }

    fn entry(group: &str, key: String, share: f64) -> WhereEntry {
        WhereEntry {
            level: "lengths".into(),
            group: group.into(),
            key,
            share,
            rms_m: 5e-8,
            p_value: 1e-6,
        }
    }

    fn candidate(effect: &str, status: &str, params: &[(&str, f64)]) -> Candidate {
        Candidate {
            effect: effect.into(),
            params: params
                .iter()
                .map(|(k, v)| (k.to_string(), (*v).into()))
                .collect(),
            rms_after_m: 2e-8,
            heldout_rms_after_m: 2.1e-8,
            bic_delta: -200.0,
            p_value: 1e-30,
            round: 0,
            df: 3,
            chi2_drop: 250.0,
            status: status.into(),
            confounded_with: Vec::new(),
        }
    }

    /// A station drift explained, 12 stations, every station and time block failing, one
    /// passing station in the leave-one-station-out table, five selected effects.
    fn crowded() -> Diagnosis {
        let stations: Vec<String> = (0..12).map(|k| format!("s{k}")).collect();
        let mut where_: Vec<WhereEntry> = stations
            .iter()
            .enumerate()
            .map(|(k, s)| entry("station", s.clone(), 0.2 - 0.01 * k as f64))
            .collect();
        where_.extend(
            (0..10).map(|b| entry("time", format!("{}-{} s", 100 * b, 100 * b + 100), 0.1)),
        );
        where_.push(entry("station", "s3 held out".into(), 0.5));
        let mut drift: Vec<(String, f64)> = Vec::new();
        for (k, s) in stations.iter().enumerate() {
            for axis in ["wx", "wy", "wz"] {
                drift.push((format!("{s}.{axis}_m_s"), 1e-9 * k as f64));
                drift.push((format!("{s}.{axis}_m_s.sigma"), 1e-10));
            }
        }
        let drift: Vec<(&str, f64)> = drift.iter().map(|(k, v)| (k.as_str(), *v)).collect();
        let selected = [
            "station_drift",
            "reversal",
            "length_step",
            "air_refraction",
            "thermal_expansion",
        ];
        let candidates = vec![
            candidate("station_drift", "selected", &drift),
            candidate(
                "reversal",
                "selected",
                &[
                    ("bx_m", 1.021e-6),
                    ("bx_m.sigma", 1.2e-8),
                    ("by_m", -3e-9),
                    ("by_m.sigma", 1.2e-8),
                    ("bz_m", 4e-9),
                    ("bz_m.sigma", 1.5e-8),
                ],
            ),
            candidate(
                "length_step",
                "selected",
                &[("step_m", 5e-7), ("step_m.sigma", 2e-8)],
            ),
            candidate(
                "air_refraction",
                "selected",
                &[("edlen_scale", 1.02), ("edlen_scale.sigma", 0.013)],
            ),
            candidate(
                "thermal_expansion",
                "selected",
                &[("alpha_x_per_k", 2e-6), ("alpha_x_per_k.sigma", 1e-7)],
            ),
        ];
        Diagnosis {
            format: crate::diagnose::DIAGNOSIS_FORMAT.into(),
            session_id: "crowded".into(),
            noise_floor_m: 2e-8,
            gap: gap(4.2),
            where_,
            candidates,
            selected: selected.iter().map(|s| s.to_string()).collect(),
            gap_after: gap(0.99),
            unexplained: false,
            noise_scale: Some(crate::diagnose::NoiseScale {
                k: 1.2,
                k_low: 1.1,
                k_high: 1.3,
                confidence: 0.95,
                dof: 300,
                statement: "the declared noise model is 1.20x too small".into(),
            }),
            corrected: Some(crate::diagnose::CorrectedCalibration {
                command: "geocal solve s.mcap --effects station_drift,reversal".into(),
                effects: vec!["station_drift".into(), "reversal".into()],
                points_moved_rms_m: 1.234e-6,
                points_moved_rms_sigma: 2.1,
            }),
            points_level: None,
            points_level_after: None,
            model: None,
            leave_one_station_out: stations
                .iter()
                .map(|s| HeldOutStation {
                    station: s.clone(),
                    lengths: 50,
                    dof: 40,
                    heldout_rms_m: 3e-8,
                    floor_m: 2e-8,
                    ratio: if s == "s3" { 3.0 } else { 1.0 },
                    p_value: if s == "s3" { 1e-9 } else { 0.5 },
                })
                .collect(),
            twin: None,
            observations: 600,
            notes: vec!["a note".into()],
        }
    }

    #[test]
    fn summary_fits_ten_lines_and_leads_the_report() {
        let d = crowded();
        let lines = summary(&d);
        assert!(lines.len() <= SUMMARY_MAX_LINES, "{lines:#?}");
        assert!(lines.iter().all(|l| !l.contains('\n')), "{lines:#?}");
        let report = text(&d);
        assert!(report.starts_with(&lines.join("\n")), "{report}");
        let summary = lines.join("\n");
        assert!(
            summary.contains("verdict: explained by station_drift + reversal"),
            "{summary}"
        );
        assert!(
            summary.contains(
                "where: station s0 (20 % of the residual, RMS 50.0 nm), time 0-100 s (10 %"
            ),
            "{summary}"
        );
        assert!(
            summary.contains("which: station_drift: s11 (largest of 12): wx 11.00 ± 0.10"),
            "{summary}"
        );
        assert!(
            summary.contains("reversal: bx 1.021 ± 0.012, by -0.003 ± 0.012, bz 0.004 ± 0.015 µm"),
            "{summary}"
        );
        // Five effects do not fit beside the other lines: the last are counted.
        assert!(
            summary.contains("and 2 more: air_refraction, thermal_expansion"),
            "{summary}"
        );
        assert!(
            summary.contains("how far: gap 4.20 → 0.99 × noise"),
            "{summary}"
        );
        assert!(
            summary.contains("k = 1.20, 95 % interval 1.10-1.30"),
            "{summary}"
        );
        assert!(summary.contains("points move 1.234 µm RMS"), "{summary}");
    }

    #[test]
    fn detail_tables_show_failing_groups_only_capped() {
        let report = text(&crowded());
        // 22 lengths-level groups fail (the held-out station is in its own table).
        assert!(
            report.contains("where, lengths level (22 groups failing the noise model"),
            "{report}"
        );
        assert!(
            report.contains(&format!("    and {} more\n", 22 - TABLE_MAX_ROWS)),
            "{report}"
        );
        // Leave-one-station-out: the failing station, the passing ones only as a range.
        assert!(
            report.contains(
                "1 of 12 stations fail the noise model; the others standardised 1.00-1.00"
            ),
            "{report}"
        );
        assert!(report.contains("    s3 "), "{report}");
        assert!(!report.contains("    s4          50 lengths"), "{report}");
        // The selected effect's parameters of all 12 stations, capped.
        let drift = report
            .split("station_drift parameters:\n")
            .nth(1)
            .expect("station_drift parameters");
        assert!(drift.contains("    and 4 more\n"), "{report}");
        assert!(report.contains("  note: a note"), "{report}");
    }

    #[test]
    fn a_direction_the_data_do_not_determine_is_not_identified() {
        let params =
            [("e", 4.41e-6, 6.1e-7), ("ez", -3e-19, 2e-19)].map(|(symbol, value, sigma)| Param {
                owner: None,
                leaf: format!("{symbol}_m"),
                value,
                sigma,
            });
        assert_eq!(
            format_params(&params),
            "e 4.41 ± 0.61, ez not identified µm"
        );
    }

    #[test]
    fn nothing_selected_says_so() {
        let mut d = crowded();
        d.selected.clear();
        d.candidates.clear();
        d.noise_scale = None;
        d.corrected = None;
        d.where_.clear();
        let summary = summary(&d).join("\n");
        assert!(
            summary.contains("verdict: consistent with the noise model"),
            "{summary}"
        );
        assert!(
            summary.contains("which: none (no effect needed)"),
            "{summary}"
        );
        assert!(summary.contains("where: no group departs"), "{summary}");
        d.unexplained = true;
        let summary = super::summary(&d).join("\n");
        assert!(summary.contains("verdict: unexplained"), "{summary}");
        assert!(summary.contains("which: none: unexplained"), "{summary}");
    }
}
