//! The observations the diagnosis works on, from the session alone: settled lengths with their
//! time, station, pass, approach directions, homing reference and the logged air at that time.

use std::collections::BTreeMap;
use std::path::Path;

use crate::extract::windows::Dwell;
pub use crate::extract::RawWindow;
use crate::extract::{
    stream_dwells, Lengths, NoiseModel, SettledDwells, SettledSession, WindowSamples,
};
use crate::session::messages::{EnvSample, SessionHeader};
use crate::session::reader::{read_session, ReadError, Session, Stamped};
use crate::sim::effects::edlen_dn;
use crate::solve::multilateration::{
    solve, MultilaterationProblem, MultilaterationSolution, SolveOptions,
};

#[derive(Debug, Clone)]
pub struct Obs {
    pub station: usize,
    pub segment: usize,
    pub point: usize,
    pub pass: usize,
    /// Index into `Data::passes`: one homing (station, target, pass, beam segment).
    pub pass_group: usize,
    /// The observation taken right after this pass's homing (point 0), whose effect value
    /// the homing zeroed: every effect column is f(obs) − f(home).
    pub home: usize,
    /// Middle of the settled stretch, device seconds.
    pub t_s: f64,
    pub length_m: f64,
    pub sigma_m: f64,
    /// Sign of the last move of x, y, z before this dwell (−1, 0 or 1).
    pub approach: [i8; 3],
    /// Edlén n − n_ref from the logged air at t_s, when the session has an environment log.
    pub dn: Option<f64>,
    /// Mean logged material temperature at t_s minus 20 °C, when the log has material sensors.
    pub material_dt_k: Option<f64>,
    /// Commanded axis positions x, y, z (from `point_begin`; 0 for an axis not named).
    pub axes_m: [f64; 3],
}

impl Obs {
    /// The approach signs as numbers.
    pub fn approach_sign(&self, axis: usize) -> f64 {
        f64::from(self.approach[axis])
    }
}

/// The state of a pass's homing (the instant its counter was zeroed, just before the home
/// dwell begins), with the logged air and material temperature then: an effect that changes in
/// time is zeroed at that instant, not at the home dwell's middle.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Zeroing {
    pub t_s: f64,
    pub dn: Option<f64>,
    pub material_dt_k: Option<f64>,
}

#[derive(Debug, Clone)]
pub struct Data {
    pub session_id: String,
    pub obs: Vec<Obs>,
    pub station_ids: Vec<String>,
    /// Per pass group: observation indices in time order, a readable name and its homing.
    pub passes: Vec<Vec<usize>>,
    pub pass_names: Vec<String>,
    pub pass_zeroings: Vec<Zeroing>,
    pub problem: MultilaterationProblem,
    /// The calibration: `problem` solved (the fit its σ were fixed at, so solving `problem`
    /// again gives it back); taken by the diagnosis. None when that solve failed, or taken.
    pub nominal: Option<MultilaterationSolution>,
    /// Per station: the first observation time (origin of drift ramps).
    pub station_start_s: Vec<f64>,
    pub has_env: bool,
    /// Every length has a logged material temperature.
    pub has_material: bool,
    /// Per observation: its raw window (None when the session's events do not locate it).
    pub windows: Vec<Option<RawWindow>>,
    pub dropped_windows: usize,
    /// Per problem point: (target, plan point index, nominal) and its commanded axes; the
    /// header's machine (structure, target offsets): the points level needs them.
    pub points: Vec<(String, usize, [f64; 3])>,
    pub point_axes_m: Vec<Option<[f64; 3]>>,
    pub machine: crate::session::messages::MachineInfo,
    /// The tracer's declared dead path (m): part of the absolute optical path the air acts on.
    pub declared_dead_path_m: f64,
    /// The session's header (its kind and plan).
    pub header: crate::session::messages::SessionHeader,
    /// The stations on a rotary table and its commanded angle there.
    pub rotations: Vec<(String, f64)>,
}

#[derive(Debug, thiserror::Error)]
pub enum DataError {
    #[error("point extraction: {0}")]
    Extract(#[from] crate::extract::points::ExtractError),
    #[error("no settled point windows in the session ({0} dropped)")]
    NoPoints(usize),
    #[error(
        "session kind `{0}` cannot be diagnosed: `geocal diagnose` supports `{1}` \
         sessions only (its effect library models tracer lengths); for `{0}` use `geocal solve` \
         (fit, χ²/dof and residuals) and `geocal check` (what the plan can identify)"
    )]
    Kind(String, String),
}

