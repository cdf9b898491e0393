//! A table being filled row by row (cells by column name, checked against the table's
//! definition; the run's columns filled once for every row), turned into one Arrow record
//! batch.

use std::sync::Arc;

use arrow_array::builder::{ListBuilder, StringBuilder};
use arrow_array::Array;
use arrow_array::{
    ArrayRef, BooleanArray, Date32Array, Float64Array, Int32Array, Int64Array, RecordBatch,
    StringArray, TimestampMicrosecondArray,
};

use super::schema::{Column, ColumnType, TableDef};

/// One cell.
#[derive(Debug, Clone, PartialEq)]
pub enum Cell {
    Null,
    Int(i64),
    Float(f64),
    Bool(bool),
    Text(String),
    TextList(Vec<String>),
    /// Nanoseconds since the Unix epoch (a timestamp column).
    TimeNs(i64),
    /// Days since the Unix epoch (a date column).
    Days(i32),
}

impl From<f64> for Cell {
    fn from(v: f64) -> Cell {
        Cell::Float(v)
    }
}
impl From<Option<f64>> for Cell {
    fn from(v: Option<f64>) -> Cell {
        v.map_or(Cell::Null, Cell::Float)
    }
}
impl From<bool> for Cell {
    fn from(v: bool) -> Cell {
        Cell::Bool(v)
    }
}
impl From<i64> for Cell {
    fn from(v: i64) -> Cell {
        Cell::Int(v)
    }
}
impl From<usize> for Cell {
    fn from(v: usize) -> Cell {
        Cell::Int(i64::try_from(v).unwrap_or(i64::MAX))
    }
}
impl From<&str> for Cell {
    fn from(v: &str) -> Cell {
        Cell::Text(v.to_owned())
    }
}
impl From<String> for Cell {
    fn from(v: String) -> Cell {
        Cell::Text(v)
    }
}
impl From<Option<String>> for Cell {
    fn from(v: Option<String>) -> Cell {
        v.map_or(Cell::Null, Cell::Text)
    }
}
impl From<Vec<String>> for Cell {
    fn from(v: Vec<String>) -> Cell {
        Cell::TextList(v)
    }
}

