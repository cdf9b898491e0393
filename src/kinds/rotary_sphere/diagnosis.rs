//! The rotary sphere's residual model and effect library for `geocal diagnose` and `geocal
//! solve --effects` (docs/diagnosis.md, "rotary_sphere").
//!
//! Measured: each point's mean probe reading (how far beyond the nominal surface point, along
//! its probing direction, the probe met the sphere). Parameters: for the diagnosis, the axis
//! model (each height's sphere position, the location errors and harmonic motion errors of the
//! plan's order), which predicts every centre; for `solve --effects`, every probed sphere's
//! centre free (height × angle), as the kind's solve has them. Residual = R − |p − c| (p the
//! probed point, nominal − reading × direction): the reading minus the one the sphere at c
//! predicts, to first order. Each effect's column is what it adds to the modelled reading.

use nalgebra::{DMatrix, DVector, Vector3};

use crate::kinds::rotary_sphere::plan::SpherePlan;
use crate::kinds::rotary_sphere::solve::{probed_with_times, ProbedSphere};
use crate::method::diagnosis::{Effect, ResidualLabel, ResidualModel};
use crate::model::rotary_sphere::{
    harmonic_basis, located_centre_jacobian, motion_jacobian, rz, LOCATION_NAMES, MOTION_NAMES,
};
use crate::session::reader::Session;

const TIME_BLOCKS: usize = 8;

/// One probed point in the model.
struct Point {
    sphere: usize,
    direction_index: usize,
    nominal_m: Vector3<f64>,
    direction: Vector3<f64>,
    reading_m: f64,
    angle_rad: f64,
    t_s: f64,
}

pub struct SphereResidualModel {
    session_id: String,
    radius_m: f64,
    points: Vec<Point>,
    directions: usize,
    /// (height, angle) of each sphere, in centre order.
    spheres: Vec<(usize, usize)>,
    /// With the axis model, the centres as a linear map of its parameters; without it every
    /// centre is free (3 parameters per sphere).
    axis: Option<AxisMap>,
    start: DVector<f64>,
    sigma: Vec<f64>,
    labels: Vec<ResidualLabel>,
}

/// The centres predicted by the axis model (docs/diagnosis.md, "rotary_sphere"): every
/// centre c(h, θ) = Rz(θ) q_h + (I − Rz(θ)) a + w × (Rz q̄_h) − Rz (w × q̄_h) + J(Rz q̄_h) m(θ),
/// with q_h the sphere's position at height h, a = (EXOC, EYOC, 0), w = (EAOC, EBOC, 0) and the
/// motion errors m(θ) harmonic series of the plan's order, linearised at the first centres'
/// positions q̄_h (the products of two small errors dropped, as in `model::rotary_sphere`).
struct AxisMap {
    /// 3 × spheres rows (x, y, z of each centre) by the axis parameters.
    g: DMatrix<f64>,
    names: Vec<String>,
    start: DVector<f64>,
}

