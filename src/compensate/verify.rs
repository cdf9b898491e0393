//! A verification run's before/after: each error its tables target, from the calibration the
//! tables were made from (before) and from the same plan on the compensated machine (after),
//! and the pass rule RMS(after) ≤ 2·RMS(σ) + interpolation error (docs/compensation.md).

use super::applied::TableRecord;
use super::{Calibration, Curve, AXES, POSITIONING};

/// One compensated error before and after, on the calibrated grid of its base axis (metres).
#[derive(Debug, Clone, PartialEq)]
pub struct Comparison {
    /// `EXX`, or for a cross pair the straightness with its squareness (`EXY − EC0Y·y`).
    pub name: String,
    pub base: usize,
    pub compensated: usize,
    pub positions_m: Vec<f64>,
    pub before_m: Vec<f64>,
    pub after_m: Vec<f64>,
    pub sigma_before_m: Vec<f64>,
    pub sigma_after_m: Vec<f64>,
    /// What the tables remove at each position (their sum).
    pub tables_m: Vec<f64>,
    /// Largest departure, over the calibrated travel, of the tables (interpolated as the
    /// controller does) from the before curve: the step's interpolation error and the
    /// rounding of the written values.
    pub interpolation_error_m: f64,
}

fn rms(v: &[f64]) -> f64 {
    (v.iter().map(|x| x * x).sum::<f64>() / v.len().max(1) as f64).sqrt()
}

fn max_abs(v: &[f64]) -> f64 {
    v.iter().fold(0.0, |m, x| m.max(x.abs()))
}

impl Comparison {
    /// σ of the difference at each position: the first calibration's error and the second
    /// run's noise, independent.
    pub fn sigma_m(&self) -> Vec<f64> {
        self.sigma_before_m
            .iter()
            .zip(&self.sigma_after_m)
            .map(|(b, a)| b.hypot(*a))
            .collect()
    }

    pub fn rms_before_m(&self) -> f64 {
        rms(&self.before_m)
    }

    pub fn rms_after_m(&self) -> f64 {
        rms(&self.after_m)
    }

    pub fn max_before_m(&self) -> f64 {
        max_abs(&self.before_m)
    }

    pub fn max_after_m(&self) -> f64 {
        max_abs(&self.after_m)
    }

    pub fn sigma_rms_m(&self) -> f64 {
        rms(&self.sigma_m())
    }

    /// 2·RMS(σ) + interpolation error: what may be left after a right table.
    pub fn bound_m(&self) -> f64 {
        2.0 * self.sigma_rms_m() + self.interpolation_error_m
    }

    pub fn passes(&self) -> bool {
        self.rms_after_m() <= self.bound_m()
    }
}

/// The error a table between `base` and `compensated` removes, by name.
pub fn error_name(base: usize, compensated: usize) -> String {
    if base == compensated {
        return POSITIONING[base].to_string();
    }
    let straightness = format!(
        "E{}{}",
        AXES[compensated].to_uppercase(),
        AXES[base].to_uppercase()
    );
    match (base, compensated) {
        (1, 0) => format!("{straightness} − EC0Y·y"),
        (2, 1) => format!("{straightness} − EA0Z·z"),
        (2, 0) => format!("{straightness} + EB0Z·z"),
        _ => straightness,
    }
}

/// The curve a table pair targets in a calibration (branch-signed, as the tables hold it).
pub fn target_curve(calibration: &Calibration, base: usize, compensated: usize) -> Option<Curve> {
    if base == compensated {
        calibration.positioning(base).ok()
    } else {
        calibration.cross(base, compensated)
    }
}

/// Values and sigmas of a curve known everywhere (datum sigmas are 0).
fn known(curve: &Curve) -> Option<(Vec<f64>, Vec<f64>)> {
    let values = curve.values.iter().copied().collect::<Option<Vec<f64>>>()?;
    let sigma = curve.sigma.iter().map(|s| s.unwrap_or(0.0)).collect();
    Some((values, sigma))
}

/// Every (base, compensated) pair the tables act on, in table order, compared before and
/// after; a pair that cannot be compared says why.
pub fn compare(
    before: &Calibration,
    after: &Calibration,
    tables: &[TableRecord],
) -> Vec<Result<Comparison, String>> {
    let mut pairs: Vec<(usize, usize)> = Vec::new();
    for t in tables {
        if let (Some(b), Some(c)) = (t.base(), t.compensated()) {
            if !pairs.contains(&(b, c)) {
                pairs.push((b, c));
            }
        }
    }
    pairs
        .into_iter()
        .map(|(b, c)| {
            let of_pair: Vec<&TableRecord> = tables
                .iter()
                .filter(|t| t.base() == Some(b) && t.compensated() == Some(c))
                .collect();
            compare_pair(before, after, b, c, &of_pair)
        })
        .collect()
}

