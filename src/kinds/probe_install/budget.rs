//! The uncertainty budget of the 11 installation parameters and the measured sphere radius
//! (docs/uncertainty.md, "probe_install"): sensitivities by central differences through the LM
//! solver started at the solution, each declared input moved in the observations it acts on.

use crate::evaluate::uncertainty::{
    central_difference, kind_budgets, Declared, KindBudgets, Quantity,
};
use crate::model::probe_install::{
    beam_in_base, surface_point, InstallParams, ProbeObservation, N_PARAMS, PARAM_NAMES,
};
use crate::solve::probe_install::{
    measured_radius_m, solve_lm, LmOptions, ProbeInstallError, ProbeInstallProblem,
};

use super::config::ProbeInstallUncertainty;

/// Steps of the differences: inside the solver's linear range, far above its convergence.
const READING_STEP_M: f64 = 1e-6;
const SCALE_STEP: f64 = 1e-5;
const RADIUS_STEP_M: f64 = 1e-6;

/// Units of the parameters, in `PARAM_NAMES` order (the beam direction is a unit vector).
const PARAM_UNITS: [&str; N_PARAMS] = ["rad", "m", "1", "1", "1", "m", "m", "m", "m", "m", "m"];

/// The reported quantities: the 11 parameters and the radius measured with them.
fn quantities(
    problem: &ProbeInstallProblem,
    start: &InstallParams,
) -> Result<Vec<f64>, ProbeInstallError> {
    let lm = solve_lm(problem, start, &LmOptions::default())?;
    let mut out: Vec<f64> = lm.params.to_vector().iter().copied().collect();
    out.push(measured_radius_m(&lm.params, &problem.observations)?);
    Ok(out)
}

/// The problem with every observation changed by `change`.
fn with(
    problem: &ProbeInstallProblem,
    change: impl Fn(&mut ProbeObservation),
) -> ProbeInstallProblem {
    let mut p = problem.clone();
    p.observations.iter_mut().for_each(change);
    p
}

