//! Hexapod hinge coordinates from relative leg-length changes at measured platform poses:
//! damped least squares (LM), then the published grid multi-start on the vertical base hinges.

use nalgebra::{SMatrix, SVector};
use serde::Serialize;

use crate::model::hexapod::{relative_length, HexapodGeometry, Pose, LEGS};

type Leg = SVector<f64, 6>;

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum HexapodError {
    #[error("need the reference pose and at least {needed} more, found {found} poses")]
    TooFewPoses { needed: usize, found: usize },
    #[error("{poses} poses but {lengths} rows of leg-length changes")]
    Shape { poses: usize, lengths: usize },
    #[error("search pose index {0} is out of range or is the reference pose 0")]
    BadSearchPose(usize),
    #[error("leg {0}: the poses do not determine its hinges (singular normal equations)")]
    Singular(usize),
    #[error("the residual covariance is not positive definite (zero encoder noise?)")]
    SingularNoise,
}

/// Relative leg-length readings. Pose 0 is the reference: `delta_lengths_m[k][i]` is leg i's
/// length at pose k minus its length at pose 0 (row 0 is ignored).
#[derive(Debug, Clone)]
pub struct HexapodObservations {
    pub poses: Vec<Pose>,
    pub delta_lengths_m: Vec<[f64; LEGS]>,
    /// Standard deviation of one reading (m).
    pub sigma_m: f64,
    /// The poses the damped least squares fits ("search poses" in ref5); None = all. The
    /// objective that judges solutions always uses every pose.
    pub search_poses: Option<Vec<usize>>,
}

impl HexapodObservations {
    fn check(&self) -> Result<Vec<usize>, HexapodError> {
        if self.delta_lengths_m.len() != self.poses.len() {
            return Err(HexapodError::Shape {
                poses: self.poses.len(),
                lengths: self.delta_lengths_m.len(),
            });
        }
        let search: Vec<usize> = match &self.search_poses {
            Some(s) => s.clone(),
            None => (1..self.poses.len()).collect(),
        };
        if let Some(&k) = search.iter().find(|&&k| k == 0 || k >= self.poses.len()) {
            return Err(HexapodError::BadSearchPose(k));
        }
        // 6 unknowns per leg, one equation per leg and pose.
        if search.len() < 6 {
            return Err(HexapodError::TooFewPoses {
                needed: 6,
                found: search.len(),
            });
        }
        Ok(search)
    }

    /// Residuals (measured − predicted) and Jacobian of the predictions for one leg.
    fn leg_system(&self, leg: usize, x: &Leg, poses: &[usize]) -> (Vec<f64>, Vec<[f64; 6]>) {
        let mut r = Vec::with_capacity(poses.len());
        let mut j = Vec::with_capacity(poses.len());
        for &k in poses {
            let (dl, g) = relative_length(x, &self.poses[0], &self.poses[k]);
            r.push(self.delta_lengths_m[k][leg] - dl);
            j.push(std::array::from_fn(|c| g[c]));
        }
        (r, j)
    }

    fn leg_cost(&self, leg: usize, x: &Leg, poses: &[usize]) -> f64 {
        poses
            .iter()
            .map(|&k| {
                let (dl, _) = relative_length(x, &self.poses[0], &self.poses[k]);
                (self.delta_lengths_m[k][leg] - dl).powi(2)
            })
            .sum()
    }

    fn all_poses(&self) -> Vec<usize> {
        (1..self.poses.len()).collect()
    }

