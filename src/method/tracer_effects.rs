//! What a plan kind whose session is a tracer network (stations measuring lengths to the
//! machine's points, solved by the multilateration) adds to the diagnosis of those lengths:
//! its effect library, its own models of effects on the lengths, and a test of the solved
//! stations against the kind's model of them (e.g. a circle for stations on a rotary table).
//! The diagnosis and the solve with effects use it without naming a kind.

use nalgebra::{DMatrix, Vector3};

use crate::session::messages::SessionHeader;

/// One length as a kind's effect model sees it.
#[derive(Debug, Clone, Copy)]
pub struct BeamObservation {
    /// Index into the session's stations (the extraction's order).
    pub station: usize,
    /// Unit vector from the station to the target point (the beam leaving the station).
    pub beam: Vector3<f64>,
    /// Device time of the length, seconds.
    pub t_s: f64,
}

/// What a kind's effect models may read of the session.
#[derive(Debug, Clone, Copy)]
pub struct NetworkSession<'a> {
    pub header: &'a SessionHeader,
    /// The stations, in the extraction's order.
    pub station_ids: &'a [String],
    /// The stations that stood on a rotary table and its commanded angle there.
    pub rotations: &'a [(String, f64)],
}

/// An effect on the lengths modelled by the kind: columns in its own parameters.
pub trait LengthEffect: Send + Sync + std::fmt::Debug {
    /// The effect's name (the kind's library vocabulary).
    fn name(&self) -> &'static str;
    /// Parameter names with their units, in column order.
    fn param_names(&self) -> Vec<String>;
    /// f(obs) per unit of each parameter: the effect's error in the absolute optical distance
    /// (rows: observations). The homing's zeroing (f − f(home)) is the caller's.
    fn absolute(&self, obs: &[BeamObservation]) -> DMatrix<f64>;
}

/// The solved stations and their joint covariance (3m × 3m, station-major).
#[derive(Debug, Clone, Copy)]
pub struct SolvedStations<'a> {
    pub positions_m: &'a [Vector3<f64>],
    pub covariance_m2: &'a DMatrix<f64>,
}

/// The test of the solved stations against the kind's model of them, and of one effect
/// there (linearised at the nominal fit; generalised least squares with the stations' joint
/// covariance).
#[derive(Debug, Clone, PartialEq)]
pub struct StationsLevel {
    /// What the stations are tested against, for the report.
    pub model: String,
    /// The effect tested at this level.
    pub effect: &'static str,
    pub chi2: f64,
    pub dof: usize,
    /// The effect's identifiable parameters and the χ² it takes away.
    pub df: usize,
    pub chi2_drop: f64,
    /// Per parameter: (name, value, σ).
    pub params: Vec<(String, f64, f64)>,
    /// Per station tested: its residual against the model before and after the effect.
    pub stations: Vec<StationResidual>,
    /// RMS of the stations' residuals before and after the effect, metres.
    pub rms_m: f64,
    pub rms_after_m: f64,
    /// Held-out: each station's residual predicted from the others, in units of its predicted
    /// standard deviation; RMS before and after the effect (1 = noise).
    pub heldout_ratio: f64,
    pub heldout_ratio_after: f64,
}

#[derive(Debug, Clone, PartialEq)]
pub struct StationResidual {
    pub station: String,
    /// Where it lies, e.g. "tab07 at 30.0°".
    pub label: String,
    /// The components tested (e.g. radial and axial), metres, before and after the effect.
    pub residual_m: Vec<f64>,
    pub residual_after_m: Vec<f64>,
    /// Its χ² against the noise model (the stations' covariance), before the effect.
    pub chi2: f64,
}

/// A plan kind whose session is a tracer network, as the diagnosis sees it.
pub trait TracerNetworkDiagnosis: Sync {
    /// Every effect of the kind's library, in the order candidates are listed.
    fn library(&self) -> &'static [&'static str];

    /// The kind's own model of the lengths-level effect `name` for this session. None: the
    /// tracer network's shared model of that name (or an effect tested on the stations).
    fn length_effect(
        &self,
        name: &str,
        session: &NetworkSession<'_>,
    ) -> Option<Result<Box<dyn LengthEffect>, String>>;

    /// The effect tested on the solved stations, if the kind has one.
    fn stations_effect(&self) -> Option<&'static str> {
        None
    }

    /// The stations-level test. None: the kind has none, or the session cannot be tested
    /// there (the reason).
    fn stations_level(
        &self,
        _session: &NetworkSession<'_>,
        _stations: &SolvedStations<'_>,
    ) -> Result<Option<StationsLevel>, String> {
        Ok(None)
    }

    /// A station's place in the kind's coordinates (e.g. "tab07 at 30.0°"), for the
    /// residuals and their plot; None: its id says it.
    fn station_label(&self, _session: &NetworkSession<'_>, _station: &str) -> Option<String> {
        None
    }
}