/// Linear interpolation of the logged air at t (held constant outside the log).
fn air_at(env: &[(f64, f64, f64, f64)], t_s: f64) -> Option<f64> {
    let first = env.first()?;
    let k = env.partition_point(|e| e.0 <= t_s);
    let (_, temp, p, rh) = if k == 0 {
        *first
    } else if k >= env.len() {
        env[env.len() - 1]
    } else {
        let (a, b) = (env[k - 1], env[k]);
        let f = if b.0 > a.0 {
            (t_s - a.0) / (b.0 - a.0)
        } else {
            0.0
        };
        let lerp = |x: f64, y: f64| x + f * (y - x);
        (t_s, lerp(a.1, b.1), lerp(a.2, b.2), lerp(a.3, b.3))
    };
    Some(edlen_dn(temp, p, rh))
}

/// Linear interpolation of a (t, value) series at t (held constant outside it).
fn interpolate(series: &[(f64, f64)], t_s: f64) -> Option<f64> {
    let first = series.first()?;
    let k = series.partition_point(|e| e.0 <= t_s);
    Some(if k == 0 {
        first.1
    } else if k >= series.len() {
        series[series.len() - 1].1
    } else {
        let (a, b) = (series[k - 1], series[k]);
        let f = if b.0 > a.0 {
            (t_s - a.0) / (b.0 - a.0)
        } else {
            0.0
        };
        a.1 + f * (b.1 - a.1)
    })
}

/// A clear error for a session kind the diagnosis has no model for (the kind says,
/// `Kind::diagnosable`).
pub fn check_kind(kind: &str) -> Result<(), DataError> {
    if crate::kinds::kind_named(kind).is_some_and(|k| k.diagnosable()) {
        return Ok(());
    }
    let supported = crate::kinds::KINDS
        .iter()
        .filter(|k| k.diagnosable())
        .map(|k| k.name())
        .collect::<Vec<_>>()
        .join("`, `");
    Err(DataError::Kind(kind.to_string(), supported))
}

/// A session file's settled windows in the compact form the diagnosis holds (`SettledDwells`:
/// the solve's lengths, no per-window names or maps), the windows' raw samples as `keep`
/// says: streamed when the file is clean (its tracer stream never held whole), else from the
/// whole read (damaged, cut short, repaired, of another kind). The outer error: the file
/// could not be read.
pub fn dwells_of_file(
    path: &Path,
    keep: WindowSamples,
) -> Result<Result<SettledDwells, DataError>, ReadError> {
    if let Some(dwells) = stream_dwells(path, diagnosable, keep) {
        return Ok(Ok(dwells));
    }
    let session = read_session(path)?;
    Ok(check_kind(&session.header.kind).and_then(|()| {
        let dwells = SettledDwells::of_settled(SettledSession::of_session(&session)?);
        Ok(match keep {
            WindowSamples::Kept => dwells,
            WindowSamples::ArrivalOnly => dwells.without_window_samples(),
        })
    }))
}

fn diagnosable(kind: &str) -> bool {
    check_kind(kind).is_ok()
}

impl Data {
    pub fn from_session(session: &Session) -> Result<Data, DataError> {
        check_kind(&session.header.kind)?;
        Data::from_settled(SettledSession::of_session(session)?)
    }

    /// From a session reduced to its settled windows (`SettledSession`, streamed or of a whole
    /// read): the same observations as `from_session` of that session.
    pub fn from_settled(settled: SettledSession) -> Result<Data, DataError> {
        check_kind(&settled.header.kind)?;
        Data::from_dwells(SettledDwells::of_settled(settled))
    }

    /// From the compact settled windows (`SettledDwells`): the same observations as
    /// `from_settled` of the session they were read from.
    pub fn from_dwells(settled: SettledDwells) -> Result<Data, DataError> {
        check_kind(&settled.header.kind)?;
        let SettledDwells {
            header,
            env,
            noise,
            lengths,
            dwells,
            windows,
            rotations,
            ..
        } = settled;
        let observed = Observed::of(&env, &lengths, &dwells, &windows)?;
        // Held once, in the observations and the problem, before the solve of `solved`.
        let Lengths {
            measurements,
            stations,
            dropped,
            ..
        } = lengths;
        drop((measurements, dwells, env));
        let station_ids = stations.iter().map(|s| s.id.clone()).collect();
        Ok(observed.solved(
            header,
            noise,
            windows,
            rotations,
            station_ids,
            dropped.len(),
        ))
    }