impl AxisMap {
    /// `centres`: each sphere's (height, commanded angle) and its own fitted centre.
    fn new(centres: &[(usize, f64, Vector3<f64>)], heights: usize, order: usize) -> AxisMap {
        let mut q_bar = vec![Vector3::zeros(); heights];
        let mut count = vec![0usize; heights];
        for (h, theta, c) in centres {
            q_bar[*h] += rz(-theta) * c;
            count[*h] += 1;
        }
        for (q, n) in q_bar.iter_mut().zip(&count) {
            *q /= (*n).max(1) as f64;
        }
        let used: Vec<usize> = (0..heights).filter(|&h| count[h] > 0).collect();
        let terms = 2 * order + 1;
        let motion_at = 3 * used.len() + 4;
        let width = motion_at + 6 * terms;
        let mut names: Vec<String> = used
            .iter()
            .flat_map(|h| ["x", "y", "z"].map(|c| format!("sphere_h{h}.{c}_m")))
            .collect();
        names.extend(LOCATION_NAMES.iter().map(|n| n.to_string()));
        for m in MOTION_NAMES {
            names.push(format!("{m}.c0"));
            for k in 1..=order {
                names.push(format!("{m}.a{k}"));
                names.push(format!("{m}.b{k}"));
            }
        }
        let mut g = DMatrix::zeros(3 * centres.len(), width);
        for (s, (h, theta, _)) in centres.iter().enumerate() {
            let at = used.iter().position(|u| u == h).unwrap_or(0);
            let (dq, dl) = located_centre_jacobian(*theta, &q_bar[*h], &[0.0; 4]);
            let jm = motion_jacobian(&(rz(*theta) * q_bar[*h]));
            let basis = harmonic_basis(*theta, order);
            for r in 0..3 {
                let row = 3 * s + r;
                for c in 0..3 {
                    g[(row, 3 * at + c)] = dq[(r, c)];
                }
                for c in 0..4 {
                    g[(row, 3 * used.len() + c)] = dl[(r, c)];
                }
                for e in 0..6 {
                    for (k, b) in basis.iter().enumerate() {
                        g[(row, motion_at + e * terms + k)] = jm[(r, e)] * b;
                    }
                }
            }
        }
        let mut start = DVector::zeros(width);
        for (at, h) in used.iter().enumerate() {
            for c in 0..3 {
                start[3 * at + c] = q_bar[*h][c];
            }
        }
        AxisMap { g, names, start }
    }
}

impl SphereResidualModel {
    /// The model with every probed sphere's centre free (what `solve --effects` corrects).
    pub fn new(session: &Session) -> anyhow::Result<SphereResidualModel> {
        Self::build(session, false)
    }

    /// The model with the centres predicted by the axis model (what the diagnosis tests): a
    /// drift between spheres, which free centres absorb, stays in the residuals.
    pub fn with_axis(session: &Session) -> anyhow::Result<SphereResidualModel> {
        Self::build(session, true)
    }

    fn build(session: &Session, axis_model: bool) -> anyhow::Result<SphereResidualModel> {
        let (plan_config, noise_m, probed, times) = probed_with_times(session)?;
        let plan = SpherePlan::from_config(&plan_config);
        let mut points = Vec::new();
        let mut spheres = Vec::new();
        let mut start = Vec::new();
        for (sphere, point_times) in probed.iter().zip(&times) {
            if sphere.points.len() < 4 {
                continue;
            }
            let s = spheres.len();
            spheres.push((sphere.height_index, sphere.angle_index));
            start.extend(centre_start(sphere, plan.radius_m).iter());
            for (p, (k, t_s)) in sphere.points.iter().zip(point_times) {
                points.push(Point {
                    sphere: s,
                    direction_index: *k,
                    nominal_m: p.nominal_m,
                    direction: p.direction,
                    reading_m: p.mean_m,
                    angle_rad: sphere.commanded_rad,
                    t_s: *t_s,
                });
            }
        }
        let readings: Vec<usize> = probed
            .iter()
            .filter(|s| s.points.len() >= 4)
            .flat_map(|s| s.points.iter().map(|p| p.readings))
            .collect();
        let t_end = points.iter().map(|p| p.t_s).fold(0.0, f64::max).max(1e-9);
        let mut sigma = Vec::new();
        let mut labels = Vec::new();
        for (p, n) in points.iter().zip(&readings) {
            sigma.push(noise_m / (*n as f64).sqrt());
            let (h, a) = spheres[p.sphere];
            let block = ((p.t_s / t_end) * TIME_BLOCKS as f64).floor() as usize;
            let d = p.direction;
            let name = format!(
                "direction {} (az {:.0}°, el {:.0}°)",
                p.direction_index,
                d.y.atan2(d.x).to_degrees(),
                d.z.clamp(-1.0, 1.0).asin().to_degrees()
            );
            labels.push(ResidualLabel {
                groups: vec![
                    ("direction", name.clone()),
                    ("height", format!("height {h}")),
                    ("angle", format!("angle {:.0}°", p.angle_rad.to_degrees())),
                    (
                        "time",
                        format!("block {} of {TIME_BLOCKS}", block.min(TIME_BLOCKS - 1) + 1),
                    ),
                ],
                row: name,
                x: p.angle_rad.to_degrees() + 360.0 * h as f64,
                // Held out by (angle + direction): every held-out reading keeps its sphere's
                // other points and its direction at other angles.
                holdout: Some(a + p.direction_index),
                unit: "m",
            });
        }
        let mut start = DVector::from_vec(start);
        let angles: std::collections::BTreeSet<usize> = spheres.iter().map(|s| s.1).collect();
        let axis = (axis_model && angles.len() >= 3).then(|| {
            let centres: Vec<(usize, f64, Vector3<f64>)> = spheres
                .iter()
                .enumerate()
                .map(|(s, &(h, a))| {
                    let theta = points
                        .iter()
                        .find(|p| p.sphere == s)
                        .map_or(plan.angles_rad[a], |p| p.angle_rad);
                    (
                        h,
                        theta,
                        Vector3::new(start[3 * s], start[3 * s + 1], start[3 * s + 2]),
                    )
                })
                .collect();
            let order = plan_config.max_harmonic_order.min((angles.len() - 1) / 2);
            AxisMap::new(&centres, plan.heights.len(), order)
        });
        if let Some(map) = &axis {
            start = map.start.clone();
        }
        Ok(SphereResidualModel {
            session_id: session.header.session_id.clone(),
            radius_m: plan.radius_m,
            directions: plan.directions.len(),
            points,
            spheres,
            axis,
            start,
            sigma,
            labels,
        })
    }

