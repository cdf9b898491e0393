//! Plan check of kind `hexapod`: σ of the 36 hinge coordinates from the relative leg-length
//! changes at the planned poses (design hinges), and the hinge combinations the poses cannot see.

use nalgebra::DMatrix;

use crate::kinds::hexapod::config::{HexapodConfig, KIND};
use crate::kinds::hexapod::plan::HexapodPlan;
use crate::kinds::hexapod::sim::to_pose;
use crate::method::plan_check_kinds::linear::{analyse, BlockAnalysis};
use crate::method::plan_check_kinds::{merge, summarise, KindPlanCheck, PredictedSigma};
use crate::model::hexapod::{relative_length, Pose, LEGS};
use crate::solve::hexapod::HexapodObservations;
use crate::solve::hexapod_weighted::{refine_weighted, HexapodNoise, PoseNoise};

/// Name of coordinate k (0..3) of leg i's base (`base`) or platform hinge.
fn name(part: &str, leg: usize, k: usize) -> String {
    format!("{part}_{leg}_{}_m", ["x", "y", "z"][k])
}

/// Names of one leg's 6 unknowns in the solver's order [B_i, P_i].
fn leg_names(leg: usize) -> Vec<String> {
    (0..6)
        .map(|c| name(if c < 3 { "base" } else { "platform" }, leg, c % 3))
        .collect()
}

/// The planned poses as the solver sees them (commanded = measured in the prediction).
pub fn plan_poses(plan: &HexapodPlan) -> Vec<Pose> {
    plan.poses
        .iter()
        .map(|p| {
            to_pose(&geocal_drivers::PlatformPose {
                translation_m: p.translation_m,
                rotation_vector_rad: p.rotation_vector_rad,
            })
        })
        .collect()
}

/// σ of one relative change as the method forms it: σ_enc·√(1/n + 1/n₀).
pub fn sigma_change_m(config: &HexapodConfig) -> f64 {
    let p = &config.plan;
    config.devices.hexapod.encoder_noise_m
        * (1.0 / p.readings_per_pose.max(1) as f64 + 1.0 / p.reference_readings.max(1) as f64)
            .sqrt()
}

/// The solver's noise model for the planned poses: the encoder σ, the readings per pose (the
/// reference pose's at home) and the pose sensor's σ (0 without one: commanded poses).
fn noise_model(config: &HexapodConfig, poses: usize) -> HexapodNoise {
    let p = &config.plan;
    let (translation_sigma_m, rotation_sigma_rad) = config
        .devices
        .pose_sensor
        .as_ref()
        .map_or((0.0, 0.0), |s| (s.noise_m, s.noise_rad));
    HexapodNoise {
        encoder_sigma_m: config.devices.hexapod.encoder_noise_m,
        poses: (0..poses)
            .map(|k| PoseNoise {
                readings: if k == 0 {
                    p.reference_readings
                } else {
                    p.readings_per_pose
                },
                translation_sigma_m,
                rotation_sigma_rad,
            })
            .collect(),
    }
}

