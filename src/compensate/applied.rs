//! What a verification run applies: the SINUMERIK `$AN_CEC` cross tables mapped onto the
//! machine's axes, and the record of every table loaded (in the tool-to-workpiece sign) that
//! the session header keeps, so that a report needs neither the table files nor the formats.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::sinumerik::{CecTable, Program};
use super::source::{sha256_hex, Source};
use super::{
    input_error, interpolate, load_table, AppliedTable, CompensateError, TableFormat, AXES,
};

/// A `$AN_CEC` table acting between two machine axes (indices into x, y, z).
#[derive(Debug, Clone, PartialEq)]
pub struct CrossTable {
    pub index: usize,
    pub base: usize,
    pub compensated: usize,
    pub table: CecTable,
}

/// The machine axis (0, 1, 2) a controller's axis name stands for.
fn machine_axis(name: &str, axis_names: &[String; 3]) -> Option<usize> {
    axis_names.iter().position(|n| n == name)
}

/// Every `$AN_CEC` table of a SINUMERIK program, its base and compensation axes taken from
/// `$AN_CEC_INPUT_AXIS` / `$AN_CEC_OUTPUT_AXIS` and named by `axis_names` (x, y, z).
pub fn load_cross_tables(
    file: &Path,
    axis_names: &[String; 3],
) -> Result<Vec<CrossTable>, CompensateError> {
    let text = std::fs::read_to_string(file).map_err(|source| CompensateError::Io {
        file: file.to_path_buf(),
        source,
    })?;
    let tables = Program::parse(&text, file)?.cec_tables(file)?;
    if tables.is_empty() {
        return Err(input_error(
            file,
            "no $AN_CEC table: an entry without `axis` applies the file's cross tables (name \
             the `axis` of a $AA_ENC_COMP table)",
        ));
    }
    tables
        .into_iter()
        .enumerate()
        .map(|(index, table)| {
            let axis = |name: &str, what: &str| {
                machine_axis(name, axis_names).ok_or_else(|| {
                    input_error(
                        file,
                        format!(
                            "$AN_CEC[{index}]: {what} `{name}` is none of the machine's axes {} \
                             (x, y, z; set `axis_names`)",
                            axis_names.join(", ")
                        ),
                    )
                })
            };
            Ok(CrossTable {
                index,
                base: axis(&table.input_axis, "input axis")?,
                compensated: axis(&table.output_axis, "output axis")?,
                table,
            })
        })
        .collect()
}

/// One table as the controller loaded it: what it removes from the compensated axis's
/// tool-to-workpiece deviation as the base axis moves (metres; the sign of each format undone).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TableRecord {
    pub name: String,
    pub base_axis: String,
    pub compensated_axis: String,
    pub positions_m: Vec<f64>,
    /// The deviation the table removes at each position: −trim for LinuxCNC (the mean of the
    /// forward and reverse columns), the value for SINUMERIK.
    pub deviation_m: Vec<f64>,
    /// Half the difference of LinuxCNC's reverse and forward trims (the reversal B/2), when
    /// the columns differ.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub half_reversal_m: Option<Vec<f64>>,
    /// `$AN_CEC_DIRECTION` (0: both directions of the base axis).
    #[serde(default)]
    pub direction: i32,
}

impl TableRecord {
    pub fn base(&self) -> Option<usize> {
        AXES.iter().position(|a| *a == self.base_axis)
    }

    pub fn compensated(&self) -> Option<usize> {
        AXES.iter().position(|a| *a == self.compensated_axis)
    }

    /// The deviation removed at base position `q_m`, as the controller interpolates it.
    pub fn deviation_at(&self, q_m: f64) -> f64 {
        interpolate(&self.positions_m, &self.deviation_m, q_m)
    }

    /// The step between positions when equally spaced (every format here but LinuxCNC's may
    /// differ), else None.
    pub fn step_m(&self) -> Option<f64> {
        let p = &self.positions_m;
        let step = (p.last()? - p.first()?) / (p.len().checked_sub(1)?.max(1)) as f64;
        p.windows(2)
            .all(|w| ((w[1] - w[0]) - step).abs() <= 1e-9 + 1e-6 * step.abs())
            .then_some(step)
    }
}

