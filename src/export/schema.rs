//! The export's tables: every column's name, type, unit and meaning (docs/fleet.md), and the
//! schema version that every file carries. Names are stable: a change adds columns, never
//! renames or retypes one, and a breaking change raises `SCHEMA_VERSION`.

use std::collections::HashMap;
use std::sync::Arc;

use arrow_schema::{DataType, Field, Schema, TimeUnit};

/// The version of the export's schema: in every file's key-value metadata
/// (`geocal.schema_version`) and in the `runs` table's `schema_version` column.
pub const SCHEMA_VERSION: i32 = 2;

/// File metadata keys.
pub const META_SCHEMA_VERSION: &str = "geocal.schema_version";
pub const META_TABLE: &str = "geocal.table";

/// The partition column: every table's files lie in `machine_key=<key>` folders (the machine's
/// key, docs/fleet.md "One machine"); a reader of the table gets it as a string column.
pub const MACHINE_KEY: &str = "machine_key";

/// A column's type.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ColumnType {
    Int32,
    Int64,
    Float64,
    Bool,
    Utf8,
    /// A list of strings.
    Utf8List,
    /// UTC timestamp, microseconds.
    TimestampUs,
    /// A calendar date (days since the Unix epoch).
    Date,
}

impl ColumnType {
    fn data_type(self) -> DataType {
        match self {
            ColumnType::Int32 => DataType::Int32,
            ColumnType::Int64 => DataType::Int64,
            ColumnType::Float64 => DataType::Float64,
            ColumnType::Bool => DataType::Boolean,
            ColumnType::Utf8 => DataType::Utf8,
            ColumnType::Utf8List => {
                DataType::List(Arc::new(Field::new("item", DataType::Utf8, true)))
            }
            ColumnType::TimestampUs => {
                DataType::Timestamp(TimeUnit::Microsecond, Some("UTC".into()))
            }
            ColumnType::Date => DataType::Date32,
        }
    }
}

/// One column: its stable name, type, whether it may be null, its SI unit ("" when it has
/// none, "row" when the row's `unit` column says) and what it holds.
#[derive(Debug, Clone, Copy)]
pub struct Column {
    pub name: &'static str,
    pub kind: ColumnType,
    pub nullable: bool,
    pub unit: &'static str,
    pub about: &'static str,
}

const fn col(
    name: &'static str,
    kind: ColumnType,
    nullable: bool,
    unit: &'static str,
    about: &'static str,
) -> Column {
    Column {
        name,
        kind,
        nullable,
        unit,
        about,
    }
}

use ColumnType::*;

/// One table of the export: a folder `DEST/<name>/machine_key=…/`.
#[derive(Debug, Clone, Copy)]
pub struct TableDef {
    pub name: &'static str,
    pub about: &'static str,
    /// The table's own columns, after the run's (`RUN_COLUMNS`).
    pub own_columns: &'static [Column],
}

impl TableDef {
    /// Every column of the table's files: the run's, then its own.
    pub fn columns(&self) -> impl Iterator<Item = &'static Column> + Clone {
        RUN_COLUMNS.iter().chain(self.own_columns.iter())
    }

    /// The Arrow schema, with each field's unit as field metadata (`unit`) and the table's
    /// name and schema version as schema metadata.
    pub fn schema(&self) -> Arc<Schema> {
        self.schema_with(&[])
    }

    /// The schema of a table's file when no run has rows for it: the columns, then the
    /// partition column that the folders give otherwise, so that every reader sees the same
    /// columns whether the table has rows or not.
    pub fn empty_schema(&self) -> Arc<Schema> {
        self.schema_with(&[Field::new(MACHINE_KEY, DataType::Utf8, false)])
    }

    fn schema_with(&self, extra: &[Field]) -> Arc<Schema> {
        let fields: Vec<Field> = self
            .columns()
            .map(|c| {
                let field = Field::new(c.name, c.kind.data_type(), c.nullable);
                if c.unit.is_empty() {
                    field
                } else {
                    field.with_metadata(HashMap::from([("unit".to_owned(), c.unit.to_owned())]))
                }
            })
            .chain(extra.iter().cloned())
            .collect();
        Arc::new(Schema::new(fields).with_metadata(HashMap::from([
            (META_TABLE.to_owned(), self.name.to_owned()),
            (META_SCHEMA_VERSION.to_owned(), SCHEMA_VERSION.to_string()),
        ])))
    }

    pub fn index_of(&self, name: &str) -> Option<usize> {
        self.columns().position(|c| c.name == name)
    }
}

