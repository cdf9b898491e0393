//! Text report of the probe_install results: what an engineer reads at the end of a run.

use std::fmt::Write;

use super::solve::ProbeInstallResults;
use crate::method::report::um;

pub fn text(r: &ProbeInstallResults) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "probe installation ({}): {} points ({} readings, {} out of range) at {} postures, \
         sphere r = {:.4} mm",
        r.session_id,
        r.points,
        r.readings,
        r.readings_out_of_range,
        r.postures_rad.len(),
        r.sphere_radius_m * 1e3
    );
    let _ = writeln!(
        s,
        "  LM: residual rms {:.3} µm, chi²/dof {:.3} ({} dof), {} iterations{}",
        um(r.residual_rms_m),
        r.chi2_per_dof,
        r.dof,
        r.lm.iterations,
        if r.lm.converged {
            ""
        } else {
            " (NOT converged)"
        }
    );
    let _ = writeln!(
        s,
        "  {:<20} {:>16} {:>12} {:>16} {:>16}",
        "parameter", "LM value", "σ", "GA value", "nominal"
    );
    for (k, p) in r.parameters.iter().enumerate() {
        let ga = r.ga.values.get(k).copied().unwrap_or(f64::NAN);
        let _ = writeln!(
            s,
            "  {:<20} {:>16.9e} {:>12.3e} {:>16.9e} {:>16.9e}",
            p.name, p.value, p.sigma, ga, p.nominal
        );
    }
    let _ = writeln!(
        s,
        "  objective G (M = 1e4): LM {:.4e} (h {:.1e}), GA {:.4e} (h {:.1e}; N = {}, {} generations, {} evaluations)",
        r.lm.objective,
        r.lm.unit_norm_violation,
        r.ga.objective,
        r.ga.unit_norm_violation,
        r.ga.population,
        r.ga.generations,
        r.ga.evaluations
    );
    let _ = writeln!(
        s,
        "  sphere radius measured: before {:.4} mm, after LM {:.4} mm, after GA {:.4} mm",
        r.radius_before_m * 1e3,
        r.radius_after_m * 1e3,
        r.radius_after_ga_m * 1e3
    );
    s
}

impl crate::method::KindResults for ProbeInstallResults {
    fn report(&self) -> String {
        text(self)
    }
}