    /// As `from_dwells`, borrowing them, without the raw windows (`windows` left empty, as the
    /// diagnosis leaves it once the settling test is done): what the effects' fit reads.
    pub fn of_dwells(settled: &SettledDwells) -> Result<Data, DataError> {
        check_kind(&settled.header.kind)?;
        let lengths = &settled.lengths;
        let observed = Observed::of(&settled.env, lengths, &settled.dwells, &settled.windows)?;
        Ok(observed.solved(
            settled.header.clone(),
            settled.noise,
            Vec::new(),
            settled.rotations.clone(),
            lengths.stations.iter().map(|s| s.id.clone()).collect(),
            lengths.dropped.len(),
        ))
    }
}

/// The observations of a session's dwells, before their σ are fixed at the calibration's
/// solution.
struct Observed {
    obs: Vec<Obs>,
    passes: Vec<Vec<usize>>,
    pass_names: Vec<String>,
    pass_zeroings: Vec<Zeroing>,
    built: crate::method::multilateration::Problem,
    station_start_s: Vec<f64>,
}

impl Observed {
    fn of(
        env_log: &BTreeMap<String, Vec<Stamped<EnvSample>>>,
        extraction: &Lengths,
        dwells: &[Dwell],
        windows: &[Option<RawWindow>],
    ) -> Result<Observed, DataError> {
        if dwells.is_empty() {
            return Err(DataError::NoPoints(extraction.dropped.len()));
        }
        let mut env: Vec<(f64, f64, f64, f64)> = env_log
            .values()
            .next()
            .map(|v| {
                v.iter()
                    .map(|s| {
                        (
                            s.msg.t_s,
                            s.msg.air_temp_k,
                            s.msg.pressure_pa,
                            s.msg.humidity_pct,
                        )
                    })
                    .filter(|e| e.0.is_finite() && e.1.is_finite() && e.2.is_finite())
                    .collect()
            })
            .unwrap_or_default();
        env.sort_by(|a, b| a.0.total_cmp(&b.0));
        // Mean of the material sensors (machine structure, scales) per environment sample.
        let mut material: Vec<(f64, f64)> = env_log
            .values()
            .next()
            .map(|v| {
                v.iter()
                    .filter(|s| !s.msg.material_temp_k.is_empty())
                    .map(|s| {
                        let m = &s.msg.material_temp_k;
                        (s.msg.t_s, m.iter().sum::<f64>() / m.len() as f64)
                    })
                    .filter(|e| e.0.is_finite() && e.1.is_finite())
                    .collect()
            })
            .unwrap_or_default();
        material.sort_by(|a, b| a.0.total_cmp(&b.0));

        // The same adjustment problem `geocal solve` builds; observation i is measurement i.
        let built = crate::method::multilateration::Problem::of_lengths(extraction);
        let mut pass_index: BTreeMap<(usize, usize, usize, u32), usize> = BTreeMap::new();
        let mut passes: Vec<Vec<usize>> = Vec::new();
        let mut pass_names = Vec::new();
        let mut obs = Vec::with_capacity(extraction.measurements.len());
        // Per observation: the first sample time after its `point_begin` (for the home dwell:
        // the first sample after the zeroing).
        let mut arrival_s = Vec::with_capacity(extraction.measurements.len());
        let material_dt_k = |t_s: f64| {
            interpolate(&material, t_s).map(|k| k - crate::sim::effects::REFERENCE_MATERIAL_TEMP_K)
        };
        for ((m, d), o) in extraction
            .measurements
            .iter()
            .zip(dwells)
            .zip(&built.problem.observations)
        {
            let (segment, point) = (o.segment, o.point);
            let pass_key = (m.station_index, m.target, m.pass, m.beam_segment);
            let pass_group = *pass_index.entry(pass_key).or_insert_with(|| {
                passes.push(Vec::new());
                pass_names.push(format!(
                    "{} pass {}{}",
                    extraction.station(m),
                    m.pass,
                    if m.beam_segment > 0 {
                        format!(" segment {}", m.beam_segment)
                    } else {
                        String::new()
                    }
                ));
                passes.len() - 1
            });
            let t_s = 0.5 * (d.settled_from_s + d.settled_to_s);
            passes[pass_group].push(obs.len());
            arrival_s.push(
                windows
                    .get(obs.len())
                    .and_then(|w| w.as_ref())
                    .map_or(d.settled_from_s, |w| w.arrival_s),
            );
            obs.push(Obs {
                station: m.station_index,
                segment,
                point,
                pass: m.pass,
                pass_group,
                home: usize::MAX,
                t_s,
                length_m: m.length_m,
                sigma_m: m.sigma_m,
                approach: d.approach,
                dn: air_at(&env, t_s),
                material_dt_k: material_dt_k(t_s),
                axes_m: d.axes_m,
            });
        }
        let mut pass_zeroings = Vec::with_capacity(passes.len());
        for members in &mut passes {
            members.sort_by(|&a, &b| obs[a].t_s.total_cmp(&obs[b].t_s));
            // The homing point's dwell comes first after homing; if it was dropped, the
            // earliest dwell of the pass stands in for the homing state.
            let home = members
                .iter()
                .copied()
                .find(|&i| built.points[obs[i].point].1 == 0)
                .unwrap_or(members[0]);
            let t_s = arrival_s[home];
            pass_zeroings.push(Zeroing {
                t_s,
                dn: air_at(&env, t_s),
                material_dt_k: material_dt_k(t_s),
            });
            for &i in members.iter() {
                obs[i].home = home;
            }
        }
        let m = extraction.stations.len();
        let mut station_start_s = vec![f64::INFINITY; m];
        for o in &obs {
            station_start_s[o.station] = station_start_s[o.station].min(o.t_s);
        }
        Ok(Observed {
            obs,
            passes,
            pass_names,
            pass_zeroings,
            built,
            station_start_s,
        })
    }

