//! Method of plan kind `hexapod`: relative leg-length changes at the measured poses from the
//! session, then the 36 hinge coordinates by plain damped least squares and by the two-stage
//! method (LM, then the grid multi-start on the vertical base coordinates).
//!
//! Each pose's readings are averaged; pose 0 (home) is the reference of every change. The final
//! fit weights the changes with their full covariance (solve::hexapod_weighted): the shared
//! home reading, and the pose sensor's declared noise on every measured pose.

use serde::{Deserialize, Serialize};

use crate::kinds::hexapod::config::{HexapodMachine, HexapodPlanConfig, KIND};
use crate::kinds::hexapod::sim::to_pose;
use crate::model::hexapod::{HexapodGeometry, Pose, LEGS};
use crate::session::kind_messages::{
    hexapod_legs_topic, hexapod_pose_topic, LegSample, PlatformPoseSample,
};
use crate::session::messages::RunEvent;
use crate::session::reader::Session;
use crate::solve::hexapod::{
    solve_lm, solve_two_stage, GridRound, HexapodError, HexapodObservations, LmOptions,
    TwoStageOptions,
};
use crate::solve::hexapod_weighted::{refine_weighted, HexapodNoise, PoseNoise};

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
    #[error(
        "the reference pose 0 was lost in a damaged chunk: leg changes cannot be referenced \
         (`geocal repair` cannot bring it back; measure again)"
    )]
    ReferenceLost,
    #[error(
        "session header: pose sensor `{sensor}` (driver `{driver}`) declares no `{key}`: its \
         measured poses have no noise model (give 0 for a noise-free sensor)"
    )]
    PoseSensorNoise {
        sensor: String,
        driver: String,
        key: &'static str,
    },
    #[error(
        "poses published on {found}: the contract (docs/session-format.md) is \
         `/hexapod/<hexapod id>/pose` or `/hexapod/<pose sensor id>/pose`, here {expected}; \
         no pose is taken from another topic"
    )]
    MisplacedPoses { found: String, expected: String },
    #[error(
        "poses published on both {first} and {second}: which of them measures the platform is \
         ambiguous; no pose is taken"
    )]
    AmbiguousPoses { first: String, second: String },
    #[error(
        "session header: pose sensor `{sensor}` measures the poses but {topic} holds no pose in \
         any pose window: commanded poses would be used as exact"
    )]
    NoMeasuredPoses { sensor: String, topic: String },
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
    /// σ of the measured poses per translation coordinate (m) and rotation-vector component
    /// (rad), from the pose sensor's declared noise; 0 when the poses are commanded.
    #[serde(default)]
    pub pose_sigma_m: f64,
    #[serde(default)]
    pub pose_sigma_rad: f64,
    /// The weighted (generalised least-squares) refinement of the two-stage result, with its
    /// standard uncertainties: encoder and pose noise in the weights and the covariance.
    pub hinges: Vec<HingeResult>,
    /// Covariance of the 36 hinge coordinates (B_0..B_5 then P_0..P_5, x y z each), m²: the
    /// shared pose errors correlate the legs.
    #[serde(default)]
    pub covariance_m2: Vec<Vec<f64>>,
    /// Gauss–Newton iterations of the weighted refinement.
    #[serde(default)]
    pub weighted_iterations: usize,
    /// Σ of squared residuals over every pose change and leg, two-stage result (m²); the
    /// chi²/dof below is the weighted one of `hinges` (rᵀC⁻¹r over `dof`), null at 0 dof.
    pub objective_m2: f64,
    pub residual_rms_m: f64,
    pub chi2_per_dof: Option<f64>,
    pub dof: usize,
    pub two_stage: TwoStageSummary,
    pub lm: PlainLmSummary,
    pub note: String,
    /// Present when χ²/dof is improbable for its degrees of freedom (p < 1e-3): the σ are
    /// then not trustworthy; `sigma_scale` = √(χ²/dof) (docs/uncertainty.md, "Misfit").
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub misfit: Option<crate::solve::misfit::Misfit>,
    /// `geocal solve --effects`: the effects fitted jointly with the hinges (effect →
    /// parameter → value, with `<parameter>.sigma`); the hinges, covariance and χ² are then
    /// those of the joint fit.
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub effects: std::collections::BTreeMap<String, std::collections::BTreeMap<String, f64>>,
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

