//! Rotary axis from a reference sphere (plan kind `rotary_sphere`): probed points from the
//! session's events and raw probe readings -> sphere centres -> axis errors -> results.

use std::collections::btree_map::Entry;
use std::collections::BTreeMap;

use nalgebra::Vector3;
use serde::Serialize;

use crate::kinds::rotary_sphere::config::{HeightRole, SpherePlanConfig, KIND};
use crate::kinds::rotary_sphere::plan::SpherePlan;
use crate::method::multilateration::RESULTS_FORMAT;
use crate::model::rotary_sphere::{LOCATION_NAMES, MOTION_NAMES};
use crate::session::messages::RunEvent;
use crate::session::reader::Session;
use crate::solve::rotary_sphere::{
    fit_sphere, identify_rotary_axis, validate, CentreSeries, HarmonicFit, HarmonicOrder,
    IdentifyOptions, RotaryAxisIdentification, RotarySphereError, SphereFit, TangentialConvention,
};

/// The tolerance of the published prediction check (~80 % of residuals within 10 µm).
pub const PUBLISHED_TOLERANCE_M: f64 = 10e-6;

#[derive(Debug, thiserror::Error)]
pub enum RotarySphereMethodError {
    #[error("session header: `plan` is not a rotary_sphere plan: {0}")]
    Plan(String),
    #[error(
        "session header: no device of kind `probe` with `noise_m` > 0 (the probe's repeatability)"
    )]
    NoProbeNoise,
    #[error("no readings on /probe/{0}/reading")]
    NoReadings(String),
    #[error("`{kind}` event at log_time {log_time_ns} ns names height {height_index}, angle {angle_index} or point {point}, outside the plan")]
    OutsidePlan {
        kind: &'static str,
        log_time_ns: u64,
        height_index: usize,
        angle_index: usize,
        point: usize,
    },
    #[error("fit heights share {0} completely probed angles; the identification needs at least 3")]
    TooFewAngles(usize),
    #[error("sphere at height {height_index}, angle {angle_index}: {source}")]
    Sphere {
        height_index: usize,
        angle_index: usize,
        source: RotarySphereError,
    },
    #[error("axis identification: {0}")]
    Identify(RotarySphereError),
    #[error("validation at height {height_index}: {source}")]
    Validation {
        height_index: usize,
        source: RotarySphereError,
    },
}