    /// The diagnosis's data: the path-dependent σ evaluated once at the calibration's
    /// solution and then held, so that every fit of the diagnosis weighs the lengths alike.
    fn solved(
        self,
        header: SessionHeader,
        noise: Option<NoiseModel>,
        windows: Vec<Option<RawWindow>>,
        rotations: Vec<(String, f64)>,
        station_ids: Vec<String>,
        dropped_windows: usize,
    ) -> Data {
        let Observed {
            mut obs,
            passes,
            pass_names,
            pass_zeroings,
            built,
            station_start_s,
        } = self;
        let mut problem = built.problem;
        let nominal = solve(&problem, &SolveOptions::default()).ok();
        if let Some(solution) = &nominal {
            problem = problem.with_fixed_sigmas(&solution.sigmas_m);
            for (o, fixed) in obs.iter_mut().zip(&problem.observations) {
                o.sigma_m = fixed.sigma_m;
            }
        }
        Data {
            rotations,
            declared_dead_path_m: noise.map_or(0.0, |n| n.dead_path_m),
            points: built.points,
            point_axes_m: built.axes_m,
            machine: header.machine.clone(),
            session_id: header.session_id.clone(),
            header,
            has_env: obs.iter().all(|o| o.dn.is_some()),
            has_material: obs.iter().all(|o| o.material_dt_k.is_some()),
            windows,
            obs,
            station_ids,
            passes,
            pass_names,
            pass_zeroings,
            problem,
            nominal,
            station_start_s,
            dropped_windows,
        }
    }
}
impl Data {
    /// What a plan kind's effect models may read of this session.
    pub fn network_session(&self) -> crate::method::tracer_effects::NetworkSession<'_> {
        crate::method::tracer_effects::NetworkSession {
            header: &self.header,
            station_ids: &self.station_ids,
            rotations: &self.rotations,
        }
    }

    /// The same observations with every σ multiplied by `k` (a common scale of the declared
    /// noise model).
    pub fn with_sigma_scaled(&self, k: f64) -> Data {
        let mut scaled = self.clone();
        for o in &mut scaled.obs {
            o.sigma_m *= k;
        }
        for o in &mut scaled.problem.observations {
            o.sigma_m *= k;
        }
        scaled
    }
}