/// The columns every table starts with: which run, of which machine, of which kind, when.
pub const RUN_COLUMNS: &[Column] = &[
    col(
        "run_id",
        Utf8,
        false,
        "",
        "the run: `r-` and 16 hex digits of the SHA-256 of its session id; joins the tables",
    ),
    col(
        "session_id",
        Utf8,
        false,
        "",
        "the run's session id (geocal-session/1 header)",
    ),
    col(
        "machine",
        Utf8,
        true,
        "",
        "the machine's configured name, as written (null when none is configured)",
    ),
    col(
        "machine_serial",
        Utf8,
        true,
        "",
        "the machine's serial where its configuration declares one",
    ),
    col(
        "machine_id",
        Utf8,
        true,
        "",
        "the machine's declared id ([machine] id) where there is one",
    ),
    col(
        "kind",
        Utf8,
        false,
        "",
        "plan kind (multilateration, rotary_tracer, rotary_sphere, probe_install, hexapod)",
    ),
    col(
        "started_at",
        TimestampUs,
        false,
        "s",
        "when the run started (session header, else the results file's time), UTC",
    ),
];

pub const RUNS: TableDef = TableDef {
    name: "runs",
    about: "one row per run",
    own_columns: &[
        col(
            "schema_version",
            Int32,
            false,
            "",
            "the export schema's version (2)",
        ),
        col("date", Date, false, "", "the UTC date of started_at"),
        col(
            "structure",
            Utf8,
            true,
            "",
            "the machine's kinematic chain (session header), e.g. FYXZ; null without a session",
        ),
        col(
            "source",
            Utf8,
            false,
            "",
            "the results file the row was exported from",
        ),
        col(
            "job_id",
            Int64,
            true,
            "",
            "the daemon's job id (catalog export), else null",
        ),
        col("chi2_per_dof", Float64, true, "", "χ²/dof of the fit"),
        col("dof", Int64, true, "", "degrees of freedom of the fit"),
        col(
            "residual_rms_m",
            Float64,
            true,
            "m",
            "RMS residual of the fit",
        ),
        col(
            "converged",
            Bool,
            true,
            "",
            "whether the solver converged (kinds that say)",
        ),
        col(
            "misfit",
            Bool,
            false,
            "",
            "the fit's χ²/dof is improbable (p < 1e-3): σ too small by sigma_scale",
        ),
        col(
            "misfit_sigma_scale",
            Float64,
            true,
            "",
            "√(χ²/dof) when misfit, else null",
        ),
        col(
            "windows_used",
            Int64,
            true,
            "",
            "tracer windows used (tracer kinds)",
        ),
        col(
            "windows_dropped",
            Int64,
            true,
            "",
            "tracer windows dropped (tracer kinds)",
        ),
        col(
            "damaged_chunks",
            Int64,
            true,
            "",
            "damaged chunks of the session the results came from (tracer kinds)",
        ),
        col(
            "iso230_2_note",
            Utf8,
            true,
            "",
            "why the run has no iso230_2 rows, when it has none",
        ),
        col(
            "raw_samples",
            Int64,
            true,
            "",
            "tracer samples written to tracer_samples (--raw), else null",
        ),
    ],
};

pub const PARAMETERS: TableDef = TableDef {
    name: "parameters",
    about: "one row per estimated scalar parameter with its standard uncertainty",
    own_columns: &[
        col(
            "category",
            Utf8,
            false,
            "",
            "station, squareness, location, parameter, hinge, rotary_axis or effect",
        ),
        col(
            "name",
            Utf8,
            false,
            "",
            "stable parameter name as the history names it, e.g. EC0Y, station.s1.x",
        ),
        col(
            "value",
            Float64,
            true,
            "row",
            "estimate; null where the data cannot determine it",
        ),
        col(
            "sigma",
            Float64,
            true,
            "row",
            "standard uncertainty (1 σ); null where not determined",
        ),
        col(
            "unit",
            Utf8,
            false,
            "",
            "SI unit of value and sigma: m, rad or 1",
        ),
        col(
            "identifiable",
            Bool,
            false,
            "",
            "the data determine this parameter",
        ),
    ],
};

