//! `[sim]` sections the simulator reads: the unmodelled effects, the truth's error sizes and
//! a passive machine's behaviour. Declared here so that the configuration needs no simulator.

use serde::{Deserialize, Serialize};

/// One switch with a size; `size_m` (or m/s for drift) is the effect's scale.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Default)]
#[serde(deny_unknown_fields, default)]
pub struct EffectSwitch {
    pub enabled: bool,
    /// Size of the effect: metres (station_drift: metres per second; air_refraction: scale
    /// of the Edlén-predicted error, 1 = an uncompensated tracer).
    pub size: f64,
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Default)]
#[serde(deny_unknown_fields, default)]
pub struct EccentricitySwitch {
    pub enabled: bool,
    /// Horizontal eccentricity e of the tracer's reference, metres.
    pub size_m: f64,
    /// Vertical term ez, metres.
    pub z_size_m: f64,
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Default)]
#[serde(deny_unknown_fields, default)]
pub struct PeriodicSwitch {
    pub enabled: bool,
    pub size_m: f64,
    pub period_m: f64,
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Default)]
#[serde(deny_unknown_fields, default)]
pub struct SettlingSwitch {
    pub enabled: bool,
    /// Offset at the end of a move, [0.5, 1]·size_m per axis, metres.
    pub size_m: f64,
    /// Decay time constant, seconds.
    pub tau_s: f64,
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Default)]
#[serde(deny_unknown_fields, default)]
pub struct TargetOffsetSwitch {
    pub enabled: bool,
    /// Length of the offset error, metres.
    pub size_m: f64,
}

/// `[sim.effects]`: every effect off by default.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Default)]
#[serde(deny_unknown_fields, default)]
pub struct EffectsConfig {
    /// Station moves during its pass at `size` m/s in a random direction per station.
    pub station_drift: EffectSwitch,
    /// Axis reversal offset B/2·sign(approach), |B| about `size` metres per axis.
    pub reversal: EffectSwitch,
    /// An unflagged fringe loss of `size` metres in one station, at a random time in its pass.
    pub length_step: EffectSwitch,
    /// The tracer is not compensated for air: error dn·L_abs, L_abs the absolute optical path
    /// (beam plus declared dead path), scaled by `size` (1 = physical).
    pub air_refraction: EffectSwitch,
    /// Length error e·cos(azimuth − φ0) + ez·sin(elevation) of the beam from each station.
    pub tracer_eccentricity: EccentricitySwitch,
    /// The target (machine) drifts at `size` m/s in a random direction from the session start,
    /// A(t) = A + v·t: every station sees the same motion.
    pub thermal_drift: EffectSwitch,
    /// The dead path (the optical path from the interferometer's zero) differs from the one
    /// declared, so the air compensation misses dn(t) times that difference: [0.5, 1]·`size`
    /// metres per station.
    pub dead_path: EffectSwitch,
    /// The machine's scales are not compensated for temperature: each axis position is
    /// scaled by `size`·(T_material − 20 °C), `size` the expansion coefficient in 1/K
    /// (11.5e-6 for steel), T_material the mean of the material sensors.
    pub thermal_expansion: EffectSwitch,
    /// Each axis that moved lags behind its target along the approach direction by an offset
    /// that decays after the move: −sign(move)·s_a·exp(−(t − t_end)/tau_s).
    pub settling: SettlingSwitch,
    /// The reflector sits `size_m` from its configured offset (tool frame), in a random
    /// direction per target: the machine's angular errors turn it with the axes.
    pub target_offset: TargetOffsetSwitch,
    /// Not in the diagnosis library (a test of `unexplained`): interferometer nonlinearity
    /// size·sin(2π·L/period) in the absolute distance.
    pub periodic_nonlinearity: PeriodicSwitch,
    /// Not in the diagnosis library (a test of the points level): a local bump of the tool
    /// position that the quasi-rigid 21-error model cannot express (src/sim/bump.rs).
    pub local_bump: BumpSwitch,
    /// The rotary table's error motions, periodic in the table angle: radial and axial
    /// (harmonics 2-4) and tilt (2-3), `size` metres of pivot displacement per component; the
    /// tracer on the table stands off the circle its pivot would turn on (src/sim/rotary.rs).
    pub table_error_motion: EffectSwitch,
}

