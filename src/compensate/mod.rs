//! Compensation tables from a calibration's results: what each controller loads (LinuxCNC,
//! SINUMERIK, plain CSV/JSON), parsed back as the controller reads it and applied as it does.
//!
//! Every table holds the tool-to-workpiece deviation of an axis along (or across) its own
//! travel as a function of its commanded position: the carriage's error with the sign flip of
//! the workpiece branch (docs/kinematics.md). Sign conventions are each format's own
//! (docs/compensation.md).

pub mod applied;
pub mod linuxcnc;
pub mod sinumerik;
pub mod source;
pub mod table;
pub mod verify;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::model::kinematics::Structure;

pub const AXES: [&str; 3] = ["x", "y", "z"];
/// Positioning error of each axis under its ISO name.
pub const POSITIONING: [&str; 3] = ["EXX", "EYY", "EZZ"];

#[derive(Debug, thiserror::Error)]
pub enum CompensateError {
    #[error("{file}: {message}")]
    Input { file: PathBuf, message: String },
    #[error("{file}: line {line}: {message}")]
    Line {
        file: PathBuf,
        line: usize,
        message: String,
    },
    #[error("{0}")]
    Limit(String),
    #[error("{file}: {source}")]
    Io {
        file: PathBuf,
        source: std::io::Error,
    },
}

pub(crate) fn input_error(file: &Path, message: impl Into<String>) -> CompensateError {
    CompensateError::Input {
        file: file.to_path_buf(),
        message: message.into(),
    }
}

/// The table formats `geocal compensate` writes and the simulator loads.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum TableFormat {
    /// LinuxCNC `COMP_FILE_TYPE = 0`: nominal, actual reached moving +, moving −.
    LinuxcncType0,
    /// LinuxCNC `COMP_FILE_TYPE = 1`: nominal, forward trim, reverse trim.
    LinuxcncType1,
    /// SINUMERIK `$AA_ENC_COMP` (and `$AN_CEC` cross tables).
    Sinumerik,
    Csv,
    Json,
}

impl TableFormat {
    pub const NAMES: [&'static str; 5] = [
        "linuxcnc-type0",
        "linuxcnc-type1",
        "sinumerik",
        "csv",
        "json",
    ];

    pub fn parse(name: &str) -> Option<TableFormat> {
        match name {
            "linuxcnc-type0" => Some(TableFormat::LinuxcncType0),
            "linuxcnc-type1" => Some(TableFormat::LinuxcncType1),
            "sinumerik" => Some(TableFormat::Sinumerik),
            "csv" => Some(TableFormat::Csv),
            "json" => Some(TableFormat::Json),
            _ => None,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            TableFormat::LinuxcncType0 => "linuxcnc-type0",
            TableFormat::LinuxcncType1 => "linuxcnc-type1",
            TableFormat::Sinumerik => "sinumerik",
            TableFormat::Csv => "csv",
            TableFormat::Json => "json",
        }
    }
}

/// One error function of the results on its axis grid (None where not identifiable).
#[derive(Debug, Clone, PartialEq)]
pub struct Curve {
    pub positions_m: Vec<f64>,
    pub values: Vec<Option<f64>>,
    pub sigma: Vec<Option<f64>>,
    pub unit: String,
}

impl Curve {
    /// Linear interpolation between grid positions, constant beyond the ends (None if the
    /// function is not identified there).
    pub fn at(&self, q_m: f64) -> Option<f64> {
        let values: Option<Vec<f64>> = self.values.iter().copied().collect();
        Some(interpolate(&self.positions_m, &values?, q_m))
    }

    /// RMS of the known sigmas, 0 for none (datum values have sigma 0 and are left out).
    pub fn sigma_rms(&self) -> f64 {
        let s: Vec<f64> = self
            .sigma
            .iter()
            .flatten()
            .copied()
            .filter(|s| *s > 0.0)
            .collect();
        if s.is_empty() {
            0.0
        } else {
            (s.iter().map(|v| v * v).sum::<f64>() / s.len() as f64).sqrt()
        }
    }
}