/// One pose's data: the pose, the mean leg reading, how many readings made it and how many
/// pose messages the measured pose averages (0: commanded, taken as exact).
pub(crate) struct PoseData {
    pub(crate) pose: Pose,
    pub(crate) mean_m: [f64; LEGS],
    pub(crate) n: usize,
    pub(crate) pose_messages: usize,
    /// The commanded pose, and the middle of the pose's window (s since the session's first
    /// pose window began): what the diagnosis's effects depend on.
    pub(crate) commanded: Pose,
    pub(crate) t_s: f64,
}

/// The topic of the measured poses: the hexapod's own (`/hexapod/<hexapod id>/pose`, what
/// geocal records) or, as devices name their topics by their own id, the pose sensor's
/// (`/hexapod/<pose sensor id>/pose`). Poses on any other `/hexapod/*/pose` topic, or on
/// both, are refused rather than ignored: commanded poses would silently count as exact.
pub(crate) fn measured_pose_topic(
    session: &Session,
    hexapod_id: &str,
    pose_sensor_id: Option<&str>,
) -> Result<String, HexapodMethodError> {
    let own = hexapod_pose_topic(hexapod_id);
    let sensors = pose_sensor_id.map(hexapod_pose_topic);
    let mut holding = None;
    for topic in session
        .topics
        .iter()
        .filter(|(t, messages)| {
            t.starts_with("/hexapod/") && t.ends_with("/pose") && !messages.is_empty()
        })
        .map(|(t, _)| t)
    {
        if *topic != own && Some(topic) != sensors.as_ref() {
            return Err(HexapodMethodError::MisplacedPoses {
                found: topic.clone(),
                expected: own,
            });
        }
        if let Some(first) = holding.replace(topic.clone()) {
            return Err(HexapodMethodError::AmbiguousPoses {
                first,
                second: topic.clone(),
            });
        }
    }
    Ok(holding.unwrap_or(own))
}

fn pose_data(
    session: &Session,
    id: &str,
    pose_topic: &str,
) -> Result<(Vec<PoseData>, bool), HexapodMethodError> {
    let legs_topic = hexapod_legs_topic(id);
    let empty = Vec::new();
    let legs = session.topics.get(&legs_topic).unwrap_or(&empty);
    let measured = session.topics.get(pose_topic).unwrap_or(&empty);
    let mut open: Option<(usize, u64, Pose)> = None;
    let mut out = Vec::new();
    let mut any_measured = false;
    let mut first_begin_ns: Option<u64> = None;
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
                    if session.lost_between(0, e.log_time_ns) {
                        return Err(HexapodMethodError::ReferenceLost);
                    }
                    return Err(HexapodMethodError::NoReference(*pose));
                }
                open = Some((*pose, e.log_time_ns, to_pose(&commanded)));
            }
            // A pose left open by the interruption is measured again after this.
            RunEvent::Resume { .. } => open = None,
            RunEvent::PoseEnd { pose } => {
                let Some((p, begin_ns, commanded)) = open.take() else {
                    continue;
                };
                if p != *pose {
                    continue;
                }
                let end_ns = e.log_time_ns;
                if session.lost_between(begin_ns, end_ns) {
                    continue;
                }
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
                // Several pose messages in one window (the platform at rest) are averaged:
                // their mean has σ / √k per coordinate.
                let mut t_sum = [0.0; 3];
                let mut w_sum = [0.0; 3];
                let mut k = 0usize;
                for m in measured.iter().filter(|m| within(m.log_time_ns)) {
                    let s: PlatformPoseSample = parse(pose_topic, m.log_time_ns, &m.msg)?;
                    for c in 0..3 {
                        t_sum[c] += s.translation_m[c];
                        w_sum[c] += s.rotation_vector_rad[c];
                    }
                    k += 1;
                }
                let pose = if k > 0 {
                    any_measured = true;
                    to_pose(&geocal_drivers::PlatformPose {
                        translation_m: t_sum.map(|v| v / k as f64),
                        rotation_vector_rad: w_sum.map(|v| v / k as f64),
                    })
                } else {
                    commanded
                };
                let first_ns = *first_begin_ns.get_or_insert(begin_ns);
                out.push(PoseData {
                    pose,
                    mean_m: sum.map(|s| s / n as f64),
                    n,
                    pose_messages: k,
                    commanded,
                    t_s: (begin_ns.saturating_sub(first_ns) + end_ns.saturating_sub(begin_ns) / 2)
                        as f64
                        * 1e-9,
                });
            }
            _ => {}
        }
    }
    Ok((out, any_measured))
}