impl EffectsConfig {
    pub fn any(&self) -> bool {
        self.station_drift.enabled
            || self.reversal.enabled
            || self.length_step.enabled
            || self.air_refraction.enabled
            || self.tracer_eccentricity.enabled
            || self.thermal_drift.enabled
            || self.dead_path.enabled
            || self.thermal_expansion.enabled
            || self.settling.enabled
            || self.target_offset.enabled
            || self.periodic_nonlinearity.enabled
            || self.local_bump.enabled
            || self.table_error_motion.enabled
    }

    /// Ranges serde cannot check; on failure (key, what was expected).
    pub fn validate(&self) -> Result<(), (String, String)> {
        let sizes = [
            ("station_drift.size", self.station_drift.size),
            ("reversal.size", self.reversal.size),
            ("length_step.size", self.length_step.size),
            ("air_refraction.size", self.air_refraction.size),
            (
                "tracer_eccentricity.size_m",
                self.tracer_eccentricity.size_m,
            ),
            (
                "tracer_eccentricity.z_size_m",
                self.tracer_eccentricity.z_size_m,
            ),
            ("thermal_drift.size", self.thermal_drift.size),
            ("dead_path.size", self.dead_path.size),
            ("thermal_expansion.size", self.thermal_expansion.size),
            ("settling.size_m", self.settling.size_m),
            ("target_offset.size_m", self.target_offset.size_m),
            ("table_error_motion.size", self.table_error_motion.size),
            (
                "periodic_nonlinearity.size_m",
                self.periodic_nonlinearity.size_m,
            ),
        ];
        for (key, v) in sizes {
            if !(v.is_finite() && v >= 0.0) {
                return Err((
                    format!("sim.effects.{key}"),
                    format!("expected a number >= 0, found {v}"),
                ));
            }
        }
        let st = &self.settling;
        if st.enabled && !(st.tau_s.is_finite() && st.tau_s > 0.0) {
            return Err((
                "sim.effects.settling.tau_s".into(),
                format!(
                    "expected a positive time constant when enabled, found {}",
                    st.tau_s
                ),
            ));
        }
        let pn = &self.periodic_nonlinearity;
        if pn.enabled && !(pn.period_m.is_finite() && pn.period_m > 0.0) {
            return Err((
                "sim.effects.periodic_nonlinearity.period_m".into(),
                format!(
                    "expected a positive period when enabled, found {}",
                    pn.period_m
                ),
            ));
        }
        Ok(())
    }
}

/// Target RMS sizes of the truth errors over the travel (metres, radians).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct ErrorSizes {
    /// Positioning errors (EXX, EYY, EZZ).
    pub positioning_m: f64,
    /// Straightness errors (EYX, EZX, EXY, EZY, EXZ, EYZ).
    pub straightness_m: f64,
    /// Roll, pitch and yaw (EAX … ECZ).
    pub angular_rad: f64,
    /// Typical magnitude of each squareness error (EC0Y, EA0Z, EB0Z).
    pub squareness_rad: f64,
}

impl Default for ErrorSizes {
    fn default() -> Self {
        ErrorSizes {
            positioning_m: 5e-6,
            straightness_m: 3e-6,
            angular_rad: 5e-6,
            squareness_rad: 5e-6,
        }
    }
}

impl ErrorSizes {
    /// Every size must be finite and non-negative; the error names the offending key.
    pub fn check(&self) -> Result<(), String> {
        for (key, v) in [
            ("positioning_m", self.positioning_m),
            ("straightness_m", self.straightness_m),
            ("angular_rad", self.angular_rad),
            ("squareness_rad", self.squareness_rad),
        ] {
            if !v.is_finite() || v < 0.0 {
                return Err(format!("{key} must be a finite number >= 0, got {v}"));
            }
        }
        Ok(())
    }
}