pub fn check(config: &HexapodConfig) -> Result<KindPlanCheck, String> {
    let plan = HexapodPlan::from_config(config);
    let design = config.machine.nominal();
    let poses = plan_poses(&plan);
    let sigma_m = sigma_change_m(config);
    let changes = poses.len().saturating_sub(1);
    // Per leg, the whitened Jacobian of the changes from home (the model the solver fits).
    let blocks: Vec<BlockAnalysis> = (0..LEGS)
        .map(|leg| {
            let x = design.leg(leg);
            let j = DMatrix::from_fn(changes, 6, |r, c| {
                relative_length(&x, &poses[0], &poses[r + 1]).1[c] / sigma_m
            });
            analyse(&leg_names(leg), &j)
        })
        .collect();
    let names: Vec<Vec<String>> = (0..LEGS).map(leg_names).collect();
    let identifiability = merge(
        &blocks.iter().collect::<Vec<_>>(),
        6 * LEGS,
        &names,
        Vec::new(),
    );
    let mut warnings = Vec::new();
    // Where every leg is identified, the σ are the solver's own (`coordinate_sigmas_m` at the
    // design hinges); otherwise the blocks' σ of what stays identifiable.
    let solver_sigmas = if identifiability.deficiency == 0 {
        let obs = HexapodObservations {
            delta_lengths_m: poses
                .iter()
                .map(|p| std::array::from_fn(|i| relative_length(&design.leg(i), &poses[0], p).0))
                .collect(),
            poses: poses.clone(),
            sigma_m,
            search_poses: None,
        };
        // The weighted refit's covariance at the design hinges: noise-free changes, so it
        // stays there; the pose sensor's noise enters the weights as in the solver.
        match refine_weighted(&obs, &noise_model(config, poses.len()), &design) {
            Ok(fit) => Some(fit.sigmas_m()),
            Err(e) => {
                warnings.push(format!("the solver's covariance is not available: {e}"));
                None
            }
        }
    } else {
        None
    };
    // Parameters in the order of `HexapodGeometry::to_vec`: B_0..B_5, then P_0..P_5.
    let mut parameters = Vec::with_capacity(6 * LEGS);
    for part in 0..2 {
        for leg in 0..LEGS {
            for k in 0..3 {
                let c = 3 * part + k;
                let sigma = match &solver_sigmas {
                    Some(s) => Some(s[3 * (part * LEGS + leg) + k]),
                    None => blocks[leg].sigma[c],
                };
                parameters.push(PredictedSigma {
                    name: leg_names(leg)[c].clone(),
                    unit: "m",
                    sigma,
                });
            }
        }
    }
    let summary = summarise(&parameters, |n| {
        let part = if n.starts_with("base") {
            "base"
        } else {
            "platform"
        };
        let axis = if n.ends_with("_z_m") { "z" } else { "x, y" };
        format!("{part} hinges {axis}")
    });
    if changes < 6 {
        warnings.push(format!(
            "{changes} poses besides home: each leg has 6 unknowns, at least 6 are needed"
        ));
    }
    match &config.devices.pose_sensor {
        Some(_) => {}
        None => warnings.push(
            "no pose sensor: the solver uses the commanded poses, exact only if the platform \
             reaches them exactly"
                .into(),
        ),
    }
    let poses_with_rotation = plan.poses[1..]
        .iter()
        .filter(|p| p.rotation_vector_rad.iter().any(|r| *r != 0.0))
        .count();
    if poses_with_rotation == 0 {
        warnings.push(
            "no pose rotates the platform: a pure translation sees only P_i − B_i of each leg"
                .into(),
        );
    }
    Ok(KindPlanCheck {
        kind: KIND.into(),
        plan: format!(
            "{} poses with home ({} rotated), {} leg readings per pose, {} at home",
            plan.poses.len(),
            poses_with_rotation,
            plan.readings_per_pose,
            plan.reference_readings
        ),
        noise_model: {
            let (pose_m, pose_rad) = config
                .devices
                .pose_sensor
                .as_ref()
                .map_or((0.0, 0.0), |s| (s.noise_m, s.noise_rad));
            format!(
                "leg encoder σ {:.3e} m per reading; each change from home σ_enc·√(1/n + 1/n₀) = \
                 {sigma_m:.3e} m; pose σ {pose_m:.3e} m, {pose_rad:.3e} rad (in the weights, \
                 as the solver's weighted refit)",
                config.devices.hexapod.encoder_noise_m
            )
        },
        observations: changes * LEGS,
        unknowns: 6 * LEGS,
        identifiability,
        parameters,
        summary,
        details: serde_json::json!({
            "sigma_change_m": sigma_m,
            "per_leg_rank": blocks.iter().map(|b| b.rank).collect::<Vec<_>>(),
            "per_leg_condition_number": blocks.iter().map(|b| b.condition_number).collect::<Vec<_>>(),
            "sigma_source": if solver_sigmas.is_some() { "the weighted refit's covariance at the design hinges" } else { "block analysis (the solver cannot solve this plan)" },
        }),
        warnings,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const EXAMPLE: &str = include_str!("../../../config/hexapod.toml");

    fn config(text: &str) -> HexapodConfig {
        HexapodConfig::parse(text, std::path::Path::new("hexapod-test.toml")).expect("config")
    }

    #[test]
    fn the_example_plan_identifies_all_36_coordinates() {
        let c = check(&config(EXAMPLE)).expect("check");
        assert_eq!(c.identifiability.deficiency, 0, "{:?}", c.identifiability);
        assert_eq!(c.parameters.len(), 36);
        // Platform hinges are known better than base hinges, the vertical base worst.
        let s = |n: &str| {
            c.parameters
                .iter()
                .find(|p| p.name == n)
                .and_then(|p| p.sigma)
                .expect(n)
        };
        assert!(s("base_0_z_m") > s("platform_0_x_m"), "{:?}", c.summary);
        assert!(c
            .parameters
            .iter()
            .all(|p| p.sigma.is_some_and(|v| v > 0.0)));
    }

    /// Pure translations: each leg sees only P_i − B_i: three null directions per leg, each
    /// pairing a base coordinate with the same platform coordinate.
    #[test]
    fn translations_only_leave_base_and_platform_confounded() {
        let c = check(&config(&EXAMPLE.replace(
            "tilt_half_range_rad = 0.17453292519943295",
            "tilt_half_range_rad = 0.0",
        )))
        .expect("check");
        let id = &c.identifiability;
        assert_eq!(id.deficiency, 18, "{id:?}");
        assert_eq!(id.unidentifiable.len(), 36);
        for d in &id.null_directions {
            assert_eq!(d.parameters.len(), 2, "{d:?}");
            let coord = |n: &str| n.split('_').skip(1).collect::<Vec<_>>().join("_");
            assert_eq!(coord(&d.parameters[0]), coord(&d.parameters[1]), "{d:?}");
            assert!((d.coefficients[1] - 1.0).abs() < 1e-6, "{d:?}");
        }
        assert!(c.warnings.iter().any(|w| w.contains("P_i − B_i")));
    }
}
