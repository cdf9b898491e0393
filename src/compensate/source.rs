//! Where a set of tables came from: the sidecar `geocal-source.json` that `geocal compensate`
//! writes beside its tables (the results file, its SHA-256 and session), so that a
//! verification run's report can find the "before" results and check they are the same.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::{input_error, Calibration, CompensateError, StepReport, TableFormat};

pub const SOURCE_FILE: &str = "geocal-source.json";
pub const SOURCE_FORMAT: &str = "geocal-compensation-source/1";

/// Hex SHA-256 of `bytes`.
pub fn sha256_hex(bytes: &[u8]) -> String {
    use sha2::Digest;
    sha2::Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// The sidecar's content.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Source {
    pub format: String,
    /// The results file the tables were made from (absolute when it could be resolved).
    pub results: PathBuf,
    pub results_sha256: String,
    pub session_id: String,
    /// The table format written (`linuxcnc-type1`, `sinumerik`, …).
    pub table_format: String,
    /// The step statement of each axis table, as printed by `geocal compensate`.
    pub steps: Vec<StepReport>,
}

impl Source {
    pub fn new(calibration: &Calibration, format: TableFormat, steps: &[StepReport]) -> Source {
        let results = std::fs::canonicalize(&calibration.source)
            .unwrap_or_else(|_| calibration.source.clone());
        Source {
            format: SOURCE_FORMAT.into(),
            results,
            results_sha256: calibration.source_sha256.clone(),
            session_id: calibration.session_id.clone(),
            table_format: format.name().into(),
            steps: steps.to_vec(),
        }
    }

    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).unwrap_or_default() + "\n"
    }

    /// Read a sidecar; a relative `results` is taken from the sidecar's folder.
    pub fn load(path: &Path) -> Result<Source, CompensateError> {
        let text = std::fs::read_to_string(path).map_err(|source| CompensateError::Io {
            file: path.to_path_buf(),
            source,
        })?;
        let de = &mut serde_json::Deserializer::from_str(&text);
        let mut source: Source = serde_path_to_error::deserialize(de)
            .map_err(|e| input_error(path, format!("at `{}`: {}", e.path(), e.inner())))?;
        if source.format != SOURCE_FORMAT {
            return Err(input_error(
                path,
                format!("format `{}`, expected `{SOURCE_FORMAT}`", source.format),
            ));
        }
        if source.results.is_relative() {
            if let Some(dir) = path.parent() {
                source.results = dir.join(&source.results);
            }
        }
        Ok(source)
    }

    /// The sidecar beside a table file, if there is one (None: no sidecar; Some(Err): one
    /// that cannot be read).
    pub fn beside(table_file: &Path) -> Option<Result<Source, CompensateError>> {
        let path = table_file.parent()?.join(SOURCE_FILE);
        path.is_file().then(|| Source::load(&path))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sha256_of_the_empty_string() {
        assert_eq!(
            sha256_hex(b""),
            "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855"
        );
    }

    #[test]
    fn a_sidecar_of_another_format_is_refused_by_name() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join(SOURCE_FILE);
        std::fs::write(
            &path,
            r#"{"format":"x","results":"r.json","results_sha256":"","session_id":"","table_format":"sinumerik","steps":[]}"#,
        )
        .expect("write");
        let e = Source::load(&path).unwrap_err().to_string();
        assert!(e.contains(SOURCE_FILE) && e.contains("format `x`"), "{e}");
        std::fs::write(&path, "{").expect("write");
        assert!(Source::load(&path).is_err());
    }
}
