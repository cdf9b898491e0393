//! Method of plan kind `probe_install`: sphere readings per posture from the session, then the
//! 11 installation parameters by LM (with covariance) and by the improved GA, and the radius check.
//!
//! Each point's observation is the mean of its valid raw readings (σ = probe noise / √n) at the
//! machine position reported on arrival (`/machine/pose`, the commanded one if none reported).

use serde::{Deserialize, Serialize};

use crate::kinds::probe_install::config::{ProbeInstallPlan, KIND};
use crate::model::probe_install::{ProbeObservation, N_PARAMS, PARAM_NAMES};
use crate::session::kind_messages::{MachinePoseSample, TOPIC_MACHINE_POSE};
use crate::session::messages::RunEvent;
use crate::session::reader::Session;
use crate::solve::genetic::GeneticOptions;
use crate::solve::probe_install::{
    measured_radius_m, solve_ga, solve_lm_with_design, LmOptions, ProbeInstallError,
    ProbeInstallProblem, SearchBox,
};

/// A reported posture within this of a planned one (servo and encoder scatter) is that
/// posture for the identifiability check.
const POSTURE_SNAP_RAD: f64 = 1e-3;

#[derive(Debug, thiserror::Error)]
pub enum ProbeInstallMethodError {
    #[error("session header: `plan` is not a probe_install plan: {0}")]
    Plan(String),
    #[error("session header: no device of kind `probe` with `noise_m`")]
    NoProbe,
    #[error("message on {topic} at log_time {log_time_ns} ns: {message}")]
    Message {
        topic: String,
        log_time_ns: u64,
        message: String,
    },
    #[error("`probe_begin` of posture {posture} point {point} outside a posture")]
    OutsidePosture { posture: usize, point: usize },
    #[error("point {point} of posture {posture}: no machine position recorded before it")]
    NoPosition { posture: usize, point: usize },
    #[error("point {point} of posture {posture}: machine position lacks axis `{axis}`")]
    MissingAxis {
        posture: usize,
        point: usize,
        axis: String,
    },
    #[error(transparent)]
    Solve(#[from] ProbeInstallError),
}

/// geocal-results/1 of kind `probe_install`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct ProbeInstallResults {
    pub format: String,
    pub kind: String,
    pub session_id: String,
    pub sphere_radius_m: f64,
    /// Points used (with at least one valid reading), and raw readings in them.
    pub points: usize,
    pub readings: usize,
    /// Raw readings recorded without a value (out of range).
    pub readings_out_of_range: usize,
    pub postures_rad: Vec<[f64; 2]>,
    /// The LM estimate with its standard uncertainties (Cramér–Rao at the solution).
    pub parameters: Vec<ParameterResult>,
    /// The exterior-penalty objective of the reported (LM) parameters (M = penalty).
    pub objective: f64,
    pub residual_rms_m: f64,
    /// Null at 0 degrees of freedom.
    pub chi2_per_dof: Option<f64>,
    pub dof: usize,
    /// Parameters the postures cannot see (σ null): each takes part in a direction along which
    /// no reading changes. Their values are conditional on `held_at_nominal`.
    pub not_identifiable: Vec<String>,
    /// One free parameter per unseen direction, held at its nominal value during LM.
    pub held_at_nominal: Vec<String>,
    /// The unseen directions as combinations of the solver's free parameters.
    pub unseen_directions: Vec<String>,
    pub lm: LmSummary,
    pub ga: GaSummary,
    /// Sphere radius measured from all points with the nominal installation (before) and with
    /// the calibrated one (after LM, after GA).
    pub radius_before_m: f64,
    pub radius_after_m: f64,
    pub radius_after_ga_m: f64,
    pub note: String,
    /// Present when χ²/dof is improbable for its degrees of freedom (p < 1e-3): the σ are
    /// then not trustworthy; `sigma_scale` = √(χ²/dof) (docs/uncertainty.md, "Misfit").
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub misfit: Option<crate::solve::misfit::Misfit>,
    /// `geocal solve --effects`: the effects fitted jointly with the installation (effect →
    /// parameter → value, with `<parameter>.sigma`); the parameters, σ and χ² are then the
    /// joint fit's.
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub effects: std::collections::BTreeMap<String, std::collections::BTreeMap<String, f64>>,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct ParameterResult {
    pub name: String,
    pub value: f64,
    /// Null when the postures cannot see the parameter.
    pub sigma: Option<f64>,
    pub nominal: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct LmSummary {
    pub objective: f64,
    pub unit_norm_violation: f64,
    pub iterations: usize,
    pub converged: bool,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct GaSummary {
    pub objective: f64,
    pub unit_norm_violation: f64,
    pub population: usize,
    pub generations: usize,
    pub seed: u64,
    pub evaluations: usize,
    /// Individuals replaced for lying within the diversity threshold of the best.
    pub replaced: usize,
    /// The GA's parameters, in the order of `parameters`.
    pub values: Vec<f64>,
}

fn parse<T: serde::de::DeserializeOwned>(
    topic: &str,
    log_time_ns: u64,
    v: &serde_json::Value,
) -> Result<T, ProbeInstallMethodError> {
    T::deserialize(v).map_err(|e| ProbeInstallMethodError::Message {
        topic: topic.to_string(),
        log_time_ns,
        message: e.to_string(),
    })
}

/// One closed `probe_begin`..`probe_end` window: its posture, its observation (None when no
/// reading had a value) and its reading counts.
struct PointWindow {
    posture: usize,
    observation: Option<ProbeObservation>,
    valid: usize,
    out_of_range: usize,
    /// When its window began (log time).
    begin_ns: u64,
}

/// A point's observation with its posture and when it was probed (s since the session's
/// first probed point): what the diagnosis's labels and time-dependent effects need.
#[derive(Debug, Clone, Copy)]
pub struct TimedObservation {
    pub observation: ProbeObservation,
    pub posture: usize,
    pub t_s: f64,
}

/// The observations as `observations` gives them, each with its posture and time.
pub fn timed_observations(
    session: &Session,
    noise_m: f64,
    probe_id: &str,
) -> Result<Vec<TimedObservation>, ProbeInstallMethodError> {
    let windows = point_windows(session, noise_m, probe_id)?;
    let first = windows
        .iter()
        .filter(|w| w.observation.is_some())
        .map(|w| w.begin_ns)
        .min()
        .unwrap_or(0);
    Ok(windows
        .into_iter()
        .filter_map(|w| {
            w.observation.map(|observation| TimedObservation {
                observation,
                posture: w.posture,
                t_s: w.begin_ns.saturating_sub(first) as f64 * 1e-9,
            })
        })
        .collect())
}

/// The observations (one per point with a valid reading), the valid raw readings in them and
/// the out-of-range count. A posture a resumed run measures again (`posture_begin` repeated,
/// or left unfinished at a `resume` event) keeps only its last attempt, so every posture is
/// used once.
pub fn observations(
    session: &Session,
    noise_m: f64,
    probe_id: &str,
) -> Result<(Vec<ProbeObservation>, usize, usize), ProbeInstallMethodError> {
    let windows = point_windows(session, noise_m, probe_id)?;
    let raw = windows.iter().map(|w| w.valid).sum();
    let out_of_range = windows.iter().map(|w| w.out_of_range).sum();
    let out = windows.into_iter().filter_map(|w| w.observation).collect();
    Ok((out, raw, out_of_range))
}

fn point_windows(
    session: &Session,
    noise_m: f64,
    probe_id: &str,
) -> Result<Vec<PointWindow>, ProbeInstallMethodError> {
    let empty = Vec::new();
    let no_readings = Vec::new();
    let readings = session.probes.get(probe_id).unwrap_or(&no_readings);
    let poses = session.topics.get(TOPIC_MACHINE_POSE).unwrap_or(&empty);
    let mut posture: Option<(usize, f64, f64)> = None;
    let mut open: Option<(usize, usize, u64)> = None;
    let mut windows: Vec<PointWindow> = Vec::new();
    let set_aside = |windows: &mut Vec<PointWindow>, p: usize| windows.retain(|w| w.posture != p);
    for e in &session.events {
        match &e.msg {
            RunEvent::PostureBegin {
                posture: p,
                a_rad,
                b_rad,
            } => {
                set_aside(&mut windows, *p);
                posture = Some((*p, *a_rad, *b_rad));
            }
            RunEvent::PostureEnd { .. } => posture = None,
            // The interrupted attempt of an unfinished posture: measured again after this.
            RunEvent::Resume { .. } => {
                if let Some((p, _, _)) = posture.take() {
                    set_aside(&mut windows, p);
                }
                open = None;
            }
            RunEvent::ProbeBegin {
                posture: p, point, ..
            } => {
                if posture.is_none_or(|(q, _, _)| q != *p) {
                    // Its posture_begin was lost in a damaged chunk: the point is dropped.
                    if session.lost_between(0, e.log_time_ns) {
                        open = None;
                        continue;
                    }
                    return Err(ProbeInstallMethodError::OutsidePosture {
                        posture: *p,
                        point: *point,
                    });
                }
                open = Some((*p, *point, e.log_time_ns));
            }
            RunEvent::ProbeEnd { posture: p, point } => {
                let Some((op, opoint, begin_ns)) = open.take() else {
                    continue;
                };
                if (op, opoint) != (*p, *point) {
                    continue;
                }
                let end_ns = e.log_time_ns;
                if session.lost_between(begin_ns, end_ns) {
                    continue;
                }
                let mut values = Vec::new();
                let mut out_of_range = 0;
                for r in readings
                    .iter()
                    .filter(|r| r.log_time_ns >= begin_ns && r.log_time_ns <= end_ns)
                {
                    match r.msg.value_m {
                        Some(v) => values.push(v),
                        None => out_of_range += 1,
                    }
                }
                let observation = if values.is_empty() {
                    None
                } else {
                    let stamped = poses
                        .iter()
                        .rev()
                        .find(|m| m.log_time_ns <= begin_ns)
                        .ok_or(ProbeInstallMethodError::NoPosition {
                            posture: *p,
                            point: *point,
                        })?;
                    let pose: MachinePoseSample =
                        parse(TOPIC_MACHINE_POSE, stamped.log_time_ns, &stamped.msg)?;
                    let axis = |name: &str| {
                        pose.reported
                            .get(name)
                            .or_else(|| pose.commanded.get(name))
                            .copied()
                            .ok_or_else(|| ProbeInstallMethodError::MissingAxis {
                                posture: *p,
                                point: *point,
                                axis: name.to_string(),
                            })
                    };
                    let n = values.len() as f64;
                    Some(ProbeObservation {
                        a_rad: axis("a")?,
                        b_rad: axis("b")?,
                        machine_m: [axis("x")?, axis("y")?, axis("z")?],
                        reading_m: values.iter().sum::<f64>() / n,
                        sigma_m: noise_m / n.sqrt(),
                    })
                };
                windows.push(PointWindow {
                    posture: *p,
                    observation,
                    valid: values.len(),
                    out_of_range,
                    begin_ns,
                });
            }
            _ => {}
        }
    }
    Ok(windows)
}

/// What the solvers take from a session: its plan, the problem (nominal installation, the
/// calibrated radius, the observations), the valid raw readings and the out-of-range count.
pub fn problem(
    session: &Session,
) -> Result<(ProbeInstallPlan, ProbeInstallProblem, usize, usize), ProbeInstallMethodError> {
    let plan: ProbeInstallPlan = serde_json::from_value(session.header.plan.clone())
        .map_err(|e| ProbeInstallMethodError::Plan(e.to_string()))?;
    let probe = session
        .header
        .devices
        .iter()
        .find(|d| d.kind == "probe" && d.noise_m.is_some())
        .ok_or(ProbeInstallMethodError::NoProbe)?;
    let noise_m = probe.noise_m.ok_or(ProbeInstallMethodError::NoProbe)?;
    let (obs, readings, out_of_range) = observations(session, noise_m, &probe.id)?;
    let problem = ProbeInstallProblem {
        nominal: plan.nominal.params(),
        sphere_radius_m: plan.sphere_radius_m,
        observations: obs,
    };
    Ok((plan, problem, readings, out_of_range))
}

pub fn solve(session: &Session) -> Result<ProbeInstallResults, ProbeInstallMethodError> {
    let (plan, problem, readings, out_of_range) = problem(session)?;
    let nominal = problem.nominal;
    // Identifiability is judged on the plan's postures (the commanded ones), not on the
    // encoders' scatter around them.
    let design = ProbeInstallProblem {
        observations: problem
            .observations
            .iter()
            .map(|o| {
                let mut d = *o;
                if let Some(p) = plan.postures_rad.iter().min_by(|p, q| {
                    let dist = |p: &&[f64; 2]| (p[0] - o.a_rad).hypot(p[1] - o.b_rad);
                    dist(p).total_cmp(&dist(q))
                }) {
                    if (p[0] - o.a_rad).hypot(p[1] - o.b_rad) < POSTURE_SNAP_RAD {
                        d.a_rad = p[0];
                        d.b_rad = p[1];
                    }
                }
                d
            })
            .collect(),
        ..problem.clone()
    };
    let lm = solve_lm_with_design(&problem, &nominal, &LmOptions::default(), &design)?;
    let s = &plan.solver;
    let ga = solve_ga(
        &problem,
        &SearchBox::default(),
        s.penalty,
        &GeneticOptions {
            population: s.ga_population,
            generations: s.ga_generations,
            crossover_probability: s.ga_crossover,
            mutation_probability: s.ga_mutation,
            seed: s.ga_seed,
            ..GeneticOptions::default()
        },
    )?;
    let lm_objective =
        crate::solve::probe_install::penalty_objective(&problem, &lm.params, s.penalty);
    let values = lm.params.to_vector();
    let nominal_values = nominal.to_vector();
    let parameters = (0..N_PARAMS)
        .map(|k| ParameterResult {
            name: PARAM_NAMES[k].to_string(),
            value: values[k],
            sigma: lm.identifiable[k].then_some(lm.sigma[k]),
            nominal: nominal_values[k],
        })
        .collect();
    Ok(ProbeInstallResults {
        format: "geocal-results/1".into(),
        kind: KIND.into(),
        session_id: session.header.session_id.clone(),
        sphere_radius_m: plan.sphere_radius_m,
        points: problem.observations.len(),
        readings,
        readings_out_of_range: out_of_range,
        postures_rad: plan.postures_rad.clone(),
        parameters,
        objective: lm_objective,
        residual_rms_m: lm.residual_rms_m,
        chi2_per_dof: (lm.dof > 0).then(|| lm.chi2 / lm.dof as f64),
        dof: lm.dof,
        misfit: crate::solve::misfit::Misfit::check(lm.chi2, lm.dof),
        effects: Default::default(),
        not_identifiable: (0..N_PARAMS)
            .filter(|&k| !lm.identifiable[k])
            .map(|k| PARAM_NAMES[k].to_string())
            .collect(),
        held_at_nominal: lm.held_at_start.iter().map(|s| s.to_string()).collect(),
        unseen_directions: lm.unseen_directions.clone(),
        lm: LmSummary {
            objective: lm_objective,
            unit_norm_violation: lm.unit_norm_violation,
            iterations: lm.iterations,
            converged: lm.converged,
        },
        ga: GaSummary {
            objective: ga.objective,
            unit_norm_violation: ga.unit_norm_violation,
            population: s.ga_population,
            generations: s.ga_generations,
            seed: s.ga_seed,
            evaluations: ga.evaluations,
            replaced: ga.replaced,
            values: ga.params.to_vector().iter().copied().collect(),
        },
        radius_before_m: measured_radius_m(&nominal, &problem.observations)?,
        radius_after_m: measured_radius_m(&lm.params, &problem.observations)?,
        radius_after_ga_m: measured_radius_m(&ga.params, &problem.observations)?,
        note: "parameters from LM on the constrained problem (beam as two angles, |(l,m,n)| = 1 \
               exactly), sigmas from the Cramér-Rao covariance at the solution (the beam's is \
               rank 2 on the unit sphere); the GA minimises the exterior-penalty objective over \
               nominal ± SearchBox; radii from one sphere fitted through all points"
            .into(),
    })
}

/// The residual model of a session (docs/diagnosis.md, "probe_install"), started at its
/// solve's installation.
pub fn residual_model(
    session: &Session,
    solved: &ProbeInstallResults,
) -> anyhow::Result<super::diagnosis::ProbeResidualModel> {
    let values: Vec<f64> = solved.parameters.iter().map(|p| p.value).collect();
    let params =
        crate::model::probe_install::InstallParams::from_vector(
            &nalgebra::SVector::<f64, N_PARAMS>::from_column_slice(&values),
        );
    super::diagnosis::ProbeResidualModel::new(session, &params, solved.sphere_radius_m)
}

/// `geocal solve --effects NAMES`: the solve, then the installation and the named effects of
/// the probe's library fitted jointly: parameters, σ (the beam's mapped from its two angles)
/// and χ² of the joint fit. A parameter the postures cannot see keeps σ null.
pub fn solve_with_effects(
    session: &Session,
    names: &[String],
) -> anyhow::Result<ProbeInstallResults> {
    use crate::method::diagnosis::{effect_parameters, effects_named, joint_fit, ResidualModel};
    let mut results = solve(session)?;
    let model = residual_model(session, &results)?;
    let library = model.effects();
    let effects = effects_named(&library, names).map_err(anyhow::Error::msg)?;
    let fit = joint_fit(&model, &effects, &model.start());
    let installed = model.params(&fit.params).to_vector();
    let beam_jac = model.beam_jacobian(&fit.params);
    let chart_cov = nalgebra::Matrix2::from_fn(|i, j| fit.covariance[(2 + i, 2 + j)]);
    let beam_cov = beam_jac * chart_cov * beam_jac.transpose();
    // Model parameter of each of the 11 (None: a beam component, from the chart).
    let index = [
        Some(0),
        Some(1),
        None,
        None,
        None,
        Some(4),
        Some(5),
        Some(6),
        Some(7),
        Some(8),
        Some(9),
    ];
    for (k, p) in results.parameters.iter_mut().enumerate() {
        p.value = installed[k];
        let sigma = match index[k] {
            Some(j) => fit.sigma(j),
            None => beam_cov[(k - 2, k - 2)].max(0.0).sqrt(),
        };
        p.sigma = p.sigma.map(|_| sigma);
    }
    results.dof = fit.dof;
    results.chi2_per_dof = (fit.dof > 0).then(|| fit.chi2 / fit.dof as f64);
    results.misfit = crate::solve::misfit::Misfit::check(fit.chi2, fit.dof);
    results.effects = effect_parameters(&effects, &fit, fit.params.len());
    results.note.push_str(&format!(
        "; with --effects {}: parameters, sigmas and chi2_per_dof from the joint fit of the \
         installation and the effects (the residual model of docs/diagnosis.md)",
        crate::method::diagnosis::effect_names(&effects)
    ));
    Ok(results)
}