/// One `[sim] compensation` entry as applied: the file, its SHA-256, the sidecar that names
/// the results it was made from, and its tables.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AppliedFile {
    pub format: String,
    pub file: PathBuf,
    pub file_sha256: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub source: Option<Source>,
    /// Why the sidecar beside the file could not be read, when there is one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub source_error: Option<String>,
    pub tables: Vec<TableRecord>,
}

/// Which tables of `file` an entry applies: one axis's own table, or the cross tables.
pub enum Selection<'a> {
    Axis {
        axis: usize,
        controller_axis: &'a str,
    },
    Cross {
        axis_names: &'a [String; 3],
    },
}

/// Load `file` as its controller reads it and record what it applies.
pub fn describe(
    format: TableFormat,
    file: &Path,
    selection: Selection<'_>,
) -> Result<AppliedFile, CompensateError> {
    let bytes = std::fs::read(file).map_err(|source| CompensateError::Io {
        file: file.to_path_buf(),
        source,
    })?;
    let tables = match selection {
        Selection::Axis {
            axis,
            controller_axis,
        } => vec![axis_record(
            &load_table(format, file, controller_axis)?,
            axis,
            file,
            controller_axis,
        )],
        Selection::Cross { axis_names } => load_cross_tables(file, axis_names)?
            .iter()
            .map(|c| cross_record(c, axis_names))
            .collect(),
    };
    let (source, source_error) = match Source::beside(file) {
        Some(Ok(s)) => (Some(s), None),
        Some(Err(e)) => (None, Some(e.to_string())),
        None => (None, None),
    };
    Ok(AppliedFile {
        format: format.name().into(),
        file: file.to_path_buf(),
        file_sha256: sha256_hex(&bytes),
        source,
        source_error,
        tables,
    })
}

fn axis_record(
    table: &AppliedTable,
    axis: usize,
    file: &Path,
    controller_axis: &str,
) -> TableRecord {
    let name = |what: String| TableRecord {
        name: what,
        base_axis: AXES[axis].into(),
        compensated_axis: AXES[axis].into(),
        positions_m: Vec::new(),
        deviation_m: Vec::new(),
        half_reversal_m: None,
        direction: 0,
    };
    match table {
        AppliedTable::LinuxCnc(t) => {
            let file_name = file
                .file_name()
                .map(|f| f.to_string_lossy().into_owned())
                .unwrap_or_default();
            let mut r = name(format!("{file_name} (joint {axis})"));
            r.positions_m = t
                .entries
                .iter()
                .map(|e| e.nominal / t.units_per_m)
                .collect();
            r.deviation_m = t
                .entries
                .iter()
                .map(|e| -(f64::from(e.fwd_trim) + f64::from(e.rev_trim)) / 2.0 / t.units_per_m)
                .collect();
            if t.entries.iter().any(|e| e.fwd_trim != e.rev_trim) {
                r.half_reversal_m = Some(
                    t.entries
                        .iter()
                        .map(|e| {
                            (f64::from(e.rev_trim) - f64::from(e.fwd_trim)) / 2.0 / t.units_per_m
                        })
                        .collect(),
                );
            }
            r
        }
        AppliedTable::Sinumerik(t) => {
            let mut r = name(format!("$AA_ENC_COMP[0,…,{controller_axis}]"));
            r.positions_m = (0..t.values_mm.len())
                .map(|n| (t.min_mm + n as f64 * t.step_mm) * 1e-3)
                .collect();
            r.deviation_m = t.values_mm.iter().map(|v| v * 1e-3).collect();
            r
        }
    }
}

