//! Shared by the kinds' Monte Carlo checks of their budgets: the spread 2s of each reported
//! quantity over the draws against the budget's U.
#![allow(dead_code)]

/// Draws per check (GUM Supplement 1 style; the acceptance asks for at least 200).
pub const DRAWS: usize = 200;

/// Agreement asked of 2s / U (the acceptance: within 15 %).
pub const TOLERANCE: f64 = 0.15;

pub fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len() as f64
}

pub fn std(v: &[f64]) -> f64 {
    let m = mean(v);
    (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (v.len() - 1) as f64).sqrt()
}

/// Per quantity, 2s of its draws (`draws[d][q]`) over `expanded[q]`.
pub fn ratios(draws: &[Vec<f64>], expanded: &[f64]) -> Vec<f64> {
    (0..expanded.len())
        .map(|q| {
            let values: Vec<f64> = draws.iter().map(|d| d[q]).collect();
            2.0 * std(&values) / expanded[q]
        })
        .collect()
}
