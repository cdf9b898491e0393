//! The truth machine's 21 geometric errors: seeded smooth random curves of realistic size.
//! Implements `GeometricErrors`, so the exact kinematic model simulates a machine with them.
//!
//! Each curve is a Legendre series in the normalised axis coordinate u ∈ [−1, 1] over the
//! travel, without the constant term: a constant linear error is an origin shift and a
//! constant angular error looks like squareness plus an offset in the volumetric error, so
//! the truth keeps those in `squareness` and leaves the curves zero-mean over the travel.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use serde_json::{json, Map, Value};

pub use crate::config::sim::ErrorSizes;
use crate::model::kinematics::{Axis, AxisErrors, GeometricErrors, Squareness};

/// A smooth error curve: `Σ legendre[k] · P_k(u)` for u ∈ [−1, 1]; outside, continued along
/// the tangent at the nearer end (C¹, grows only linearly, unlike the polynomial itself).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Curve {
    /// Coefficients of P_0, P_1, … (value units: m or rad).
    pub legendre: Vec<f64>,
}

impl Curve {
    /// Value at normalised coordinate `u`.
    pub fn eval(&self, u: f64) -> f64 {
        if u > 1.0 {
            self.end_value(1.0) + self.end_slope(1.0) * (u - 1.0)
        } else if u < -1.0 {
            self.end_value(-1.0) + self.end_slope(-1.0) * (u + 1.0)
        } else {
            self.series(u)
        }
    }

    /// RMS over u uniform in [−1, 1], exact: mean of P_k² is 1/(2k+1) and P_k are orthogonal.
    pub fn rms(&self) -> f64 {
        self.legendre
            .iter()
            .enumerate()
            .map(|(k, c)| c * c / (2 * k + 1) as f64)
            .sum::<f64>()
            .sqrt()
    }

    fn series(&self, u: f64) -> f64 {
        // Bonnet recurrence: (k+1) P_{k+1} = (2k+1) u P_k − k P_{k−1}.
        let (mut p_prev, mut p) = (1.0, u);
        let mut sum = 0.0;
        for (k, c) in self.legendre.iter().enumerate() {
            let pk = match k {
                0 => 1.0,
                1 => u,
                _ => {
                    let kf = (k - 1) as f64;
                    let next = ((2.0 * kf + 1.0) * u * p - kf * p_prev) / (kf + 1.0);
                    p_prev = p;
                    p = next;
                    next
                }
            };
            sum += c * pk;
        }
        sum
    }

    /// P_k(±1) = (±1)^k.
    fn end_value(&self, end: f64) -> f64 {
        self.legendre
            .iter()
            .enumerate()
            .map(|(k, c)| c * end.powi(k as i32))
            .sum()
    }

    /// P_k'(±1) = (±1)^(k+1) · k(k+1)/2.
    fn end_slope(&self, end: f64) -> f64 {
        self.legendre
            .iter()
            .enumerate()
            .map(|(k, c)| c * end.powi(k as i32 + 1) * (k * (k + 1)) as f64 / 2.0)
            .sum()
    }

    /// Random zero-mean curve with P_1.. weights `shape`, scaled to RMS `rms`. Uniform draws
    /// only (no transcendental functions) so the result is bit-identical on every platform.
    fn random(rng: &mut ChaCha8Rng, shape: &[f64], rms: f64) -> Curve {
        let mut legendre = vec![0.0];
        legendre.extend(shape.iter().map(|w| w * rng.random_range(-1.0..=1.0)));
        let mut curve = Curve { legendre };
        let now = curve.rms();
        // A spread of ±30 % around the requested size, so curves of one type differ in size.
        let target = rms * rng.random_range(0.7..=1.3);
        let scale = if now > 0.0 { target / now } else { 0.0 };
        curve.legendre.iter_mut().for_each(|c| *c *= scale);
        curve
    }
}

/// The 6 error curves of one axis, in `AxisErrors` order (linear x, y, z; angular x, y, z).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct AxisCurves {
    pub linear_m: [Curve; 3],
    pub angular_rad: [Curve; 3],
}

/// Relative weights of P_1..P_5: positioning is dominated by a scale (linear) term,
/// straightness and angular errors by low-order bows.
const POSITIONING_SHAPE: [f64; 5] = [1.0, 0.5, 0.35, 0.25, 0.15];
const STRAIGHTNESS_SHAPE: [f64; 5] = [0.4, 1.0, 0.6, 0.35, 0.2];
const ANGULAR_SHAPE: [f64; 5] = [0.7, 1.0, 0.6, 0.35, 0.2];