/// Linear interpolation in a table of increasing `xs`, constant beyond the first and last
/// entry: how every controller here applies its table.
pub fn interpolate(xs: &[f64], ys: &[f64], x: f64) -> f64 {
    let n = xs.len().min(ys.len());
    if n == 0 {
        return 0.0;
    }
    if x <= xs[0] {
        return ys[0];
    }
    if x >= xs[n - 1] {
        return ys[n - 1];
    }
    let i = xs[..n].partition_point(|&v| v <= x).clamp(1, n - 1);
    let (x0, x1, y0, y1) = (xs[i - 1], xs[i], ys[i - 1], ys[i]);
    if x1 <= x0 {
        return y1;
    }
    y0 + (y1 - y0) * (x - x0) / (x1 - x0)
}

/// What a compensation needs from a results file.
#[derive(Debug, Clone)]
pub struct Calibration {
    pub source: PathBuf,
    /// SHA-256 of the results file's bytes: ties the tables to the calibration they came from.
    pub source_sha256: String,
    pub session_id: String,
    pub structure: String,
    /// Per axis x, y, z: on the workpiece branch (left of F)?
    pub workpiece_branch: [bool; 3],
    /// Per axis: grid positions and every error function under its ISO name.
    pub axes: [BTreeMap<String, Curve>; 3],
    pub axis_positions_m: [Vec<f64>; 3],
    /// Squareness EC0Y, EA0Z, EB0Z (None where not identifiable).
    pub squareness_rad: BTreeMap<String, (Option<f64>, Option<f64>)>,
    /// Reversal span B per axis (`solve --effects reversal`), metres; 0 without one.
    pub reversal_m: [f64; 3],
    pub reversal_fitted: bool,
}

#[derive(Deserialize)]
struct ResultsFile {
    #[serde(default)]
    kind: Option<String>,
    #[serde(default)]
    session_id: String,
    geometric_errors: Option<GeometricErrorsJson>,
    #[serde(default)]
    effects: BTreeMap<String, BTreeMap<String, f64>>,
}

#[derive(Deserialize)]
struct GeometricErrorsJson {
    structure: String,
    axes: BTreeMap<String, AxisJson>,
    #[serde(default)]
    squareness: BTreeMap<String, SquarenessJson>,
}

#[derive(Deserialize)]
struct AxisJson {
    positions_m: Vec<f64>,
    errors: BTreeMap<String, ErrorJson>,
}

#[derive(Deserialize)]
struct ErrorJson {
    unit: String,
    values: Vec<Option<f64>>,
    sigma: Vec<Option<f64>>,
}

#[derive(Deserialize)]
struct SquarenessJson {
    value_rad: Option<f64>,
    sigma_rad: Option<f64>,
}

impl Calibration {
    pub fn load(path: &Path) -> Result<Calibration, CompensateError> {
        let text = std::fs::read_to_string(path).map_err(|source| CompensateError::Io {
            file: path.to_path_buf(),
            source,
        })?;
        Calibration::parse(&text, path)
    }

