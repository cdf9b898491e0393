//! A local, non-rigid machine error for the simulated world (`[sim.effects] local_bump`): a
//! Gaussian bump of the tool position in one region, which no 21-error quasi-rigid model expresses.

pub use crate::config::sim::BumpSwitch;

impl BumpSwitch {
    /// The axes displaced by the bump (unchanged when off or degenerate).
    pub fn displace(&self, axes_m: [f64; 3]) -> [f64; 3] {
        let norm = self.direction.iter().map(|d| d * d).sum::<f64>().sqrt();
        if !self.enabled || norm == 0.0 || self.radius_m <= 0.0 {
            return axes_m;
        }
        let d2: f64 = (0..3).map(|k| (axes_m[k] - self.centre_m[k]).powi(2)).sum();
        let g = self.size_m * (-d2 / (2.0 * self.radius_m * self.radius_m)).exp();
        std::array::from_fn(|k| axes_m[k] + g * self.direction[k] / norm)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn peak_at_centre_and_off_when_disabled() {
        let mut b = BumpSwitch {
            enabled: true,
            size_m: 1e-6,
            centre_m: [1.0, 2.0, 0.5],
            radius_m: 0.2,
            direction: [0.0, 0.0, 2.0],
        };
        let at = b.displace([1.0, 2.0, 0.5]);
        assert!((at[2] - 0.5 - 1e-6).abs() < 1e-15 && at[0] == 1.0);
        // One radius away: exp(−1/2).
        let off = b.displace([1.2, 2.0, 0.5]);
        assert!((off[2] - 0.5 - 1e-6 * (-0.5f64).exp()).abs() < 1e-15);
        b.enabled = false;
        assert_eq!(b.displace([1.0, 2.0, 0.5]), [1.0, 2.0, 0.5]);
    }
}