    fn probed_point(p: &Point) -> Vector3<f64> {
        SpherePlan::measured_point(&p.nominal_m, &p.direction, p.reading_m)
    }

    fn centre(&self, params: &DVector<f64>, s: usize) -> Vector3<f64> {
        match &self.axis {
            Some(map) => Vector3::from_fn(|r, _| map.g.row(3 * s + r).transpose().dot(params)),
            None => Vector3::new(params[3 * s], params[3 * s + 1], params[3 * s + 2]),
        }
    }

    /// Every sphere's centre at `params`, each made once for all its points.
    fn centres(&self, params: &DVector<f64>) -> Vec<Vector3<f64>> {
        (0..self.spheres.len())
            .map(|s| self.centre(params, s))
            .collect()
    }

    /// The outward normal at each probed point (from its sphere's centre).
    fn normals(&self, params: &DVector<f64>) -> Vec<Vector3<f64>> {
        let centres = self.centres(params);
        self.points
            .iter()
            .map(|p| {
                let d = Self::probed_point(p) - centres[p.sphere];
                if d.norm() > 0.0 {
                    d.normalize()
                } else {
                    p.direction
                }
            })
            .collect()
    }

    /// M (3 × directions) of the lobing's constraint Σ_k w_k d_k n_k = 0: column k is
    /// w_k n_k, with n_k the direction's probing direction and w_k = Σ 1/σ² of its points.
    fn direction_constraint(&self) -> DMatrix<f64> {
        let mut m = DMatrix::zeros(3, self.directions);
        for (p, s) in self.points.iter().zip(&self.sigma) {
            if p.direction_index < self.directions {
                for r in 0..3 {
                    m[(r, p.direction_index)] += p.direction[r] / (s * s);
                }
            }
        }
        m
    }

    /// (height, angle) of each sphere, in parameter order (3 centre coordinates each).
    pub fn sphere_keys(&self) -> &[(usize, usize)] {
        &self.spheres
    }

    /// Each point's direction index, reading and sphere (what a corrected solve changes).
    pub fn point_keys(&self) -> Vec<((usize, usize), usize)> {
        self.points
            .iter()
            .map(|p| (self.spheres[p.sphere], p.direction_index))
            .collect()
    }
}

/// A sphere's centre from its points at the known radius: the nominal points' centre moved by
/// the mean reading along each direction (the kind's own fit is the start's refinement).
fn centre_start(sphere: &ProbedSphere, radius_m: f64) -> [f64; 3] {
    let pts: Vec<Vector3<f64>> = sphere
        .points
        .iter()
        .map(|p| SpherePlan::measured_point(&p.nominal_m, &p.direction, p.mean_m))
        .collect();
    match crate::solve::rotary_sphere::fit_sphere(&pts, Some(radius_m), None) {
        Ok(fit) => fit.centre_m,
        Err(_) => {
            let c = sphere
                .points
                .iter()
                .map(|p| p.nominal_m - radius_m * p.direction)
                .sum::<Vector3<f64>>()
                / sphere.points.len() as f64;
            c.into()
        }
    }
}