fn cross_record(c: &CrossTable, axis_names: &[String; 3]) -> TableRecord {
    let t = &c.table;
    TableRecord {
        name: format!(
            "$AN_CEC[{}]: {} on {}",
            c.index, axis_names[c.compensated], axis_names[c.base]
        ),
        base_axis: AXES[c.base].into(),
        compensated_axis: AXES[c.compensated].into(),
        positions_m: (0..t.values_mm.len())
            .map(|n| (t.min_mm + n as f64 * t.step_mm) * 1e-3)
            .collect(),
        deviation_m: t.values_mm.iter().map(|v| v * 1e-3).collect(),
        half_reversal_m: None,
        direction: t.direction,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const CEC: &str = "%_N_NC_CEC_INI\nCHANDATA(1)\n\
        $AN_CEC[0,0]=0.0\n$AN_CEC[0,1]=0.002\n$AN_CEC[0,2]=-0.004\n\
        $AN_CEC_INPUT_AXIS[0]=(X1)\n$AN_CEC_OUTPUT_AXIS[0]=(Y1)\n\
        $AN_CEC_STEP[0]=500.0\n$AN_CEC_MIN[0]=100.0\n$AN_CEC_MAX[0]=1100.0\n\
        $AN_CEC_DIRECTION[0]=0\n$AN_CEC_MULT_BY_TABLE[0]=0\n$AN_CEC_IS_MODULO[0]=0\nM17\n";

    fn names() -> [String; 3] {
        ["X1", "Y1", "Z1"].map(String::from)
    }

    #[test]
    fn cross_tables_map_onto_the_axes_and_keep_their_end_values() {
        let dir = tempfile::tempdir().expect("tempdir");
        let file = dir.path().join("cec.ini");
        std::fs::write(&file, CEC).expect("write");
        let t = load_cross_tables(&file, &names()).expect("tables");
        assert_eq!((t[0].base, t[0].compensated), (0, 1));
        let c = &t[0].table;
        assert!((c.value_m(0.35) - 1e-6).abs() < 1e-15);
        assert!(
            (c.value_m(0.0) - 0.0).abs() < 1e-15,
            "first value before MIN"
        );
        assert!(
            (c.value_m(2.0) + 4e-6).abs() < 1e-15,
            "last value beyond MAX"
        );
        assert!(c.acts(0.0) && c.acts(-1.0));
        let record = describe(
            TableFormat::Sinumerik,
            &file,
            Selection::Cross {
                axis_names: &names(),
            },
        )
        .expect("record");
        assert_eq!(record.tables[0].positions_m, vec![0.1, 0.6, 1.1]);
        assert!(record.source.is_none() && record.source_error.is_none());
    }

    #[test]
    fn bad_cross_tables_name_the_table_and_axis() {
        let dir = tempfile::tempdir().expect("tempdir");
        let file = dir.path().join("cec.ini");
        for (text, expect) in [
            (CEC.replace("(Y1)", "(U1)"), "output axis `U1`"),
            (
                CEC.replace("DIRECTION[0]=0", "DIRECTION[0]=2"),
                "$AN_CEC_DIRECTION 2",
            ),
            (
                CEC.replace("MULT_BY_TABLE[0]=0", "MULT_BY_TABLE[0]=1"),
                "multiplication",
            ),
            ("%_N_NC_CEC_INI\nM17\n".to_string(), "no $AN_CEC table"),
        ] {
            std::fs::write(&file, &text).expect("write");
            let e = load_cross_tables(&file, &names()).unwrap_err().to_string();
            assert!(e.contains("cec.ini") && e.contains(expect), "{e}");
        }
    }

    #[test]
    fn a_linuxcnc_record_holds_minus_the_mean_trim_and_half_the_reversal() {
        let dir = tempfile::tempdir().expect("tempdir");
        let file = dir.path().join("comp-x.txt");
        // Type 1 trims in mm: forward −0.011, reverse −0.009 at 100 mm.
        std::fs::write(&file, "0 0 0\n100 -0.011 -0.009\n").expect("write");
        let r = describe(
            TableFormat::LinuxcncType1,
            &file,
            Selection::Axis {
                axis: 0,
                controller_axis: "X1",
            },
        )
        .expect("record");
        let t = &r.tables[0];
        assert_eq!((t.base(), t.compensated()), (Some(0), Some(0)));
        assert!(
            (t.deviation_at(0.1) - 10e-6).abs() < 1e-12,
            "{:?}",
            t.deviation_m
        );
        let half = t.half_reversal_m.as_ref().expect("columns differ");
        assert!((half[1] - 1e-6).abs() < 1e-12, "{half:?}");
        assert_eq!(t.step_m(), Some(0.1));
    }

    #[test]
    fn a_direction_dependent_table_acts_in_its_direction_only() {
        let t = CecTable {
            values_mm: vec![0.0, 1.0],
            step_mm: 1.0,
            max_mm: 1.0,
            direction: -1,
            ..Default::default()
        };
        assert!(t.acts(-1.0) && !t.acts(1.0) && !t.acts(0.0));
    }
}