pub const ERROR_FUNCTIONS: TableDef = TableDef {
    name: "error_functions",
    about: "one row per error function (ISO 230-1 name) at one position of its axis",
    own_columns: &[
        col(
            "axis",
            Utf8,
            false,
            "",
            "the axis: x, y, z, or the rotary table's id",
        ),
        col(
            "error_function",
            Utf8,
            false,
            "",
            "ISO 230-1 name (EXX, EYX, …, EXC, …) or step_error",
        ),
        col(
            "parameter",
            Utf8,
            false,
            "",
            "the function at its position as the history names it, e.g. ECY@y=1.200",
        ),
        col(
            "position",
            Float64,
            false,
            "row",
            "axis position, in position_unit",
        ),
        col(
            "position_unit",
            Utf8,
            false,
            "",
            "m (linear axis) or rad (rotary axis)",
        ),
        col(
            "value",
            Float64,
            true,
            "row",
            "the error at that position; null where not determined",
        ),
        col(
            "sigma",
            Float64,
            true,
            "row",
            "its standard uncertainty (1 σ)",
        ),
        col(
            "unit",
            Utf8,
            false,
            "",
            "SI unit of value and sigma: m or rad",
        ),
        col(
            "identifiable",
            Bool,
            false,
            "",
            "the data determine this function",
        ),
    ],
};

pub const POINTS: TableDef = TableDef {
    name: "points",
    about: "one row per measured point of a tracer network (machine frame)",
    own_columns: &[
        col("target", Utf8, false, "", "reflector target id"),
        col("point", Int64, false, "", "point number in the plan"),
        col("nominal_x_m", Float64, false, "m", "nominal position x"),
        col("nominal_y_m", Float64, false, "m", "nominal position y"),
        col("nominal_z_m", Float64, false, "m", "nominal position z"),
        col(
            "error_x_m",
            Float64,
            false,
            "m",
            "volumetric error x (actual − nominal)",
        ),
        col("error_y_m", Float64, false, "m", "volumetric error y"),
        col("error_z_m", Float64, false, "m", "volumetric error z"),
        col(
            "sigma_x_m",
            Float64,
            false,
            "m",
            "standard uncertainty of error_x_m",
        ),
        col(
            "sigma_y_m",
            Float64,
            false,
            "m",
            "standard uncertainty of error_y_m",
        ),
        col(
            "sigma_z_m",
            Float64,
            false,
            "m",
            "standard uncertainty of error_z_m",
        ),
        col(
            "observations",
            Int64,
            false,
            "",
            "lengths that measured the point",
        ),
    ],
};