/// The cells of the run's columns (`schema::RUN_COLUMNS`), the same in every row of a run.
pub type RunCells = Vec<(&'static str, Cell)>;

/// Rows of one table; every row holds a cell for every column.
#[derive(Debug, Clone)]
pub struct Table {
    pub def: &'static TableDef,
    /// A new row before its own cells: the run's cells, the rest null.
    template: Vec<Cell>,
    rows: Vec<Vec<Cell>>,
}

impl Table {
    pub fn new(def: &'static TableDef) -> Table {
        Table {
            def,
            template: vec![Cell::Null; def.columns().count()],
            rows: Vec::new(),
        }
    }

    /// A table of one run's rows: `run` fills the run's columns of every row.
    pub fn of_run(def: &'static TableDef, run: &RunCells) -> Table {
        let mut table = Table::new(def);
        for (name, cell) in run {
            match def.index_of(name) {
                Some(i) => table.template[i] = cell.clone(),
                None => debug_assert!(false, "table {} has no column {name}", def.name),
            }
        }
        table
    }

    pub fn len(&self) -> usize {
        self.rows.len()
    }

    pub fn is_empty(&self) -> bool {
        self.rows.is_empty()
    }

    /// Add a row from `(column, cell)` pairs; columns not named are null. A column name the
    /// table does not have, or a value of the wrong type, is a programming error: it panics
    /// in tests (debug) and is written as null otherwise.
    pub fn push(&mut self, cells: Vec<(&str, Cell)>) {
        let mut row = self.template.clone();
        for (name, cell) in cells {
            match self.def.index_of(name) {
                Some(i) => row[i] = cell,
                None => debug_assert!(false, "table {} has no column {name}", self.def.name),
            }
        }
        self.rows.push(row);
    }

    /// The rows as one record batch of the table's schema. A null in a column that may not be
    /// null is an error naming the column.
    pub fn to_batch(&self) -> anyhow::Result<RecordBatch> {
        let mut arrays: Vec<ArrayRef> = Vec::new();
        for (i, column) in self.def.columns().enumerate() {
            arrays.push(column_array(
                self.def,
                column,
                self.rows.iter().map(|r| &r[i]),
            )?);
        }
        Ok(RecordBatch::try_new(self.def.schema(), arrays)?)
    }

    /// The run's columns of `rows` rows (each the run's cell), for a batch built elsewhere.
    pub fn run_arrays(&self, rows: usize) -> anyhow::Result<Vec<ArrayRef>> {
        crate::export::schema::RUN_COLUMNS
            .iter()
            .enumerate()
            .map(|(i, column)| {
                column_array(
                    self.def,
                    column,
                    std::iter::repeat_n(&self.template[i], rows),
                )
            })
            .collect()
    }
}

/// One column's cells as an Arrow array; a null where the column may have none is an error.
fn column_array<'a>(
    def: &TableDef,
    column: &Column,
    cells: impl Iterator<Item = &'a Cell>,
) -> anyhow::Result<ArrayRef> {
    let array: ArrayRef = match column.kind {
        ColumnType::Int32 => Arc::new(Int32Array::from_iter(cells.map(|c| match c {
            Cell::Int(v) => i32::try_from(*v).ok(),
            _ => None,
        }))),
        ColumnType::Int64 => Arc::new(Int64Array::from_iter(cells.map(|c| match c {
            Cell::Int(v) => Some(*v),
            _ => None,
        }))),
        ColumnType::Float64 => Arc::new(Float64Array::from_iter(cells.map(|c| match c {
            Cell::Float(v) => Some(*v),
            _ => None,
        }))),
        ColumnType::Bool => Arc::new(BooleanArray::from_iter(cells.map(|c| match c {
            Cell::Bool(v) => Some(*v),
            _ => None,
        }))),
        ColumnType::Utf8 => Arc::new(StringArray::from_iter(cells.map(|c| match c {
            Cell::Text(v) => Some(v.as_str()),
            _ => None,
        }))),
        ColumnType::Utf8List => {
            let mut builder = ListBuilder::new(StringBuilder::new());
            for c in cells {
                match c {
                    Cell::TextList(items) => {
                        for item in items {
                            builder.values().append_value(item);
                        }
                        builder.append(true);
                    }
                    _ => builder.append(false),
                }
            }
            Arc::new(builder.finish())
        }
        ColumnType::TimestampUs => Arc::new(
            TimestampMicrosecondArray::from_iter(cells.map(|c| match c {
                Cell::TimeNs(ns) => Some(ns.div_euclid(1000)),
                _ => None,
            }))
            .with_timezone("UTC"),
        ),
        ColumnType::Date => Arc::new(Date32Array::from_iter(cells.map(|c| match c {
            Cell::Days(d) => Some(*d),
            _ => None,
        }))),
    };
    if !column.nullable && array.null_count() > 0 {
        anyhow::bail!(
            "table {}: column `{}` has {} missing values, expected none",
            def.name,
            column.name,
            array.null_count()
        );
    }
    Ok(array)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::export::schema::{DIAGNOSES, RUN_COLUMNS};

    fn run() -> RunCells {
        vec![
            ("run_id", "r-1".into()),
            ("session_id", "s".into()),
            ("machine", "Fräse 7".into()),
            ("kind", "multilateration".into()),
            ("started_at", Cell::TimeNs(1_700_000_000_000_000_000)),
        ]
    }

    #[test]
    fn a_missing_required_value_is_an_error_naming_the_column() {
        let mut table = Table::of_run(&DIAGNOSES, &run());
        table.push(vec![("verdict", "consistent".into())]);
        let e = table.to_batch().expect_err("columns left null");
        assert!(e.to_string().contains("column `selected`"), "{e}");
        let mut table = Table::new(&DIAGNOSES);
        table.push(vec![("verdict", "consistent".into())]);
        let e = table.to_batch().expect_err("run columns left null");
        assert!(e.to_string().contains("column `run_id`"), "{e}");
    }

    #[test]
    fn rows_become_a_batch_of_the_table_schema() {
        let mut table = Table::of_run(&DIAGNOSES, &run());
        table.push(vec![
            ("verdict", "explained".into()),
            ("selected", vec!["reversal".to_owned()].into()),
            ("unexplained", false.into()),
            ("noise_floor_m", 1e-8.into()),
            ("gap_rms_m", 2e-8.into()),
            ("gap_heldout_ratio", 1.0.into()),
            ("gap_after_rms_m", 1e-8.into()),
            ("gap_after_heldout_ratio", 1.0.into()),
            ("observations", 100usize.into()),
        ]);
        let batch = table.to_batch().expect("batch");
        assert_eq!(batch.num_rows(), 1);
        assert_eq!(batch.schema(), DIAGNOSES.schema());
        let noise_scale = RUN_COLUMNS.len() + 3;
        assert_eq!(
            batch.column(noise_scale).null_count(),
            1,
            "noise_scale_k left null"
        );
        assert_eq!(table.run_arrays(3).expect("run columns")[2].len(), 3);
    }
}