/// The truth machine's geometric errors.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TruthErrors {
    /// Travel [lo, hi] of X, Y, Z in commanded coordinates, metres; the curves span it.
    pub travel_m: [[f64; 2]; 3],
    /// Curves of X, Y, Z.
    pub axes: [AxisCurves; 3],
    pub squareness: Squareness,
}

impl TruthErrors {
    /// Seeded random errors; same seed and sizes give bit-identical curves everywhere.
    pub fn random(seed: u64, travel_m: [[f64; 2]; 3], sizes: &ErrorSizes) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let axes = Axis::ALL.map(|axis| {
            let linear_m = std::array::from_fn(|k| {
                if k == axis.index() {
                    Curve::random(&mut rng, &POSITIONING_SHAPE, sizes.positioning_m)
                } else {
                    Curve::random(&mut rng, &STRAIGHTNESS_SHAPE, sizes.straightness_m)
                }
            });
            let angular_rad =
                std::array::from_fn(|_| Curve::random(&mut rng, &ANGULAR_SHAPE, sizes.angular_rad));
            AxisCurves {
                linear_m,
                angular_rad,
            }
        });
        let mut squareness_value = || {
            let sign = if rng.random_bool(0.5) { 1.0 } else { -1.0 };
            sign * sizes.squareness_rad * rng.random_range(0.5..=1.5)
        };
        let squareness = Squareness {
            xy_rad: squareness_value(),
            yz_rad: squareness_value(),
            zx_rad: squareness_value(),
        };
        TruthErrors {
            travel_m,
            axes,
            squareness,
        }
    }

    /// A perfect machine with the given travel.
    pub fn zero(travel_m: [[f64; 2]; 3]) -> Self {
        TruthErrors {
            travel_m,
            axes: Default::default(),
            squareness: Squareness::default(),
        }
    }

    /// Normalised coordinate of `q_m` on `axis`: −1 at the low end of travel, +1 at the high
    /// end. A zero-length travel maps everything to 0.
    pub fn normalised(&self, axis: Axis, q_m: f64) -> f64 {
        let [lo, hi] = self.travel_m[axis.index()];
        let half = 0.5 * (hi - lo);
        if half.abs() > 0.0 {
            (q_m - 0.5 * (lo + hi)) / half
        } else {
            0.0
        }
    }

    /// The errors sampled at `points_per_axis` evenly spaced positions over each travel,
    /// under their ISO 230-1 names (m, rad), for exporting the truth next to a result.
    pub fn sample_table(&self, points_per_axis: usize) -> Value {
        let mut axes = Map::new();
        for axis in Axis::ALL {
            let [lo, hi] = self.travel_m[axis.index()];
            let q_m: Vec<f64> = match points_per_axis {
                0 => Vec::new(),
                1 => vec![0.5 * (lo + hi)],
                n => (0..n)
                    .map(|i| lo + (hi - lo) * i as f64 / (n - 1) as f64)
                    .collect(),
            };
            let values: Vec<AxisErrors> = q_m.iter().map(|&q| self.axis(axis, q)).collect();
            let mut table = Map::new();
            table.insert("q_m".into(), json!(q_m));
            for (k, name) in axis.iso_names().iter().enumerate() {
                let column: Vec<f64> = values
                    .iter()
                    .map(|e| {
                        if k < 3 {
                            e.linear_m[k]
                        } else {
                            e.angular_rad[k - 3]
                        }
                    })
                    .collect();
                table.insert((*name).into(), json!(column));
            }
            axes.insert(axis.letter().to_string(), Value::Object(table));
        }
        let [n_xy, n_yz, n_zx] = Squareness::ISO_NAMES;
        json!({
            "units": { "linear": "m", "angular": "rad", "q": "m" },
            "travel_m": { "X": self.travel_m[0], "Y": self.travel_m[1], "Z": self.travel_m[2] },
            "squareness_rad": {
                n_xy: self.squareness.xy_rad,
                n_yz: self.squareness.yz_rad,
                n_zx: self.squareness.zx_rad,
            },
            "axes": Value::Object(axes),
        })
    }
}

impl GeometricErrors for TruthErrors {
    fn axis(&self, axis: Axis, q_m: f64) -> AxisErrors {
        let u = self.normalised(axis, q_m);
        let c = &self.axes[axis.index()];
        AxisErrors {
            linear_m: std::array::from_fn(|k| c.linear_m[k].eval(u)),
            angular_rad: std::array::from_fn(|k| c.angular_rad[k].eval(u)),
        }
    }

