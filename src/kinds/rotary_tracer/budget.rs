//! The uncertainty budget of each step-angle error (docs/uncertainty.md, "Angles"): the
//! solve's σ and the reflector/probe uncertainty of the two stations the angle is taken between.

use super::solve::RotaryResult;
use crate::config::uncertainty::UncertaintyConfig;
use crate::evaluate::uncertainty::{angle_budget, Budget};

/// One budget per step, in the order of `rotary.steps`. An angle between two stations on a
/// circle of radius R moves by u/R for each station's tangential uncertainty u: with two
/// stations, the lever is R/√2. The reference station's error is 0 by definition.
pub fn step_angle_budgets(rotary: &RotaryResult, declared: &UncertaintyConfig) -> Vec<Budget> {
    rotary
        .steps
        .iter()
        .map(|s| {
            let name = format!(
                "step-angle error at {:.4}° ({})",
                s.commanded_rad.to_degrees(),
                s.station
            );
            let lever_m = if s.station == rotary.reference_station {
                0.0
            } else {
                rotary.radius_m / std::f64::consts::SQRT_2
            };
            angle_budget(&name, s.error_rad, s.sigma_rad, lever_m, declared)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinds::rotary_tracer::solve::StepResult;

    #[test]
    fn reference_has_no_uncertainty_and_steps_combine_both_stations() {
        let step = |station: &str, sigma_rad: f64| StepResult {
            station: station.into(),
            commanded_rad: 0.5,
            encoder_rad: None,
            measured_rad: 0.5,
            error_rad: 1e-5,
            sigma_rad,
            approach: None,
        };
        let rotary = RotaryResult {
            table: "c".into(),
            axis_point_m: [0.0; 3],
            axis_point_sigma_m: [0.0; 3],
            axis_direction: [0.0, 0.0, 1.0],
            axis_direction_sigma: [0.0; 3],
            radius_m: 0.2,
            radius_sigma_m: 0.0,
            circle_residual_rms_m: 0.0,
            reference_station: "c0".into(),
            note: String::new(),
            steps: vec![step("c0", 0.0), step("c1", 3e-6)],
            error_covariance_rad2: Vec::new(),
        };
        let b = step_angle_budgets(&rotary, &UncertaintyConfig::default());
        assert_eq!(b[0].combined_standard_uncertainty, 0.0);
        // u = sqrt((3e-6)² + (2e-7·√2 / 0.2)²) = sqrt(9e-12 + 2e-12).
        assert!((b[1].combined_standard_uncertainty - 11e-12f64.sqrt()).abs() < 1e-15);
        assert!((b[1].expanded_uncertainty - 2.0 * 11e-12f64.sqrt()).abs() < 1e-15);
    }
}