#[derive(Debug, Clone, Serialize)]
pub struct RotarySphereResults {
    pub format: String,
    pub kind: String,
    pub session_id: String,
    pub table: String,
    pub sphere_radius_m: f64,
    /// The probe's repeatability per reading (the noise model of every uncertainty here).
    pub probe_noise_m: f64,
    pub spheres: Vec<SphereResult>,
    /// EXOC, EYOC (m), EAOC, EBOC (rad) with standard uncertainties.
    pub location: Vec<NamedValue>,
    pub location_covariance: [[f64; 4]; 4],
    /// How the tangential combination t + r·ECC is split (one sphere radius cannot split it).
    pub convention: TangentialConvention,
    pub reference_radius_m: f64,
    /// The sphere's nominal azimuth φ at θ = 0 (the plan's fit heights): at angle θ, EXC and
    /// EYC are the radial translation written along (cos(θ + φ), sin(θ + φ)).
    pub radial_azimuth_rad: f64,
    pub motion_names: [&'static str; 6],
    pub motion: Vec<MotionAtAngle>,
    /// Per motion error, its harmonic model value(θ) = c0 + Σ a_k cos kθ + b_k sin kθ.
    pub harmonics: Vec<HarmonicFit>,
    /// χ² of the per-angle motion model and its degrees of freedom (> 0 with > 2 fit heights).
    pub chi2: f64,
    pub dof: usize,
    pub validation: Vec<ValidationResult>,
    pub notes: Vec<String>,
    /// Present when χ²/dof is improbable for its degrees of freedom (p < 1e-3): the σ are
    /// then not trustworthy; `sigma_scale` = √(χ²/dof) (docs/uncertainty.md, "Misfit").
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub misfit: Option<crate::solve::misfit::Misfit>,
    /// `geocal solve --effects`: the effects fitted jointly with the sphere centres (effect
    /// → parameter → value, with `<parameter>.sigma`); every reading is then corrected by
    /// their fitted contribution before the centres and the axis are solved.
    #[serde(skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub effects: BTreeMap<String, BTreeMap<String, f64>>,
}

#[derive(Debug, Clone, Serialize)]
pub struct NamedValue {
    pub name: &'static str,
    pub value: f64,
    pub sigma: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct SphereResult {
    pub height_index: usize,
    pub role: HeightRole,
    pub angle_index: usize,
    pub commanded_rad: f64,
    pub centre_m: [f64; 3],
    pub centre_sigma_m: [f64; 3],
    pub centre_covariance_m2: [[f64; 3]; 3],
    /// Probed points used and the RMS distance of their points from the fitted sphere.
    pub points: usize,
    pub readings: usize,
    pub residual_rms_m: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct MotionAtAngle {
    pub angle_index: usize,
    pub commanded_rad: f64,
    /// EXC, EYC, EZC (m), EAC, EBC, ECC (rad) and their standard uncertainties.
    pub errors: [f64; 6],
    pub sigma: [f64; 6],
    /// The convention-free tangential combination t + r·ECC, metres.
    pub tangential_m: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct ValidationResult {
    pub height_index: usize,
    pub sphere_position_m: [f64; 3],
    pub angles_rad: Vec<f64>,
    /// measured − predicted centre, and the predicted σ of each coordinate.
    pub residuals_m: Vec<[f64; 3]>,
    pub residual_sigma_m: Vec<[f64; 3]>,
    /// Share of 3-D residual lengths and of single coordinates within 10 µm (the published
    /// check: ~80 %), and of coordinates within 3 predicted σ.
    pub share_norm_within_10um: f64,
    pub share_coordinates_within_10um: f64,
    pub share_within_3_sigma: f64,
    pub chi2: f64,
    pub count: usize,
}

/// A probed point's window in the session: its nominal surface point, direction, the times of
/// its events and the sum of the readings inside.
#[derive(Debug, Clone)]
struct PointWindow {
    nominal_m: Vector3<f64>,
    direction: Vector3<f64>,
    begin_ns: u64,
    end_ns: Option<u64>,
    sum_m: f64,
    readings: usize,
}

/// The spheres of the session: (height, angle) -> (commanded angle, points by index).
type Spheres = BTreeMap<(usize, usize), (f64, BTreeMap<usize, PointWindow>)>;

fn collect_points(
    session: &Session,
    plan: &SpherePlan,
) -> Result<Spheres, RotarySphereMethodError> {
    let mut spheres: Spheres = BTreeMap::new();
    let outside = |kind, log_time_ns, height_index, angle_index, point| {
        RotarySphereMethodError::OutsidePlan {
            kind,
            log_time_ns,
            height_index,
            angle_index,
            point,
        }
    };
    let (nh, na, np) = (
        plan.heights.len(),
        plan.angles_rad.len(),
        plan.directions.len(),
    );
    for e in &session.events {
        match &e.msg {
            RunEvent::SphereBegin {
                height_index: h,
                angle_index: a,
                commanded_rad,
            } => {
                if *h >= nh || *a >= na {
                    return Err(outside("sphere_begin", e.log_time_ns, *h, *a, 0));
                }
                // A repeated sphere (a resumed run) replaces the earlier one.
                spheres.insert((*h, *a), (*commanded_rad, BTreeMap::new()));
            }
            RunEvent::ProbePointBegin {
                height_index: h,
                angle_index: a,
                point,
                nominal_m,
                direction,
            } => {
                if *h >= nh || *a >= na || *point >= np {
                    return Err(outside("probe_point_begin", e.log_time_ns, *h, *a, *point));
                }
                let sphere = match spheres.entry((*h, *a)) {
                    Entry::Occupied(sphere) => sphere.into_mut(),
                    // Its sphere_begin was lost in a damaged chunk: the plan has the angle.
                    Entry::Vacant(v) if session.lost_between(0, e.log_time_ns) => {
                        v.insert((plan.angles_rad[*a], BTreeMap::new()))
                    }
                    Entry::Vacant(_) => {
                        return Err(outside("probe_point_begin", e.log_time_ns, *h, *a, *point))
                    }
                };
                sphere.1.insert(
                    *point,
                    PointWindow {
                        nominal_m: Vector3::from(*nominal_m),
                        direction: Vector3::from(*direction).normalize(),
                        begin_ns: e.log_time_ns,
                        end_ns: None,
                        sum_m: 0.0,
                        readings: 0,
                    },
                );
            }
            RunEvent::ProbePointEnd {
                height_index: h,
                angle_index: a,
                point,
            } => {
                let Some(p) = spheres.get_mut(&(*h, *a)).and_then(|s| s.1.get_mut(point)) else {
                    if *point < np && session.lost_between(0, e.log_time_ns) {
                        continue;
                    }
                    return Err(outside("probe_point_end", e.log_time_ns, *h, *a, *point));
                };
                // A window that may have lost readings in a damaged chunk stays unused.
                if !session.lost_between(p.begin_ns, e.log_time_ns) {
                    p.end_ns = Some(e.log_time_ns);
                }
            }
            _ => {}
        }
    }
    Ok(spheres)
}

/// Attribute every reading to the point whose window (begin, end] holds its log time.
fn attach_readings(spheres: &mut Spheres, readings: &[(u64, f64)]) {
    let mut windows: Vec<&mut PointWindow> = spheres
        .values_mut()
        .flat_map(|s| s.1.values_mut())
        .filter(|p| p.end_ns.is_some())
        .collect();
    windows.sort_by_key(|p| p.begin_ns);
    let mut w = 0;
    for &(t, v) in readings {
        while w < windows.len() && windows[w].end_ns.is_some_and(|end| end < t) {
            w += 1;
        }
        if let Some(p) = windows.get_mut(w) {
            if p.begin_ns < t {
                p.sum_m += v;
                p.readings += 1;
            }
        }
    }
}

fn sqrt_diag(c: &[[f64; 3]; 3]) -> [f64; 3] {
    std::array::from_fn(|k| c[k][k].max(0.0).sqrt())
}

/// One probed point with readings: its nominal surface point, outward probing direction, the
/// mean of its readings and how many there were.
#[derive(Debug, Clone)]
pub struct ProbedPoint {
    pub nominal_m: Vector3<f64>,
    pub direction: Vector3<f64>,
    pub mean_m: f64,
    pub readings: usize,
}

/// One probed sphere: its height, commanded angle and the points that got readings.
#[derive(Debug, Clone)]
pub struct ProbedSphere {
    pub height_index: usize,
    pub angle_index: usize,
    pub commanded_rad: f64,
    pub points: Vec<ProbedPoint>,
}

/// What a session holds for the solver: the plan, the probe's noise per reading and the
/// probed spheres.
pub fn probed(
    session: &Session,
) -> Result<(SpherePlanConfig, f64, Vec<ProbedSphere>), RotarySphereMethodError> {
    probed_with_times(session).map(|(plan, noise, spheres, _)| (plan, noise, spheres))
}

/// Per probed sphere, per point with readings: its index in the plan's directions and when
/// its window began (s since the first point's).
pub type PointTimes = Vec<Vec<(usize, f64)>>;

/// `probed`, with each point's direction index and time (what the diagnosis needs).
pub fn probed_with_times(
    session: &Session,
) -> Result<(SpherePlanConfig, f64, Vec<ProbedSphere>, PointTimes), RotarySphereMethodError> {
    let plan_config: SpherePlanConfig = serde_json::from_value(session.header.plan.clone())
        .map_err(|e| RotarySphereMethodError::Plan(e.to_string()))?;
    let plan = SpherePlan::from_config(&plan_config);
    let probe = session
        .header
        .devices
        .iter()
        .find(|d| d.kind == "probe")
        .filter(|d| d.noise_m.is_some_and(|n| n > 0.0))
        .ok_or(RotarySphereMethodError::NoProbeNoise)?;
    let noise_m = probe.noise_m.unwrap_or_default();
    let readings: Vec<(u64, f64)> = session
        .probes
        .get(&probe.id)
        .map(|v| {
            v.iter()
                .filter_map(|s| Some((s.log_time_ns, s.msg.value_m?)))
                .collect()
        })
        .unwrap_or_default();
    if readings.is_empty() {
        return Err(RotarySphereMethodError::NoReadings(probe.id.clone()));
    }
    let mut spheres = collect_points(session, &plan)?;
    attach_readings(&mut spheres, &readings);
    let first_ns = spheres
        .values()
        .flat_map(|s| s.1.values())
        .filter(|p| p.readings > 0)
        .map(|p| p.begin_ns)
        .min()
        .unwrap_or(0);
    let times: PointTimes = spheres
        .values()
        .map(|(_, points)| {
            points
                .iter()
                .filter(|(_, p)| p.readings > 0)
                .map(|(k, p)| (*k, p.begin_ns.saturating_sub(first_ns) as f64 * 1e-9))
                .collect()
        })
        .collect();
    let probed = spheres
        .into_iter()
        .map(|((h, a), (commanded_rad, points))| ProbedSphere {
            height_index: h,
            angle_index: a,
            commanded_rad,
            points: points
                .into_values()
                .filter(|p| p.readings > 0)
                .map(|p| ProbedPoint {
                    nominal_m: p.nominal_m,
                    direction: p.direction,
                    mean_m: p.sum_m / p.readings as f64,
                    readings: p.readings,
                })
                .collect(),
        })
        .collect();
    Ok((plan_config, noise_m, probed, times))
}

/// The sphere's nominal azimuth at θ = 0: that of the mean of the fit heights' nominal
/// positions (the direction EXC, EYC are written along, turned by each angle).
pub fn nominal_azimuth_rad(plan: &SpherePlanConfig) -> f64 {
    let (x, y) = plan
        .heights
        .iter()
        .filter(|h| h.role == HeightRole::Fit)
        .fold((0.0, 0.0), |(x, y), h| {
            (x + h.sphere_m[0], y + h.sphere_m[1])
        });
    y.atan2(x)
}

/// The sphere fits by (height, angle): commanded angle, fit, readings used.
pub type Fits = BTreeMap<(usize, usize), (f64, SphereFit, usize)>;

/// Centres and axis of probed spheres: the fits, how many spheres lacked points, the angles
/// probed at every fit height and the identification from them.
pub struct Identified {
    pub fits: Fits,
    pub incomplete: usize,
    pub common: Vec<usize>,
    pub identification: RotaryAxisIdentification,
}

/// Sphere centres with the known radius (σ of a point = σ_reading / √(its readings)), then
/// the axis from the angles probed at every fit height.
pub fn identify(
    plan_config: &SpherePlanConfig,
    noise_m: f64,
    probed: &[ProbedSphere],
) -> Result<Identified, RotarySphereMethodError> {
    identify_with(plan_config, noise_m, probed, &BTreeMap::new())
}

/// Centre covariances by (height, angle) that replace the sphere fits' own (the centres fitted
/// jointly with effects carry the effects' uncertainty too).
pub type CentreCovariances = BTreeMap<(usize, usize), [[f64; 3]; 3]>;

/// `identify`, with the centres' covariances taken from `covariances` where it has them.
fn identify_with(
    plan_config: &SpherePlanConfig,
    noise_m: f64,
    probed: &[ProbedSphere],
    covariances: &CentreCovariances,
) -> Result<Identified, RotarySphereMethodError> {
    let plan = SpherePlan::from_config(plan_config);
    let mut fits: Fits = BTreeMap::new();
    let mut incomplete = 0;
    for sphere in probed {
        let (h, a) = (sphere.height_index, sphere.angle_index);
        let used = &sphere.points;
        if used.len() < plan.directions.len() {
            incomplete += 1;
        }
        if used.len() < 4 {
            continue;
        }
        let fewest = used.iter().map(|p| p.readings).min().unwrap_or(1);
        let pts: Vec<Vector3<f64>> = used
            .iter()
            .map(|p| SpherePlan::measured_point(&p.nominal_m, &p.direction, p.mean_m))
            .collect();
        let fit = match fit_sphere(
            &pts,
            Some(plan.radius_m),
            Some(noise_m / (fewest as f64).sqrt()),
        ) {
            Ok(fit) => fit,
            // The points left of an incomplete sphere may not determine it (e.g. all on the
            // equator): it is left out like one with fewer than 4.
            Err(_) if used.len() < plan.directions.len() => continue,
            Err(source) => {
                return Err(RotarySphereMethodError::Sphere {
                    height_index: h,
                    angle_index: a,
                    source,
                })
            }
        };
        let mut fit = fit;
        if let Some(c) = covariances.get(&(h, a)) {
            fit.centre_covariance_m2 = *c;
        }
        let n_readings = used.iter().map(|p| p.readings).sum();
        fits.insert((h, a), (sphere.commanded_rad, fit, n_readings));
    }

    // Angles probed at every fit height.
    let fit_heights: Vec<usize> = (0..plan.heights.len())
        .filter(|&h| plan.heights[h].role == HeightRole::Fit)
        .collect();
    let common: Vec<usize> = (0..plan.angles_rad.len())
        .filter(|&a| fit_heights.iter().all(|&h| fits.contains_key(&(h, a))))
        .collect();
    if common.len() < 3 {
        return Err(RotarySphereMethodError::TooFewAngles(common.len()));
    }
    let series: Vec<CentreSeries> = fit_heights
        .iter()
        .map(|&h| series_of(&fits, h, &common))
        .collect();
    let max_order = plan_config.max_harmonic_order.min((common.len() - 1) / 2);
    let identification = identify_rotary_axis(
        &series,
        &IdentifyOptions {
            convention: TangentialConvention::AngularPositioning,
            harmonics: HarmonicOrder::Bic { max_order },
            radial_azimuth_rad: Some(nominal_azimuth_rad(plan_config)),
        },
    )
    .map_err(RotarySphereMethodError::Identify)?;
    Ok(Identified {
        fits,
        incomplete,
        common,
        identification,
    })
}

/// The centres at height `h` at the given angles (those fitted).
fn series_of(fits: &Fits, h: usize, angles: &[usize]) -> CentreSeries {
    let list: Vec<(f64, SphereFit)> = angles
        .iter()
        .filter_map(|a| fits.get(&(h, *a)).map(|(c, f, _)| (*c, f.clone())))
        .collect();
    let (ang, f): (Vec<f64>, Vec<SphereFit>) = list.into_iter().unzip();
    CentreSeries::from_fits(ang, &f)
}

/// Solve a rotary_sphere session.
pub fn solve(session: &Session) -> Result<RotarySphereResults, RotarySphereMethodError> {
    let (plan_config, noise_m, probed) = probed(session)?;
    solve_probed(session, plan_config, noise_m, probed, &BTreeMap::new())
}

/// Solve the probed spheres of a session (their readings as the session holds them, or
/// corrected by fitted effects).
fn solve_probed(
    session: &Session,
    plan_config: SpherePlanConfig,
    noise_m: f64,
    probed: Vec<ProbedSphere>,
    covariances: &CentreCovariances,
) -> Result<RotarySphereResults, RotarySphereMethodError> {
    let plan = SpherePlan::from_config(&plan_config);
    let Identified {
        fits,
        incomplete,
        common,
        identification: id,
    } = identify_with(&plan_config, noise_m, &probed, covariances)?;
    let mut notes = Vec::new();
    if incomplete > 0 {
        notes.push(format!(
            "{incomplete} sphere(s) lack some probed points; spheres with fewer than 4, or whose \
             points left do not determine them, are left out"
        ));
    }
    if common.len() < plan.angles_rad.len() {
        notes.push(format!(
            "{} of {} commanded angles were probed at every fit height; the others are left out",
            common.len(),
            plan.angles_rad.len()
        ));
    }
    let points_of = |h: usize, a: usize| {
        probed
            .iter()
            .find(|s| (s.height_index, s.angle_index) == (h, a))
            .map_or(0, |s| s.points.len())
    };
    let mut validation = Vec::new();
    for h in (0..plan.heights.len()).filter(|&h| plan.heights[h].role == HeightRole::Validation) {
        let angles: Vec<usize> = (0..plan.angles_rad.len())
            .filter(|a| fits.contains_key(&(h, *a)))
            .collect();
        if angles.is_empty() {
            notes.push(format!("validation height {h} has no probed sphere"));
            continue;
        }
        let s = series_of(&fits, h, &angles);
        let v = validate(&id, &s).map_err(|source| RotarySphereMethodError::Validation {
            height_index: h,
            source,
        })?;
        validation.push(ValidationResult {
            height_index: h,
            sphere_position_m: v.sphere_position_m,
            angles_rad: s.angles_rad.clone(),
            share_norm_within_10um: v.share_norm_within(PUBLISHED_TOLERANCE_M),
            share_coordinates_within_10um: v.share_coordinates_within(PUBLISHED_TOLERANCE_M),
            share_within_3_sigma: v.share_within_sigmas(3.0),
            residuals_m: v.residuals_m,
            residual_sigma_m: v.residual_sigma_m,
            chi2: v.chi2,
            count: v.count,
        });
    }

    let spheres_out = fits
        .iter()
        .map(|(&(h, a), (commanded_rad, fit, readings))| SphereResult {
            height_index: h,
            role: plan.heights[h].role,
            angle_index: a,
            commanded_rad: *commanded_rad,
            centre_m: fit.centre_m,
            centre_sigma_m: sqrt_diag(&fit.centre_covariance_m2),
            centre_covariance_m2: fit.centre_covariance_m2,
            points: points_of(h, a),
            readings: *readings,
            residual_rms_m: fit.residual_rms_m,
        })
        .collect();
    let motion = common
        .iter()
        .enumerate()
        .map(|(i, &a)| MotionAtAngle {
            angle_index: a,
            commanded_rad: id.angles_rad[i],
            errors: id.motion[i],
            sigma: id.motion_sigma[i],
            tangential_m: id.tangential_m[i],
        })
        .collect();
    notes.push(
        "location errors: the least-squares axis through every centre at the fit heights \
         (motion errors zero); motion errors: what is left per angle, so they carry no part a \
         fixed axis explains; ECC carries the tangential deviation (t + r·ECC cannot be split \
         with one sphere radius); uncertainties propagated from the probe's repeatability"
            .into(),
    );
    Ok(RotarySphereResults {
        format: RESULTS_FORMAT.into(),
        kind: KIND.into(),
        session_id: session.header.session_id.clone(),
        table: plan.table.clone(),
        sphere_radius_m: plan.radius_m,
        probe_noise_m: noise_m,
        spheres: spheres_out,
        location: (0..4)
            .map(|k| NamedValue {
                name: LOCATION_NAMES[k],
                value: id.location[k],
                sigma: id.location_sigma[k],
            })
            .collect(),
        location_covariance: id.location_covariance,
        convention: id.convention,
        reference_radius_m: id.reference_radius_m,
        radial_azimuth_rad: id.radial_azimuth_rad,
        motion_names: MOTION_NAMES,
        motion,
        harmonics: id.harmonics,
        chi2: id.chi2,
        dof: id.dof,
        misfit: crate::solve::misfit::Misfit::check(id.chi2, id.dof),
        validation,
        notes,
        effects: BTreeMap::new(),
    })
}

/// `geocal solve --effects NAMES`: the named effects of the sphere's library fitted jointly
/// with every sphere centre (docs/diagnosis.md, "rotary_sphere"), each reading corrected by
/// their fitted contribution, then the solve on the corrected readings.
pub fn solve_with_effects(
    session: &Session,
    names: &[String],
) -> anyhow::Result<RotarySphereResults> {
    use crate::method::diagnosis::{effect_parameters, effects_named, joint_fit, ResidualModel};
    let model = super::diagnosis::SphereResidualModel::new(session)?;
    let library = model.effects();
    let effects = effects_named(&library, names).map_err(anyhow::Error::msg)?;
    let fit = joint_fit(&model, &effects, &model.start());
    let correction: BTreeMap<((usize, usize), usize), f64> = model
        .point_keys()
        .into_iter()
        .zip(fit.effect_contribution.iter().copied())
        .collect();
    let (plan_config, noise_m, mut spheres, times) = probed_with_times(session)?;
    for (sphere, point_times) in spheres.iter_mut().zip(&times) {
        let key = (sphere.height_index, sphere.angle_index);
        for (p, (k, _)) in sphere.points.iter_mut().zip(point_times) {
            if let Some(c) = correction.get(&(key, *k)) {
                p.mean_m -= c;
            }
        }
    }
    // Each centre's covariance from the joint fit: the effects' uncertainty is in it (the
    // correlation it gives between spheres is not carried into the axis fit).
    let covariances: CentreCovariances = model
        .sphere_keys()
        .iter()
        .enumerate()
        .map(|(s, key)| {
            let c = std::array::from_fn(|r| {
                std::array::from_fn(|k| fit.covariance[(3 * s + r, 3 * s + k)])
            });
            (*key, c)
        })
        .collect();
    let mut results = solve_probed(session, plan_config, noise_m, spheres, &covariances)?;
    results.effects = effect_parameters(&effects, &fit, fit.params.len());
    results.notes.push(format!(
        "with --effects {}: each reading corrected by the effects' contribution fitted jointly \
         with the sphere centres (the residual model of docs/diagnosis.md), then solved",
        crate::method::diagnosis::effect_names(&effects)
    ));
    Ok(results)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn point(begin_ns: u64, end_ns: Option<u64>) -> PointWindow {
        PointWindow {
            nominal_m: Vector3::zeros(),
            direction: Vector3::z(),
            begin_ns,
            end_ns,
            sum_m: 0.0,
            readings: 0,
        }
    }

    /// A reading belongs to the window (begin, end]: one at the instant a point ends and the
    /// next begins is the ending point's; readings outside every window count for none.
    #[test]
    fn readings_go_to_their_window() {
        let mut spheres: Spheres = BTreeMap::new();
        spheres.insert(
            (0, 0),
            (
                0.0,
                BTreeMap::from([
                    (0, point(10, Some(20))),
                    (1, point(20, Some(30))),
                    (2, point(30, None)),
                ]),
            ),
        );
        attach_readings(
            &mut spheres,
            &[
                (5, 9.0),
                (10, 9.0),
                (15, 1.0),
                (20, 2.0),
                (25, 3.0),
                (26, 5.0),
                (35, 9.0),
            ],
        );
        let p = &spheres[&(0, 0)].1;
        assert_eq!((p[&0].readings, p[&0].sum_m), (2, 3.0));
        assert_eq!((p[&1].readings, p[&1].sum_m), (2, 8.0));
        // An unfinished point (the run stopped) gets nothing.
        assert_eq!(p[&2].readings, 0);
    }
}