/// `[sim.passive]`.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct SimPassiveConfig {
    /// Stops the program does not hold: the machine pauses part way through a move.
    pub unplanned_stops: Vec<UnplannedStop>,
    /// Each G4 dwell lasts up to this much longer or shorter (uniform), seconds; keep it
    /// below `devices.machine.passive.dwell_margin_s`.
    pub dwell_jitter_s: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct UnplannedStop {
    /// Which G1 of the program (0-based, counting every move).
    pub move_index: usize,
    /// Where along the move the machine pauses, 0..1.
    pub fraction: f64,
    pub duration_s: f64,
}

/// Displacement size·d̂·exp(−|q − c|²/(2 r²)) of the axes at commanded axes q (machine frame,
/// m). A product of functions of x, y and z, so no sum of per-axis error functions (the
/// quasi-rigid model) holds it; the lengths' model absorbs it, since the points are free there.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct BumpSwitch {
    pub enabled: bool,
    /// Peak displacement, metres.
    pub size_m: f64,
    /// Centre of the bump in axis coordinates, metres.
    pub centre_m: [f64; 3],
    /// Gaussian radius r, metres.
    pub radius_m: f64,
    /// Direction of the displacement (normalised here).
    pub direction: [f64; 3],
}

impl Default for BumpSwitch {
    fn default() -> Self {
        BumpSwitch {
            enabled: false,
            size_m: 0.0,
            centre_m: [0.0; 3],
            radius_m: 0.1,
            direction: [0.0, 0.0, 1.0],
        }
    }
}

/// `[sim] compensation = [{ format = "linuxcnc-type1", file = "comp-x.txt", axis = "x" }]`:
/// a controller's table the simulated machine applies to one axis, as that controller does
/// (a verification run after `geocal compensate`). A `sinumerik` entry without `axis` applies
/// the file's `$AN_CEC` cross tables, their base and compensation axes named in the file. A
/// relative `file` is read from the configuration's folder.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SimCompensation {
    /// `linuxcnc-type0`, `linuxcnc-type1` or `sinumerik`.
    pub format: crate::compensate::TableFormat,
    pub file: std::path::PathBuf,
    /// The machine axis the table acts on: x, y or z; left out for `$AN_CEC` cross tables.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub axis: Option<String>,
    /// SINUMERIK: the machine axis name in `$AA_ENC_COMP[0,N,AX]` (default X1, Y1, Z1).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub controller_axis: Option<String>,
    /// SINUMERIK cross tables: the machine axis names of x, y, z (default X1, Y1, Z1).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub axis_names: Option<Vec<String>>,
}

impl SimCompensation {
    /// The axis index (0, 1, 2), or None without an axis or for a name other than x, y, z.
    pub fn axis_index(&self) -> Option<usize> {
        let axis = self.axis.as_deref()?;
        crate::compensate::AXES.iter().position(|a| *a == axis)
    }

    /// The name the controller's table uses for this entry's axis.
    pub fn controller_axis_name(&self) -> String {
        self.controller_axis.clone().unwrap_or_else(|| {
            format!(
                "{}1",
                self.axis.as_deref().unwrap_or_default().to_uppercase()
            )
        })
    }

    /// A SINUMERIK entry without an axis: the file's `$AN_CEC` cross tables.
    pub fn is_cross(&self) -> bool {
        self.format == crate::compensate::TableFormat::Sinumerik && self.axis.is_none()
    }

    /// The controller's names of x, y, z for cross tables (the validation checked there are 3).
    pub fn machine_axis_names(&self) -> [String; 3] {
        match self.axis_names.as_deref() {
            Some([x, y, z]) => [x.clone(), y.clone(), z.clone()],
            _ => ["X1", "Y1", "Z1"].map(String::from),
        }
    }

    /// The tables of this entry, for `compensate::applied::describe`.
    pub fn selection<'a>(
        &'a self,
        axis_names: &'a [String; 3],
        controller_axis: &'a str,
    ) -> Option<crate::compensate::applied::Selection<'a>> {
        use crate::compensate::applied::Selection;
        if self.is_cross() {
            return Some(Selection::Cross { axis_names });
        }
        Some(Selection::Axis {
            axis: self.axis_index()?,
            controller_axis,
        })
    }
}
