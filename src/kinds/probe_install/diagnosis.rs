//! The probe installation's residual model and effect library for `geocal diagnose` and
//! `geocal solve --effects` (docs/diagnosis.md, "probe_install").
//!
//! Measured: each point's mean probe reading at its posture and machine position. Residual:
//! the probed point's distance from the reference sphere's surface, |q0 − S0| − R, with
//! σ = σ_t · max(|e·w|, 0.05) as the solve weights it (e the sphere normal at the point, w the
//! beam). Parameters: the installation as the solve's LM has it, the beam as two tilt angles
//! (α, β) about the solved beam (|(l, m, n)| = 1 exactly): δB, y32, α, β, the zero point, the
//! sphere centre. Each effect's column is what it adds to the modelled surface distance.

use nalgebra::{DMatrix, DVector, Matrix3, Rotation3, Unit, Vector3};

use crate::kinds::probe_install::solve::{timed_observations, TimedObservation};
use crate::method::diagnosis::{Effect, ResidualLabel, ResidualModel};
use crate::model::probe_install::{rot_x, rot_z, InstallParams, ProbeObservation};
use crate::session::reader::Session;
use crate::solve::probe_install::tangent_basis;

/// The least |cos| between sphere normal and beam in the weights (the solve's floor).
const COSINE_FLOOR: f64 = 0.05;
const TIME_BLOCKS: usize = 8;
/// Reading bins of the `where` test (over the probe's range used).
const READING_BINS: usize = 4;
pub const PARAMETERS: [&str; 10] = [
    "b_offset_rad",
    "y_offset_m",
    "beam_alpha_rad",
    "beam_beta_rad",
    "zero_point_x_m",
    "zero_point_y_m",
    "zero_point_z_m",
    "sphere_centre_x_m",
    "sphere_centre_y_m",
    "sphere_centre_z_m",
];

pub struct ProbeResidualModel {
    session_id: String,
    points: Vec<TimedObservation>,
    radius_m: f64,
    /// The solved beam and its tangent basis: the beam's chart.
    e: [Vector3<f64>; 3],
    start: DVector<f64>,
    sigma: Vec<f64>,
    labels: Vec<ResidualLabel>,
}

impl ProbeResidualModel {
    /// The model of a session, started at the installation `solved` (the solve's LM).
    pub fn new(
        session: &Session,
        solved: &InstallParams,
        radius_m: f64,
    ) -> anyhow::Result<ProbeResidualModel> {
        let probe = session
            .header
            .devices
            .iter()
            .find(|d| d.kind == "probe" && d.noise_m.is_some())
            .ok_or_else(|| {
                anyhow::anyhow!("session header: no device of kind `probe` with `noise_m`")
            })?;
        let points = timed_observations(session, probe.noise_m.unwrap_or(0.0), &probe.id)?;
        let e3 = solved.beam().normalize();
        let (e1, e2) = tangent_basis(&e3);
        let mut start = DVector::zeros(PARAMETERS.len());
        start[0] = solved.b_offset_rad;
        start[1] = solved.y_offset_m;
        for k in 0..3 {
            start[4 + k] = solved.zero_point_m[k];
            start[7 + k] = solved.sphere_centre_m[k];
        }
        let mut model = ProbeResidualModel {
            session_id: session.header.session_id.clone(),
            points,
            radius_m,
            e: [e1, e2, e3],
            start,
            sigma: Vec::new(),
            labels: Vec::new(),
        };
        let params = model.params(&model.start);
        let t_end = model
            .points
            .iter()
            .map(|p| p.t_s)
            .fold(0.0, f64::max)
            .max(1e-9);
        let (t_lo, t_hi) =
            model
                .points
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| {
                    (
                        lo.min(p.observation.reading_m),
                        hi.max(p.observation.reading_m),
                    )
                });
        let span = (t_hi - t_lo).max(1e-12);
        for (i, p) in model.points.iter().enumerate() {
            let (normal, beam) = normal_and_beam(&params, &p.observation);
            let cosine = normal.dot(&beam).abs().max(COSINE_FLOOR);
            model.sigma.push(p.observation.sigma_m * cosine);
            let block = ((p.t_s / t_end) * TIME_BLOCKS as f64).floor() as usize;
            let bin =
                (((p.observation.reading_m - t_lo) / span) * READING_BINS as f64).floor() as usize;
            let bin = bin.min(READING_BINS - 1);
            let posture = format!(
                "posture {} (A {:.0}°, B {:.0}°)",
                p.posture,
                p.observation.a_rad.to_degrees(),
                p.observation.b_rad.to_degrees()
            );
            model.labels.push(ResidualLabel {
                groups: vec![
                    ("posture", posture.clone()),
                    (
                        "reading",
                        format!(
                            "reading {:.2}..{:.2} mm",
                            1e3 * (t_lo + span * bin as f64 / READING_BINS as f64),
                            1e3 * (t_lo + span * (bin + 1) as f64 / READING_BINS as f64)
                        ),
                    ),
                    (
                        "time",
                        format!("block {} of {TIME_BLOCKS}", block.min(TIME_BLOCKS - 1) + 1),
                    ),
                ],
                row: posture,
                x: p.t_s,
                holdout: Some(i),
                unit: "m",
            });
        }
        Ok(model)
    }

    /// The installation at model parameters `p`.
    pub fn params(&self, p: &DVector<f64>) -> InstallParams {
        let [e1, e2, e3] = self.e;
        let (a, b) = (p[2], p[3]);
        let beam = b.cos() * (a.cos() * e3 + a.sin() * e1) + b.sin() * e2;
        InstallParams {
            b_offset_rad: p[0],
            y_offset_m: p[1],
            beam_dir: beam.into(),
            zero_point_m: [p[4], p[5], p[6]],
            sphere_centre_m: [p[7], p[8], p[9]],
        }
    }

    /// ∂(l, m, n)/∂(α, β) at `p` (3 × 2): maps the chart's covariance to the beam's.
    pub fn beam_jacobian(&self, p: &DVector<f64>) -> nalgebra::Matrix3x2<f64> {
        let [e1, e2, e3] = self.e;
        let (a, b) = (p[2], p[3]);
        let da = b.cos() * (-a.sin() * e3 + a.cos() * e1);
        let db = -b.sin() * (a.cos() * e3 + a.sin() * e1) + b.cos() * e2;
        nalgebra::Matrix3x2::from_columns(&[da, db])
    }
}

