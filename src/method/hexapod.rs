//! Method of plan kind `hexapod`: relative leg-length changes at the measured poses from the
//! session, then the 36 hinge coordinates by plain damped least squares and by the two-stage
//! method (LM, then the grid multi-start on the vertical base coordinates).
//!
//! Each pose's readings are averaged; pose 0 (home) is the reference of every change. The
//! per-change σ is σ_enc·√(1/n + 1/n₀) (n readings at the pose, n₀ at home), the changes being
//! treated as independent (their shared home term is small when n₀ ≫ n).

use serde::{Deserialize, Serialize};

use crate::config::hexapod::{HexapodMachine, HexapodPlanConfig, KIND};
use crate::model::hexapod::{Pose, LEGS};
use crate::session::kind_messages::{
    hexapod_legs_topic, hexapod_pose_topic, LegSample, PlatformPoseSample,
};
use crate::session::messages::RunEvent;
use crate::session::reader::Session;
use crate::sim::hexapod::to_pose;
use crate::solve::hexapod::{
    solve_lm, solve_two_stage, GridRound, HexapodError, HexapodObservations, LmOptions,
    TwoStageOptions,
};

#[derive(Debug, thiserror::Error)]
pub enum HexapodMethodError {
    #[error("session header: `plan` is not a hexapod plan: {0}")]
    Plan(String),
    #[error("session header: machine hinges: {0}")]
    Machine(String),
    #[error("session header: no device of kind `hexapod` with `noise_m`")]
    NoHexapod,
    #[error("message on {topic} at log_time {log_time_ns} ns: {message}")]
    Message {
        topic: String,
        log_time_ns: u64,
        message: String,
    },
    #[error("pose {pose}: no leg readings between its pose_begin and pose_end")]
    NoReadings { pose: usize },
    #[error("pose {pose}: `pose_begin` lacks axis `{axis}`")]
    MissingAxis { pose: usize, axis: String },
    #[error("the first measured pose is {0}, not the reference pose 0")]
    NoReference(usize),
    #[error(transparent)]
    Solve(#[from] HexapodError),
}

/// geocal-results/1 of kind `hexapod`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct HexapodResults {
    pub format: String,
    pub kind: String,
    pub session_id: String,
    /// Poses used (home included) and raw leg readings in them.
    pub poses: usize,
    pub readings: usize,
    /// `measured` (from `/hexapod/<id>/pose`) or `commanded` (from `pose_begin`).
    pub pose_source: String,
    /// σ of one relative leg-length change used by the solvers, metres.
    pub sigma_change_m: f64,
    /// The two-stage result with its standard uncertainties (Cramér–Rao at the solution).
    pub hinges: Vec<HingeResult>,
    /// Σ of squared residuals over every pose change and leg, two-stage result (m²).
    pub objective_m2: f64,
    pub residual_rms_m: f64,
    pub chi2_per_dof: f64,
    pub dof: usize,
    pub two_stage: TwoStageSummary,
    pub lm: PlainLmSummary,
    pub note: String,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct HingeResult {
    pub leg: usize,
    pub base_m: [f64; 3],
    pub base_sigma_m: [f64; 3],
    pub platform_m: [f64; 3],
    pub platform_sigma_m: [f64; 3],
    pub nominal_base_m: [f64; 3],
    pub nominal_platform_m: [f64; 3],
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct TwoStageSummary {
    pub objective_initial_m2: f64,
    pub objective_stage1_m2: f64,
    pub objective_m2: f64,
    pub rounds: Vec<RoundSummary>,
    pub leg_solves: usize,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct RoundSummary {
    pub step_m: f64,
    pub objective_m2: f64,
    pub improved_legs: Vec<usize>,
}

/// Plain damped least squares from the design geometry, for comparison.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct PlainLmSummary {
    pub objective_m2: f64,
    pub iterations: usize,
    pub base_m: Vec<[f64; 3]>,
    pub platform_m: Vec<[f64; 3]>,
    /// Largest coordinate difference between the plain LM and the two-stage result, metres.
    pub max_difference_m: f64,
}

fn parse<T: serde::de::DeserializeOwned>(
    topic: &str,
    log_time_ns: u64,
    v: &serde_json::Value,
) -> Result<T, HexapodMethodError> {
    T::deserialize(v).map_err(|e| HexapodMethodError::Message {
        topic: topic.to_string(),
        log_time_ns,
        message: e.to_string(),
    })
}

/// One pose's data: the pose, the mean leg reading and how many readings made it.
struct PoseData {
    pose: Pose,
    mean_m: [f64; LEGS],
    n: usize,
}

fn pose_data(session: &Session, id: &str) -> Result<(Vec<PoseData>, bool), HexapodMethodError> {
    let legs_topic = hexapod_legs_topic(id);
    let pose_topic = hexapod_pose_topic(id);
    let empty = Vec::new();
    let legs = session.topics.get(&legs_topic).unwrap_or(&empty);
    let measured = session.topics.get(&pose_topic).unwrap_or(&empty);
    let mut open: Option<(usize, u64, Pose)> = None;
    let mut out = Vec::new();
    let mut any_measured = false;
    for e in &session.events {
        match &e.msg {
            RunEvent::PoseBegin { pose, axes } => {
                let a = |name: &str| {
                    axes.get(name)
                        .copied()
                        .ok_or_else(|| HexapodMethodError::MissingAxis {
                            pose: *pose,
                            axis: name.to_string(),
                        })
                };
                let commanded = geocal_drivers::PlatformPose {
                    translation_m: [a("x")?, a("y")?, a("z")?],
                    rotation_vector_rad: [a("rx")?, a("ry")?, a("rz")?],
                };
                if out.is_empty() && *pose != 0 {
                    return Err(HexapodMethodError::NoReference(*pose));
                }
                open = Some((*pose, e.log_time_ns, to_pose(&commanded)));
            }
            RunEvent::PoseEnd { pose } => {
                let Some((p, begin_ns, commanded)) = open.take() else {
                    continue;
                };
                if p != *pose {
                    continue;
                }
                let end_ns = e.log_time_ns;
                let within = |t: u64| t >= begin_ns && t <= end_ns;
                let mut sum = [0.0; LEGS];
                let mut n = 0;
                for r in legs.iter().filter(|r| within(r.log_time_ns)) {
                    let s: LegSample = parse(&legs_topic, r.log_time_ns, &r.msg)?;
                    for (acc, v) in sum.iter_mut().zip(s.lengths_m) {
                        *acc += v;
                    }
                    n += 1;
                }
                if n == 0 {
                    return Err(HexapodMethodError::NoReadings { pose: p });
                }
                let pose = match measured.iter().rfind(|m| within(m.log_time_ns)) {
                    Some(m) => {
                        let s: PlatformPoseSample = parse(&pose_topic, m.log_time_ns, &m.msg)?;
                        any_measured = true;
                        to_pose(&geocal_drivers::PlatformPose {
                            translation_m: s.translation_m,
                            rotation_vector_rad: s.rotation_vector_rad,
                        })
                    }
                    None => commanded,
                };
                out.push(PoseData {
                    pose,
                    mean_m: sum.map(|s| s / n as f64),
                    n,
                });
            }
            _ => {}
        }
    }
    Ok((out, any_measured))
}

pub fn solve(session: &Session) -> Result<HexapodResults, HexapodMethodError> {
    let plan: HexapodPlanConfig = serde_json::from_value(session.header.plan.clone())
        .map_err(|e| HexapodMethodError::Plan(e.to_string()))?;
    let hexapod = session
        .header
        .devices
        .iter()
        .find(|d| d.kind == "hexapod" && d.noise_m.is_some())
        .ok_or(HexapodMethodError::NoHexapod)?;
    let noise_m = hexapod.noise_m.ok_or(HexapodMethodError::NoHexapod)?;
    let machine: HexapodMachine = serde_json::from_value(
        hexapod
            .extra
            .get("design")
            .cloned()
            .unwrap_or(serde_json::Value::Null),
    )
    .map_err(|e| HexapodMethodError::Machine(e.to_string()))?;
    if machine.base_hinges_m.len() != LEGS || machine.platform_hinges_m.len() != LEGS {
        return Err(HexapodMethodError::Machine(format!(
            "expected {LEGS} base and {LEGS} platform hinges"
        )));
    }
    let nominal = machine.nominal();
    let (data, any_measured) = pose_data(session, &hexapod.id)?;
    let Some(reference) = data.first() else {
        return Err(HexapodMethodError::NoReadings { pose: 0 });
    };
    let n_other = data.iter().skip(1).map(|d| d.n).min().unwrap_or(1);
    let sigma_change_m = noise_m * (1.0 / n_other as f64 + 1.0 / reference.n as f64).sqrt();
    let obs = HexapodObservations {
        poses: data.iter().map(|d| d.pose).collect(),
        delta_lengths_m: data
            .iter()
            .map(|d| std::array::from_fn(|i| d.mean_m[i] - reference.mean_m[i]))
            .collect(),
        sigma_m: sigma_change_m,
        search_poses: None,
    };
    let lm = solve_lm(&obs, &nominal, &LmOptions::default())?;
    let s = &plan.solver;
    let two = solve_two_stage(
        &obs,
        &nominal,
        &TwoStageOptions {
            initial_step_m: s.initial_step_m,
            min_step_m: s.min_step_m,
            shrink: s.shrink,
            ..TwoStageOptions::default()
        },
    )?;
    let changes = (data.len() - 1) * LEGS;
    let dof = changes.saturating_sub(6 * LEGS);
    let max_difference_m = lm
        .geometry
        .to_vec()
        .iter()
        .zip(two.geometry.to_vec())
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max);
    let hinges = (0..LEGS)
        .map(|i| HingeResult {
            leg: i,
            base_m: two.base_m[i],
            base_sigma_m: two.base_sigma_m[i],
            platform_m: two.platform_m[i],
            platform_sigma_m: two.platform_sigma_m[i],
            nominal_base_m: nominal.base_m[i].into(),
            nominal_platform_m: nominal.platform_m[i].into(),
        })
        .collect();
    Ok(HexapodResults {
        format: "geocal-results/1".into(),
        kind: KIND.into(),
        session_id: session.header.session_id.clone(),
        poses: data.len(),
        readings: data.iter().map(|d| d.n).sum(),
        pose_source: if any_measured {
            "measured"
        } else {
            "commanded"
        }
        .into(),
        sigma_change_m,
        hinges,
        objective_m2: two.objective_m2,
        residual_rms_m: two.residual_rms_m,
        chi2_per_dof: two.objective_m2 / (sigma_change_m * sigma_change_m) / dof.max(1) as f64,
        dof,
        two_stage: TwoStageSummary {
            objective_initial_m2: two.objective_initial_m2,
            objective_stage1_m2: two.objective_stage1_m2,
            objective_m2: two.objective_m2,
            rounds: two
                .rounds
                .iter()
                .map(|r: &GridRound| RoundSummary {
                    step_m: r.step_m,
                    objective_m2: r.objective_m2,
                    improved_legs: r.improved_legs.clone(),
                })
                .collect(),
            leg_solves: two.leg_solves,
        },
        lm: PlainLmSummary {
            objective_m2: lm.objective_m2,
            iterations: lm.iterations,
            base_m: lm.geometry.base_m.iter().map(|v| (*v).into()).collect(),
            platform_m: lm.geometry.platform_m.iter().map(|v| (*v).into()).collect(),
            max_difference_m,
        },
        note: "hinges from the two-stage method (damped least squares from the design geometry, \
               then the grid multi-start on the vertical base coordinates, never above its \
               start's objective); sigmas from σ²(JᵀJ)⁻¹ per leg at the solution, poses taken \
               as exact; `lm` is plain damped least squares from the design geometry"
            .into(),
    })
}
