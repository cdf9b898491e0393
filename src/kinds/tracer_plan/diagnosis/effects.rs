//! The effect library: for each unmodelled effect, a parametric model that adds to the nominal
//! predicted lengths, as Jacobian columns in its own parameters evaluated at the fitted geometry.

use std::sync::Arc;

use nalgebra::{DMatrix, DVector, Vector3};

use super::data::{Data, Obs};
use crate::diagnose::columns::{Columns, RowSparse};
use crate::method::tracer_effects::{BeamObservation, LengthEffect, TracerNetworkDiagnosis};
use crate::solve::multilateration::MultilaterationSolution;

/// The fitted geometry the columns are evaluated at.
#[derive(Debug, Clone)]
pub struct Geometry {
    pub points: Vec<Vector3<f64>>,
    pub stations: Vec<Vector3<f64>>,
    pub distances_m: Vec<f64>,
}

impl Geometry {
    pub fn from_solution(s: &MultilaterationSolution) -> Geometry {
        Geometry {
            points: s.points.clone(),
            stations: s.stations.clone(),
            distances_m: s.segment_distance_m.clone(),
        }
    }

    /// Unit vector from the target point to the station (a station shift δP changes the
    /// length by u·δP, a target shift δX by −u·δX) and the distance.
    pub fn beam(&self, data: &Data, i: usize) -> (Vector3<f64>, f64) {
        self.beam_of(&data.obs[i])
    }

    /// [`Geometry::beam`] of one observation.
    pub fn beam_of(&self, o: &Obs) -> (Vector3<f64>, f64) {
        self.beam_between(o.station, o.point)
    }

    /// The unit vector from `point` to `station` and their distance.
    pub fn beam_between(&self, station: usize, point: usize) -> (Vector3<f64>, f64) {
        let v = self.stations[station] - self.points[point];
        let d = v.norm();
        (v / d, d)
    }

    pub fn predicted_m(&self, data: &Data, i: usize) -> f64 {
        self.beam(data, i).1 - self.distances_m[data.obs[i].segment]
    }

