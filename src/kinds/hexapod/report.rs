//! Text report of the hexapod results: what an engineer reads at the end of a run.

use std::fmt::Write;

use super::solve::HexapodResults;
use crate::method::report::um;

pub fn text(r: &HexapodResults) -> String {
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

impl crate::method::KindResults for HexapodResults {
    fn report(&self) -> String {
        text(self)
    }
}
