//! The stations level: a plan kind's test of the solved stations against its model of them
//! (`method::tracer_effects::StationsLevel`), judged with the diagnosis's rules — the
//! effect's χ² drop at the library's Bonferroni share, BIC and the held-out ratio; what still
//! fails afterwards makes the session `unexplained`.

use std::collections::BTreeMap;

use serde_json::Value;

use super::locate::WhereEntry;
use super::stats::chi2_sf;
use super::Candidate;
use crate::method::tracer_effects::StationsLevel;

/// What the diagnosis takes from the stations level.
pub struct Judged {
    pub candidate: Candidate,
    pub selected: bool,
    pub unexplained: bool,
    pub where_: Vec<WhereEntry>,
    pub notes: Vec<String>,
}

/// The level's effect is selected when its χ² drop passes at `alpha / library_size`, BIC
/// improves and the held-out stations are predicted better; the level is unexplained when
/// its χ² (after the effect, if selected) fails at `alpha_part`.
pub fn judge(level: &StationsLevel, alpha: f64, library_size: usize, alpha_part: f64) -> Judged {
    let rows: usize = level.stations.iter().map(|s| s.residual_m.len()).sum();
    let p_value = if level.df > 0 {
        chi2_sf(level.chi2_drop, level.df as f64)
    } else {
        1.0
    };
    let bic_delta = -level.chi2_drop + level.df as f64 * (rows.max(1) as f64).ln();
    let threshold = alpha / library_size.max(1) as f64;
    let improves = level.heldout_ratio_after < level.heldout_ratio;
    let selected = level.df > 0 && p_value < threshold && bic_delta < 0.0 && improves;
    let status = if selected {
        "selected (stations level)".to_string()
    } else {
        let mut why = Vec::new();
        if p_value >= threshold {
            why.push(format!("p {p_value:.2e} >= {threshold:.2e}"));
        }
        if bic_delta >= 0.0 {
            why.push("BIC does not improve".into());
        }
        if !improves {
            why.push("held-out stations not predicted better".into());
        }
        format!("rejected (stations level): {}", why.join("; "))
    };
    let mut params: BTreeMap<String, Value> = BTreeMap::new();
    for (name, v, s) in &level.params {
        params.insert(name.clone(), (*v).into());
        params.insert(format!("{name}.sigma"), (*s).into());
    }
    params.insert("stations_chi2".into(), level.chi2.into());
    params.insert("stations_dof".into(), level.dof.into());
    params.insert("stations_rms_m".into(), level.rms_m.into());
    params.insert("stations_heldout_ratio".into(), level.heldout_ratio.into());
    params.insert(
        "stations_heldout_ratio_after".into(),
        level.heldout_ratio_after.into(),
    );
    let (chi2_final, dof_final) = if selected {
        (
            level.chi2 - level.chi2_drop,
            level.dof.saturating_sub(level.df),
        )
    } else {
        (level.chi2, level.dof)
    };
    let p_final = chi2_sf(chi2_final, dof_final.max(1) as f64);
    let unexplained = p_final < alpha_part;
    let mut notes = vec![format!(
        "stations level: {}: chi2/dof {:.2} on {} dof (RMS {:.1} nm){}",
        level.model,
        level.chi2 / level.dof.max(1) as f64,
        level.dof,
        1e9 * level.rms_m,
        if selected {
            format!(
                "; with {} {:.2} (RMS {:.1} nm)",
                level.effect,
                chi2_final / dof_final.max(1) as f64,
                1e9 * level.rms_after_m
            )
        } else {
            String::new()
        }
    )];
    if unexplained {
        notes.push(format!(
            "stations level: chi2/dof {:.2} (p = {p_final:.1e}) after the selected effects: the stations depart from their model beyond the noise",
            chi2_final / dof_final.max(1) as f64
        ));
    }
    // Where: the stations that fail the noise model on their own (Bonferroni over them).
    let total: f64 = level.stations.iter().map(|s| s.chi2).sum();
    let count = level.stations.len().max(1) as f64;
    let mut where_: Vec<WhereEntry> = level
        .stations
        .iter()
        .filter_map(|s| {
            let k = s.residual_m.len().max(1) as f64;
            let p = (chi2_sf(s.chi2, k) * count).min(1.0);
            (p < alpha).then(|| WhereEntry {
                level: "stations".into(),
                group: "table angle".into(),
                key: s.label.clone(),
                share: s.chi2 / total.max(f64::MIN_POSITIVE),
                rms_m: (s.residual_m.iter().map(|r| r * r).sum::<f64>() / k).sqrt(),
                p_value: p,
            })
        })
        .collect();
    where_.sort_by(|a, b| b.share.total_cmp(&a.share));
    Judged {
        candidate: Candidate {
            effect: level.effect.to_string(),
            params,
            rms_after_m: level.rms_after_m,
            heldout_rms_after_m: level.rms_after_m,
            bic_delta,
            p_value,
            round: 0,
            df: level.df,
            chi2_drop: level.chi2_drop,
            status,
            confounded_with: Vec::new(),
        },
        selected,
        unexplained,
        where_,
        notes,
    }
}
