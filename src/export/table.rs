//! A table being filled row by row (cells by column name, checked against the table's
//! definition), turned into one Arrow record batch.

use std::sync::Arc;

use arrow_array::builder::{ListBuilder, StringBuilder};
use arrow_array::Array;
use arrow_array::{
    ArrayRef, BooleanArray, Float64Array, Int32Array, Int64Array, RecordBatch, StringArray,
    TimestampMicrosecondArray,
};

use super::schema::{ColumnType, TableDef};

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

/// Rows of one table; every row holds a cell for every column.
#[derive(Debug, Clone)]
pub struct Table {
    pub def: &'static TableDef,
    rows: Vec<Vec<Cell>>,
}

impl Table {
    pub fn new(def: &'static TableDef) -> Table {
        Table {
            def,
            rows: Vec::new(),
        }
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
        let mut row = vec![Cell::Null; self.def.columns.len()];
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
        let mut arrays: Vec<ArrayRef> = Vec::with_capacity(self.def.columns.len());
        for (i, column) in self.def.columns.iter().enumerate() {
            let cells = self.rows.iter().map(|r| &r[i]);
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
            };
            if !column.nullable && array.null_count() > 0 {
                anyhow::bail!(
                    "table {}: column `{}` has {} missing values, expected none",
                    self.def.name,
                    column.name,
                    array.null_count()
                );
            }
            arrays.push(array);
        }
        Ok(RecordBatch::try_new(self.def.schema(), arrays)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::export::schema::DIAGNOSES;

    #[test]
    fn a_missing_required_value_is_an_error_naming_the_column() {
        let mut table = Table::new(&DIAGNOSES);
        table.push(vec![
            ("session_id", "s".into()),
            ("verdict", "consistent".into()),
        ]);
        let e = table.to_batch().expect_err("columns left null");
        assert!(e.to_string().contains("column `selected`"), "{e}");
    }

    #[test]
    fn rows_become_a_batch_of_the_table_schema() {
        let mut table = Table::new(&DIAGNOSES);
        table.push(vec![
            ("session_id", "s".into()),
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
        assert_eq!(batch.column(4).null_count(), 1, "noise_scale_k left null");
    }
}