fn compare_pair(
    before: &Calibration,
    after: &Calibration,
    base: usize,
    compensated: usize,
    tables: &[&TableRecord],
) -> Result<Comparison, String> {
    let name = error_name(base, compensated);
    let curve = |cal: &Calibration, which: &str| {
        target_curve(cal, base, compensated)
            .and_then(|c| known(&c).map(|k| (c, k)))
            .ok_or_else(|| format!("{name} is not identifiable in the {which} results"))
    };
    let (before_curve, (before_m, sigma_before_m)) = curve(before, "before")?;
    let (after_curve, (after_m, sigma_after_m)) = curve(after, "verification run's")?;
    let grid = &before_curve.positions_m;
    let same_grid = grid.len() == after_curve.positions_m.len()
        && grid
            .iter()
            .zip(&after_curve.positions_m)
            .all(|(a, b)| (a - b).abs() <= 1e-9);
    if !same_grid {
        return Err(format!(
            "{name}: the before results' {} grid ({} positions) is not this run's ({} \
             positions): not the same plan",
            AXES[base],
            grid.len(),
            after_curve.positions_m.len()
        ));
    }
    let removed = |q: f64| tables.iter().map(|t| t.deviation_at(q)).sum::<f64>();
    let zero = before_curve.at(grid[0]).unwrap_or(0.0);
    // Both the fitted curve (linear between grid positions) and the tables (linear between
    // nodes) kink only at their nodes: the largest departure lies at or between them.
    let (lo, hi) = (grid[0], *grid.last().unwrap_or(&grid[0]));
    let mut knots: Vec<f64> = grid.clone();
    for t in tables {
        knots.extend(
            t.positions_m
                .iter()
                .copied()
                .filter(|q| (lo..=hi).contains(q)),
        );
    }
    knots.sort_by(f64::total_cmp);
    knots.dedup();
    let mut interpolation_error_m: f64 = 0.0;
    for w in knots.windows(2) {
        for i in 0..=8 {
            let q = w[0] + (w[1] - w[0]) * f64::from(i) / 8.0;
            if let Some(fitted) = before_curve.at(q) {
                interpolation_error_m =
                    interpolation_error_m.max((removed(q) - (fitted - zero)).abs());
            }
        }
    }
    Ok(Comparison {
        name,
        base,
        compensated,
        tables_m: grid.iter().map(|&q| removed(q)).collect(),
        positions_m: grid.clone(),
        before_m,
        after_m,
        sigma_before_m,
        sigma_after_m,
        interpolation_error_m,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn comparison(after: Vec<f64>, sigma: f64, interp: f64) -> Comparison {
        let n = after.len();
        Comparison {
            name: "EXX".into(),
            base: 0,
            compensated: 0,
            positions_m: (0..n).map(|i| i as f64).collect(),
            before_m: vec![1e-5; n],
            after_m: after,
            sigma_before_m: vec![sigma; n],
            sigma_after_m: vec![sigma; n],
            tables_m: vec![0.0; n],
            interpolation_error_m: interp,
        }
    }

    #[test]
    fn the_pass_rule_is_rms_against_two_sigma_plus_interpolation() {
        // σ of the difference: √2·σ = 1 µm when σ = 0.7071 µm.
        let s = 1e-6 / 2f64.sqrt();
        let c = comparison(vec![2e-6, -2e-6], s, 0.0);
        assert!((c.bound_m() - 2e-6).abs() < 1e-15);
        assert!(c.passes());
        let c = comparison(vec![2.1e-6, -2.1e-6], s, 0.0);
        assert!(!c.passes());
        let c = comparison(vec![2.1e-6, -2.1e-6], s, 0.2e-6);
        assert!(c.passes());
    }

    #[test]
    fn names_carry_the_squareness_of_the_pair() {
        assert_eq!(error_name(1, 1), "EYY");
        assert_eq!(error_name(1, 0), "EXY − EC0Y·y");
        assert_eq!(error_name(0, 1), "EYX");
        assert_eq!(error_name(2, 0), "EXZ + EB0Z·z");
    }
}