/// What the solvers take from a session: the plan, the design geometry, each pose's data,
/// the observations (changes from the reference pose) and their noise model.
pub struct Prepared {
    plan: HexapodPlanConfig,
    pub nominal: HexapodGeometry,
    pub(crate) data: Vec<PoseData>,
    pub(crate) any_measured: bool,
    sigma_change_m: f64,
    pub(crate) pose_sigma_m: f64,
    pub(crate) pose_sigma_rad: f64,
    pub observations: HexapodObservations,
    pub noise: HexapodNoise,
}

pub fn prepare(session: &Session) -> Result<Prepared, HexapodMethodError> {
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
    let sensor = session
        .header
        .devices
        .iter()
        .find(|d| d.kind == "pose_sensor");
    let pose_topic = measured_pose_topic(session, &hexapod.id, sensor.map(|d| d.id.as_str()))?;
    // The pose sensor's declared noise applies to the measured poses; a sensor that measures
    // (any driver but `given`, which takes the commanded poses as exact) must declare it.
    let measuring = sensor.filter(|d| d.driver != "given");
    let (pose_sigma_m, pose_sigma_rad) = match measuring {
        Some(d) => {
            let missing = |key| HexapodMethodError::PoseSensorNoise {
                sensor: d.id.clone(),
                driver: d.driver.clone(),
                key,
            };
            let m = d.noise_m.filter(|v| v.is_finite() && *v >= 0.0);
            let r = d
                .extra
                .get("noise_rad")
                .and_then(|v| v.as_f64())
                .filter(|v| v.is_finite() && *v >= 0.0);
            (
                m.ok_or_else(|| missing("noise_m"))?,
                r.ok_or_else(|| missing("noise_rad"))?,
            )
        }
        None => (0.0, 0.0),
    };
    let (data, any_measured) = pose_data(session, &hexapod.id, &pose_topic)?;
    if let (Some(d), false) = (measuring, any_measured) {
        return Err(HexapodMethodError::NoMeasuredPoses {
            sensor: d.id.clone(),
            topic: pose_topic,
        });
    }
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
    let noise = HexapodNoise {
        encoder_sigma_m: noise_m,
        poses: data
            .iter()
            .map(|d| {
                let averaged = (d.pose_messages.max(1) as f64).sqrt();
                let measured = d.pose_messages > 0;
                PoseNoise {
                    readings: d.n,
                    translation_sigma_m: if measured {
                        pose_sigma_m / averaged
                    } else {
                        0.0
                    },
                    rotation_sigma_rad: if measured {
                        pose_sigma_rad / averaged
                    } else {
                        0.0
                    },
                }
            })
            .collect(),
    };
    Ok(Prepared {
        plan,
        nominal,
        data,
        any_measured,
        sigma_change_m,
        pose_sigma_m,
        pose_sigma_rad,
        observations: obs,
        noise,
    })
}

