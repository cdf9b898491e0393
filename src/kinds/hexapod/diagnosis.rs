//! The hexapod's residual model and effect library for `geocal diagnose` and `geocal solve
//! --effects` (docs/diagnosis.md, "hexapod").
//!
//! Measured: each pose's mean leg reading (6 legs) and, with a measuring pose sensor, its mean
//! measured pose (translation and rotation vector). Parameters: the 36 hinge coordinates, each
//! leg's encoder constant (the reading at zero length; the incremental encoders count from an
//! unknown start) and, with a measuring pose sensor, each pose's true pose (the sensor's
//! readings are measurements of it). Leg residual = reading − (L_i(pose) + c_i); sensor
//! residual = measured − true pose. Without a measuring sensor the poses are exact.

use nalgebra::{DMatrix, DVector, Rotation3, Vector3};

use crate::kinds::hexapod::solve::{prepare, HexapodMethodError, HexapodResults, PoseData};
use crate::method::diagnosis::{Effect, LocalBlock, ResidualLabel, ResidualModel};
use crate::model::hexapod::{leg_length, pose_jacobian, HexapodGeometry, Pose, LEGS};
use crate::session::reader::Session;

/// Hinges (36) then the legs' encoder constants (6), then 6 per pose when the poses are free.
const HINGES: usize = 6 * LEGS;
const CONSTANTS: usize = HINGES + LEGS;
/// Time blocks of the `where` test: a drift or a step is localised, each block holds tens of
/// residuals.
const TIME_BLOCKS: usize = 8;
const POSE_NAMES: [&str; 6] = ["x", "y", "z", "rx", "ry", "rz"];

pub struct HexapodResidualModel {
    session_id: String,
    poses: Vec<PoseData>,
    /// The poses are parameters measured by the pose sensor (else exact).
    free_poses: bool,
    start: DVector<f64>,
    sigma: Vec<f64>,
    labels: Vec<ResidualLabel>,
    /// Per pose and leg: the sign of the leg's last motion (the design lengths at the
    /// commanded poses; 0 at the first pose, reached without a measured motion).
    motion_sign: Vec<[f64; LEGS]>,
}

fn pose_vector(p: &Pose) -> [f64; 6] {
    let w = p.rotation.scaled_axis();
    [
        p.translation_m.x,
        p.translation_m.y,
        p.translation_m.z,
        w.x,
        w.y,
        w.z,
    ]
}

fn pose_of(v: &[f64]) -> Pose {
    Pose {
        rotation: Rotation3::new(Vector3::new(v[3], v[4], v[5])),
        translation_m: Vector3::new(v[0], v[1], v[2]),
    }
}

impl HexapodResidualModel {
    /// The model of a session, started at its nominal solve's hinges.
    pub fn new(session: &Session, nominal: &HexapodResults) -> Result<Self, HexapodMethodError> {
        let prepared = prepare(session)?;
        let encoder_sigma = prepared.noise.encoder_sigma_m;
        let design = prepared.nominal.clone();
        let poses = prepared.data;
        let free_poses = prepared.any_measured
            && prepared.pose_sigma_m > 0.0
            && prepared.pose_sigma_rad > 0.0
            && poses.iter().all(|p| p.pose_messages > 0);
        let hinges: Vec<f64> = nominal
            .hinges
            .iter()
            .flat_map(|h| h.base_m)
            .chain(nominal.hinges.iter().flat_map(|h| h.platform_m))
            .collect();
        let geometry = HexapodGeometry::from_slice(&hinges);
        let mut start = DVector::zeros(CONSTANTS + if free_poses { 6 * poses.len() } else { 0 });
        start.rows_mut(0, HINGES).copy_from_slice(&hinges);
        for i in 0..LEGS {
            start[HINGES + i] = poses
                .iter()
                .map(|p| p.mean_m[i] - leg_length(&geometry.leg(i), &p.pose).0)
                .sum::<f64>()
                / poses.len().max(1) as f64;
        }
        if free_poses {
            for (k, p) in poses.iter().enumerate() {
                start
                    .rows_mut(CONSTANTS + 6 * k, 6)
                    .copy_from_slice(&pose_vector(&p.pose));
            }
        }
        let t_end = poses.iter().map(|p| p.t_s).fold(0.0, f64::max).max(1e-9);
        let block = |t: f64| {
            let b = ((t / t_end) * TIME_BLOCKS as f64).floor() as usize;
            format!("block {} of {TIME_BLOCKS}", b.min(TIME_BLOCKS - 1) + 1)
        };
        let design_lengths: Vec<[f64; LEGS]> = poses
            .iter()
            .map(|p| std::array::from_fn(|i| leg_length(&design.leg(i), &p.commanded).0))
            .collect();
        let motion_sign: Vec<[f64; LEGS]> = (0..poses.len())
            .map(|k| {
                std::array::from_fn(|i| {
                    if k == 0 {
                        0.0
                    } else {
                        (design_lengths[k][i] - design_lengths[k - 1][i]).signum()
                    }
                })
            })
            .collect();
        let mut sigma = Vec::new();
        let mut labels = Vec::new();
        for (k, (p, signs)) in poses.iter().zip(&motion_sign).enumerate() {
            for (i, sign) in signs.iter().enumerate() {
                sigma.push(encoder_sigma / (p.n.max(1) as f64).sqrt());
                let motion = match *sign {
                    s if s > 0.0 => "extending",
                    s if s < 0.0 => "retracting",
                    _ => "at rest",
                };
                labels.push(ResidualLabel {
                    groups: vec![
                        ("leg", format!("leg {i}")),
                        ("leg motion", format!("leg {i} {motion}")),
                        ("time", block(p.t_s)),
                    ],
                    row: format!("leg {i}"),
                    x: p.t_s,
                    holdout: Some(k),
                    unit: "m",
                });
            }
        }
        if free_poses {
            for p in &poses {
                let averaged = (p.pose_messages.max(1) as f64).sqrt();
                for (j, name) in POSE_NAMES.iter().enumerate() {
                    let (s, unit, row) = if j < 3 {
                        (
                            prepared.pose_sigma_m / averaged,
                            "m",
                            "pose sensor translation",
                        )
                    } else {
                        (
                            prepared.pose_sigma_rad / averaged,
                            "rad",
                            "pose sensor rotation",
                        )
                    };
                    sigma.push(s);
                    labels.push(ResidualLabel {
                        groups: vec![
                            ("pose sensor", format!("pose sensor {name}")),
                            ("time", block(p.t_s)),
                        ],
                        row: row.into(),
                        x: p.t_s,
                        holdout: None,
                        unit,
                    });
                }
            }
        }
        Ok(Self {
            session_id: session.header.session_id.clone(),
            poses,
            free_poses,
            start,
            sigma,
            labels,
            motion_sign,
        })
    }