/// The probed point with the A rotation `rx` (about a possibly tilted axis).
fn surface_point_with(p: &InstallParams, o: &ProbeObservation, rx: &Matrix3<f64>) -> Vector3<f64> {
    let w = p.zero_point() + o.reading_m * p.beam();
    let v = Vector3::new(0.0, p.y_offset_m, 0.0) + rx * w;
    Vector3::from(o.machine_m) + rot_z(o.b_rad + p.b_offset_rad) * v
}

/// The sphere's outward normal at the probed point and the beam in the base frame.
fn normal_and_beam(p: &InstallParams, o: &ProbeObservation) -> (Vector3<f64>, Vector3<f64>) {
    let q = surface_point_with(p, o, &rot_x(o.a_rad));
    let d = q - p.sphere_centre();
    let normal = if d.norm() > 0.0 {
        d.normalize()
    } else {
        Vector3::z()
    };
    let beam = rot_z(o.b_rad + p.b_offset_rad) * rot_x(o.a_rad) * p.beam();
    (normal, beam)
}

/// The A rotation about the axis (1, 0, τ) (tilted out of the plane normal to B).
pub fn tilted_a_rotation(a_rad: f64, tilt_rad: f64) -> Matrix3<f64> {
    Rotation3::from_axis_angle(
        &Unit::new_normalize(Vector3::new(1.0, 0.0, tilt_rad)),
        a_rad,
    )
    .into_inner()
}

/// The reference sphere's form error terms (degree 2 and 3).
pub use crate::model::sphere_form::{harmonics as form_harmonics, TERMS as FORM_TERMS};

impl ResidualModel for ProbeResidualModel {
    fn kind(&self) -> &'static str {
        crate::kinds::probe_install::config::KIND
    }
    fn session_id(&self) -> &str {
        &self.session_id
    }
    fn x_axis(&self) -> &'static str {
        "time since the first point [s]"
    }
    fn parameter_names(&self) -> Vec<String> {
        PARAMETERS.iter().map(|s| s.to_string()).collect()
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
    fn step(&self, j: usize) -> f64 {
        // Angles in radians, lengths in metres: steps of ~1e-7 of their scale.
        if j < 4 {
            1e-8
        } else {
            1e-9
        }
    }
    fn residuals(&self, p: &DVector<f64>) -> DVector<f64> {
        let params = self.params(p);
        DVector::from_iterator(
            self.points.len(),
            self.points.iter().map(|t| {
                let o = &t.observation;
                (surface_point_with(&params, o, &rot_x(o.a_rad)) - params.sphere_centre()).norm()
                    - self.radius_m
            }),
        )
    }
    fn effects(&self) -> Vec<Box<dyn Effect + '_>> {
        vec![
            Box::new(AAxisTilt(self)),
            Box::new(SphereForm(self)),
            Box::new(ReadingScale(self)),
            Box::new(ThermalDrift(self)),
        ]
    }
}