    fn squareness(&self) -> Squareness {
        self.squareness
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const TRAVEL: [[f64; 2]; 3] = [[0.0, 1.4], [-0.2, 2.2], [-1.0, 0.0]];

    /// RMS over the travel by dense sampling (independent of `Curve::rms`).
    fn sampled_rms(t: &TruthErrors, axis: Axis, k: usize) -> f64 {
        let [lo, hi] = t.travel_m[axis.index()];
        let n = 4001;
        let ms: f64 = (0..n)
            .map(|i| {
                // Midpoint rule: no extra weight on the ends, where the curves are largest.
                let q = lo + (hi - lo) * (i as f64 + 0.5) / n as f64;
                let e = t.axis(axis, q);
                let v = if k < 3 {
                    e.linear_m[k]
                } else {
                    e.angular_rad[k - 3]
                };
                v * v
            })
            .sum::<f64>()
            / n as f64;
        ms.sqrt()
    }

    #[test]
    fn same_seed_same_curves_different_seed_different() {
        let sizes = ErrorSizes::default();
        let a = TruthErrors::random(42, TRAVEL, &sizes);
        let b = TruthErrors::random(42, TRAVEL, &sizes);
        let c = TruthErrors::random(43, TRAVEL, &sizes);
        assert_eq!(a, b);
        assert_ne!(a, c);
        assert_ne!(a.axes[0].linear_m[0], c.axes[0].linear_m[0]);
        assert_ne!(a.squareness, c.squareness);
    }

    #[test]
    fn rms_of_each_curve_type_near_requested_size() {
        let sizes = ErrorSizes {
            positioning_m: 5e-6,
            straightness_m: 3e-6,
            angular_rad: 7e-6,
            squareness_rad: 4e-6,
        };
        for seed in 0..20 {
            let t = TruthErrors::random(seed, TRAVEL, &sizes);
            for axis in Axis::ALL {
                for k in 0..6 {
                    let want = if k == axis.index() {
                        sizes.positioning_m
                    } else if k < 3 {
                        sizes.straightness_m
                    } else {
                        sizes.angular_rad
                    };
                    let got = sampled_rms(&t, axis, k);
                    let name = axis.iso_names()[k];
                    assert!(
                        got > want / 2.0 && got < want * 2.0,
                        "seed {seed} {name}: rms {got:e} vs {want:e}"
                    );
                    let curve = if k < 3 {
                        &t.axes[axis.index()].linear_m[k]
                    } else {
                        &t.axes[axis.index()].angular_rad[k - 3]
                    };
                    assert!((curve.rms() - got).abs() < 1e-3 * want, "{name}: exact rms");
                }
            }
            for s in [
                t.squareness.xy_rad,
                t.squareness.yz_rad,
                t.squareness.zx_rad,
            ] {
                assert!(
                    s.abs() >= sizes.squareness_rad / 2.0 && s.abs() <= sizes.squareness_rad * 2.0
                );
            }
        }
    }

    #[test]
    fn curves_are_zero_mean_over_travel() {
        let t = TruthErrors::random(5, TRAVEL, &ErrorSizes::default());
        for axis in Axis::ALL {
            let [lo, hi] = t.travel_m[axis.index()];
            let n = 2000;
            let mut mean = [0.0; 6];
            for i in 0..n {
                let q = lo + (hi - lo) * (i as f64 + 0.5) / n as f64;
                let e = t.axis(axis, q);
                for k in 0..3 {
                    mean[k] += e.linear_m[k] / n as f64;
                    mean[k + 3] += e.angular_rad[k] / n as f64;
                }
            }
            assert!(mean.iter().all(|m| m.abs() < 1e-11), "{axis}: {mean:?}");
        }
    }

    #[test]
    fn truth_machine_volumetric_error_is_micrometres_and_first_order() {
        use crate::model::kinematics::{
            actual_position, error_jacobian, error_vector, nominal_position, Structure,
        };
        let t = TruthErrors::random(3, TRAVEL, &ErrorSizes::default());
        let s = Structure::parse("FYXZ").unwrap();
        let off = [0.0, 0.0, -0.1];
        let mut worst = 0.0f64;
        for &q in &[
            [0.0, -0.2, -1.0],
            [1.4, 2.2, 0.0],
            [0.7, 1.0, -0.5],
            [1.2, 0.1, -0.9],
        ] {
            let a = actual_position(&s, &t, q, off);
            let n = nominal_position(q, off);
            let lin = error_jacobian(&s, q, off) * error_vector(&t, q);
            for k in 0..3 {
                let dev = a[k] - n[k];
                worst = worst.max(dev.abs());
                assert!(dev.abs() < 1e-4, "{q:?}: {dev:e}");
                assert!(
                    (dev - lin[k]).abs() < 1e-9,
                    "{q:?}: {dev:e} vs {:e}",
                    lin[k]
                );
            }
        }
        assert!(
            worst > 1e-6,
            "volumetric error {worst:e} too small to be realistic"
        );
    }

    #[test]
    fn legendre_series_matches_closed_forms() {
        let c = Curve {
            legendre: vec![0.5, -1.0, 2.0, 3.0, -0.25],
        };
        for u in [-1.0f64, -0.3, 0.0, 0.7, 1.0] {
            let p2 = 0.5 * (3.0 * u * u - 1.0);
            let p3 = 0.5 * (5.0 * u * u * u - 3.0 * u);
            let p4 = (35.0 * u.powi(4) - 30.0 * u * u + 3.0) / 8.0;
            let want = 0.5 - u + 2.0 * p2 + 3.0 * p3 - 0.25 * p4;
            assert!((c.eval(u) - want).abs() < 1e-14, "u {u}");
        }
    }

    #[test]
    fn extrapolation_is_continuous_and_tangent() {
        let t = TruthErrors::random(9, TRAVEL, &ErrorSizes::default());
        let c = &t.axes[1].angular_rad[2];
        for end in [-1.0, 1.0] {
            let h = 1e-6;
            let inside = c.eval(end - end * h);
            let at = c.eval(end);
            let outside = c.eval(end + end * h);
            // The one-sided slopes agree (C¹; a jump would blow up slope_out).
            let slope_in = (at - inside) / h;
            let slope_out = (outside - at) / h;
            assert!(
                (slope_in - slope_out).abs() < 1e-4 * slope_in.abs().max(1e-9),
                "end {end}"
            );
        }
        // Far outside it grows linearly, not like u^5.
        let far = c.eval(3.0);
        assert_eq!(far, c.end_value(1.0) + c.end_slope(1.0) * 2.0);
        let fd_slope = (c.eval(1.0) - c.eval(1.0 - 1e-6)) / 1e-6;
        assert!((fd_slope - c.end_slope(1.0)).abs() < 1e-4 * c.end_slope(1.0).abs());
        assert!((c.eval(-1.0) - c.end_value(-1.0)).abs() < 1e-20);
    }

    #[test]
    fn zero_truth_has_no_errors() {
        let t = TruthErrors::zero(TRAVEL);
        for axis in Axis::ALL {
            assert_eq!(t.axis(axis, 0.37), AxisErrors::default());
            assert_eq!(t.axis(axis, 9.0), AxisErrors::default());
        }
        assert_eq!(t.squareness(), Squareness::default());
    }

    #[test]
    fn serde_roundtrip_and_sample_table() {
        let t = TruthErrors::random(1, TRAVEL, &ErrorSizes::default());
        let json = serde_json::to_string(&t).unwrap();
        let back: TruthErrors = serde_json::from_str(&json).unwrap();
        assert_eq!(back, t);

        let table = t.sample_table(5);
        let x = &table["axes"]["X"];
        assert_eq!(x["q_m"].as_array().unwrap().len(), 5);
        assert_eq!(x["q_m"][0].as_f64().unwrap(), 0.0);
        assert_eq!(x["q_m"][4].as_f64().unwrap(), 1.4);
        let q2 = x["q_m"][2].as_f64().unwrap();
        assert_eq!(
            x["EBX"][2].as_f64().unwrap(),
            t.axis(Axis::X, q2).angular_rad[1]
        );
        assert_eq!(table["axes"]["Z"]["EZZ"].as_array().unwrap().len(), 5);
        assert_eq!(
            table["squareness_rad"]["EC0Y"].as_f64().unwrap(),
            t.squareness.xy_rad
        );
        assert_eq!(
            t.sample_table(1)["axes"]["Y"]["q_m"][0].as_f64().unwrap(),
            1.0
        );
    }

    #[test]
    fn sizes_default_and_deny_unknown_fields() {
        let s: ErrorSizes = serde_json::from_str(r#"{"angular_rad": 1e-6}"#).unwrap();
        assert_eq!(s.angular_rad, 1e-6);
        assert_eq!(s.positioning_m, ErrorSizes::default().positioning_m);
        assert!(serde_json::from_str::<ErrorSizes>(r#"{"angle_rad": 1e-6}"#).is_err());
        let bad = ErrorSizes {
            straightness_m: -1.0,
            ..Default::default()
        };
        assert!(bad.check().unwrap_err().contains("straightness_m"));
        assert!(ErrorSizes::default().check().is_ok());
    }

    #[test]
    fn golden_first_coefficient() {
        // Guards reproducibility across platforms and dependency updates: a change here
        // means recorded simulations no longer regenerate the same truth.
        let t = TruthErrors::random(2024, TRAVEL, &ErrorSizes::default());
        let got = t.axes[0].linear_m[0].legendre[1];
        assert_eq!(got.to_bits(), GOLDEN_EXX_P1_BITS, "EXX P1 = {got:e}");
    }

    /// −7.399976646964202e-6 m.
    const GOLDEN_EXX_P1_BITS: u64 = 13753722413157664254;
}