    pub fn parse(text: &str, path: &Path) -> Result<Calibration, CompensateError> {
        let de = &mut serde_json::Deserializer::from_str(text);
        let results: ResultsFile = serde_path_to_error::deserialize(de).map_err(|e| {
            input_error(
                path,
                format!("not a geocal results file at `{}`: {}", e.path(), e.inner()),
            )
        })?;
        let geo = results.geometric_errors.ok_or_else(|| {
            input_error(
                path,
                format!(
                    "no `geometric_errors` in these results (kind {}): a compensation needs \
                     a multilateration calibration whose plan identifies the 21 errors",
                    results.kind.as_deref().unwrap_or("unknown")
                ),
            )
        })?;
        let structure = Structure::parse(&geo.structure)
            .map_err(|e| input_error(path, format!("geometric_errors.structure: {e}")))?;
        let letters: Vec<char> = structure.as_str().chars().collect();
        let f_at = letters.iter().position(|&c| c == 'F').unwrap_or(0);
        let workpiece_branch = ["X", "Y", "Z"].map(|a| {
            letters
                .iter()
                .position(|c| c.to_string() == a)
                .is_some_and(|i| i < f_at)
        });
        let mut axes: [BTreeMap<String, Curve>; 3] = Default::default();
        let mut axis_positions_m: [Vec<f64>; 3] = Default::default();
        for (k, name) in AXES.iter().enumerate() {
            let axis = geo.axes.get(*name).ok_or_else(|| {
                input_error(path, format!("geometric_errors.axes has no axis `{name}`"))
            })?;
            let p = &axis.positions_m;
            if p.is_empty()
                || p.windows(2).any(|w| w[1] <= w[0])
                || p.iter().any(|v| !v.is_finite())
            {
                return Err(input_error(
                    path,
                    format!(
                        "geometric_errors.axes.{name}.positions_m: expected finite, strictly \
                         increasing positions"
                    ),
                ));
            }
            for (iso, e) in &axis.errors {
                if e.values.len() != p.len() || e.sigma.len() != p.len() {
                    return Err(input_error(
                        path,
                        format!(
                            "geometric_errors.axes.{name}.errors.{iso}: {} values and {} sigmas \
                             for {} positions",
                            e.values.len(),
                            e.sigma.len(),
                            p.len()
                        ),
                    ));
                }
                axes[k].insert(
                    iso.clone(),
                    Curve {
                        positions_m: p.clone(),
                        values: e.values.clone(),
                        sigma: e.sigma.clone(),
                        unit: e.unit.clone(),
                    },
                );
            }
            if !axes[k].contains_key(POSITIONING[k]) {
                return Err(input_error(
                    path,
                    format!(
                        "geometric_errors.axes.{name}.errors has no {}",
                        POSITIONING[k]
                    ),
                ));
            }
            axis_positions_m[k] = p.clone();
        }
        let squareness_rad = geo
            .squareness
            .iter()
            .map(|(k, s)| (k.clone(), (s.value_rad, s.sigma_rad)))
            .collect();
        let (reversal_m, reversal_fitted) = match results.effects.get("reversal") {
            Some(r) => {
                let mut b = [0.0; 3];
                for (k, key) in ["bx_m", "by_m", "bz_m"].iter().enumerate() {
                    b[k] = *r.get(*key).ok_or_else(|| {
                        input_error(path, format!("effects.reversal has no `{key}`"))
                    })?;
                }
                (b, true)
            }
            None => ([0.0; 3], false),
        };
        Ok(Calibration {
            source: path.to_path_buf(),
            source_sha256: source::sha256_hex(text.as_bytes()),
            session_id: results.session_id,
            structure: structure.as_str().to_string(),
            workpiece_branch,
            axes,
            axis_positions_m,
            squareness_rad,
            reversal_m,
            reversal_fitted,
        })
    }

    /// +1 for a tool-branch axis, −1 for a workpiece-branch axis: the factor from the
    /// carriage's own error to the tool-to-workpiece deviation.
    pub fn branch_sign(&self, axis: usize) -> f64 {
        if self.workpiece_branch[axis] {
            -1.0
        } else {
            1.0
        }
    }

    /// The tool-to-workpiece positioning deviation d(q) of `axis` on its grid (metres):
    /// the carriage reaches q + d(q) when commanded to q (approach-independent part).
    pub fn positioning(&self, axis: usize) -> Result<Curve, CompensateError> {
        let curve = &self.axes[axis][POSITIONING[axis]];
        if curve.values.iter().any(Option::is_none) {
            return Err(input_error(
                &self.source,
                format!(
                    "{} is not identifiable in these results: no table can be made for axis {}",
                    POSITIONING[axis], AXES[axis]
                ),
            ));
        }
        let s = self.branch_sign(axis);
        Ok(Curve {
            values: curve.values.iter().map(|v| v.map(|v| s * v)).collect(),
            ..curve.clone()
        })
    }

