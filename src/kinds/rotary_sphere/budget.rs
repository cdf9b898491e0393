//! The uncertainty budget of the location errors (PIGE) and of the six motion errors at each
//! angle (docs/uncertainty.md, "rotary_sphere"): systematic inputs by central differences
//! through the centre fits and the axis identification, the sphere's form as the readings'
//! noise propagates.

use crate::evaluate::uncertainty::{
    central_difference, kind_budgets, Declared, KindBudgets, Quantity,
};
use crate::model::rotary_sphere::{LOCATION_NAMES, MOTION_NAMES};

use super::config::{SpherePlanConfig, SphereUncertainty};
use super::solve::{identify, ProbedSphere, RotarySphereMethodError};

/// Steps of the differences: the readings' scale by 0.1 %, the radius by 1 µm; both far
/// inside the solvers' linear range and far above their convergence.
const SCALE_STEP: f64 = 1e-3;
const RADIUS_STEP_M: f64 = 1e-6;

/// Units of the motion errors, in `MOTION_NAMES` order, and of the location errors.
const MOTION_UNITS: [&str; 6] = ["m", "m", "m", "rad", "rad", "rad"];
const LOCATION_UNITS: [&str; 4] = ["m", "m", "rad", "rad"];

/// The reported quantities with their σ: EXOC, EYOC, EAOC, EBOC, then the six motion errors
/// at each angle probed at every fit height.
fn quantities(
    plan: &SpherePlanConfig,
    noise_m: f64,
    probed: &[ProbedSphere],
) -> Result<Vec<Quantity>, RotarySphereMethodError> {
    let id = identify(plan, noise_m, probed)?.identification;
    let mut out: Vec<Quantity> = (0..4)
        .map(|k| Quantity {
            name: LOCATION_NAMES[k].to_string(),
            unit: LOCATION_UNITS[k],
            value: id.location[k],
            sigma: id.location_sigma[k],
        })
        .collect();
    for (i, angle) in id.angles_rad.iter().enumerate() {
        for k in 0..6 {
            out.push(Quantity {
                name: format!("{} at {:.1}°", MOTION_NAMES[k], angle.to_degrees()),
                unit: MOTION_UNITS[k],
                value: id.motion[i][k],
                sigma: id.motion_sigma[i][k],
            });
        }
    }
    Ok(out)
}

fn values(
    plan: &SpherePlanConfig,
    noise_m: f64,
    probed: &[ProbedSphere],
) -> Result<Vec<f64>, RotarySphereMethodError> {
    Ok(quantities(plan, noise_m, probed)?
        .iter()
        .map(|q| q.value)
        .collect())
}

/// The budgets of the identification from `probed` (plan `plan`, σ of one reading `noise_m`)
/// with the contributors `declared`.
pub fn budgets(
    plan: &SpherePlanConfig,
    noise_m: f64,
    probed: &[ProbedSphere],
    declared: &SphereUncertainty,
) -> Result<KindBudgets, RotarySphereMethodError> {
    let quantities = quantities(plan, noise_m, probed)?;
    // The probe reads (1 + g) times the travel to the surface.
    let probe_scale = central_difference(SCALE_STEP, |h| {
        let mut p = probed.to_vec();
        for point in p.iter_mut().flat_map(|s| s.points.iter_mut()) {
            point.mean_m *= 1.0 + h;
        }
        values(plan, noise_m, &p)
    })?;
    let radius = central_difference(RADIUS_STEP_M, |h| {
        let mut p = plan.clone();
        p.sphere_radius_m += h;
        values(&p, noise_m, probed)
    })?;
    // A radial form deviation at a probed point moves its reading as the probe's noise does
    // (the probe meets the surface along its normal); independent between points, it adds to
    // each quantity the variance of the noise scaled by (u_form / σ_point)², σ_point the
    // noise of the points' mean readings the fits weigh with.
    let readings = probed
        .iter()
        .flat_map(|s| s.points.iter().map(|p| p.readings))
        .min()
        .unwrap_or(1);
    let sigma_point = noise_m / (readings as f64).sqrt();
    let form: Vec<f64> = quantities.iter().map(|q| q.sigma / sigma_point).collect();
    let ppm = |c: Vec<f64>| c.iter().map(|v| v * 1e-6).collect::<Vec<f64>>();
    let declared_inputs = [
        Declared {
            name: "probe calibration (scale)",
            key: "probe_scale_ppm",
            unit: "ppm",
            u: declared.probe_scale_ppm,
        },
        Declared {
            name: "reference sphere radius",
            key: "sphere_radius_m",
            unit: "m",
            u: declared.sphere_radius_m,
        },
        Declared {
            name: "reference sphere form",
            key: "sphere_form_m",
            unit: "m",
            u: declared.sphere_form_m,
        },
    ];
    Ok(kind_budgets(
        &quantities,
        &declared_inputs,
        &[ppm(probe_scale), radius, form],
    ))
}