    fn pose(&self, p: &DVector<f64>, k: usize) -> Pose {
        if self.free_poses {
            pose_of(p.rows(CONSTANTS + 6 * k, 6).as_slice())
        } else {
            self.poses[k].pose
        }
    }

    fn geometry(p: &DVector<f64>) -> HexapodGeometry {
        HexapodGeometry::from_slice(&p.as_slice()[..HINGES])
    }

    /// Rows of the leg residuals: pose k, leg i.
    fn leg_row(k: usize, i: usize) -> usize {
        k * LEGS + i
    }

    fn sensor_row(&self, k: usize, j: usize) -> usize {
        self.poses.len() * LEGS + 6 * k + j
    }
}

impl ResidualModel for HexapodResidualModel {
    fn kind(&self) -> &'static str {
        crate::kinds::hexapod::config::KIND
    }

    fn session_id(&self) -> &str {
        &self.session_id
    }

    fn x_axis(&self) -> &'static str {
        "time since the first pose [s]"
    }

    fn parameter_names(&self) -> Vec<String> {
        let mut names = Vec::new();
        for what in ["B", "P"] {
            for i in 0..LEGS {
                for axis in ["x", "y", "z"] {
                    names.push(format!("{what}{i}.{axis}_m"));
                }
            }
        }
        for i in 0..LEGS {
            names.push(format!("leg{i}.encoder_constant_m"));
        }
        if self.free_poses {
            for k in 0..self.poses.len() {
                for name in POSE_NAMES {
                    names.push(format!("pose{k}.{name}"));
                }
            }
        }
        names
    }

    fn reported_parameters(&self) -> Vec<usize> {
        (0..HINGES).collect()
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

    fn residuals(&self, p: &DVector<f64>) -> DVector<f64> {
        let g = Self::geometry(p);
        let mut r = DVector::zeros(self.sigma.len());
        for (k, data) in self.poses.iter().enumerate() {
            let pose = self.pose(p, k);
            for i in 0..LEGS {
                r[Self::leg_row(k, i)] =
                    data.mean_m[i] - leg_length(&g.leg(i), &pose).0 - p[HINGES + i];
            }
            if self.free_poses {
                let measured = pose_vector(&data.pose);
                for (j, m) in measured.iter().enumerate() {
                    r[self.sensor_row(k, j)] = m - p[CONSTANTS + 6 * k + j];
                }
            }
        }
        r
    }

    fn jacobian(&self, p: &DVector<f64>) -> DMatrix<f64> {
        let g = Self::geometry(p);
        let mut jac = DMatrix::zeros(self.sigma.len(), p.len());
        for k in 0..self.poses.len() {
            let pose = self.pose(p, k);
            let pose_jac = self.free_poses.then(|| pose_jacobian(&g, &pose));
            for i in 0..LEGS {
                let row = Self::leg_row(k, i);
                let (_, grad) = leg_length(&g.leg(i), &pose);
                for c in 0..3 {
                    jac[(row, 3 * i + c)] = grad[c];
                    jac[(row, 3 * (LEGS + i) + c)] = grad[3 + c];
                }
                jac[(row, HINGES + i)] = 1.0;
                if let Some(a) = &pose_jac {
                    for c in 0..6 {
                        jac[(row, CONSTANTS + 6 * k + c)] = a[(i, c)];
                    }
                }
            }
            if self.free_poses {
                for j in 0..6 {
                    jac[(self.sensor_row(k, j), CONSTANTS + 6 * k + j)] = 1.0;
                }
            }
        }
        jac
    }

    /// Each measured pose's six parameters: its leg rows and its sensor rows.
    fn local_blocks(&self) -> Vec<LocalBlock> {
        if !self.free_poses {
            return Vec::new();
        }
        (0..self.poses.len())
            .map(|k| LocalBlock {
                columns: CONSTANTS + 6 * k..CONSTANTS + 6 * (k + 1),
                rows: (0..LEGS)
                    .map(|i| Self::leg_row(k, i))
                    .chain((0..6).map(|j| self.sensor_row(k, j)))
                    .collect(),
            })
            .collect()
    }

    fn effects(&self) -> Vec<Box<dyn Effect + '_>> {
        let mut library: Vec<Box<dyn Effect + '_>> =
            vec![Box::new(LegScale(self)), Box::new(LegBacklash(self))];
        if self.free_poses {
            library.push(Box::new(SensorDrift(self)));
        }
        library
    }
}