/// The sphere's form error terms that change when the table turns (the zonal ones are the
/// same at every angle: a probe lobing pattern).
pub use crate::model::sphere_form::{
    azimuthal_harmonics as turning_form_harmonics, AZIMUTHAL_TERMS as TURNING_FORM_TERMS,
};

impl ResidualModel for SphereResidualModel {
    fn kind(&self) -> &'static str {
        crate::kinds::rotary_sphere::config::KIND
    }
    fn session_id(&self) -> &str {
        &self.session_id
    }
    fn x_axis(&self) -> &'static str {
        "table angle [°] + 360° × height index"
    }
    fn parameter_names(&self) -> Vec<String> {
        if let Some(map) = &self.axis {
            return map.names.clone();
        }
        self.spheres
            .iter()
            .flat_map(|(h, a)| ["x", "y", "z"].map(|c| format!("centre_h{h}_a{a}.{c}_m")))
            .collect()
    }
    fn start(&self) -> DVector<f64> {
        self.start.clone()
    }
    fn sigma(&self) -> &[f64] {
        &self.sigma
    }
    fn labels(&self) -> &[ResidualLabel] {
        &self.labels
    }
    fn residuals(&self, params: &DVector<f64>) -> DVector<f64> {
        let centres = self.centres(params);
        DVector::from_iterator(
            self.points.len(),
            self.points
                .iter()
                .map(|p| self.radius_m - (Self::probed_point(p) - centres[p.sphere]).norm()),
        )
    }
    fn jacobian(&self, params: &DVector<f64>) -> DMatrix<f64> {
        // The modelled reading falls as the centre moves along the outward normal (the
        // sphere meets the probe earlier).
        let mut jac = DMatrix::zeros(self.points.len(), params.len());
        for (i, (p, n)) in self.points.iter().zip(self.normals(params)).enumerate() {
            match &self.axis {
                Some(map) => {
                    let row = -(n.transpose() * map.g.rows(3 * p.sphere, 3));
                    jac.row_mut(i).copy_from(&row);
                }
                None => {
                    for k in 0..3 {
                        jac[(i, 3 * p.sphere + k)] = -n[k];
                    }
                }
            }
        }
        jac
    }
    fn effects(&self) -> Vec<Box<dyn Effect + '_>> {
        vec![
            Box::new(ProbeLobing(self)),
            Box::new(SphereForm(self)),
            Box::new(ThermalDrift(self)),
        ]
    }
}

/// `probe_lobing`: the probe reads off by d_k in probing direction k (the same at every angle
/// and height: the directions are fixed in the probe's frame). Its degree-1 part, d_k = n_k·v
/// (a probe-tip offset v), moves every centre by the same −v and cannot be told from it: the
/// lobing is held to Σ_k w_k d_k n_k = 0 (w_k the direction's weight, Σ 1/σ² of its readings),
/// so that the centres carry that part as a known-radius sphere fit does. The parameters are
/// d_k of the free directions; the three dependent ones follow from the constraint.
struct ProbeLobing<'a>(&'a SphereResidualModel);

impl ProbeLobing<'_> {
    /// d (every direction) = B d_free: the free directions and B (directions × free).
    fn basis(&self) -> (Vec<usize>, DMatrix<f64>) {
        lobing_basis(&self.0.direction_constraint())
    }
}

