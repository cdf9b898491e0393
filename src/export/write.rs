//! The export's files: `DEST/<table>/machine_key=<key>/<run id>.parquet`, one file per run and
//! table, or `DEST/<table>/empty.parquet` (no rows, the table's columns) while no run has rows
//! for the table. Files are written in `DEST/_staging/` (outside every table's folder, which
//! is what readers read) and renamed into place, so no reader sees half a file; exporting a
//! run again first removes every earlier file of it, wherever it lies.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use anyhow::Context;
use arrow_array::RecordBatch;
use parquet::arrow::ArrowWriter;
use parquet::basic::Compression;
use parquet::file::metadata::KeyValue;
use parquet::file::properties::WriterProperties;
use sha2::{Digest, Sha256};

use super::schema::{
    TableDef, MACHINE_KEY, META_SCHEMA_VERSION, META_TABLE, SCHEMA_VERSION, TABLES,
};

/// Files being written, outside the tables' folders.
pub const STAGING_DIR: &str = "_staging";
/// A table's file while no run has rows for it.
pub const EMPTY_FILE: &str = "empty.parquet";

/// A run's id: `r-` and the first 16 hex digits of the SHA-256 of its session id (ASCII, a
/// file name on every system).
pub fn run_id(session_id: &str) -> String {
    let hash = format!("{:x}", Sha256::digest(session_id.as_bytes()));
    format!("r-{}", &hash[..16])
}