fn per_leg(what: &str) -> Vec<String> {
    (0..LEGS).map(|i| format!("leg{i}.{what}")).collect()
}

/// `leg_scale`: leg i's encoder reads (1 + k_i) × its change since the first pose:
/// reading += k_i (L_i(pose) − L_i(pose 0)).
struct LegScale<'a>(&'a HexapodResidualModel);

impl Effect for LegScale<'_> {
    fn name(&self) -> &'static str {
        "leg_scale"
    }
    fn parameter_names(&self) -> Vec<String> {
        per_leg("k")
    }
    fn columns(&self, p: &DVector<f64>) -> DMatrix<f64> {
        let m = self.0;
        let g = HexapodResidualModel::geometry(p);
        let mut a = DMatrix::zeros(m.sigma.len(), LEGS);
        let pose0 = m.pose(p, 0);
        for k in 0..m.poses.len() {
            let pose = m.pose(p, k);
            for i in 0..LEGS {
                a[(HexapodResidualModel::leg_row(k, i), i)] =
                    leg_length(&g.leg(i), &pose).0 - leg_length(&g.leg(i), &pose0).0;
            }
        }
        a
    }
}

/// `leg_backlash`: leg i's reading is off by b_i × the sign of its last motion (+ extending,
/// − retracting; 0 at the first pose).
struct LegBacklash<'a>(&'a HexapodResidualModel);

impl Effect for LegBacklash<'_> {
    fn name(&self) -> &'static str {
        "leg_backlash"
    }
    fn parameter_names(&self) -> Vec<String> {
        per_leg("b_m")
    }
    fn columns(&self, _: &DVector<f64>) -> DMatrix<f64> {
        let m = self.0;
        let mut a = DMatrix::zeros(m.sigma.len(), LEGS);
        for (k, signs) in m.motion_sign.iter().enumerate() {
            for (i, s) in signs.iter().enumerate() {
                a[(HexapodResidualModel::leg_row(k, i), i)] = *s;
            }
        }
        a
    }
}

/// `sensor_drift`: the pose sensor's reading drifts linearly in time: measured pose += v t
/// (t since the first pose; v per translation coordinate in m/s and per rotation-vector
/// component in rad/s).
struct SensorDrift<'a>(&'a HexapodResidualModel);

impl Effect for SensorDrift<'_> {
    fn name(&self) -> &'static str {
        "sensor_drift"
    }
    fn parameter_names(&self) -> Vec<String> {
        [
            "vx_m_per_s",
            "vy_m_per_s",
            "vz_m_per_s",
            "vrx_rad_per_s",
            "vry_rad_per_s",
            "vrz_rad_per_s",
        ]
        .map(String::from)
        .to_vec()
    }
    fn columns(&self, _: &DVector<f64>) -> DMatrix<f64> {
        let m = self.0;
        let mut a = DMatrix::zeros(m.sigma.len(), 6);
        for (k, data) in m.poses.iter().enumerate() {
            for j in 0..6 {
                a[(m.sensor_row(k, j), j)] = data.t_s;
            }
        }
        a
    }
}