    /// The objective of ref5: Σ over every pose and leg of the squared residual (m²).
    pub fn objective(&self, geometry: &HexapodGeometry) -> f64 {
        let all = self.all_poses();
        (0..LEGS)
            .map(|i| self.leg_cost(i, &geometry.leg(i), &all))
            .sum()
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct LmOptions {
    pub max_iterations: usize,
    pub initial_lambda: f64,
}

impl Default for LmOptions {
    fn default() -> Self {
        LmOptions {
            max_iterations: 200,
            initial_lambda: 1e-3,
        }
    }
}

/// Levenberg–Marquardt on one leg's 6 hinge coordinates (the legs do not share unknowns, so
/// the 36-parameter problem is six independent 6-parameter ones). Returns the leg and the
/// iteration count; every accepted step lowers the cost.
fn lm_leg(
    obs: &HexapodObservations,
    leg: usize,
    start: &Leg,
    poses: &[usize],
    opts: &LmOptions,
) -> (Leg, usize) {
    let mut x = *start;
    let mut cost = obs.leg_cost(leg, &x, poses);
    let mut lambda = opts.initial_lambda;
    let mut it = 0;
    while it < opts.max_iterations {
        it += 1;
        let (r, j) = obs.leg_system(leg, &x, poses);
        let mut jtj = SMatrix::<f64, 6, 6>::zeros();
        let mut jtr = Leg::zeros();
        for (row, res) in j.iter().zip(&r) {
            let g = Leg::from_column_slice(row);
            jtj += g * g.transpose();
            jtr += g * *res;
        }
        // Marquardt's scaling: the vertical base coordinate is far worse determined than the
        // rest (it moves nearly along the leg), so a plain λI would stall it.
        let mut accepted = false;
        while lambda < 1e16 {
            let mut a = jtj;
            for d in 0..6 {
                a[(d, d)] += lambda * jtj[(d, d)].max(1e-30);
            }
            let Some(chol) = a.cholesky() else {
                lambda *= 10.0;
                continue;
            };
            let step = chol.solve(&jtr);
            let trial = x + step;
            let c = obs.leg_cost(leg, &trial, poses);
            if c < cost {
                let small = step.amax() < 1e-15 || cost - c <= 1e-15 * cost;
                x = trial;
                cost = c;
                lambda = (lambda * 0.1).max(1e-12);
                accepted = true;
                if small {
                    return (x, it);
                }
                break;
            }
            lambda *= 10.0;
        }
        if !accepted {
            break;
        }
    }
    (x, it)
}

/// Damped least squares from `initial` on the search poses.
#[derive(Debug, Clone)]
pub struct LmSolution {
    pub geometry: HexapodGeometry,
    /// The all-pose objective at the start and at the end (m²).
    pub objective_initial_m2: f64,
    pub objective_m2: f64,
    pub iterations: usize,
}

pub fn solve_lm(
    obs: &HexapodObservations,
    initial: &HexapodGeometry,
    opts: &LmOptions,
) -> Result<LmSolution, HexapodError> {
    let search = obs.check()?;
    let mut geometry = initial.clone();
    let mut iterations = 0;
    for leg in 0..LEGS {
        let (x, it) = lm_leg(obs, leg, &initial.leg(leg), &search, opts);
        geometry.set_leg(leg, &x);
        iterations += it;
    }
    Ok(LmSolution {
        objective_initial_m2: obs.objective(initial),
        objective_m2: obs.objective(&geometry),
        geometry,
        iterations,
    })
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct TwoStageOptions {
    pub lm: LmOptions,
    /// First grid step of the vertical base coordinates (m).
    pub initial_step_m: f64,
    /// Factor the step shrinks by after every round.
    pub shrink: f64,
    /// The search stops once the step falls below this (m) …
    pub min_step_m: f64,
    /// … or the objective reaches this (m²); None: the noise floor, σ² · 1.5 · readings.
    pub target_objective_m2: Option<f64>,
}

impl Default for TwoStageOptions {
    fn default() -> Self {
        TwoStageOptions {
            lm: LmOptions::default(),
            initial_step_m: 8e-3,
            shrink: 0.5,
            min_step_m: 0.2e-3,
            target_objective_m2: None,
        }
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct GridRound {
    pub step_m: f64,
    pub objective_m2: f64,
    /// Legs whose best start moved in this round.
    pub improved_legs: Vec<usize>,
}

/// Calibrated hinge coordinates with uncertainties.
#[derive(Debug, Clone, Serialize)]
pub struct HexapodCalibration {
    pub base_m: Vec<[f64; 3]>,
    pub platform_m: Vec<[f64; 3]>,
    pub base_sigma_m: Vec<[f64; 3]>,
    pub platform_sigma_m: Vec<[f64; 3]>,
    /// Per leg, the 6x6 covariance of [B_i, P_i] (m²) from σ and the search poses.
    pub leg_covariance_m2: Vec<[[f64; 6]; 6]>,
    pub objective_initial_m2: f64,
    pub objective_stage1_m2: f64,
    pub objective_m2: f64,
    /// RMS residual over every pose and leg (m).
    pub residual_rms_m: f64,
    pub rounds: Vec<GridRound>,
    /// LM solves run in both stages (per leg).
    pub leg_solves: usize,
    #[serde(skip)]
    pub geometry: HexapodGeometry,
}

/// The two-stage method of ref5. Stage 1: LM from `initial`. Stage 2: around the best point so
/// far, each vertical base coordinate B_iz is stepped up and down by the step and LM re-run
/// from there; the best by the all-pose objective is kept (the current point is always a
/// candidate, so the objective never rises), then the step shrinks.
///
/// The full grid of ref5 (3⁶ starts per step) needs no 729 solves here: the objective is a sum
/// of per-leg terms and each leg's hinges enter only its own term, so the best grid point is
/// the best start per leg — 3 per leg, the same optimum.
pub fn solve_two_stage(
    obs: &HexapodObservations,
    initial: &HexapodGeometry,
    opts: &TwoStageOptions,
) -> Result<HexapodCalibration, HexapodError> {
    let search = obs.check()?;
    let all = obs.all_poses();
    let mut best: Vec<(Leg, f64)> = Vec::with_capacity(LEGS);
    let mut leg_solves = 0;
    for leg in 0..LEGS {
        let x0 = initial.leg(leg);
        let f0 = obs.leg_cost(leg, &x0, &all);
        let (x1, _) = lm_leg(obs, leg, &x0, &search, &opts.lm);
        leg_solves += 1;
        let f1 = obs.leg_cost(leg, &x1, &all);
        // The search-pose fit can raise the all-pose objective; the start stays a candidate.
        best.push(if f1 <= f0 { (x1, f1) } else { (x0, f0) });
    }
    let total = |b: &[(Leg, f64)]| b.iter().map(|(_, f)| f).sum::<f64>();
    let objective_initial_m2 = obs.objective(initial);
    let objective_stage1_m2 = total(&best);
    let readings = (all.len() * LEGS) as f64;
    let target = opts
        .target_objective_m2
        .unwrap_or(1.5 * readings * obs.sigma_m * obs.sigma_m);
    let mut rounds = Vec::new();
    let mut step = opts.initial_step_m;
    while step >= opts.min_step_m && total(&best) > target {
        let mut improved_legs = Vec::new();
        for (leg, b) in best.iter_mut().enumerate() {
            let centre = b.0;
            for sign in [1.0, -1.0] {
                let mut start = centre;
                start[2] += sign * step;
                let (x, _) = lm_leg(obs, leg, &start, &search, &opts.lm);
                leg_solves += 1;
                let f = obs.leg_cost(leg, &x, &all);
                if f < b.1 {
                    *b = (x, f);
                    if improved_legs.last() != Some(&leg) {
                        improved_legs.push(leg);
                    }
                }
            }
        }
        rounds.push(GridRound {
            step_m: step,
            objective_m2: total(&best),
            improved_legs,
        });
        step *= opts.shrink;
    }
    let mut geometry = initial.clone();
    for (leg, (x, _)) in best.iter().enumerate() {
        geometry.set_leg(leg, x);
    }
    let mut leg_covariance_m2 = Vec::with_capacity(LEGS);
    for leg in 0..LEGS {
        let (_, j) = obs.leg_system(leg, &geometry.leg(leg), &search);
        let mut jtj = SMatrix::<f64, 6, 6>::zeros();
        for row in &j {
            let g = Leg::from_column_slice(row);
            jtj += g * g.transpose();
        }
        let cov =
            jtj.try_inverse().ok_or(HexapodError::Singular(leg))? * (obs.sigma_m * obs.sigma_m);
        leg_covariance_m2.push(std::array::from_fn(|r| {
            std::array::from_fn(|c| cov[(r, c)])
        }));
    }
    let objective_m2 = total(&best);
    let sig = |c: &[[f64; 6]; 6], o: usize| -> [f64; 3] {
        std::array::from_fn(|k| c[o + k][o + k].max(0.0).sqrt())
    };
    Ok(HexapodCalibration {
        base_m: geometry.base_m.iter().map(|v| (*v).into()).collect(),
        platform_m: geometry.platform_m.iter().map(|v| (*v).into()).collect(),
        base_sigma_m: leg_covariance_m2.iter().map(|c| sig(c, 0)).collect(),
        platform_sigma_m: leg_covariance_m2.iter().map(|c| sig(c, 3)).collect(),
        leg_covariance_m2,
        objective_initial_m2,
        objective_stage1_m2,
        objective_m2,
        residual_rms_m: (objective_m2 / readings).sqrt(),
        rounds,
        leg_solves,
        geometry,
    })
}

/// Standard deviations (m) of the 36 coordinates (order of `HexapodGeometry::to_vec`) that the
/// search poses give at `geometry` with the observations' σ.
pub fn coordinate_sigmas_m(
    obs: &HexapodObservations,
    geometry: &HexapodGeometry,
) -> Result<Vec<f64>, HexapodError> {
    let search = obs.check()?;
    let mut out = vec![0.0; 6 * LEGS];
    for (leg, cov) in leg_covariances(obs, geometry, &search)?.iter().enumerate() {
        for k in 0..3 {
            out[3 * leg + k] = cov[(k, k)].max(0.0).sqrt();
            out[3 * (LEGS + leg) + k] = cov[(3 + k, 3 + k)].max(0.0).sqrt();
        }
    }
    Ok(out)
}

fn leg_covariances(
    obs: &HexapodObservations,
    geometry: &HexapodGeometry,
    search: &[usize],
) -> Result<Vec<SMatrix<f64, 6, 6>>, HexapodError> {
    (0..LEGS)
        .map(|leg| {
            let (_, j) = obs.leg_system(leg, &geometry.leg(leg), search);
            let mut jtj = SMatrix::<f64, 6, 6>::zeros();
            for row in &j {
                let g = Leg::from_column_slice(row);
                jtj += g * g.transpose();
            }
            jtj.try_inverse()
                .map(|c| c * (obs.sigma_m * obs.sigma_m))
                .ok_or(HexapodError::Singular(leg))
        })
        .collect()
}

/// Per leg, the singular values of the σ-free Jacobian of the relative lengths with respect to
/// [B_i, P_i] at `geometry`, largest first: a zero marks a combination the poses cannot see.
pub fn leg_singular_values(obs: &HexapodObservations, geometry: &HexapodGeometry) -> Vec<[f64; 6]> {
    let all = obs.all_poses();
    (0..LEGS)
        .map(|leg| {
            let (_, j) = obs.leg_system(leg, &geometry.leg(leg), &all);
            let m = nalgebra::DMatrix::from_fn(j.len(), 6, |r, c| j[r][c]);
            let mut s: Vec<f64> = m.singular_values().iter().copied().collect();
            s.sort_by(|a, b| b.total_cmp(a));
            std::array::from_fn(|k| s[k])
        })
        .collect()
}

/// A simulated hexapod and its measurement (tests and examples).
pub mod simulation {
    use super::*;
    use nalgebra::{Rotation3, Vector3};
    use rand::Rng;
    use rand_distr::{Distribution, StandardNormal};

    /// A machine-tool hexapod: base hinges in pairs on a 0.45 m circle (z = 0), platform hinges
    /// on a 0.2 m circle, platform 0.7 m below; small build errors on every coordinate.
    pub fn nominal_geometry() -> HexapodGeometry {
        let ring = |radius: f64, centre_deg: f64, i: usize| {
            let pair = (i / 2) as f64 * 120.0 + centre_deg;
            let a = (pair + if i % 2 == 0 { -12.0 } else { 12.0 }).to_radians();
            Vector3::new(radius * a.cos(), radius * a.sin(), 0.0)
        };
        HexapodGeometry {
            base_m: std::array::from_fn(|i| ring(0.45, 0.0, i)),
            platform_m: std::array::from_fn(|i| ring(0.2, 60.0, (i + 1) % 6)),
        }
    }

    /// Random poses in the workspace: ±60 mm in x, y, ±40 mm in z about 0.7 m below the base,
    /// ±`tilt_deg` about every axis. Pose 0 is home.
    pub fn random_poses<R: Rng>(rng: &mut R, count: usize, tilt_deg: f64) -> Vec<Pose> {
        let home = Pose {
            rotation: Rotation3::identity(),
            translation_m: Vector3::new(0.0, 0.0, -0.7),
        };
        let mut poses = vec![home];
        while poses.len() < count {
            let mut u = |s: f64| rng.random_range(-s..=s);
            let t = Vector3::new(u(0.06), u(0.06), -0.7 + u(0.04));
            let r = Rotation3::new(Vector3::new(
                u(tilt_deg.to_radians()),
                u(tilt_deg.to_radians()),
                u(tilt_deg.to_radians()),
            ));
            poses.push(Pose {
                rotation: r,
                translation_m: t,
            });
        }
        poses
    }

    /// Relative leg-length readings of `truth` at `poses` with Gaussian noise σ.
    pub fn measure<R: Rng>(
        rng: &mut R,
        truth: &HexapodGeometry,
        poses: &[Pose],
        sigma_m: f64,
    ) -> HexapodObservations {
        let delta_lengths_m = poses
            .iter()
            .map(|p| {
                std::array::from_fn(|i| {
                    let z: f64 = StandardNormal.sample(rng);
                    relative_length(&truth.leg(i), &poses[0], p).0 + sigma_m * z
                })
            })
            .collect();
        HexapodObservations {
            poses: poses.to_vec(),
            delta_lengths_m,
            sigma_m,
            search_poses: None,
        }
    }

    /// Every coordinate of `g` moved by a uniform error in ±`amplitude_m`.
    pub fn perturbed<R: Rng>(
        rng: &mut R,
        g: &HexapodGeometry,
        amplitude_m: f64,
    ) -> HexapodGeometry {
        let v: Vec<f64> = g
            .to_vec()
            .iter()
            .map(|x| x + rng.random_range(-amplitude_m..=amplitude_m))
            .collect();
        HexapodGeometry::from_slice(&v)
    }

    /// Largest coordinate error against the truth (m).
    pub fn max_error_m(a: &HexapodGeometry, truth: &HexapodGeometry) -> f64 {
        a.to_vec()
            .iter()
            .zip(truth.to_vec())
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f64::max)
    }
}

#[cfg(test)]
mod tests {
    use super::simulation::*;
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn truth<R: rand::Rng>(rng: &mut R) -> HexapodGeometry {
        perturbed(rng, &nominal_geometry(), 2e-3)
    }

    #[test]
    fn noise_free_exact_recovery() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let t = truth(&mut rng);
        let poses = random_poses(&mut rng, 30, 10.0);
        let obs = measure(&mut rng, &t, &poses, 0.0);
        let start = perturbed(&mut rng, &t, 1e-3);
        let lm = solve_lm(&obs, &start, &LmOptions::default()).unwrap();
        assert!(
            max_error_m(&lm.geometry, &t) < 1e-9,
            "{}",
            max_error_m(&lm.geometry, &t)
        );
        let two = solve_two_stage(&obs, &start, &TwoStageOptions::default()).unwrap();
        assert!(max_error_m(&two.geometry, &t) < 1e-9);
        assert!(two.objective_m2 <= two.objective_initial_m2);
    }

    /// All 36 coordinates are identifiable from relative lengths once the platform tilts; with
    /// translations only, B_i and P_i enter only as B_i − P_i (3 of 6 per leg are lost).
    #[test]
    fn identifiability_is_numerically_full_with_rotations() {
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let t = truth(&mut rng);
        let poses = random_poses(&mut rng, 30, 10.0);
        let obs = measure(&mut rng, &t, &poses, 0.0);
        for s in leg_singular_values(&obs, &t) {
            assert!(s[5] > 1e-4 * s[0], "{s:?}");
        }
        let poses = random_poses(&mut rng, 30, 0.0);
        let flat = measure(&mut rng, &t, &poses, 0.0);
        for s in leg_singular_values(&flat, &t) {
            assert!(s[2] > 1e-3 * s[0] && s[3] < 1e-12 * s[0], "{s:?}");
        }
    }

    #[test]
    fn noisy_within_three_sigma() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let (mut inside, mut total) = (0, 0);
        for _ in 0..5 {
            let t = truth(&mut rng);
            let poses = random_poses(&mut rng, 40, 10.0);
            let obs = measure(&mut rng, &t, &poses, 1e-6);
            let start = perturbed(&mut rng, &t, 1e-3);
            let c = solve_two_stage(&obs, &start, &TwoStageOptions::default()).unwrap();
            for i in 0..LEGS {
                for k in 0..3 {
                    total += 2;
                    if (c.base_m[i][k] - t.base_m[i][k]).abs() <= 3.0 * c.base_sigma_m[i][k] {
                        inside += 1;
                    }
                    if (c.platform_m[i][k] - t.platform_m[i][k]).abs()
                        <= 3.0 * c.platform_sigma_m[i][k]
                    {
                        inside += 1;
                    }
                }
            }
        }
        let share = inside as f64 / total as f64;
        assert!(share >= 0.97, "{share}");
    }

    /// 50 seeds of random initial errors on all 36 coordinates: ±5 mm with 1 µm noise and LM
    /// on every pose, and ±100 mm noise-free with the patent's exactly determined search set
    /// (where plain LM can land on a wrong root). The two-stage result is never worse than its
    /// start and succeeds at least as often as plain LM.
    #[test]
    fn two_stage_never_worse_and_at_least_as_successful() {
        for (amplitude, noise, patent) in [(5e-3, 1e-6, false), (100e-3, 0.0, true)] {
            let mut rng = ChaCha8Rng::seed_from_u64(4);
            let (mut ok_lm, mut ok_two) = (0, 0);
            for _ in 0..50 {
                let t = truth(&mut rng);
                let poses = random_poses(&mut rng, 30, 10.0);
                let mut obs = measure(&mut rng, &t, &poses, noise);
                if patent {
                    obs.search_poses = Some((1..=6).collect());
                }
                let start = perturbed(&mut rng, &t, amplitude);
                let lm = solve_lm(&obs, &start, &LmOptions::default()).unwrap();
                let opts = TwoStageOptions {
                    initial_step_m: amplitude.max(8e-3),
                    ..Default::default()
                };
                let two = solve_two_stage(&obs, &start, &opts).unwrap();
                assert!(two.objective_m2 <= two.objective_initial_m2);
                assert!(two.objective_m2 <= two.objective_stage1_m2);
                let sigma = coordinate_sigmas_m(&obs, &t).unwrap();
                let success = |g: &HexapodGeometry| {
                    g.to_vec()
                        .iter()
                        .zip(t.to_vec())
                        .zip(&sigma)
                        .all(|((x, y), s)| (x - y).abs() <= 5.0 * s + 1e-9)
                };
                ok_lm += success(&lm.geometry) as usize;
                ok_two += success(&two.geometry) as usize;
            }
            eprintln!("±{amplitude} m: LM {ok_lm}/50, two-stage {ok_two}/50");
            assert!(ok_two >= ok_lm, "two-stage {ok_two} vs LM {ok_lm}");
            if !patent {
                assert_eq!(ok_two, 50);
            }
        }
    }
}