/// The lobing d with M d = 0 (M: 3 × directions) written by its free directions: three
/// dependent directions chosen greedily (each the most independent of those already chosen),
/// d_dep = −M_dep⁻¹ M_free d_free. Without three independent columns (a degenerate plan) every
/// direction stays free.
fn lobing_basis(m: &DMatrix<f64>) -> (Vec<usize>, DMatrix<f64>) {
    let n = m.ncols();
    let unconstrained = || ((0..n).collect(), DMatrix::identity(n, n));
    let mut dependent: Vec<usize> = Vec::new();
    let mut basis: Vec<DVector<f64>> = Vec::new();
    for _ in 0..3 {
        let best = (0..n)
            .filter(|k| !dependent.contains(k))
            .map(|k| {
                let mut v: DVector<f64> = m.column(k).into_owned();
                for b in &basis {
                    v -= b * b.dot(&v);
                }
                (k, v)
            })
            .max_by(|a, b| a.1.norm().total_cmp(&b.1.norm()));
        let Some((k, v)) = best else {
            return unconstrained();
        };
        let scale = m.column(k).norm();
        if v.norm() <= 1e-9 * scale.max(f64::MIN_POSITIVE) {
            return unconstrained();
        }
        basis.push(v.normalize());
        dependent.push(k);
    }
    let free: Vec<usize> = (0..n).filter(|k| !dependent.contains(k)).collect();
    let m_dep = DMatrix::from_fn(3, 3, |r, c| m[(r, dependent[c])]);
    let m_free = DMatrix::from_fn(3, free.len(), |r, c| m[(r, free[c])]);
    let Some(inverse) = m_dep.try_inverse() else {
        return unconstrained();
    };
    let dep_of_free = -inverse * m_free;
    let mut b = DMatrix::zeros(n, free.len());
    for (c, &k) in free.iter().enumerate() {
        b[(k, c)] = 1.0;
    }
    for (r, &k) in dependent.iter().enumerate() {
        b.row_mut(k).copy_from(&dep_of_free.row(r));
    }
    (free, b)
}

impl Effect for ProbeLobing<'_> {
    fn name(&self) -> &'static str {
        "probe_lobing"
    }
    fn parameter_names(&self) -> Vec<String> {
        self.basis()
            .0
            .iter()
            .map(|k| format!("direction{k}_m"))
            .collect()
    }
    fn columns(&self, _: &DVector<f64>) -> DMatrix<f64> {
        let m = self.0;
        let (_, b) = self.basis();
        let mut a = DMatrix::zeros(m.points.len(), b.ncols());
        for (i, p) in m.points.iter().enumerate() {
            a.row_mut(i).copy_from(&b.row(p.direction_index));
        }
        a
    }
}

/// `sphere_form`: the sphere's radius varies with the direction n from its centre in the
/// sphere's own frame (turning with the table: n_sphere = Rz(−θ) n), R + Σ c_k Y_k(n_sphere)
/// over the non-zonal harmonics of degree 2 and 3 (metres). A larger radius meets the probe
/// earlier: the reading falls by the form.
struct SphereForm<'a>(&'a SphereResidualModel);

impl Effect for SphereForm<'_> {
    fn name(&self) -> &'static str {
        "sphere_form"
    }
    fn parameter_names(&self) -> Vec<String> {
        TURNING_FORM_TERMS
            .iter()
            .map(|t| format!("{t}_m"))
            .collect()
    }
    fn columns(&self, params: &DVector<f64>) -> DMatrix<f64> {
        let m = self.0;
        let mut a = DMatrix::zeros(m.points.len(), TURNING_FORM_TERMS.len());
        for (i, (p, normal)) in m.points.iter().zip(m.normals(params)).enumerate() {
            let n = rz(-p.angle_rad) * normal;
            for (k, y) in turning_form_harmonics(&n).iter().enumerate() {
                a[(i, k)] = -y;
            }
        }
        a
    }
}

/// `thermal_drift`: the sphere (with the axis) moves linearly in time, c + v t (m/s): the
/// reading falls by the normal's part of v t.
struct ThermalDrift<'a>(&'a SphereResidualModel);