    /// The tool-to-workpiece deviation along `comp` while `base` moves (straightness of the
    /// base axis, branch-signed, plus the squareness between the two), metres on the base
    /// axis's grid; None when a part of it is not identifiable. Its σ combines the
    /// straightness's and the squareness's as if independent (the results hold no covariance
    /// between them).
    pub fn cross(&self, base: usize, comp: usize) -> Option<Curve> {
        let iso = format!(
            "E{}{}",
            AXES[comp].to_uppercase(),
            AXES[base].to_uppercase()
        );
        let curve = self.axes[base].get(&iso)?;
        let s = self.branch_sign(base);
        // Squareness (docs/kinematics.md): moving +y by L shifts x by −EC0Y·L, moving +z by
        // L shifts y by −EA0Z·L and x by +EB0Z·L; it acts alike on both branches.
        let squareness = |name: &str, sign: f64| {
            let (value, sigma) = self.squareness_rad.get(name)?;
            Some((sign * (*value)?, sigma.unwrap_or(0.0)))
        };
        let (slope, slope_sigma) = match (base, comp) {
            (1, 0) => squareness("EC0Y", -1.0)?,
            (2, 1) => squareness("EA0Z", -1.0)?,
            (2, 0) => squareness("EB0Z", 1.0)?,
            _ => (0.0, 0.0),
        };
        let q0 = curve.positions_m[0];
        let values = curve
            .values
            .iter()
            .zip(&curve.positions_m)
            .map(|(v, q)| v.map(|v| s * v + slope * (q - q0)))
            .collect::<Vec<_>>();
        if values.iter().any(Option::is_none) {
            return None;
        }
        let sigma = curve
            .sigma
            .iter()
            .zip(&curve.positions_m)
            .map(|(sg, q)| sg.map(|sg| sg.hypot(slope_sigma * (q - q0))))
            .collect();
        Some(Curve {
            values,
            sigma,
            ..curve.clone()
        })
    }
}

/// Equally spaced table nominals over `[lo, hi]` with spacing `step_m` (the last entry at or
/// just beyond `hi`, so the table covers the calibrated travel).
pub fn table_positions(lo: f64, hi: f64, step_m: f64) -> Result<Vec<f64>, CompensateError> {
    if !(step_m.is_finite() && step_m > 0.0) {
        return Err(CompensateError::Limit(format!(
            "table step {step_m} m: expected a positive number of metres"
        )));
    }
    let intervals = ((hi - lo) / step_m - 1e-9).ceil().max(1.0);
    if intervals > 1e6 {
        return Err(CompensateError::Limit(format!(
            "table step {step_m} m gives {intervals} intervals over {lo}..{hi} m"
        )));
    }
    Ok((0..=intervals as usize)
        .map(|i| lo + i as f64 * step_m)
        .collect())
}

/// The default step: the grid spacing divided by the largest whole number that keeps the
/// table within `max_entries` (so table nodes fall on the calibrated grid when it is
/// uniform), else the span over `max_entries − 1`.
pub fn default_step_m(grid_m: &[f64], max_entries: usize) -> f64 {
    let lo = grid_m.first().copied().unwrap_or(0.0);
    let hi = grid_m.last().copied().unwrap_or(1.0);
    let span = (hi - lo).max(1e-6);
    let intervals = grid_m.len().saturating_sub(1).max(1);
    let spacing = span / intervals as f64;
    let uniform = grid_m
        .windows(2)
        .all(|w| ((w[1] - w[0]) - spacing).abs() < 1e-9);
    let max_intervals = max_entries.saturating_sub(1).max(1);
    if uniform && intervals <= max_intervals {
        spacing / (max_intervals / intervals) as f64
    } else {
        span / max_intervals as f64
    }
}

/// How far a table of `nodes` (sampled from `curve`) departs from the fitted curve between
/// its nodes, over the calibrated travel: the interpolation error of the chosen step.
pub fn interpolation_error(curve: &Curve, nodes_m: &[f64], node_values: &[f64]) -> f64 {
    let Some(first) = curve.positions_m.first() else {
        return 0.0;
    };
    let last = *curve.positions_m.last().unwrap_or(first);
    let mut worst: f64 = 0.0;
    let mut check = |q: f64| {
        if let Some(fitted) = curve.at(q) {
            worst = worst.max((interpolate(nodes_m, node_values, q) - fitted).abs());
        }
    };
    // The fitted curve is linear between its grid positions: its kinks and the table's are
    // where the largest departures lie, sampled finely between them.
    let mut knots: Vec<f64> = curve.positions_m.clone();
    knots.extend(
        nodes_m
            .iter()
            .copied()
            .filter(|q| *q >= *first && *q <= last),
    );
    knots.sort_by(f64::total_cmp);
    for w in knots.windows(2) {
        for i in 0..=8 {
            check(w[0] + (w[1] - w[0]) * i as f64 / 8.0);
        }
    }
    worst
}