/// Where one run's file of `table` goes.
pub fn run_file(dest: &Path, table: &TableDef, machine_key: &str, run_id: &str) -> PathBuf {
    dest.join(table.name)
        .join(format!("{MACHINE_KEY}={machine_key}"))
        .join(format!("{run_id}.parquet"))
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

/// The files already in an export folder, and the folder files are written in first.
pub struct Dataset {
    dest: PathBuf,
    staging: PathBuf,
    /// Run id → its files (any table, any machine key).
    runs: HashMap<String, Vec<PathBuf>>,
}

impl Dataset {
    /// Open `dest` (created when missing): index its run files, and empty the staging folder
    /// of what an interrupted export left there. An export of another layout is refused.
    pub fn open(dest: &Path) -> anyhow::Result<Dataset> {
        std::fs::create_dir_all(dest).with_context(|| format!("creating {}", dest.display()))?;
        let staging = dest.join(STAGING_DIR);
        if staging.exists() {
            std::fs::remove_dir_all(&staging)
                .with_context(|| format!("removing {}", staging.display()))?;
        }
        std::fs::create_dir_all(&staging)
            .with_context(|| format!("creating {}", staging.display()))?;
        let mut runs: HashMap<String, Vec<PathBuf>> = HashMap::new();
        for table in TABLES {
            let dir = dest.join(table.name);
            let Ok(entries) = std::fs::read_dir(&dir) else {
                continue;
            };
            for entry in entries {
                let partition = entry.with_context(|| format!("reading {}", dir.display()))?;
                let name = partition.file_name().to_string_lossy().into_owned();
                if !partition.path().is_dir() {
                    continue;
                }
                if !name.starts_with(&format!("{MACHINE_KEY}=")) {
                    anyhow::bail!(
                        "{}: a folder of another export layout (expected {MACHINE_KEY}=…, \
                         schema version {SCHEMA_VERSION}, docs/fleet.md): export into a new \
                         folder",
                        partition.path().display()
                    );
                }
                let files = std::fs::read_dir(partition.path())
                    .with_context(|| format!("reading {}", partition.path().display()))?;
                for file in files {
                    let path = file
                        .with_context(|| format!("reading {}", partition.path().display()))?
                        .path();
                    if let Some(run) = path
                        .file_name()
                        .and_then(|n| n.to_str())
                        .and_then(|n| n.strip_suffix(".parquet"))
                    {
                        runs.entry(run.to_owned()).or_default().push(path.clone());
                    }
                }
            }
        }
        Ok(Dataset {
            dest: dest.to_path_buf(),
            staging,
            runs,
        })
    }

    pub fn dest(&self) -> &Path {
        &self.dest
    }

    /// Where a file of `table` for run `run_id` is written before it is published.
    pub fn staged(&self, table: &TableDef, run_id: &str) -> PathBuf {
        self.staging
            .join(format!("{}.{run_id}.parquet", table.name))
    }

    /// Put run `run_id`'s staged files (staged path, final path) in place: first every earlier
    /// file of the run that is not replaced is removed (another machine key after a rename, a
    /// table it no longer has rows in), then each file is renamed into its table.
    pub fn publish(&mut self, run_id: &str, files: &[(PathBuf, PathBuf)]) -> anyhow::Result<()> {
        for old in self.runs.remove(run_id).unwrap_or_default() {
            if !files.iter().any(|(_, path)| *path == old) {
                remove_if_present(&old)?;
                if let Some(dir) = old.parent() {
                    // A machine key left without files goes too (it may be a renamed one).
                    let _ = std::fs::remove_dir(dir);
                }
            }
        }
        for (staged, path) in files {
            let partition = path.parent().unwrap_or(Path::new("."));
            if let Some(table) = partition.parent() {
                // A table with rows has no empty file (Spark refuses a file beside partitions).
                remove_if_present(&table.join(EMPTY_FILE))?;
            }
            std::fs::create_dir_all(partition)
                .with_context(|| format!("creating {}", partition.display()))?;
            std::fs::rename(staged, path)
                .with_context(|| format!("renaming {} to {}", staged.display(), path.display()))?;
            self.runs
                .entry(run_id.to_owned())
                .or_default()
                .push(path.clone());
        }
        Ok(())
    }

    /// End the export: every table without a run file gets its empty file; the staging
    /// folder goes.
    pub fn finish(self) -> anyhow::Result<()> {
        for table in TABLES {
            let dir = self.dest.join(table.name);
            let has_rows = std::fs::read_dir(&dir)
                .map(|entries| {
                    entries
                        .filter_map(Result::ok)
                        .any(|e| e.path().is_dir() && dir_has_parquet(&e.path()))
                })
                .unwrap_or(false);
            let empty = dir.join(EMPTY_FILE);
            if has_rows {
                remove_if_present(&empty)?;
            } else if !empty.is_file() {
                let staged = self.staging.join(format!("{}.{EMPTY_FILE}", table.name));
                let file = std::fs::File::create(&staged)
                    .with_context(|| format!("creating {}", staged.display()))?;
                let mut writer =
                    ArrowWriter::try_new(file, table.empty_schema(), Some(properties(table)))
                        .with_context(|| format!("writing {}", staged.display()))?;
                writer
                    .write(&RecordBatch::new_empty(table.empty_schema()))
                    .with_context(|| format!("writing {}", staged.display()))?;
                writer
                    .close()
                    .with_context(|| format!("finishing {}", staged.display()))?;
                std::fs::create_dir_all(&dir)
                    .with_context(|| format!("creating {}", dir.display()))?;
                std::fs::rename(&staged, &empty).with_context(|| {
                    format!("renaming {} to {}", staged.display(), empty.display())
                })?;
            }
        }
        std::fs::remove_dir_all(&self.staging)
            .with_context(|| format!("removing {}", self.staging.display()))
    }
}

fn dir_has_parquet(dir: &Path) -> bool {
    std::fs::read_dir(dir)
        .map(|entries| {
            entries
                .filter_map(Result::ok)
                .any(|e| e.path().extension().is_some_and(|x| x == "parquet"))
        })
        .unwrap_or(false)
}

fn remove_if_present(path: &Path) -> anyhow::Result<()> {
    match std::fs::remove_file(path) {
        Ok(()) => Ok(()),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
        Err(e) => Err(e).with_context(|| format!("removing {}", path.display())),
    }
}

/// A Parquet file being written batch by batch (in the staging folder).
pub struct PartFile {
    path: PathBuf,
    writer: ArrowWriter<std::fs::File>,
}

impl PartFile {
    pub fn create(path: &Path, table: &TableDef) -> anyhow::Result<PartFile> {
        let file =
            std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
        let writer = ArrowWriter::try_new(file, table.schema(), Some(properties(table)))
            .with_context(|| format!("writing {}", path.display()))?;
        Ok(PartFile {
            path: path.to_path_buf(),
            writer,
        })
    }

    pub fn write(&mut self, batch: &RecordBatch) -> anyhow::Result<()> {
        self.writer
            .write(batch)
            .with_context(|| format!("writing {}", self.path.display()))
    }

    /// Close the file (on disk before it is renamed into the dataset).
    pub fn finish(self) -> anyhow::Result<PathBuf> {
        let file = self
            .writer
            .into_inner()
            .with_context(|| format!("finishing {}", self.path.display()))?;
        file.sync_all()
            .with_context(|| format!("syncing {}", self.path.display()))?;
        Ok(self.path)
    }
}

/// Write one batch as the staged file `path`; false (and no file) when it has no rows.
pub fn write_batch(path: &Path, table: &TableDef, batch: &RecordBatch) -> anyhow::Result<bool> {
    if batch.num_rows() == 0 {
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
    fn a_run_file_sits_in_its_machine_partition() {
        let run = run_id("multilateration-1764000000000-7");
        assert!(
            run.starts_with("r-")
                && run.len() == 18
                && run[2..].bytes().all(|b| b.is_ascii_hexdigit()),
            "{run}"
        );
        let path = run_file(
            Path::new("out"),
            &super::super::schema::RUNS,
            "m-fr-se-7-0a1b2c3d",
            &run,
        );
        assert_eq!(
            path,
            Path::new("out/runs/machine_key=m-fr-se-7-0a1b2c3d").join(format!("{run}.parquet"))
        );
    }

    #[test]
    fn a_run_published_again_leaves_one_file_and_every_table_is_there() {
        use super::super::schema::{PARAMETERS, RUNS};
        let dest = tempfile::tempdir().expect("tempdir");
        let publish = |key: &str| {
            let mut dataset = Dataset::open(dest.path()).expect("open");
            let staged = dataset.staged(&PARAMETERS, "r-1");
            std::fs::write(&staged, b"rows").expect("stage");
            let path = run_file(dest.path(), &PARAMETERS, key, "r-1");
            dataset
                .publish("r-1", &[(staged, path.clone())])
                .expect("publish");
            dataset.finish().expect("finish");
            path
        };
        let old = publish("m-old-00000000");
        assert!(old.is_file());
        let new = publish("m-new-11111111");
        assert!(new.is_file() && !old.exists() && !old.parent().expect("dir").exists());
        assert!(!dest.path().join(STAGING_DIR).exists());
        // A table no run has rows for holds its empty file; one with rows does not.
        assert!(dest.path().join(RUNS.name).join(EMPTY_FILE).is_file());
        assert!(!dest.path().join(PARAMETERS.name).join(EMPTY_FILE).exists());
    }

    #[test]
    fn another_layout_is_refused() {
        let dest = tempfile::tempdir().expect("tempdir");
        std::fs::create_dir_all(dest.path().join("runs/machine=Mill/date=2026-11-01"))
            .expect("mkdir");
        let e = Dataset::open(dest.path()).err().expect("refused");
        assert!(format!("{e:#}").contains("another export layout"), "{e:#}");
    }
}