impl Effect for ThermalDrift<'_> {
    fn name(&self) -> &'static str {
        "thermal_drift"
    }
    fn parameter_names(&self) -> Vec<String> {
        ["vx_m_per_s", "vy_m_per_s", "vz_m_per_s"]
            .map(String::from)
            .to_vec()
    }
    fn columns(&self, params: &DVector<f64>) -> DMatrix<f64> {
        let m = self.0;
        let mut a = DMatrix::zeros(m.points.len(), 3);
        for (i, (p, n)) in m.points.iter().zip(m.normals(params)).enumerate() {
            for k in 0..3 {
                a[(i, k)] = -p.t_s * n[k];
            }
        }
        a
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The axis map reproduces the model's predicted centres: located centre plus harmonic
    /// motion errors, for spheres at two heights over a full turn.
    #[test]
    fn axis_map_predicts_the_centres() {
        use crate::model::rotary_sphere::predicted_centre;
        let order = 2;
        let heights = [
            Vector3::new(0.071, 0.001, 0.179),
            Vector3::new(0.0705, -0.002, 0.279),
        ];
        let loc = [2e-5, -1.5e-5, 3e-5, -2e-5];
        let coefficients: Vec<[f64; 5]> = (0..6)
            .map(|e| {
                let s = if e < 3 { 1e-6 } else { 1e-5 };
                std::array::from_fn(|k| s * ((e + 2 * k) as f64 * 0.37).sin())
            })
            .collect();
        let mut centres = Vec::new();
        let mut truth = Vec::new();
        for (h, q) in heights.iter().enumerate() {
            for a in 0..12 {
                let theta = a as f64 * std::f64::consts::TAU / 12.0;
                let basis = harmonic_basis(theta, order);
                let motion = nalgebra::Vector6::from_fn(|e, _| {
                    basis.iter().zip(&coefficients[e]).map(|(b, c)| b * c).sum()
                });
                let c = predicted_centre(theta, q, &loc, &motion);
                // The map is linearised at the centres given: nearby, as fitted centres are.
                centres.push((h, theta, c + Vector3::new(3e-6, -2e-6, 1e-6)));
                truth.push(c);
            }
        }
        let map = AxisMap::new(&centres, 2, order);
        let mut beta = DVector::zeros(map.names.len());
        for (h, q) in heights.iter().enumerate() {
            for c in 0..3 {
                beta[3 * h + c] = q[c];
            }
        }
        for k in 0..4 {
            beta[6 + k] = loc[k];
        }
        for e in 0..6 {
            for k in 0..5 {
                beta[10 + 5 * e + k] = coefficients[e][k];
            }
        }
        let predicted = &map.g * beta;
        for (s, c) in truth.iter().enumerate() {
            let got = Vector3::new(predicted[3 * s], predicted[3 * s + 1], predicted[3 * s + 2]);
            // Second-order terms only: tilts of ≤ 1e-4 rad times the linearisation point's
            // offset from q (≤ 3e-5 m: the location error and the perturbation).
            assert!((got - c).amax() < 1e-8, "sphere {s}: {got} vs {c}");
        }
    }

    /// The lobing's basis obeys its constraint, keeps each free direction's own value, and a
    /// probe-tip offset (d_k = n_k·v) has no part in it.
    #[test]
    fn lobing_basis_holds_the_constraint() {
        let directions = crate::solve::rotary_sphere::simulation::probe_directions(8);
        let weights = [1.0, 2.0, 1.0, 1.0, 0.5, 1.0, 1.0, 3.0];
        let m = DMatrix::from_fn(3, 8, |r, k| weights[k] * directions[k][r]);
        let (free, b) = lobing_basis(&m);
        assert_eq!(free.len(), 5);
        assert!((&m * &b).amax() < 1e-12, "{}", &m * &b);
        for (c, &k) in free.iter().enumerate() {
            for r in &free {
                let expected = if *r == k { 1.0 } else { 0.0 };
                assert_eq!(b[(*r, c)], expected);
            }
        }
        // A tip offset's pattern is orthogonal (in the weights) to every lobing the basis spans.
        let v = Vector3::new(0.3, -1.0, 0.7);
        let tip = DVector::from_fn(8, |k, _| weights[k] * directions[k].dot(&v));
        assert!((b.transpose() * tip).amax() < 1e-12);
        // Directions that leave space unspanned: nothing constrained.
        let flat = DMatrix::from_fn(3, 4, |r, k| if r == 2 { 0.0 } else { (k + r) as f64 });
        assert_eq!(lobing_basis(&flat).0.len(), 4);
    }
}
