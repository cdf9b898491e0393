//! Parquet files in Hive-style partitions: `DEST/<table>/machine=<name>/date=<YYYY-MM-DD>/
//! <session id>.parquet`, one file per run and table, written to a temporary name and renamed,
//! so that a reader never sees half a file and exporting a run again replaces its files.

use std::path::{Path, PathBuf};

use anyhow::Context;
use arrow_array::RecordBatch;
use parquet::arrow::ArrowWriter;
use parquet::basic::Compression;
use parquet::file::metadata::KeyValue;
use parquet::file::properties::WriterProperties;

use super::schema::{TableDef, META_SCHEMA_VERSION, META_TABLE, SCHEMA_VERSION};

/// A partition value or file name as Hive escapes it (and DuckDB and Spark unescape it): every
/// byte but ASCII letters, digits, `-`, `_` and `.` as `%XX`.
pub fn escape(value: &str) -> String {
    let mut out = String::with_capacity(value.len());
    for b in value.bytes() {
        if b.is_ascii_alphanumeric() || matches!(b, b'-' | b'_' | b'.') {
            out.push(b as char);
        } else {
            out.push_str(&format!("%{b:02X}"));
        }
    }
    // "." and ".." are not names a folder can have.
    if out.chars().all(|c| c == '.') {
        out = out.replace('.', "%2E");
    }
    out
}

/// Where one run's file of `table` goes.
pub fn run_file(
    dest: &Path,
    table: &TableDef,
    machine: &str,
    date: &str,
    session: &str,
) -> PathBuf {
    dest.join(table.name)
        .join(format!("machine={}", escape(machine)))
        .join(format!("date={}", escape(date)))
        .join(format!("{}.parquet", escape(session)))
}

fn properties(table: &TableDef) -> WriterProperties {
    WriterProperties::builder()
        .set_compression(Compression::SNAPPY)
        .set_key_value_metadata(Some(vec![
            KeyValue::new(META_SCHEMA_VERSION.to_owned(), SCHEMA_VERSION.to_string()),
            KeyValue::new(META_TABLE.to_owned(), table.name.to_owned()),
        ]))
        .build()
}

/// A Parquet file being written batch by batch under a temporary name.
pub struct PartFile {
    path: PathBuf,
    temporary: PathBuf,
    writer: ArrowWriter<std::fs::File>,
}

impl PartFile {
    pub fn create(path: &Path, table: &TableDef) -> anyhow::Result<PartFile> {
        let dir = path.parent().unwrap_or(Path::new("."));
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        // Readers skip names that start with `.` (DuckDB globs `*.parquet`; Spark hides `.`).
        let temporary = dir.join(format!(
            ".{}.partial",
            path.file_name()
                .map(|n| n.to_string_lossy())
                .unwrap_or_default()
        ));
        let file = std::fs::File::create(&temporary)
            .with_context(|| format!("creating {}", temporary.display()))?;
        let writer = ArrowWriter::try_new(file, table.schema(), Some(properties(table)))
            .with_context(|| format!("writing {}", temporary.display()))?;
        Ok(PartFile {
            path: path.to_path_buf(),
            temporary,
            writer,
        })
    }

    pub fn write(&mut self, batch: &RecordBatch) -> anyhow::Result<()> {
        self.writer
            .write(batch)
            .with_context(|| format!("writing {}", self.temporary.display()))
    }

    /// Close the file and give it its name.
    pub fn finish(self) -> anyhow::Result<PathBuf> {
        let file = self
            .writer
            .into_inner()
            .with_context(|| format!("finishing {}", self.temporary.display()))?;
        file.sync_all()
            .with_context(|| format!("syncing {}", self.temporary.display()))?;
        drop(file);
        std::fs::rename(&self.temporary, &self.path).with_context(|| {
            format!(
                "renaming {} to {}",
                self.temporary.display(),
                self.path.display()
            )
        })?;
        Ok(self.path)
    }
}

/// Write one batch as the file `path` (a run's rows of one table), replacing any earlier
/// export of it; no rows: remove an earlier file, write none.
pub fn write_batch(path: &Path, table: &TableDef, batch: &RecordBatch) -> anyhow::Result<bool> {
    if batch.num_rows() == 0 {
        match std::fs::remove_file(path) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => return Err(e).with_context(|| format!("removing {}", path.display())),
        }
        return Ok(false);
    }
    let mut file = PartFile::create(path, table)?;
    file.write(batch)?;
    file.finish()?;
    Ok(true)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn partition_values_are_escaped_as_hive_does() {
        assert_eq!(escape("Mill 3/A (é)"), "Mill%203%2FA%20%28%C3%A9%29");
        assert_eq!(escape("plain-name_1.2"), "plain-name_1.2");
        assert_eq!(escape("a=b"), "a%3Db");
        assert_eq!(escape(".."), "%2E%2E");
    }

    #[test]
    fn a_run_file_sits_in_its_partition() {
        let path = run_file(
            Path::new("out"),
            &super::super::schema::RUNS,
            "M 1",
            "2026-11-26",
            "s/1",
        );
        assert_eq!(
            path,
            Path::new("out/runs/machine=M%201/date=2026-11-26/s%2F1.parquet")
        );
    }
}
