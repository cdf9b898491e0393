//! The text report of a diagnosis.

use super::{Diagnosis, Gap};

/// A readable report of a diagnosis.
pub fn text(d: &Diagnosis) -> String {
    use std::fmt::Write;
    let nm = |v: f64| format!("{:.1} nm", v * 1e9);
    let mut s = String::new();
    let _ = writeln!(
        s,
        "Diagnosis of session {} ({} lengths)",
        d.session_id, d.observations
    );
    let _ = writeln!(
        s,
        "  noise floor (fitted RMS expected from noise alone): {}",
        nm(d.noise_floor_m)
    );
    let gap = |s: &mut String, label: &str, g: &Gap| {
        let _ = writeln!(
            s,
            "  {label}: RMS {}, held-out RMS {} (floor {}, standardised {:.2}), chi2/dof {:.2}",
            nm(g.rms_m),
            nm(g.heldout_rms_m),
            nm(g.heldout_floor_m),
            g.heldout_ratio,
            g.chi2_per_dof
        );
    };
    gap(&mut s, "gap (nominal model)", &d.gap);
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
        for dep in p.departures.iter().take(5) {
            let _ = writeln!(
                s,
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
            );
        }
    }
    let before = d.points_level.as_ref().map(|p| &p.gap);
    if let Some(g) = d.points_level_after.as_ref().filter(|g| Some(*g) != before) {
        let _ = writeln!(
            s,
            "  points level after the selected effects: chi2/dof {:.2} (chi2 {:.1}, dof {}, p {:.1e})",
            g.chi2_per_dof, g.chi2, g.dof, g.p_value
        );
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
        for dep in t.departures.iter().take(5) {
            let _ = writeln!(
                s,
                "    point {} {} pass {}: recording minus twin [{}, {}, {}] chi2 {:.1} p {:.1e}",
                dep.target,
                dep.point,
                dep.pass,
                nm(dep.residual_m[0]),
                nm(dep.residual_m[1]),
                nm(dep.residual_m[2]),
                dep.chi2,
                dep.p_value
            );
        }
    }
    if !d.leave_one_station_out.is_empty() {
        let _ = writeln!(
            s,
            "  leave-one-station-out (lengths predicted from the other stations' points):"
        );
        for h in &d.leave_one_station_out {
            let _ = writeln!(
                s,
                "    {:<9} {:>4} lengths  held-out RMS {} (floor {})  standardised {:.2}  p {:.1e}",
                h.station,
                h.lengths,
                nm(h.heldout_rms_m),
                nm(h.floor_m),
                h.ratio,
                h.p_value
            );
        }
    }
    if d.where_.is_empty() {
        let _ = writeln!(s, "  where: no group departs from the noise model");
    } else {
        let _ = writeln!(
            s,
            "  where (groups failing the noise model, largest share first):"
        );
        for w in &d.where_ {
            let _ = writeln!(
                s,
                "    {:<7} {:<9} {:<40} share {:5.1} %  RMS {}  p {:.1e}",
                w.level,
                w.group,
                w.key,
                100.0 * w.share,
                nm(w.rms_m),
                w.p_value
            );
        }
    }
    let _ = writeln!(s, "  candidates:");
    for c in &d.candidates {
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
            c.status
        );
    }
    let _ = writeln!(
        s,
        "  selected: {}",
        if d.selected.is_empty() {
            "none".to_string()
        } else {
            d.selected.join(", ")
        }
    );
    let confounded: Vec<&str> = d
        .candidates
        .iter()
        .filter(|c| c.status == "confounded")
        .map(|c| c.effect.as_str())
        .collect();
    if !confounded.is_empty() {
        let _ = writeln!(
            s,
            "  confounded (the data cannot tell them apart; none named): {}",
            confounded.join(", ")
        );
    }
    gap(&mut s, "gap after", &d.gap_after);
    let _ = writeln!(
        s,
        "  {}",
        if d.unexplained {
            "UNEXPLAINED: structure remains that no candidate explains"
        } else {
            "explained: the remaining residuals agree with the noise model"
        }
    );
    if let Some(scale) = &d.noise_scale {
        let _ = writeln!(
            s,
            "  noise: {} (k = {:.2}, {:.0} % interval {:.2}-{:.2})",
            scale.statement,
            scale.k,
            100.0 * scale.confidence,
            scale.k_low,
            scale.k_high
        );
    }
    if let Some(c) = &d.corrected {
        let _ = writeln!(
            s,
            "  corrected calibration: `{}` (points move {:.3} um RMS, {:.1} sigma)",
            c.command,
            c.points_moved_rms_m * 1e6,
            c.points_moved_rms_sigma
        );
    }
    for n in &d.notes {
        let _ = writeln!(s, "  note: {n}");
    }
    s
}
