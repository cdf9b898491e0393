//! The statistics of a machine's history: two-sided normal p-values, the Holm–Bonferroni
//! adjustment, the weighted straight line (drift) and the best single step of a series.

use crate::solve::chi2::chi2_sf;

/// P(|N(0,1)| ≥ |z|).
pub fn two_sided_p(z: f64) -> f64 {
    if !z.is_finite() {
        return if z.is_nan() { 1.0 } else { 0.0 };
    }
    chi2_sf(z * z, 1.0).clamp(0.0, 1.0)
}

/// The |z| whose two-sided p is `p` (bisection on `two_sided_p`).
pub fn two_sided_quantile(p: f64) -> f64 {
    let (mut lo, mut hi) = (0.0f64, 40.0f64);
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if two_sided_p(mid) > p {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi)
}

/// Holm–Bonferroni adjusted p-values, in the order given: a hypothesis is rejected at
/// family-wise level α when its adjusted p ≤ α (valid under any dependence of the tests).
pub fn holm(p: &[f64]) -> Vec<f64> {
    let m = p.len();
    let mut order: Vec<usize> = (0..m).collect();
    order.sort_by(|&a, &b| p[a].total_cmp(&p[b]));
    let mut adjusted = vec![1.0; m];
    let mut running: f64 = 0.0;
    for (rank, &i) in order.iter().enumerate() {
        running = running.max(((m - rank) as f64 * p[i]).min(1.0));
        adjusted[i] = running;
    }
    adjusted
}

/// A weighted straight line y = a + b·(t − t̄).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Line {
    /// Slope, units per unit of t.
    pub slope: f64,
    pub slope_sigma: f64,
    /// Σ w (y − line)², w = 1/σ².
    pub chi2: f64,
}

/// Weighted least squares of y(t) with σ: None with fewer than 3 points or one time only.
pub fn weighted_line(t: &[f64], y: &[f64], sigma: &[f64]) -> Option<Line> {
    if t.len() < 3 {
        return None;
    }
    let w: Vec<f64> = sigma.iter().map(|s| 1.0 / (s * s)).collect();
    let sw: f64 = w.iter().sum();
    let t_mean = t.iter().zip(&w).map(|(t, w)| t * w).sum::<f64>() / sw;
    let y_mean = y.iter().zip(&w).map(|(y, w)| y * w).sum::<f64>() / sw;
    let stt: f64 = t
        .iter()
        .zip(&w)
        .map(|(t, w)| w * (t - t_mean).powi(2))
        .sum();
    if stt <= 0.0 {
        return None;
    }
    let sty: f64 = t
        .iter()
        .zip(y)
        .zip(&w)
        .map(|((t, y), w)| w * (t - t_mean) * (y - y_mean))
        .sum();
    let slope = sty / stt;
    let chi2 = t
        .iter()
        .zip(y)
        .zip(&w)
        .map(|((t, y), w)| w * (y - y_mean - slope * (t - t_mean)).powi(2))
        .sum();
    Some(Line {
        slope,
        slope_sigma: (1.0 / stt).sqrt(),
        chi2,
    })
}

/// The best single step of a series: the level after `at` (the first run of the new level)
/// minus the level before, both weighted means.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Step {
    pub at: usize,
    pub size: f64,
    pub sigma: f64,
    pub z: f64,
    /// Σ w (y − its segment's mean)².
    pub chi2: f64,
}

/// The split of the series into two levels with the largest |z| (None below 2 points).
pub fn best_step(y: &[f64], sigma: &[f64]) -> Option<Step> {
    let n = y.len();
    let mut best: Option<Step> = None;
    for at in 1..n {
        let level = |range: std::ops::Range<usize>| {
            let sw: f64 = range.clone().map(|i| 1.0 / sigma[i].powi(2)).sum();
            let mean = range.clone().map(|i| y[i] / sigma[i].powi(2)).sum::<f64>() / sw;
            let chi2: f64 = range.map(|i| ((y[i] - mean) / sigma[i]).powi(2)).sum();
            (mean, 1.0 / sw, chi2)
        };
        let (before, var_before, chi2_before) = level(0..at);
        let (after, var_after, chi2_after) = level(at..n);
        let sigma_step = (var_before + var_after).sqrt();
        let step = Step {
            at,
            size: after - before,
            sigma: sigma_step,
            z: (after - before) / sigma_step,
            chi2: chi2_before + chi2_after,
        };
        if best.is_none_or(|b| step.z.abs() > b.z.abs()) {
            best = Some(step);
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn normal_tails() {
        assert!((two_sided_p(1.959964) - 0.05).abs() < 1e-5);
        assert!((two_sided_quantile(0.05) - 1.959964).abs() < 1e-4);
        assert_eq!(two_sided_p(0.0), 1.0);
    }

    #[test]
    fn holm_adjusts_step_down() {
        let adjusted = holm(&[0.01, 0.04, 0.03, 0.2]);
        // Sorted 0.01·4, 0.03·3, 0.04·2, 0.2·1 → 0.04, 0.09, 0.09 (monotone), 0.2.
        let expected = [0.04, 0.09, 0.09, 0.2];
        for (a, e) in adjusted.iter().zip(expected) {
            assert!((a - e).abs() < 1e-12, "{adjusted:?}");
        }
    }

    #[test]
    fn line_and_step_recover_what_was_put_in() {
        let t: Vec<f64> = (0..10).map(f64::from).collect();
        let y: Vec<f64> = t.iter().map(|t| 1.0 + 0.5 * t).collect();
        let line = weighted_line(&t, &y, &[0.1; 10]).expect("line");
        assert!((line.slope - 0.5).abs() < 1e-12 && line.chi2 < 1e-18);
        assert!((line.slope_sigma - 0.1 / 82.5f64.sqrt()).abs() < 1e-12);
        let y: Vec<f64> = (0..10).map(|i| if i < 6 { 0.0 } else { 1.0 }).collect();
        let step = best_step(&y, &[0.1; 10]).expect("step");
        assert_eq!(step.at, 6);
        assert!((step.size - 1.0).abs() < 1e-12);
    }
}