pub fn solve(session: &Session) -> Result<HexapodResults, HexapodMethodError> {
    let Prepared {
        plan,
        nominal,
        data,
        any_measured,
        sigma_change_m,
        pose_sigma_m,
        pose_sigma_rad,
        observations: obs,
        noise,
    } = prepare(session)?;
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
    let fit = refine_weighted(&obs, &noise, &two.geometry)?;
    let sigmas = fit.sigmas_m();
    let coord = |v: &[f64], o: usize| -> [f64; 3] { std::array::from_fn(|k| v[o + k]) };
    let estimate = fit.geometry.to_vec();
    let dof = fit.dof;
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
            base_m: coord(&estimate, 3 * i),
            base_sigma_m: coord(&sigmas, 3 * i),
            platform_m: coord(&estimate, 3 * (LEGS + i)),
            platform_sigma_m: coord(&sigmas, 3 * (LEGS + i)),
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
        pose_sigma_m: if any_measured { pose_sigma_m } else { 0.0 },
        pose_sigma_rad: if any_measured { pose_sigma_rad } else { 0.0 },
        hinges,
        covariance_m2: fit
            .covariance_m2
            .row_iter()
            .map(|r| r.iter().copied().collect())
            .collect(),
        weighted_iterations: fit.iterations,
        objective_m2: two.objective_m2,
        residual_rms_m: two.residual_rms_m,
        chi2_per_dof: (dof > 0).then(|| fit.chi2 / dof as f64),
        dof,
        misfit: crate::solve::misfit::Misfit::check(fit.chi2, dof),
        effects: Default::default(),
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
        note: "hinges: the two-stage method (damped least squares from the design geometry, \
               then the grid multi-start on the vertical base coordinates, never above its \
               start's objective), refined by generalised least squares with the full residual \
               covariance (encoder noise of both readings, pose-sensor noise of the pose and of \
               the reference pose); sigmas and covariance_m2 = (JᵀC⁻¹J)⁻¹ at the solution, \
               chi2_per_dof = rᵀC⁻¹r/dof; `lm` is plain damped least squares from the design \
               geometry"
            .into(),
    })
}

/// `geocal solve --effects NAMES`: the nominal solve, then the hinges and the named effects of
/// the hexapod's library fitted jointly (docs/diagnosis.md, "hexapod"): hinges, σ, covariance
/// and χ² of the joint fit.
pub fn solve_with_effects(
    session: &Session,
    names: &[String],
) -> Result<HexapodResults, Box<dyn std::error::Error + Send + Sync>> {
    use crate::method::diagnosis::{effect_parameters, effects_named, joint_fit, ResidualModel};
    let mut results = solve(session)?;
    let model = super::diagnosis::HexapodResidualModel::new(session, &results)?;
    let library = model.effects();
    let effects = effects_named(&library, names)?;
    let fit = joint_fit(&model, &effects, &model.start());
    let hinges = 6 * LEGS;
    for h in &mut results.hinges {
        for k in 0..3 {
            let (b, p) = (3 * h.leg + k, 3 * (LEGS + h.leg) + k);
            h.base_m[k] = fit.params[b];
            h.base_sigma_m[k] = fit.sigma(b);
            h.platform_m[k] = fit.params[p];
            h.platform_sigma_m[k] = fit.sigma(p);
        }
    }
    results.covariance_m2 = (0..hinges)
        .map(|i| (0..hinges).map(|j| fit.covariance[(i, j)]).collect())
        .collect();
    results.dof = fit.dof;
    results.chi2_per_dof = (fit.dof > 0).then(|| fit.chi2 / fit.dof as f64);
    results.misfit = crate::solve::misfit::Misfit::check(fit.chi2, fit.dof);
    results.effects = effect_parameters(&effects, &fit, fit.params.len());
    results.note.push_str(&format!(
        "; with --effects {}: hinges, sigmas, covariance_m2 and chi2_per_dof from the joint fit \
         of the hinges, the legs' encoder constants, the measured poses and the effects (the \
         residual model of docs/diagnosis.md)",
        crate::method::diagnosis::effect_names(&effects)
    ));
    Ok(results)
}
