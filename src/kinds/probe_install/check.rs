//! Plan check of kind `probe_install`: σ of the 11 installation parameters (the beam on the unit
//! sphere: two tilts) from the planned points at the design installation, and what the postures
//! cannot separate.

use nalgebra::{DMatrix, SMatrix};

use crate::kinds::probe_install::config::{ProbeInstallConfig, KIND};
use crate::kinds::probe_install::plan::ProbeInstallPlan;
use crate::method::plan_check_kinds::linear::analyse;
use crate::method::plan_check_kinds::{merge, summarise, KindPlanCheck, PredictedSigma};
use crate::model::probe_install::{
    sphere_residual_jacobian, ProbeObservation, N_PARAMS, PARAM_NAMES,
};
use crate::solve::probe_install::{
    residual_sigmas, solve_lm, tangent_basis, LmOptions, ProbeInstallProblem,
};

/// The solver's 10 free parameters: the beam as two tilts about its design direction.
const FREE_NAMES: [&str; 10] = [
    "b_offset_rad",
    "y_offset_m",
    "beam_tilt_e1_rad",
    "beam_tilt_e2_rad",
    "zero_point_x_m",
    "zero_point_y_m",
    "zero_point_z_m",
    "sphere_centre_x_m",
    "sphere_centre_y_m",
    "sphere_centre_z_m",
];

fn unit_of(name: &str) -> &'static str {
    if name.starts_with("beam_") && !name.ends_with("_rad") {
        // Direction cosines l, m, n.
        "1"
    } else if name.ends_with("_rad") {
        "rad"
    } else if name.ends_with("_m") {
        "m"
    } else {
        "1"
    }
}

/// The planned points as noise-free observations of the design installation.
pub fn nominal_problem(config: &ProbeInstallConfig) -> ProbeInstallProblem {
    let plan = ProbeInstallPlan::from_config(config);
    let sigma_m = config.devices.probe.noise_m / (plan.readings_per_point.max(1) as f64).sqrt();
    ProbeInstallProblem {
        nominal: config.plan.nominal.params(),
        sphere_radius_m: config.plan.sphere_radius_m,
        observations: plan
            .points
            .iter()
            .map(|p| ProbeObservation {
                a_rad: p.axes[3],
                b_rad: p.axes[4],
                machine_m: [p.axes[0], p.axes[1], p.axes[2]],
                reading_m: p.nominal_reading_m,
                sigma_m,
            })
            .collect(),
    }
}

pub fn check(config: &ProbeInstallConfig) -> Result<KindPlanCheck, String> {
    let problem = nominal_problem(config);
    let nominal = problem.nominal;
    let n = problem.observations.len();
    // ∂X/∂z at the design beam: the tilts move it along e1, e2 (the solver's chart at its start).
    let e3 = nominal.beam().normalize();
    let (e1, e2) = tangent_basis(&e3);
    let mut g = SMatrix::<f64, N_PARAMS, 10>::zeros();
    g[(0, 0)] = 1.0;
    g[(1, 1)] = 1.0;
    for k in 0..3 {
        g[(2 + k, 2)] = e1[k];
        g[(2 + k, 3)] = e2[k];
    }
    for k in 0..6 {
        g[(5 + k, 4 + k)] = 1.0;
    }
    let sigmas = residual_sigmas(&problem, &nominal);
    let j = DMatrix::from_fn(n, 10, |r, c| {
        let (_, jx) =
            sphere_residual_jacobian(&nominal, &problem.observations[r], problem.sphere_radius_m);
        (jx * g)[c] / sigmas[r]
    });
    let free: Vec<String> = FREE_NAMES.iter().map(|s| s.to_string()).collect();
    let block = analyse(&free, &j);
    let identifiability = merge(
        &[&block],
        10,
        std::slice::from_ref(&free),
        vec!["the beam direction (l, m, n) has unit norm: two free tilts, so its covariance is rank 2".into()],
    );
    let mut warnings = Vec::new();
    // Full rank: the solver's own covariance (LM on the noise-free plan, converged at the start).
    let solver_sigma = if identifiability.deficiency == 0 {
        match solve_lm(&problem, &nominal, &LmOptions::default()) {
            Ok(s) => Some(s.sigma),
            Err(e) => {
                warnings.push(format!("the solver's covariance is not available: {e}"));
                None
            }
        }
    } else {
        None
    };
    // The 11 parameters: from the solver, or G C Gᵀ of the block where every free parameter a
    // component depends on is identifiable.
    let cov11 =
        g * SMatrix::<f64, 10, 10>::from_fn(|r, c| block.covariance[(r, c)]) * g.transpose();
    let parameters: Vec<PredictedSigma> = (0..N_PARAMS)
        .map(|k| {
            let sigma = match &solver_sigma {
                Some(s) => Some(s[k]),
                None => (0..10)
                    .filter(|&c| g[(k, c)] != 0.0)
                    .all(|c| block.sigma[c].is_some())
                    .then(|| cov11[(k, k)].max(0.0).sqrt()),
            };
            PredictedSigma {
                name: PARAM_NAMES[k].into(),
                unit: unit_of(PARAM_NAMES[k]),
                sigma,
            }
        })
        .collect();
    let summary = summarise(&parameters, |name| {
        if name.starts_with("beam") {
            "beam direction l, m, n".into()
        } else if name.starts_with("zero_point") {
            "probe zero point".into()
        } else if name.starts_with("sphere_centre") {
            "sphere centre".into()
        } else {
            name.to_string()
        }
    });
    if n < 10 {
        warnings.push(format!(
            "{n} points: 11 parameters with one constraint need at least 10 (the solver refuses)"
        ));
    }
    let postures = config.plan.postures_rad.len();
    Ok(KindPlanCheck {
        kind: KIND.into(),
        plan: format!(
            "{postures} postures x {} points, {} readings per point",
            config.plan.points_per_posture, config.plan.readings_per_point
        ),
        noise_model: format!(
            "probe σ {:.3e} m per reading, mean of {} per point: {:.3e} m along the beam \
             (a residual's σ is that times |cos| of the beam against the surface normal)",
            config.devices.probe.noise_m,
            config.plan.readings_per_point,
            problem.observations.first().map_or(0.0, |o| o.sigma_m)
        ),
        observations: n,
        unknowns: 10,
        identifiability,
        parameters,
        summary,
        details: serde_json::json!({
            "beam_tilt_axes": { "e1": [e1.x, e1.y, e1.z], "e2": [e2.x, e2.y, e2.z] },
            "sigma_source": if solver_sigma.is_some() { "solver covariance (LM on the noise-free plan)" } else { "block analysis (the solver cannot solve this plan)" },
        }),
        warnings,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const EXAMPLE: &str = include_str!("../../../config/probe-install.toml");

    fn config(text: &str) -> ProbeInstallConfig {
        ProbeInstallConfig::parse(text, std::path::Path::new("pi-test.toml")).expect("config")
    }

    #[test]
    fn the_published_postures_identify_all_11_parameters() {
        let c = check(&config(EXAMPLE)).expect("check");
        assert_eq!(c.identifiability.deficiency, 0, "{:?}", c.identifiability);
        assert_eq!(c.parameters.len(), 11);
        assert!(c.parameters.iter().all(|p| p.sigma.is_some()));
        // The block analysis and the solver agree on every free parameter's σ.
        let b = c
            .parameters
            .iter()
            .find(|p| p.name == "b_offset_rad")
            .expect("δB");
        assert!(b.sigma.is_some_and(|s| s > 0.0 && s < 1e-3));
    }
}
