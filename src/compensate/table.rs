//! The 21 errors on a chosen grid as plain CSV and JSON, for controllers without a format
//! here, and their readers.

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::{
    common_header, default_step_m, input_error, interpolate, table_positions, Calibration,
    CompensateError, Curve, Export, ExportOptions, OutputFile, StepReport, TableFormat, AXES,
};

pub const CSV_FILE: &str = "errors.csv";
pub const JSON_FILE: &str = "errors.json";
pub const JSON_FORMAT: &str = "geocal-compensation-table/1";
/// Entries per axis when no step is given.
const DEFAULT_ENTRIES: usize = 256;

/// One value of one error: an axis function at a position, or a squareness (no axis).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Row {
    pub error: String,
    pub axis: Option<String>,
    pub position_m: Option<f64>,
    /// None where the calibration cannot identify the error.
    pub value: Option<f64>,
    /// "m" or "rad".
    pub unit: String,
    pub sigma: Option<f64>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JsonTable {
    pub format: String,
    pub notes: Vec<String>,
    pub steps: Vec<StepReportJson>,
    pub rows: Vec<Row>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StepReportJson {
    pub axis: String,
    pub step_m: f64,
    pub entries: usize,
    pub interpolation_error_m: f64,
    pub sigma_m: f64,
}

fn sampled_at(curve: &Curve, q: f64) -> (Option<f64>, Option<f64>) {
    let sigma: Option<Vec<f64>> = curve.sigma.iter().copied().collect();
    (
        curve.at(q),
        sigma.map(|s| interpolate(&curve.positions_m, &s, q)),
    )
}

/// The rows and step statements of the chosen grid. The values are the results' own (the
/// carriage's errors under their ISO names, docs/kinematics.md): no branch sign applied.
fn rows(
    calibration: &Calibration,
    options: &ExportOptions,
) -> Result<(Vec<Row>, Vec<StepReport>), CompensateError> {
    let mut rows = Vec::new();
    let mut steps = Vec::new();
    for &axis in &options.axes {
        let grid = &calibration.axis_positions_m[axis];
        let (lo, hi) = (grid[0], *grid.last().unwrap_or(&grid[0]));
        let step_m = options
            .step_m
            .unwrap_or_else(|| default_step_m(grid, DEFAULT_ENTRIES));
        let nodes = table_positions(lo, hi, step_m)?;
        let mut worst: f64 = 0.0;
        let mut sigma: f64 = 0.0;
        for (iso, curve) in &calibration.axes[axis] {
            for &q in &nodes {
                let (value, s) = sampled_at(curve, q);
                rows.push(Row {
                    error: iso.clone(),
                    axis: Some(AXES[axis].to_string()),
                    position_m: Some(q),
                    value,
                    unit: curve.unit.clone(),
                    sigma: s,
                });
            }
            if curve.unit == "m" && curve.values.iter().all(Option::is_some) {
                let values: Vec<f64> = nodes.iter().map(|&q| curve.at(q).unwrap_or(0.0)).collect();
                worst = worst.max(super::interpolation_error(curve, &nodes, &values));
                sigma = sigma.max(curve.sigma_rms());
            }
        }
        steps.push(StepReport::new(axis, step_m, nodes.len(), worst, sigma));
    }
    for (iso, (value, sigma)) in &calibration.squareness_rad {
        rows.push(Row {
            error: iso.clone(),
            axis: None,
            position_m: None,
            value: *value,
            unit: "rad".into(),
            sigma: *sigma,
        });
    }
    Ok((rows, steps))
}

fn notes(calibration: &Calibration, format: TableFormat, steps: &[StepReport]) -> Vec<String> {
    let mut out = common_header(calibration, format);
    out.push(
        "values are the carriage's own errors (results' ISO names and signs, docs/kinematics.md): \
         on the workpiece branch the tool-to-workpiece deviation is minus these; SI units (m, rad); \
         empty value = not identifiable; sigma linearly interpolated"
            .into(),
    );
    for s in steps {
        out.push(format!(
            "axis {}: step {} m, {} positions, interpolation error of the linear errors {:.3e} m \
             (calibration sigma {:.3e} m){}",
            s.axis,
            s.step_m,
            s.entries,
            s.interpolation_error_m,
            s.sigma_m,
            if s.warning.is_some() {
                " WARNING: coarser than sigma"
            } else {
                ""
            }
        ));
    }
    out
}

fn opt(v: Option<f64>) -> String {
    v.map(|v| format!("{v:e}")).unwrap_or_default()
}

pub fn export_csv(
    calibration: &Calibration,
    options: &ExportOptions,
) -> Result<Export, CompensateError> {
    let (rows, steps) = rows(calibration, options)?;
    let mut text: String = notes(calibration, TableFormat::Csv, &steps)
        .iter()
        .map(|l| format!("# {l}\n"))
        .collect();
    text.push_str("error,axis,position_m,value,unit,sigma\n");
    for r in &rows {
        text.push_str(&format!(
            "{},{},{},{},{},{}\n",
            r.error,
            r.axis.as_deref().unwrap_or(""),
            opt(r.position_m),
            opt(r.value),
            r.unit,
            opt(r.sigma)
        ));
    }
    Ok(Export {
        files: vec![OutputFile {
            name: CSV_FILE.into(),
            text,
        }],
        steps,
    })
}

pub fn export_json(
    calibration: &Calibration,
    options: &ExportOptions,
) -> Result<Export, CompensateError> {
    let (rows, steps) = rows(calibration, options)?;
    let table = JsonTable {
        format: JSON_FORMAT.into(),
        notes: notes(calibration, TableFormat::Json, &steps),
        steps: steps
            .iter()
            .map(|s| StepReportJson {
                axis: s.axis.clone(),
                step_m: s.step_m,
                entries: s.entries,
                interpolation_error_m: s.interpolation_error_m,
                sigma_m: s.sigma_m,
            })
            .collect(),
        rows,
    };
    let text = serde_json::to_string_pretty(&table)
        .map_err(|e| CompensateError::Limit(format!("JSON: {e}")))?;
    Ok(Export {
        files: vec![OutputFile {
            name: JSON_FILE.into(),
            text: text + "\n",
        }],
        steps,
    })
}

/// Read a CSV table: `#` lines, the header line, then rows of six fields.
pub fn parse_csv(text: &str, file: &Path) -> Result<Vec<Row>, CompensateError> {
    let mut out = Vec::new();
    let mut header_seen = false;
    for (n, line) in text.lines().enumerate() {
        let err = |message: String| CompensateError::Line {
            file: file.to_path_buf(),
            line: n + 1,
            message,
        };
        if line.starts_with('#') || line.trim().is_empty() {
            continue;
        }
        if !header_seen {
            if line.trim() != "error,axis,position_m,value,unit,sigma" {
                return Err(err(
                    "expected the header `error,axis,position_m,value,unit,sigma`".to_string(),
                ));
            }
            header_seen = true;
            continue;
        }
        let f: Vec<&str> = line.split(',').collect();
        if f.len() != 6 {
            return Err(err(format!("expected 6 fields, found {}", f.len())));
        }
        let num = |s: &str, what: &str| -> Result<Option<f64>, CompensateError> {
            if s.is_empty() {
                return Ok(None);
            }
            s.parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .map(Some)
                .ok_or_else(|| err(format!("{what} is not a finite number")))
        };
        if f[0].is_empty() || !(f[4] == "m" || f[4] == "rad") {
            return Err(err("expected an error name and the unit m or rad".into()));
        }
        out.push(Row {
            error: f[0].to_string(),
            axis: (!f[1].is_empty()).then(|| f[1].to_string()),
            position_m: num(f[2], "position_m")?,
            value: num(f[3], "value")?,
            unit: f[4].to_string(),
            sigma: num(f[5], "sigma")?,
        });
    }
    if !header_seen {
        return Err(input_error(file, "no header line: not a geocal CSV table"));
    }
    Ok(out)
}

pub fn parse_json(text: &str, file: &Path) -> Result<JsonTable, CompensateError> {
    let de = &mut serde_json::Deserializer::from_str(text);
    let table: JsonTable = serde_path_to_error::deserialize(de)
        .map_err(|e| input_error(file, format!("at `{}`: {}", e.path(), e.inner())))?;
    if table.format != JSON_FORMAT {
        return Err(input_error(
            file,
            format!("format `{}`, expected `{JSON_FORMAT}`", table.format),
        ));
    }
    Ok(table)
}