/// `a_axis_tilt`: the A axis turns about (1, 0, τ) instead of (1, 0, 0); τ in radians.
struct AAxisTilt<'a>(&'a ProbeResidualModel);

impl Effect for AAxisTilt<'_> {
    fn name(&self) -> &'static str {
        "a_axis_tilt"
    }
    fn parameter_names(&self) -> Vec<String> {
        vec!["tilt_rad".into()]
    }
    fn columns(&self, p: &DVector<f64>) -> DMatrix<f64> {
        let m = self.0;
        let params = m.params(p);
        let h = 1e-6;
        DMatrix::from_fn(m.points.len(), 1, |i, _| {
            let o = &m.points[i].observation;
            let at = |tilt: f64| {
                (surface_point_with(&params, o, &tilted_a_rotation(o.a_rad, tilt))
                    - params.sphere_centre())
                .norm()
            };
            // The residual falls by what the effect adds to the modelled distance.
            -(at(h) - at(-h)) / (2.0 * h)
        })
    }
}

/// The library's `sphere_form` fits the 5 harmonics of degree 2: on the cap the probe sees,
/// degree 3 adds 7 parameters that trade against the installation's and double its error.
const FITTED_FORM_TERMS: usize = 5;

/// `sphere_form`: the reference sphere's radius varies with the direction n from its centre,
/// R + Σ c_k Y_k(n) over the real harmonics of degree 2 (metres).
struct SphereForm<'a>(&'a ProbeResidualModel);

impl Effect for SphereForm<'_> {
    fn name(&self) -> &'static str {
        "sphere_form"
    }
    fn parameter_names(&self) -> Vec<String> {
        FORM_TERMS[..FITTED_FORM_TERMS]
            .iter()
            .map(|t| format!("{t}_m"))
            .collect()
    }
    fn columns(&self, p: &DVector<f64>) -> DMatrix<f64> {
        let m = self.0;
        let params = m.params(p);
        let mut a = DMatrix::zeros(m.points.len(), FITTED_FORM_TERMS);
        for (i, t) in m.points.iter().enumerate() {
            let (normal, _) = normal_and_beam(&params, &t.observation);
            for (k, y) in form_harmonics(&normal)[..FITTED_FORM_TERMS]
                .iter()
                .enumerate()
            {
                a[(i, k)] = *y;
            }
        }
        a
    }
}

/// `reading_scale`: the probe reads (1 + k) × the true distance from its zero point.
struct ReadingScale<'a>(&'a ProbeResidualModel);

impl Effect for ReadingScale<'_> {
    fn name(&self) -> &'static str {
        "reading_scale"
    }
    fn parameter_names(&self) -> Vec<String> {
        vec!["k".into()]
    }
    fn columns(&self, p: &DVector<f64>) -> DMatrix<f64> {
        let m = self.0;
        let params = m.params(p);
        DMatrix::from_fn(m.points.len(), 1, |i, _| {
            let o = &m.points[i].observation;
            let (normal, beam) = normal_and_beam(&params, o);
            // True distance t/(1 + k) ≈ t − k t: the point moves back along the beam.
            o.reading_m * normal.dot(&beam)
        })
    }
}

/// `thermal_drift`: the sphere moves against the machine linearly in time, S0 + v t (m/s).
struct ThermalDrift<'a>(&'a ProbeResidualModel);

impl Effect for ThermalDrift<'_> {
    fn name(&self) -> &'static str {
        "thermal_drift"
    }
    fn parameter_names(&self) -> Vec<String> {
        ["vx_m_per_s", "vy_m_per_s", "vz_m_per_s"]
            .map(String::from)
            .to_vec()
    }
    fn columns(&self, p: &DVector<f64>) -> DMatrix<f64> {
        let m = self.0;
        let params = m.params(p);
        let mut a = DMatrix::zeros(m.points.len(), 3);
        for (i, t) in m.points.iter().enumerate() {
            let (normal, _) = normal_and_beam(&params, &t.observation);
            for k in 0..3 {
                a[(i, k)] = t.t_s * normal[k];
            }
        }
        a
    }
}