/// The statement every table carries about its step, and the warning when the step is
/// coarser than the calibration can see.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct StepReport {
    pub axis: String,
    pub step_m: f64,
    pub entries: usize,
    pub interpolation_error_m: f64,
    /// RMS σ of the fitted curve (datum values left out).
    pub sigma_m: f64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub warning: Option<String>,
}

impl StepReport {
    pub fn new(axis: usize, step_m: f64, entries: usize, interp_m: f64, sigma_m: f64) -> Self {
        let warning = (interp_m > sigma_m).then(|| {
            format!(
                "axis {}: the interpolation error of the {:.3} mm step ({:.3} µm) exceeds the \
                 calibration's σ ({:.3} µm): choose a smaller step",
                AXES[axis],
                step_m * 1e3,
                interp_m * 1e6,
                sigma_m * 1e6
            )
        });
        StepReport {
            axis: AXES[axis].to_string(),
            step_m,
            entries,
            interpolation_error_m: interp_m,
            sigma_m,
            warning,
        }
    }
}

/// Options common to the exporters.
#[derive(Debug, Clone)]
pub struct ExportOptions {
    /// Table step, metres; None: `default_step_m`.
    pub step_m: Option<f64>,
    /// Axes to export (indices into x, y, z).
    pub axes: Vec<usize>,
    /// Where each table is zero, per axis (metres); None: the first grid position (the
    /// calibration's datum, where the fitted curve is zero anyway).
    pub reference_m: [Option<f64>; 3],
}

impl Default for ExportOptions {
    fn default() -> Self {
        ExportOptions {
            step_m: None,
            axes: vec![0, 1, 2],
            reference_m: [None; 3],
        }
    }
}

/// A file an exporter produced.
#[derive(Debug, Clone)]
pub struct OutputFile {
    pub name: String,
    pub text: String,
}

/// What an export wrote and what it found about its steps.
#[derive(Debug, Clone)]
pub struct Export {
    pub files: Vec<OutputFile>,
    pub steps: Vec<StepReport>,
}

impl Export {
    pub fn warnings(&self) -> impl Iterator<Item = &str> {
        self.steps.iter().filter_map(|s| s.warning.as_deref())
    }
}

/// The sampled curve of one axis: nominals, values, and the step statement.
pub(crate) struct Sampled {
    pub nominals_m: Vec<f64>,
    pub values_m: Vec<f64>,
    pub report: StepReport,
    pub reference_m: f64,
}

/// Sample `curve` (the positioning deviation of `axis`) at the table nodes, shifted so that
/// it is zero at the reference point.
pub(crate) fn sample(
    curve: &Curve,
    axis: usize,
    options: &ExportOptions,
    max_entries: usize,
) -> Result<Sampled, CompensateError> {
    let grid = &curve.positions_m;
    let lo = grid[0];
    let hi = *grid.last().unwrap_or(&lo);
    let step_m = options
        .step_m
        .unwrap_or_else(|| default_step_m(grid, max_entries));
    let nominals_m = table_positions(lo, hi, step_m)?;
    if nominals_m.len() > max_entries {
        return Err(CompensateError::Limit(format!(
            "axis {}: a {:.4} mm step over {:.1}..{:.1} mm gives {} entries, more than the \
             controller's {} (choose a step of at least {:.4} mm)",
            AXES[axis],
            step_m * 1e3,
            lo * 1e3,
            hi * 1e3,
            nominals_m.len(),
            max_entries,
            (hi - lo) / (max_entries.saturating_sub(1).max(1)) as f64 * 1e3
        )));
    }
    let reference_m = options.reference_m[axis].unwrap_or(lo);
    let zero = curve.at(reference_m).unwrap_or(0.0);
    let values_m: Vec<f64> = nominals_m
        .iter()
        .map(|&q| curve.at(q).unwrap_or(0.0) - zero)
        .collect();
    let shifted = Curve {
        values: curve.values.iter().map(|v| v.map(|v| v - zero)).collect(),
        ..curve.clone()
    };
    let interp = interpolation_error(&shifted, &nominals_m, &values_m);
    let report = StepReport::new(axis, step_m, nominals_m.len(), interp, curve.sigma_rms());
    Ok(Sampled {
        nominals_m,
        values_m,
        report,
        reference_m,
    })
}