    /// Number of nominal parameters: 3 per point, 3 per station, 1 per segment.
    pub fn len(&self) -> usize {
        3 * self.points.len() + 3 * self.stations.len() + self.distances_m.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Dense Jacobian of the predicted lengths (rows: observations).
    pub fn jacobian(&self, data: &Data) -> DMatrix<f64> {
        let point_of: Vec<usize> = data.obs.iter().map(|o| o.point).collect();
        self.jacobian_of(data, &point_of)
    }

    /// As [`Geometry::jacobian`], observation i measuring point `point_of[i]` of this
    /// geometry (e.g. one point per pass).
    pub fn jacobian_of(&self, data: &Data, point_of: &[usize]) -> DMatrix<f64> {
        let (n, m) = (self.points.len(), self.stations.len());
        let mut j = DMatrix::zeros(data.obs.len(), self.len());
        for (i, o) in data.obs.iter().enumerate() {
            let v = self.stations[o.station] - self.points[point_of[i]];
            let u = v / v.norm();
            for a in 0..3 {
                j[(i, 3 * point_of[i] + a)] = -u[a];
                j[(i, 3 * n + 3 * o.station + a)] = u[a];
            }
            j[(i, 3 * n + 3 * m + o.segment)] = -1.0;
        }
        j
    }

    /// Apply a step in the parameter order of `jacobian`.
    pub fn apply(&mut self, step: &[f64]) {
        let (n, m) = (self.points.len(), self.stations.len());
        for (i, p) in self.points.iter_mut().enumerate() {
            for a in 0..3 {
                p[a] += step[3 * i + a];
            }
        }
        for (j, p) in self.stations.iter_mut().enumerate() {
            for a in 0..3 {
                p[a] += step[3 * n + 3 * j + a];
            }
        }
        for (s, d) in self.distances_m.iter_mut().enumerate() {
            *d += step[3 * n + 3 * m + s];
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum EffectKind {
    StationDrift,
    Reversal,
    LengthStep,
    AirRefraction,
    TracerEccentricity,
    ThermalDrift,
    DeadPath,
    ThermalExpansion,
    Settling,
    TargetOffset,
    /// An effect on the lengths that the session's plan kind models itself
    /// (`method::tracer_effects::LengthEffect`), by its name.
    Own(&'static str),
}

/// The effects the diagnosis can name (DESIGN.md "Unmodelled effects").
pub const LIBRARY: [EffectKind; 10] = [
    EffectKind::StationDrift,
    EffectKind::Reversal,
    EffectKind::LengthStep,
    EffectKind::AirRefraction,
    EffectKind::TracerEccentricity,
    EffectKind::ThermalDrift,
    EffectKind::DeadPath,
    EffectKind::ThermalExpansion,
    EffectKind::Settling,
    EffectKind::TargetOffset,
];

impl EffectKind {
    pub fn name(self) -> &'static str {
        match self {
            EffectKind::StationDrift => "station_drift",
            EffectKind::Reversal => "reversal",
            EffectKind::LengthStep => "length_step",
            EffectKind::AirRefraction => "air_refraction",
            EffectKind::TracerEccentricity => "tracer_eccentricity",
            EffectKind::ThermalDrift => "thermal_drift",
            EffectKind::DeadPath => "dead_path",
            EffectKind::ThermalExpansion => "thermal_expansion",
            EffectKind::Settling => "settling",
            EffectKind::TargetOffset => "target_offset",
            EffectKind::Own(name) => name,
        }
    }
}

/// The effects a session's diagnosis tests: the multilateration library, or the library of
/// the session's plan kind (its own models and the shared ones it names).
pub struct Library {
    /// Every name of the library, in order.
    pub names: Vec<&'static str>,
    /// The lengths-level candidates (a length step's position is searched per round).
    pub lengths: Vec<EffectModel>,
    /// The plan kind's diagnosis of its tracer network, if it has one.
    pub network: Option<&'static dyn TracerNetworkDiagnosis>,
    /// Models that could not be built for this session, and why.
    pub notes: Vec<String>,
}

impl Library {
    /// The library of `data`'s plan kind.
    pub fn of(data: &Data) -> Library {
        let network =
            crate::kinds::kind_named(&data.header.kind).and_then(|k| k.tracer_diagnosis());
        let Some(network) = network else {
            return Library {
                names: LIBRARY.iter().map(|k| k.name()).collect(),
                lengths: LIBRARY.iter().map(|&k| EffectModel::plain(k)).collect(),
                network: None,
                notes: Vec::new(),
            };
        };
        let session = data.network_session();
        let mut lengths = Vec::new();
        let mut notes = Vec::new();
        for &name in network.library() {
            if network.stations_effect() == Some(name) {
                continue;
            }
            match network.length_effect(name, &session) {
                Some(Ok(model)) => lengths.push(EffectModel::of_kind(Arc::from(model))),
                Some(Err(why)) => notes.push(format!("{name}: cannot be tested: {why}")),
                None => match effect_by_name(name) {
                    Ok(kind) => lengths.push(EffectModel::plain(kind)),
                    Err(why) => notes.push(why),
                },
            }
        }
        Library {
            names: network.library().to_vec(),
            lengths,
            network: Some(network),
            notes,
        }
    }

    /// The lengths-level model called `name`, or why this library has none.
    pub fn model(&self, name: &str) -> Result<EffectModel, String> {
        self.lengths
            .iter()
            .find(|m| m.kind.name() == name)
            .cloned()
            .ok_or_else(|| {
                format!(
                    "effect `{name}` is not modelled on the lengths of this session's kind; its library: {}",
                    self.names.join(", ")
                )
            })
    }
}

/// Every effect name any plan kind's library holds (the multilateration's first).
pub fn known_names() -> Vec<&'static str> {
    let mut names: Vec<&'static str> = LIBRARY.iter().map(|k| k.name()).collect();
    for kind in crate::kinds::KINDS {
        if let Some(network) = kind.tracer_diagnosis() {
            for name in network.library() {
                if !names.contains(name) {
                    names.push(name);
                }
            }
        }
    }
    names
}

/// The library effect called `name`, or an error that lists the known names.
pub fn effect_by_name(name: &str) -> Result<EffectKind, String> {
    LIBRARY
        .iter()
        .copied()
        .find(|k| k.name() == name)
        .ok_or_else(|| {
            let known: Vec<&str> = LIBRARY.iter().map(|k| k.name()).collect();
            format!(
                "unknown effect `{name}`; known effects: {}",
                known.join(", ")
            )
        })
}

/// One effect as a model: its kind and, for a length step, where the step is (pass group and
/// position in the pass's time order from which the lengths are shifted); for settling, its
/// time constant; for an effect the plan kind models, that model; for the eccentricity, the
/// phases its shared size is linearised about.
#[derive(Debug, Clone)]
pub struct EffectModel {
    pub kind: EffectKind,
    pub step: Option<(usize, usize)>,
    pub tau_s: Option<f64>,
    pub own: Option<Arc<dyn LengthEffect>>,
    /// `tracer_eccentricity` with one size e for the instrument: each block's (station's, or
    /// the table's) phase φ0 the constraint is linearised about (see [`EffectModel::columns`]).
    pub phases: Option<Vec<f64>>,
}

impl PartialEq for EffectModel {
    fn eq(&self, other: &Self) -> bool {
        self.kind == other.kind
            && self.step == other.step
            && self.tau_s == other.tau_s
            && self.phases == other.phases
    }
}

/// The eccentricity's parameters come in blocks of three per placement of the tracer (a
/// station, or the table it turns with): e cos φ0, e sin φ0, ez.
const ECCENTRICITY_BLOCK: usize = 3;

impl EffectModel {
    pub fn plain(kind: EffectKind) -> EffectModel {
        EffectModel {
            kind,
            step: None,
            tau_s: None,
            own: None,
            phases: None,
        }
    }

    fn is_eccentricity(&self) -> bool {
        self.kind.name() == EffectKind::TracerEccentricity.name()
    }

    /// The eccentricity with one size e shared by every placement of the tracer, linearised
    /// about the phases of `theta` (the per-placement fit, e cos φ0, e sin φ0, ez per block):
    /// e is the instrument's (its beam pivot's offset from its rotation centre), φ0 depends on
    /// how the tracer was set down at each station (one for the table it turns with). Other
    /// models, and a `theta` that is not in blocks of three, are returned as they are.
    pub fn linearised_at(&self, theta: &[f64]) -> EffectModel {
        if !self.is_eccentricity() || theta.is_empty() || theta.len() % ECCENTRICITY_BLOCK != 0 {
            return self.clone();
        }
        let phases = theta
            .chunks(ECCENTRICITY_BLOCK)
            .map(|b| b[1].atan2(b[0]))
            .collect();
        EffectModel {
            phases: Some(phases),
            ..self.clone()
        }
    }

    /// Each model linearised at its part of `theta` (the models' parameters in column order).
    pub fn all_linearised_at(
        models: &[EffectModel],
        data: &Data,
        theta: &[f64],
    ) -> Vec<EffectModel> {
        let mut at = 0;
        models
            .iter()
            .map(|m| {
                let width = m.param_names(data).len();
                let part = theta.get(at..at + width).unwrap_or(&[]);
                at += width;
                m.linearised_at(part)
            })
            .collect()
    }

    /// Whether a model is linearised about an estimate of its own parameters (its fit is then
    /// refined by fitting again at the estimate).
    pub fn is_linearised(&self) -> bool {
        self.phases.is_some()
    }

    /// Columns in blocks of (cos az, sin az, sin el) restricted to one shared size e:
    /// f·P with P the projector onto the parameters e (cos φ_b, sin φ_b) + t_b (−sin φ_b,
    /// cos φ_b) and ez_b, the constraint |(e cos φ0, e sin φ0)| equal in every block,
    /// linearised at φ_b. The parameters keep their names and units; a minimum-norm fit lies
    /// on that set.
    fn shared_size(&self, f: DMatrix<f64>) -> DMatrix<f64> {
        let Some(p) = self.shared_projector(f.ncols()) else {
            return f;
        };
        // f·P by blocks of rows, in place (each entry's sum as of the whole product).
        let mut f = f;
        const ROWS: usize = 4096;
        let mut start = 0;
        while start < f.nrows() {
            let len = ROWS.min(f.nrows() - start);
            let block = f.rows(start, len) * &p;
            f.rows_mut(start, len).copy_from(&block);
            start += len;
        }
        f
    }

    /// The projector P of [`EffectModel::shared_size`] for k columns; None where the columns
    /// stay free.
    fn shared_projector(&self, k: usize) -> Option<DMatrix<f64>> {
        let phases = self.phases.as_ref()?;
        if k != ECCENTRICITY_BLOCK * phases.len() {
            return None;
        }
        let mut p = DMatrix::zeros(k, k);
        let norm = (phases.len() as f64).sqrt();
        let radial = DVector::from_fn(k, |c, _| {
            let phi = phases[c / ECCENTRICITY_BLOCK];
            match c % ECCENTRICITY_BLOCK {
                0 => phi.cos() / norm,
                1 => phi.sin() / norm,
                _ => 0.0,
            }
        });
        p += &radial * radial.transpose();
        for (b, phi) in phases.iter().enumerate() {
            let c = ECCENTRICITY_BLOCK * b;
            let tangential = [-phi.sin(), phi.cos()];
            for r in 0..2 {
                for s in 0..2 {
                    p[(c + r, c + s)] += tangential[r] * tangential[s];
                }
            }
            p[(c + 2, c + 2)] = 1.0;
        }
        Some(p)
    }

    /// An effect the session's plan kind models.
    pub fn of_kind(model: Arc<dyn LengthEffect>) -> EffectModel {
        EffectModel {
            kind: EffectKind::Own(model.name()),
            own: Some(model),
            ..EffectModel::plain(EffectKind::Own(""))
        }
    }

    /// Parameter names with their units, in column order.
    pub fn param_names(&self, data: &Data) -> Vec<String> {
        let per_station = |names: [&str; 3]| -> Vec<String> {
            data.station_ids
                .iter()
                .flat_map(|s| names.iter().map(move |n| format!("{s}.{n}")))
                .collect()
        };
        match self.kind {
            EffectKind::Own(_) => self.own.as_ref().map_or(Vec::new(), |m| m.param_names()),
            EffectKind::StationDrift => per_station(["wx_m_s", "wy_m_s", "wz_m_s"]),
            EffectKind::Reversal => vec!["bx_m".into(), "by_m".into(), "bz_m".into()],
            EffectKind::LengthStep => vec!["step_m".into()],
            EffectKind::AirRefraction => vec!["edlen_scale".into()],
            EffectKind::TracerEccentricity => per_station(["e_cos_phi0_m", "e_sin_phi0_m", "ez_m"]),
            EffectKind::ThermalDrift => vec!["vx_m_s".into(), "vy_m_s".into(), "vz_m_s".into()],
            EffectKind::DeadPath => data
                .station_ids
                .iter()
                .map(|s| format!("{s}.dead_path_m"))
                .collect(),
            EffectKind::ThermalExpansion => vec![
                "alpha_x_per_k".into(),
                "alpha_y_per_k".into(),
                "alpha_z_per_k".into(),
            ],
            // On the means: the offset settling leaves in each homing (the arrival before the
            // homing is not in the session), a nuisance per pass. Its offsets per axis are
            // fitted on the raw windows (settling.rs) and their bias taken off the means.
            EffectKind::Settling => data
                .pass_names
                .iter()
                .map(|p| format!("{p}.home_offset_m"))
                .collect(),
            EffectKind::TargetOffset => vec!["dox_m".into(), "doy_m".into(), "doz_m".into()],
        }
    }

    /// Columns f(obs) − f(zeroing of obs): the change of each measured relative length per
    /// unit of each parameter. The homing zeroes the counter with the effect's value at that
    /// instant (the home dwell's beam, the time, air and temperature of the zeroing), so the
    /// zeroing term belongs to the model (it is what makes passes differ).
    pub fn columns(&self, data: &Data, geom: &Geometry) -> DMatrix<f64> {
        match self.kind {
            // Already relative: the homing's own offset, constant over the pass.
            EffectKind::Settling => return self.absolute(data, &data.obs, geom),
            // Zero up to the step, which comes after the zeroing.
            EffectKind::LengthStep => {
                let mut f = DMatrix::zeros(data.obs.len(), 1);
                if let Some((g, k)) = self.step {
                    for &i in data.passes[g].iter().skip(k) {
                        f[(i, 0)] = 1.0;
                    }
                }
                return f;
            }
            _ => {}
        }
        let mut f = self.absolute(data, &data.obs, geom);
        let f0 = self.absolute(data, &zeroings(data), geom);
        // In place: a candidate's columns (lengths × up to 3 per station) are held once.
        for (c, mut column) in f.column_iter_mut().enumerate() {
            for (x, o) in column.iter_mut().zip(&data.obs) {
                *x -= f0[(o.pass_group, c)];
            }
        }
        self.shared_size(f)
    }

    /// [`EffectModel::columns`] as a candidate is evaluated: by rows where each length touches
    /// only its own station's (or pass's) parameters, so that a large session's candidate is
    /// not held dense; the same values.
    pub fn candidate_columns(&self, data: &Data, geom: &Geometry) -> Columns {
        let Some(inner) = self.own_columns(data) else {
            return Columns::Dense(self.columns(data, geom));
        };
        // Settling's columns are relative already (`columns`).
        let zeroings = (self.kind != EffectKind::Settling).then(|| zeroings(data));
        let mut m = RowSparse::new(inner, data.obs.len(), 3);
        for o in &data.obs {
            let (first, mut values, count) = self.own_entries(data, o, geom);
            if let Some(zeroings) = &zeroings {
                // The home dwell belongs to the same station: the same columns.
                let (_, at_zeroing, _) = self.own_entries(data, &zeroings[o.pass_group], geom);
                for (v, z) in values.iter_mut().zip(at_zeroing) {
                    *v -= z;
                }
            }
            m.push_row((0..count).map(|j| (first + j, values[j])));
        }
        match self.shared_projector(inner) {
            Some(p) => Columns::Sparse(m.with_right(p)),
            None => Columns::Sparse(m),
        }
    }

    /// The number of columns of an effect with parameters per station (or per pass), whose
    /// length touches only its own; None for the others.
    fn own_columns(&self, data: &Data) -> Option<usize> {
        match self.kind {
            EffectKind::StationDrift | EffectKind::TracerEccentricity => {
                Some(3 * data.station_ids.len())
            }
            EffectKind::DeadPath => Some(data.station_ids.len()),
            EffectKind::Settling => Some(data.passes.len()),
            _ => None,
        }
    }

    /// The absolute columns' entries of one length of an effect with parameters per station
    /// (or per pass, [`EffectModel::own_columns`]): its first column, values and their number.
    fn own_entries(&self, data: &Data, o: &Obs, geom: &Geometry) -> (usize, [f64; 3], usize) {
        match self.kind {
            EffectKind::StationDrift => {
                let (u, _) = geom.beam_of(o);
                let dt = o.t_s - data.station_start_s[o.station];
                (3 * o.station, [u[0] * dt, u[1] * dt, u[2] * dt], 3)
            }
            EffectKind::TracerEccentricity => {
                // The beam leaves the station towards the target: direction −u.
                let (u, _) = geom.beam_of(o);
                (3 * o.station, eccentricity_terms(-u), 3)
            }
            // dn(t) times an error of the declared dead path per station: independent of
            // where the target is.
            EffectKind::DeadPath => (o.station, [o.dn.unwrap_or(0.0), 0.0, 0.0], 1),
            // −1 on every length of a pass: the settling offset at its homing.
            EffectKind::Settling => (o.pass_group, [-1.0, 0.0, 0.0], 1),
            _ => (0, [0.0; 3], 0),
        }
    }

    /// f(obs): the effect's error in the absolute optical distance per unit parameter.
    fn absolute(&self, data: &Data, obs: &[Obs], geom: &Geometry) -> DMatrix<f64> {
        let nobs = obs.len();
        if let Some(k) = self.own_columns(data) {
            let mut f = DMatrix::zeros(nobs, k);
            for (i, o) in obs.iter().enumerate() {
                let (first, values, count) = self.own_entries(data, o, geom);
                for (j, v) in values.into_iter().take(count).enumerate() {
                    f[(i, first + j)] = v;
                }
            }
            return f;
        }
        match self.kind {
            EffectKind::Own(_) => match &self.own {
                Some(model) => {
                    let beams: Vec<BeamObservation> = obs
                        .iter()
                        .map(|o| BeamObservation {
                            station: o.station,
                            beam: -geom.beam_of(o).0,
                            t_s: o.t_s,
                        })
                        .collect();
                    model.absolute(&beams)
                }
                None => DMatrix::zeros(nobs, 0),
            },
            EffectKind::Reversal => {
                let mut f = DMatrix::zeros(nobs, 3);
                for (i, o) in obs.iter().enumerate() {
                    let (u, _) = geom.beam_of(o);
                    for a in 0..3 {
                        f[(i, a)] = -u[a] * 0.5 * o.approach_sign(a);
                    }
                }
                f
            }
            // Relative by construction (`columns`).
            EffectKind::LengthStep => DMatrix::zeros(nobs, 1),
            // The index error acts on the absolute optical path, the declared dead path included.
            EffectKind::AirRefraction => DMatrix::from_fn(nobs, 1, |i, _| {
                obs[i].dn.unwrap_or(0.0) * (geom.beam_of(&obs[i]).1 + data.declared_dead_path_m)
            }),
            // The target moves by v·t (session time) for every station alike: a target shift
            // δX changes the length by −u·δX. Per station this is a special case of a station
            // drift (w = −v, up to a station shift), so it is nested in station_drift with 3
            // parameters instead of 3 per station: BIC tells them apart.
            EffectKind::ThermalDrift => {
                let mut f = DMatrix::zeros(nobs, 3);
                for (i, o) in obs.iter().enumerate() {
                    let (u, _) = geom.beam_of(o);
                    for a in 0..3 {
                        f[(i, a)] = -u[a] * o.t_s;
                    }
                }
                f
            }
            // Axis a's position scaled by α_a·ΔT_material(t): the target moves by
            // α_a·ΔT·axis_a along machine axis a. A constant ΔT is a scale of the points the
            // free points absorb: only the temperature's variation is seen.
            EffectKind::ThermalExpansion => {
                let mut f = DMatrix::zeros(nobs, 3);
                for (i, o) in obs.iter().enumerate() {
                    let (u, _) = geom.beam_of(o);
                    let dt = o.material_dt_k.unwrap_or(0.0);
                    for a in 0..3 {
                        f[(i, a)] = -u[a] * o.axes_m[a] * dt;
                    }
                }
                f
            }
            // The reflector off by δo moves every point by R(axes)·δo ≈ δo + ε(axes)×δo. Each
            // (target, point) is a free point of the multilateration model, so any per-point
            // displacement, this one included, is absorbed: projected rank 0, never a
            // candidate on lengths (docs/diagnosis.md). The column is the constant part.
            EffectKind::TargetOffset => {
                let mut f = DMatrix::zeros(nobs, 3);
                for (i, o) in obs.iter().enumerate() {
                    let (u, _) = geom.beam_of(o);
                    for a in 0..3 {
                        f[(i, a)] = -u[a];
                    }
                }
                f
            }
            // Made from their own entries above.
            EffectKind::StationDrift
            | EffectKind::TracerEccentricity
            | EffectKind::DeadPath
            | EffectKind::Settling => DMatrix::zeros(nobs, 0),
        }
    }
}

/// One zeroing state per pass: the home dwell as it stood when the counter was zeroed.
fn zeroings(data: &Data) -> Vec<Obs> {
    data.passes
        .iter()
        .zip(&data.pass_zeroings)
        .map(|(members, z)| {
            let home = &data.obs[data.obs[members[0]].home];
            Obs {
                t_s: z.t_s,
                dn: z.dn,
                material_dt_k: z.material_dt_k,
                ..home.clone()
            }
        })
        .collect()
}

/// (cos az, sin az, sin el) of a beam leaving the station along `v`.
fn eccentricity_terms(v: Vector3<f64>) -> [f64; 3] {
    let az = v.y.atan2(v.x);
    let el = v.z.clamp(-1.0, 1.0).asin();
    [az.cos(), az.sin(), el.sin()]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The one-size projector keeps every per-placement eccentricity of the same size at the
    /// phases it is linearised at, and removes a difference of sizes between placements.
    #[test]
    fn one_size_keeps_equal_sizes_and_removes_their_difference() {
        let (e, phases) = (4e-6, [0.4, 2.9, -1.3]);
        let theta: Vec<f64> = phases
            .iter()
            .flat_map(|p: &f64| [e * p.cos(), e * p.sin(), 1e-6])
            .collect();
        let model = EffectModel::plain(EffectKind::TracerEccentricity).linearised_at(&theta);
        assert!(model.is_linearised());
        let p = model.shared_size(DMatrix::identity(9, 9));
        let t = DVector::from_column_slice(&theta);
        assert!((&p * &t - &t).amax() < 1e-18, "kept");
        assert!((&p * &p - &p).amax() < 1e-12, "a projector");
        // The first placement larger by 1 µm along its own phase: only the mean size stays.
        let mut bigger = theta.clone();
        bigger[0] += 1e-6 * phases[0].cos();
        bigger[1] += 1e-6 * phases[0].sin();
        let kept = &p * DVector::from_column_slice(&bigger);
        let size = |b: usize| kept[3 * b].hypot(kept[3 * b + 1]);
        for b in 0..3 {
            assert!((size(b) - (e + 1e-6 / 3.0)).abs() < 1e-15, "block {b}");
        }
        // Another effect, or parameters not in blocks of three, are left free.
        assert!(!EffectModel::plain(EffectKind::Reversal)
            .linearised_at(&theta)
            .is_linearised());
        assert!(!EffectModel::plain(EffectKind::TracerEccentricity)
            .linearised_at(&theta[..4])
            .is_linearised());
    }
}
