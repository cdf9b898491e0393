//! Text reports of the probe_install and hexapod results: what an engineer reads at the end
//! of a run of those kinds.

use std::fmt::Write;

use crate::method::hexapod::HexapodResults;
use crate::method::probe_install::ProbeInstallResults;

fn um(v_m: f64) -> f64 {
    v_m * 1e6
}

pub fn probe_install_text(r: &ProbeInstallResults) -> String {
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

pub fn hexapod_text(r: &HexapodResults) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "hexapod hinges ({}): {} poses ({} poses {}), {} leg readings, σ per change {:.3} µm",
        r.session_id,
        r.poses,
        r.pose_source,
        if r.pose_source == "measured" {
            "by the sensor"
        } else {
            "as commanded"
        },
        r.readings,
        um(r.sigma_change_m)
    );
    let _ = writeln!(
        s,
        "  two-stage: objective {:.4e} m² (start {:.4e}, stage 1 {:.4e}), residual rms {:.3} µm, \
         weighted chi²/dof {:.3} ({} dof), {} grid rounds, {} leg solves",
        r.two_stage.objective_m2,
        r.two_stage.objective_initial_m2,
        r.two_stage.objective_stage1_m2,
        um(r.residual_rms_m),
        r.chi2_per_dof,
        r.dof,
        r.two_stage.rounds.len(),
        r.two_stage.leg_solves
    );
    let _ = writeln!(
        s,
        "  plain LM: objective {:.4e} m², {} iterations, largest difference from two-stage {:.3} µm",
        r.lm.objective_m2,
        r.lm.iterations,
        um(r.lm.max_difference_m)
    );
    let _ = writeln!(
        s,
        "  leg  base hinge B (m)                          σ (µm)                  platform hinge P (m)                       σ (µm)"
    );
    for h in &r.hinges {
        let _ = writeln!(
            s,
            "  {:>3}  [{:+.6}, {:+.6}, {:+.6}]  [{:6.1}, {:6.1}, {:6.1}]  [{:+.6}, {:+.6}, {:+.6}]  [{:6.1}, {:6.1}, {:6.1}]",
            h.leg,
            h.base_m[0],
            h.base_m[1],
            h.base_m[2],
            um(h.base_sigma_m[0]),
            um(h.base_sigma_m[1]),
            um(h.base_sigma_m[2]),
            h.platform_m[0],
            h.platform_m[1],
            h.platform_m[2],
            um(h.platform_sigma_m[0]),
            um(h.platform_sigma_m[1]),
            um(h.platform_sigma_m[2])
        );
    }
    s
}
