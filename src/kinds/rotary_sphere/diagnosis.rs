//! The rotary sphere's residual model and effect library for `geocal diagnose` and `geocal
//! solve --effects` (docs/diagnosis.md, "rotary_sphere").
//!
//! Measured: each point's mean probe reading (how far beyond the nominal surface point, along
//! its probing direction, the probe met the sphere). Parameters: every probed sphere's centre
//! (height × angle; with two fit heights this is the axis model with its per-angle motion
//! errors, which the centres determine exactly). Residual = R − |p − c| (p the probed point,
//! nominal − reading × direction): the reading minus the one the sphere at c predicts, to first
//! order. Each effect's column is what it adds to the modelled reading.

use nalgebra::{DMatrix, DVector, Vector3};

use crate::kinds::rotary_sphere::plan::SpherePlan;
use crate::kinds::rotary_sphere::solve::{probed_with_times, ProbedSphere};
use crate::method::diagnosis::{Effect, ResidualLabel, ResidualModel};
use crate::model::rotary_sphere::rz;
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
    /// (height, angle) of each sphere, in parameter order.
    spheres: Vec<(usize, usize)>,
    start: DVector<f64>,
    sigma: Vec<f64>,
    labels: Vec<ResidualLabel>,
}

impl SphereResidualModel {
    pub fn new(session: &Session) -> anyhow::Result<SphereResidualModel> {
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
        Ok(SphereResidualModel {
            session_id: session.header.session_id.clone(),
            radius_m: plan.radius_m,
            directions: plan.directions.len(),
            points,
            spheres,
            start: DVector::from_vec(start),
            sigma,
            labels,
        })
    }

    fn probed_point(p: &Point) -> Vector3<f64> {
        SpherePlan::measured_point(&p.nominal_m, &p.direction, p.reading_m)
    }

    fn centre(&self, params: &DVector<f64>, s: usize) -> Vector3<f64> {
        Vector3::new(params[3 * s], params[3 * s + 1], params[3 * s + 2])
    }

    /// The outward normal at each probed point (from its sphere's centre).
    fn normal(&self, params: &DVector<f64>, p: &Point) -> Vector3<f64> {
        let d = Self::probed_point(p) - self.centre(params, p.sphere);
        if d.norm() > 0.0 {
            d.normalize()
        } else {
            p.direction
        }
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
        DVector::from_iterator(
            self.points.len(),
            self.points.iter().map(|p| {
                self.radius_m - (Self::probed_point(p) - self.centre(params, p.sphere)).norm()
            }),
        )
    }
    fn jacobian(&self, params: &DVector<f64>) -> DMatrix<f64> {
        // The modelled reading falls as the centre moves along the outward normal (the
        // sphere meets the probe earlier).
        let mut jac = DMatrix::zeros(self.points.len(), params.len());
        for (i, p) in self.points.iter().enumerate() {
            let n = self.normal(params, p);
            for k in 0..3 {
                jac[(i, 3 * p.sphere + k)] = -n[k];
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
/// and height: the directions are fixed in the probe's frame).
struct ProbeLobing<'a>(&'a SphereResidualModel);

impl Effect for ProbeLobing<'_> {
    fn name(&self) -> &'static str {
        "probe_lobing"
    }
    fn parameter_names(&self) -> Vec<String> {
        (0..self.0.directions)
            .map(|k| format!("direction{k}_m"))
            .collect()
    }
    fn columns(&self, _: &DVector<f64>) -> DMatrix<f64> {
        let m = self.0;
        let mut a = DMatrix::zeros(m.points.len(), m.directions);
        for (i, p) in m.points.iter().enumerate() {
            a[(i, p.direction_index)] = 1.0;
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
        for (i, p) in m.points.iter().enumerate() {
            let n = rz(-p.angle_rad) * m.normal(params, p);
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
        for (i, p) in m.points.iter().enumerate() {
            let n = m.normal(params, p);
            for k in 0..3 {
                a[(i, k)] = -p.t_s * n[k];
            }
        }
        a
    }
}