/// Write `calibration` in `format`: the files (names relative to the output directory, or
/// the one file of a single-file format) and the step statements.
pub fn export(
    calibration: &Calibration,
    format: TableFormat,
    options: &ExportOptions,
    sinumerik: &sinumerik::SinumerikOptions,
) -> Result<Export, CompensateError> {
    match format {
        TableFormat::LinuxcncType0 => {
            linuxcnc::export(calibration, linuxcnc::CompType::Type0, options)
        }
        TableFormat::LinuxcncType1 => {
            linuxcnc::export(calibration, linuxcnc::CompType::Type1, options)
        }
        TableFormat::Sinumerik => sinumerik::export(calibration, options, sinumerik),
        TableFormat::Csv => table::export_csv(calibration, options),
        TableFormat::Json => table::export_json(calibration, options),
    }
}

/// Header lines common to every format (without comment markers).
pub(crate) fn common_header(calibration: &Calibration, format: TableFormat) -> Vec<String> {
    let branch: Vec<String> = AXES
        .iter()
        .enumerate()
        .map(|(k, a)| {
            format!(
                "{a}: {}",
                if calibration.workpiece_branch[k] {
                    "workpiece branch (sign of the carriage error flipped)"
                } else {
                    "tool branch"
                }
            )
        })
        .collect();
    vec![
        format!(
            "geocal compensation, format {}, from {}",
            format.name(),
            calibration.source.display()
        ),
        format!("source results SHA-256: {}", calibration.source_sha256),
        format!(
            "source session: {}; structure {}; {}",
            calibration.session_id,
            calibration.structure,
            branch.join(", ")
        ),
        if calibration.reversal_fitted {
            format!(
                "reversal B (solve --effects reversal): x {:.3} µm, y {:.3} µm, z {:.3} µm",
                calibration.reversal_m[0] * 1e6,
                calibration.reversal_m[1] * 1e6,
                calibration.reversal_m[2] * 1e6
            )
        } else {
            "no reversal fitted: forward and reverse values are equal".to_string()
        },
    ]
}

/// A table loaded for the simulator: the correction one controller applies to one axis.
#[derive(Debug, Clone)]
pub enum AppliedTable {
    LinuxCnc(linuxcnc::CompTable),
    Sinumerik(sinumerik::EncCompTable),
}

impl AppliedTable {
    /// The joint position the controller drives to when commanded to `q_m`, with the last
    /// move along this axis in direction `approach` (+1, −1, or 0 before any move).
    pub fn joint_position_m(&self, q_m: f64, approach: f64) -> f64 {
        match self {
            AppliedTable::LinuxCnc(t) => q_m + t.trim_m(q_m, approach),
            AppliedTable::Sinumerik(t) => t.servo_position_m(q_m),
        }
    }
}

/// Load a table for axis `axis` the way its controller reads it.
pub fn load_table(
    format: TableFormat,
    file: &Path,
    controller_axis: &str,
) -> Result<AppliedTable, CompensateError> {
    let text = std::fs::read_to_string(file).map_err(|source| CompensateError::Io {
        file: file.to_path_buf(),
        source,
    })?;
    match format {
        TableFormat::LinuxcncType0 => Ok(AppliedTable::LinuxCnc(linuxcnc::CompTable::parse(
            &text,
            linuxcnc::CompType::Type0,
            file,
        )?)),
        TableFormat::LinuxcncType1 => Ok(AppliedTable::LinuxCnc(linuxcnc::CompTable::parse(
            &text,
            linuxcnc::CompType::Type1,
            file,
        )?)),
        TableFormat::Sinumerik => {
            let program = sinumerik::Program::parse(&text, file)?;
            Ok(AppliedTable::Sinumerik(program.enc_comp(
                0,
                controller_axis,
                file,
            )?))
        }
        TableFormat::Csv | TableFormat::Json => Err(input_error(
            file,
            format!(
                "format {} is a plain table, not a controller's: the simulator applies \
                 linuxcnc-type0, linuxcnc-type1 or sinumerik",
                format.name()
            ),
        )),
    }
}
