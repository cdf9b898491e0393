//! The uncertainty budget of the location errors (PIGE) and of the six motion errors at each
//! angle (docs/uncertainty.md, "rotary_sphere"): every input by central differences through
//! the centre fits and the axis identification, the sphere's form point by point of its surface.

use std::collections::BTreeSet;

use nalgebra::{Rotation3, Vector3};

use crate::evaluate::uncertainty::{
    central_difference, kind_budgets, Declared, KindBudgets, Quantity,
};
use crate::model::rotary_sphere::{LOCATION_NAMES, MOTION_NAMES};

use super::config::{SpherePlanConfig, SphereUncertainty};
use super::solve::{identify, ProbedSphere, RotarySphereMethodError};

/// Steps of the differences: the readings' scale by 0.1 %, the radius and a surface point's
/// form by 1 µm; far inside the solvers' linear range and far above their convergence.
const SCALE_STEP: f64 = 1e-3;
const RADIUS_STEP_M: f64 = 1e-6;
const FORM_STEP_M: f64 = 1e-6;

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

/// A point of the sphere's surface: the height the sphere stood at and the probing direction
/// in the sphere's frame (turned back by the commanded angle), rounded to 1e-9.
fn surface_point(height: usize, commanded_rad: f64, direction: &Vector3<f64>) -> (usize, [i64; 3]) {
    let body = Rotation3::from_axis_angle(&Vector3::z_axis(), -commanded_rad) * direction;
    (height, body.map(|v| (v * 1e9).round() as i64).into())
}

/// Per quantity, √(Σ over the sphere's surface points of (∂quantity/∂form there)²): each
/// surface point's readings moved together by central differences.
fn form_sensitivities(
    plan: &SpherePlanConfig,
    noise_m: f64,
    probed: &[ProbedSphere],
) -> Result<Vec<f64>, RotarySphereMethodError> {
    let surface_points: BTreeSet<(usize, [i64; 3])> = probed
        .iter()
        .flat_map(|s| {
            s.points
                .iter()
                .map(|p| surface_point(s.height_index, s.commanded_rad, &p.direction))
        })
        .collect();
    let mut sum_sq: Vec<f64> = Vec::new();
    for point in &surface_points {
        let c = central_difference(FORM_STEP_M, |h| {
            let mut moved = probed.to_vec();
            for s in moved.iter_mut() {
                let (height, commanded_rad) = (s.height_index, s.commanded_rad);
                for p in s.points.iter_mut() {
                    if surface_point(height, commanded_rad, &p.direction) == *point {
                        p.mean_m += h;
                    }
                }
            }
            values(plan, noise_m, &moved)
        })?;
        sum_sq.resize(c.len(), 0.0);
        for (acc, v) in sum_sq.iter_mut().zip(&c) {
            *acc += v * v;
        }
    }
    Ok(sum_sq.iter().map(|v| v.sqrt()).collect())
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
    // A radial form deviation of the sphere moves a reading that meets it by as much (the
    // probe meets the surface along its normal). The form is a function on the sphere's
    // surface, which turns with the table under probing directions fixed in the machine: a
    // surface point is met at every angle that brings it under a probe (the top pole at all
    // of them), so the readings of one surface point move together. Its variance in a
    // quantity is u² Σ over surface points of (the quantity's change per unit move of all
    // their readings)². The sphere's orientation at another height is not known: its surface
    // points there count as others.
    let form = form_sensitivities(plan, noise_m, probed)?;
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