/// The budgets of the LM solution `solution` (σ: its Cramér–Rao standard uncertainties, in
/// `PARAM_NAMES` order) of `problem`, with the contributors `declared`.
pub fn budgets(
    problem: &ProbeInstallProblem,
    solution: &InstallParams,
    sigma: &[f64],
    declared: &ProbeInstallUncertainty,
) -> Result<KindBudgets, ProbeInstallError> {
    let values = quantities(problem, solution)?;
    let n_q = values.len();
    // Per observation, ∂(quantity)/∂(reading): the radius's statistical σ and the sphere
    // form's propagation come from these.
    let mut by_reading: Vec<Vec<f64>> = Vec::with_capacity(problem.observations.len());
    for i in 0..problem.observations.len() {
        by_reading.push(central_difference(READING_STEP_M, |h| {
            let mut p = problem.clone();
            p.observations[i].reading_m += h;
            quantities(&p, solution)
        })?);
    }
    let radius_sigma = problem
        .observations
        .iter()
        .zip(&by_reading)
        .map(|(o, g)| (g[n_q - 1] * o.sigma_m).powi(2))
        .sum::<f64>()
        .sqrt();
    // A radial form deviation δ at a point moves it off the sphere as a reading change of
    // δ / (beam · normal) does.
    let centre = solution.sphere_centre();
    let incidence: Vec<f64> = problem
        .observations
        .iter()
        .map(|o| {
            let normal = (surface_point(solution, o) - centre).normalize();
            beam_in_base(solution, o.a_rad, o.b_rad)
                .normalize()
                .dot(&normal)
        })
        .collect();
    let form: Vec<f64> = (0..n_q)
        .map(|q| {
            by_reading
                .iter()
                .zip(&incidence)
                .map(|(g, c)| (g[q] / c).powi(2))
                .sum::<f64>()
                .sqrt()
        })
        .collect();
    let probe_scale = central_difference(SCALE_STEP, |h| {
        quantities(&with(problem, |o| o.reading_m *= 1.0 + h), solution)
    })?;
    let radius = central_difference(RADIUS_STEP_M, |h| {
        let mut p = problem.clone();
        p.sphere_radius_m += h;
        quantities(&p, solution)
    })?;
    let mut machine_scale = Vec::new();
    for axis in 0..3 {
        machine_scale.push(central_difference(SCALE_STEP, |h| {
            quantities(&with(problem, |o| o.machine_m[axis] *= 1.0 + h), solution)
        })?);
    }
    let ppm = |c: Vec<f64>| c.iter().map(|v| v * 1e-6).collect::<Vec<f64>>();
    let d = declared;
    let contributors = [
        (
            "probe calibration (scale)",
            "probe_scale_ppm",
            "ppm",
            d.probe_scale_ppm,
            ppm(probe_scale),
        ),
        (
            "reference sphere radius",
            "sphere_radius_m",
            "m",
            d.sphere_radius_m,
            radius,
        ),
        (
            "reference sphere form",
            "sphere_form_m",
            "m",
            d.sphere_form_m,
            form,
        ),
        (
            "machine scale x",
            "machine_scale_ppm",
            "ppm",
            d.machine_scale_ppm,
            ppm(machine_scale[0].clone()),
        ),
        (
            "machine scale y",
            "machine_scale_ppm",
            "ppm",
            d.machine_scale_ppm,
            ppm(machine_scale[1].clone()),
        ),
        (
            "machine scale z",
            "machine_scale_ppm",
            "ppm",
            d.machine_scale_ppm,
            ppm(machine_scale[2].clone()),
        ),
    ];
    let (declared, sensitivities): (Vec<Declared>, Vec<Vec<f64>>) = contributors
        .into_iter()
        .map(|(name, key, unit, u, c)| (Declared { name, key, unit, u }, c))
        .unzip();
    let quantities: Vec<Quantity> = values
        .iter()
        .enumerate()
        .map(|(q, &value)| Quantity {
            name: PARAM_NAMES
                .get(q)
                .map_or("sphere radius (after LM)".into(), |n| n.to_string()),
            unit: PARAM_UNITS.get(q).copied().unwrap_or("m"),
            value,
            sigma: sigma.get(q).copied().unwrap_or(radius_sigma),
        })
        .collect();
    Ok(kind_budgets(&quantities, &declared, &sensitivities))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solve::probe_install::{
        example_nominal, example_truth, published_postures_rad, simulate, SimulationSpec,
    };
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn problem() -> ProbeInstallProblem {
        let spec = SimulationSpec {
            postures_rad: published_postures_rad(),
            points_per_posture: 12,
            cap_half_angle_rad: 0.6,
            reading_half_range_m: 2e-3,
            noise_sigma_m: 1e-6,
        };
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        ProbeInstallProblem {
            nominal: example_nominal(),
            sphere_radius_m: 6e-3,
            observations: simulate(&example_truth(), 6e-3, &spec, &mut rng),
        }
    }

    /// The radius's statistical σ from the reading sensitivities is that of independent
    /// readings; a radius error moves the measured radius one to one when the beam's zero
    /// point cannot take it, and a sphere form error adds as the readings' noise does.
    #[test]
    fn budget_of_a_simulated_problem() {
        let p = problem();
        let lm = solve_lm(&p, &p.nominal, &LmOptions::default()).expect("lm");
        let none = budgets(
            &p,
            &lm.params,
            &lm.sigma,
            &ProbeInstallUncertainty::default(),
        )
        .expect("budget");
        assert_eq!(none.budgets.len(), 12);
        assert_eq!(none.not_declared.len(), 4, "{:?}", none.not_declared);
        for (b, s) in none.budgets.iter().zip(lm.sigma) {
            assert_eq!(b.combined_standard_uncertainty, s);
        }
        // A form as large as the readings' noise doubles every variance.
        let form = ProbeInstallUncertainty {
            sphere_form_m: Some(1e-6),
            ..Default::default()
        };
        let with_form = budgets(&p, &lm.params, &lm.sigma, &form).expect("budget");
        for (a, b) in none.budgets.iter().zip(&with_form.budgets).take(N_PARAMS) {
            let ratio = b.combined_standard_uncertainty / a.combined_standard_uncertainty;
            // 1/cos of the incidence lies in [1, 1/cos 0.6 + tilt] ≈ [1, 1.22].
            assert!(
                ratio > 2f64.sqrt() * 0.99 && ratio < 2f64.sqrt() * 1.25,
                "{} {ratio}",
                a.quantity
            );
        }
    }
}
