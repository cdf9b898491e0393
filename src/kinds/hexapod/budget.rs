//! The uncertainty budget of the 36 hinge coordinates (docs/uncertainty.md, "hexapod"):
//! sensitivities by central differences through the weighted fit started at the solution,
//! each declared calibration error applied to the observations it acts on.

use crate::evaluate::uncertainty::{
    central_difference, kind_budgets, Declared, KindBudgets, Quantity,
};
use crate::model::hexapod::{HexapodGeometry, LEGS};
use crate::solve::hexapod::{HexapodError, HexapodObservations};
use crate::solve::hexapod_weighted::{refine_weighted, HexapodNoise};

use super::config::HexapodUncertainty;

/// Relative step of the differences: far inside the fit's linear range, far above its
/// convergence (10⁻⁶ of a σ).
const SCALE_STEP: f64 = 1e-5;

/// The name of coordinate `k` of `HexapodGeometry::to_vec`.
pub fn coordinate_name(k: usize) -> String {
    let hinge = if k < 3 * LEGS { "base" } else { "platform" };
    format!(
        "leg {} {hinge} {}",
        (k % (3 * LEGS)) / 3,
        ["x", "y", "z"][k % 3]
    )
}

/// The 36 coordinates the weighted fit reaches from `start`.
fn coordinates(
    obs: &HexapodObservations,
    noise: &HexapodNoise,
    start: &HexapodGeometry,
) -> Result<Vec<f64>, HexapodError> {
    Ok(refine_weighted(obs, noise, start)?.geometry.to_vec())
}

/// The budgets of the fitted hinges `solution` (σ: its standard uncertainties, in
/// `HexapodGeometry::to_vec` order) of `obs` with noise model `noise`.
pub fn budgets(
    obs: &HexapodObservations,
    noise: &HexapodNoise,
    solution: &HexapodGeometry,
    sigma: &[f64],
    declared: &HexapodUncertainty,
) -> Result<KindBudgets, HexapodError> {
    // The pose sensor reads every translation (1 + s) times its true value.
    let pose_scale = central_difference(SCALE_STEP, |h| {
        let mut o = obs.clone();
        o.poses.iter_mut().for_each(|p| p.translation_m *= 1.0 + h);
        coordinates(&o, noise, solution)
    })?;
    // The encoders read every length change (1 + s) times its true value.
    let leg_scale = central_difference(SCALE_STEP, |h| {
        let mut o = obs.clone();
        o.delta_lengths_m
            .iter_mut()
            .for_each(|d| d.iter_mut().for_each(|v| *v *= 1.0 + h));
        coordinates(&o, noise, solution)
    })?;
    let ppm = |c: Vec<f64>| c.iter().map(|v| v * 1e-6).collect::<Vec<f64>>();
    let declared_inputs = [
        Declared {
            name: "pose sensor calibration (scale)",
            key: "pose_scale_ppm",
            unit: "ppm",
            u: declared.pose_scale_ppm,
        },
        Declared {
            name: "leg length measurement (scale)",
            key: "leg_scale_ppm",
            unit: "ppm",
            u: declared.leg_scale_ppm,
        },
    ];
    let quantities: Vec<Quantity> = solution
        .to_vec()
        .iter()
        .zip(sigma)
        .enumerate()
        .map(|(k, (&value, &sigma))| Quantity {
            name: coordinate_name(k),
            unit: "m",
            value,
            sigma,
        })
        .collect();
    Ok(kind_budgets(
        &quantities,
        &declared_inputs,
        &[ppm(pose_scale), ppm(leg_scale)],
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solve::hexapod::simulation::{measure, nominal_geometry, perturbed, random_poses};
    use crate::solve::hexapod_weighted::PoseNoise;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    /// With nothing declared a budget is the fit's σ alone, and the contributors left out are
    /// named; a declared encoder scale acts on the coordinates.
    #[test]
    fn budget_of_a_simulated_hexapod() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let truth = perturbed(&mut rng, &nominal_geometry(), 2e-3);
        let poses = random_poses(&mut rng, 30, 10.0);
        let obs = measure(&mut rng, &truth, &poses, 1e-6);
        let noise = HexapodNoise {
            encoder_sigma_m: 1e-6 / 2f64.sqrt(),
            poses: vec![
                PoseNoise {
                    readings: 1,
                    translation_sigma_m: 0.0,
                    rotation_sigma_rad: 0.0,
                };
                poses.len()
            ],
        };
        let fit = refine_weighted(&obs, &noise, &truth).expect("fit");
        let sigma = fit.sigmas_m();
        let none =
            budgets(&obs, &noise, &fit.geometry, &sigma, &Default::default()).expect("budget");
        assert_eq!(none.budgets.len(), 36);
        assert_eq!(none.not_declared.len(), 2);
        assert_eq!(none.budgets[5].combined_standard_uncertainty, sigma[5]);
        let declared = HexapodUncertainty {
            leg_scale_ppm: Some(10.0),
            ..Default::default()
        };
        let b = budgets(&obs, &noise, &fit.geometry, &sigma, &declared).expect("budget");
        let scale = &b.budgets[2].contributors[1];
        assert_eq!(scale.name, "leg length measurement (scale)");
        assert!(scale.contribution > 0.0);
        assert_eq!(coordinate_name(2), "leg 0 base z");
        assert_eq!(coordinate_name(3 * LEGS + 4), "leg 1 platform y");
    }
}