pub const ISO230_2: TableDef = TableDef {
    name: "iso230_2",
    about: "one row per axis (and target) evaluated per ISO 230-2 (docs/iso230-2.md)",
    own_columns: &[
        col("axis", Utf8, false, "", "x, y, z, or the rotary table's id"),
        col(
            "target",
            Utf8,
            true,
            "",
            "reflector target of a linear axis",
        ),
        col(
            "unit",
            Utf8,
            false,
            "",
            "SI unit of every figure of the row: m (linear) or rad (rotary)",
        ),
        col("targets", Int64, false, "", "number of target positions m"),
        col(
            "runs_up",
            Int64,
            false,
            "",
            "runs in the positive direction",
        ),
        col(
            "runs_down",
            Int64,
            false,
            "",
            "runs in the negative direction",
        ),
        col(
            "systematic_error",
            Float64,
            true,
            "row",
            "E, bidirectional systematic positioning error",
        ),
        col("systematic_error_up", Float64, true, "row", "E↑"),
        col("systematic_error_down", Float64, true, "row", "E↓"),
        col(
            "mean_error",
            Float64,
            true,
            "row",
            "M, mean bidirectional positioning error",
        ),
        col(
            "reversal",
            Float64,
            true,
            "row",
            "B, reversal value of the axis",
        ),
        col(
            "mean_reversal",
            Float64,
            true,
            "row",
            "B̄, mean reversal value",
        ),
        col(
            "repeatability",
            Float64,
            true,
            "row",
            "R, bidirectional repeatability",
        ),
        col("repeatability_up", Float64, true, "row", "R↑"),
        col("repeatability_down", Float64, true, "row", "R↓"),
        col(
            "accuracy",
            Float64,
            true,
            "row",
            "A, bidirectional accuracy",
        ),
        col("accuracy_up", Float64, true, "row", "A↑"),
        col("accuracy_down", Float64, true, "row", "A↓"),
        col(
            "deviation_sigma_median",
            Float64,
            true,
            "row",
            "median standard uncertainty of one deviation",
        ),
        col(
            "per_iso_230_2",
            Bool,
            false,
            "",
            "the measurement follows the standard's test cycle",
        ),
        col(
            "not_per_iso_230_2",
            Utf8List,
            false,
            "",
            "why not (empty when it does)",
        ),
    ],
};

pub const DIAGNOSES: TableDef = TableDef {
    name: "diagnoses",
    about: "one row per run with a diagnosis (diagnosis.json, geocal-diagnosis/1)",
    own_columns: &[
        col(
            "verdict",
            Utf8,
            false,
            "",
            "consistent, explained, confounded, noise_scale or unexplained",
        ),
        col(
            "selected",
            Utf8List,
            false,
            "",
            "effects selected (e.g. reversal, station_drift)",
        ),
        col(
            "unexplained",
            Bool,
            false,
            "",
            "structure remains that no candidate explains",
        ),
        col(
            "noise_scale_k",
            Float64,
            true,
            "",
            "the declared noise model is off by this factor, when found",
        ),
        col(
            "noise_floor_m",
            Float64,
            false,
            "m",
            "noise floor of the lengths",
        ),
        col(
            "gap_rms_m",
            Float64,
            false,
            "m",
            "RMS residual of the nominal model",
        ),
        col(
            "gap_heldout_ratio",
            Float64,
            false,
            "",
            "held-out residuals in units of their predicted σ (1 when the model holds)",
        ),
        col(
            "gap_after_rms_m",
            Float64,
            false,
            "m",
            "RMS residual with the selected effects",
        ),
        col(
            "gap_after_heldout_ratio",
            Float64,
            false,
            "",
            "held-out ratio with the selected effects",
        ),
        col(
            "observations",
            Int64,
            false,
            "",
            "lengths the diagnosis used",
        ),
    ],
};

pub const TRACER_SAMPLES: TableDef = TableDef {
    name: "tracer_samples",
    about: "with --raw: every raw tracer sample of the session, as recorded",
    own_columns: &[
        col(
            "tracer",
            Utf8,
            false,
            "",
            "tracer id (topic /tracer/<id>/range)",
        ),
        col(
            "log_time",
            TimestampUs,
            false,
            "s",
            "host time of reception, UTC (to the microsecond: Spark reads no nanoseconds)",
        ),
        col(
            "log_time_ns",
            Int64,
            false,
            "ns",
            "host time of reception, ns since the Unix epoch (exact, as recorded)",
        ),
        col("seq", Int64, false, "", "the sample's sequence number"),
        col("t_s", Float64, false, "s", "device time"),
        col(
            "length_m",
            Float64,
            false,
            "m",
            "length relative to the last homing",
        ),
        col("signal", Float64, false, "1", "signal strength, 0..1"),
        col("tracking", Bool, false, "", "the tracer was tracking"),
        col(
            "beam_segment",
            Int64,
            false,
            "",
            "beam segment (a new one after each re-homing)",
        ),
    ],
};

/// Every table of the export.
pub const TABLES: &[&TableDef] = &[
    &RUNS,
    &PARAMETERS,
    &ERROR_FUNCTIONS,
    &POINTS,
    &ISO230_2,
    &DIAGNOSES,
    &TRACER_SAMPLES,
];
