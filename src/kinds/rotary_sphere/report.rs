//! Text report of the rotary_sphere results: what an engineer reads at the end of a run.

use super::config::HeightRole;
use super::solve::RotarySphereResults;

/// Arcseconds per radian.
const ARCSEC_PER_RAD: f64 = 180.0 * 3600.0 / std::f64::consts::PI;

/// The text report section of a rotary_sphere result.
pub fn text(r: &RotarySphereResults) -> String {
    use std::fmt::Write;
    let mut s = String::new();
    let fit = r
        .spheres
        .iter()
        .filter(|s| s.role == HeightRole::Fit)
        .count();
    let _ = writeln!(
        s,
        "rotary axis {} from a reference sphere (r = {:.4} mm, probe σ {:.1} µm): {} spheres, {} at fit heights",
        r.table,
        r.sphere_radius_m * 1e3,
        r.probe_noise_m * 1e6,
        r.spheres.len(),
        fit
    );
    let _ = writeln!(s, "  location (position-independent) errors:");
    for v in &r.location {
        if v.name.starts_with("EX") || v.name.starts_with("EY") {
            let _ = writeln!(
                s,
                "    {:5} {:9.2} µm   σ {:.2} µm",
                v.name,
                v.value * 1e6,
                v.sigma * 1e6
            );
        } else {
            let _ = writeln!(
                s,
                "    {:5} {:9.2} µrad σ {:.2} µrad",
                v.name,
                v.value * 1e6,
                v.sigma * 1e6
            );
        }
    }
    let _ = writeln!(
        s,
        "  motion errors over {} angles (peak |value| and median σ; harmonic order by BIC):",
        r.motion.len()
    );
    for (k, name) in r.motion_names.iter().enumerate() {
        let peak = r
            .motion
            .iter()
            .map(|m| m.errors[k].abs())
            .fold(0.0, f64::max);
        let mut sig: Vec<f64> = r.motion.iter().map(|m| m.sigma[k]).collect();
        sig.sort_by(f64::total_cmp);
        let med = sig.get(sig.len() / 2).copied().unwrap_or(0.0);
        let order = r.harmonics.get(k).map_or(0, |h| h.order);
        if k < 3 {
            let _ = writeln!(
                s,
                "    {name:4} peak {:8.2} µm     σ {:6.2} µm     order {order}",
                peak * 1e6,
                med * 1e6
            );
        } else {
            let _ = writeln!(
                s,
                "    {name:4} peak {:8.2} arcsec σ {:6.2} arcsec order {order}",
                peak * ARCSEC_PER_RAD,
                med * ARCSEC_PER_RAD
            );
        }
    }
    if r.dof > 0 {
        let _ = writeln!(
            s,
            "  per-angle model χ²/dof {:.2} ({} dof)",
            r.chi2 / r.dof as f64,
            r.dof
        );
    }
    for v in &r.validation {
        let _ = writeln!(
            s,
            "  prediction at validation height {} ({} angles): {:.0} % of residuals within 10 µm \
             ({:.0} % of coordinates; published ~80 %), {:.0} % of coordinates within 3 predicted σ, χ²/n {:.2}",
            v.height_index,
            v.angles_rad.len(),
            100.0 * v.share_norm_within_10um,
            100.0 * v.share_coordinates_within_10um,
            100.0 * v.share_within_3_sigma,
            v.chi2 / v.count.max(1) as f64
        );
    }
    for n in &r.notes {
        let _ = writeln!(s, "  note: {n}");
    }
    s
}

impl crate::method::KindResults for RotarySphereResults {
    fn report(&self) -> String {
        text(self)
    }
}
