//! A calibration run as the machine's history sees it: its results (geocal-results/1), the
//! machine it calibrated (configured name and serial), its kind, its plan's fingerprint and
//! when it started, loaded from a run folder or a results file and what lies beside it.

use std::path::{Path, PathBuf};

use anyhow::Context;
use sha2::{Digest, Sha256};

/// The results file inside a run folder.
pub const RESULTS_FILE: &str = "results.json";
/// Configurations a run folder may hold, the run's own first (`geocal run` stores it at
/// start; a daemon job keeps the plan it was submitted).
pub const CONFIG_FILES: &[&str] = &["run-config.toml", "plan.toml"];
/// The recorded session beside the results.
pub const SESSION_FILE: &str = "session.mcap";

/// Which machine a run calibrated: the configured `[machine] name` and `serial`, or a
/// declared `[machine] id`.
///
/// The one identity rule of compare, trend, the daemon's machines and the export
/// (docs/fleet.md): a declared id alone is the machine; without one, the name and the serial
/// together are (a missing serial is a value of its own, so `Mill` and `Mill` with serial
/// `S1` are two machines). `key()` is that identity as an ASCII-safe key.
#[derive(Debug, Clone, Default, PartialEq, Eq, PartialOrd, Ord, serde::Serialize)]
pub struct MachineIdentity {
    pub name: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub serial: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub id: Option<String>,
}

/// Characters of the readable part of a machine key.
const KEY_SLUG_MAX: usize = 24;

impl MachineIdentity {
    /// The name people see: `name (serial S)`, or `unknown machine`.
    pub fn label(&self) -> String {
        let base = match (&self.name, &self.serial) {
            (Some(n), Some(s)) => format!("{n} (serial {s})"),
            (Some(n), None) => n.clone(),
            (None, Some(s)) => format!("serial {s}"),
            (None, None) => "unknown machine".into(),
        };
        match &self.id {
            Some(id) if self.name.is_none() && self.serial.is_none() => format!("machine {id}"),
            Some(id) => format!("{base} (id {id})"),
            None => base,
        }
    }

    pub fn is_known(&self) -> bool {
        self.name.is_some() || self.serial.is_some() || self.id.is_some()
    }

    /// The machine's key: `m-` (never read as a number), a readable slug of its id or name
    /// (ASCII letters and digits, lower case, `-` between words), `-`, and the first 8 hex
    /// digits of the SHA-256 of the identity, which tells apart machines whose slugs agree.
    /// Spark, Hive, DuckDB, polars and pyarrow read it as the same string.
    pub fn key(&self) -> String {
        let (readable, identity) = match &self.id {
            Some(id) => (id.as_str(), format!("id\n{id}")),
            None => (
                self.name
                    .as_deref()
                    .or(self.serial.as_deref())
                    .unwrap_or("unknown"),
                format!(
                    "name\n{}\nserial\n{}",
                    self.name.as_deref().unwrap_or(""),
                    self.serial.as_deref().unwrap_or("")
                ),
            ),
        };
        let mut slug = String::new();
        for c in readable.chars().flat_map(char::to_lowercase) {
            if c.is_ascii_alphanumeric() {
                slug.push(c);
            } else if !slug.is_empty() && !slug.ends_with('-') {
                slug.push('-');
            }
            if slug.len() >= KEY_SLUG_MAX {
                break;
            }
        }
        let slug = slug.trim_end_matches('-');
        let hash = format!("{:x}", Sha256::digest(identity.as_bytes()));
        if slug.is_empty() {
            format!("m-{}", &hash[..8])
        } else {
            format!("m-{slug}-{}", &hash[..8])
        }
    }

    /// Whether two runs are of one machine: known, and of the same key. Unknown identities
    /// match nothing.
    pub fn same_machine(&self, other: &MachineIdentity) -> bool {
        self.is_known() && other.is_known() && self.key() == other.key()
    }

    /// Whether this identity answers to `wanted`: its key, declared id, name or serial.
    pub fn answers_to(&self, wanted: &str) -> bool {
        self.key() == wanted
            || self.id.as_deref() == Some(wanted)
            || self.name.as_deref() == Some(wanted)
            || self.serial.as_deref() == Some(wanted)
    }
}

/// The runs among `runs` of the machine `wanted` (its key, id, name or serial). A name that
/// several machines share is refused, naming each with its key.
pub fn runs_of_machine<T>(
    runs: Vec<T>,
    wanted: &str,
    identity: impl Fn(&T) -> &MachineIdentity,
) -> anyhow::Result<Vec<T>> {
    let matching: Vec<T> = runs
        .into_iter()
        .filter(|r| identity(r).answers_to(wanted))
        .collect();
    let mut machines: Vec<(String, String)> = matching
        .iter()
        .map(|r| (identity(r).key(), identity(r).label()))
        .collect();
    machines.sort();
    machines.dedup();
    if machines.len() > 1 {
        anyhow::bail!(
            "\"{wanted}\" names {} machines ({}): choose one by its key",
            machines.len(),
            machines
                .iter()
                .map(|(key, label)| format!("{label}: {key}"))
                .collect::<Vec<_>>()
                .join("; ")
        );
    }
    Ok(matching)
}

/// Where a plan fingerprint came from: fingerprints of different sources are not compared.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum FingerprintSource {
    /// The `[plan]` table of the run's configuration.
    Config,
    /// The `plan` of the session header.
    Session,
}

/// A SHA-256 of the plan in canonical JSON (keys sorted), and where the plan came from.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
pub struct PlanFingerprint {
    pub source: FingerprintSource,
    pub sha256: String,
}

/// One loaded calibration run.
#[derive(Debug, Clone)]
pub struct Run {
    /// How the run is named to people: its folder's name, or the results file.
    pub label: String,
    pub results_path: PathBuf,
    pub results: serde_json::Value,
    pub kind: String,
    pub session_id: String,
    pub machine: MachineIdentity,
    pub plan: Option<PlanFingerprint>,
    /// The session header's `started_at`, else the results file's modification time.
    pub started_at: Option<chrono::DateTime<chrono::Utc>>,
    /// The session beside the results, when there is one.
    pub session_path: Option<PathBuf>,
    /// The configuration beside the results, when there is one.
    pub config_path: Option<PathBuf>,
}

impl Run {
    /// Load a run folder (results.json inside) or a results file, with the configuration and
    /// session found beside it.
    pub fn load(path: &Path) -> anyhow::Result<Run> {
        let results_path = if path.is_dir() {
            path.join(RESULTS_FILE)
        } else {
            path.to_path_buf()
        };
        let dir = results_path
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .unwrap_or(Path::new("."))
            .to_path_buf();
        let text = std::fs::read_to_string(&results_path).with_context(|| {
            format!(
                "reading {} (expected a run folder with {RESULTS_FILE}, or a results file)",
                results_path.display()
            )
        })?;
        let results = Self::parse_results(&results_path, &text)?;
        let config_path = CONFIG_FILES
            .iter()
            .map(|name| dir.join(name))
            .find(|p| p.is_file());
        let session_path = Some(dir.join(SESSION_FILE)).filter(|p| p.is_file());
        let header = match &session_path {
            Some(p) => match crate::session::file_stream::read_header_json(p) {
                Ok(h) => Some(h),
                Err(e) => {
                    tracing::warn!("{}: no session header: {e:#}", p.display());
                    None
                }
            },
            None => None,
        };
        let config = match &config_path {
            Some(p) => Some(read_config(p)?),
            None => None,
        };
        let from_header = |key: &str| {
            header
                .as_ref()
                .and_then(|h| h.pointer(&format!("/machine/{key}")))
                .and_then(text_of)
        };
        let from_config = |key: &str| {
            config
                .as_ref()
                .and_then(|c| c.get("machine"))
                .and_then(|m| m.get(key))
                .and_then(|v| v.as_str())
                .map(str::trim)
                .filter(|s| !s.is_empty())
                .map(str::to_owned)
        };
        // The configuration is what the user wrote; the header records it.
        let machine = MachineIdentity {
            name: from_config("name").or_else(|| from_header("name")),
            serial: from_config("serial").or_else(|| from_header("serial")),
            id: from_config("id").or_else(|| from_header("id")),
        };
        let plan = match (&config, &header) {
            (Some(c), _) if c.get("plan").is_some() => Some(PlanFingerprint {
                source: FingerprintSource::Config,
                sha256: fingerprint(&serde_json::to_value(c.get("plan")).unwrap_or_default()),
            }),
            (_, Some(h)) if h.get("plan").is_some_and(|p| !p.is_null()) => Some(PlanFingerprint {
                source: FingerprintSource::Session,
                sha256: fingerprint(&h["plan"]),
            }),
            _ => None,
        };
        let started_at = header
            .as_ref()
            .and_then(|h| h.get("started_at"))
            .and_then(|s| s.as_str())
            .and_then(|s| chrono::DateTime::parse_from_rfc3339(s).ok())
            .map(|t| t.with_timezone(&chrono::Utc))
            .or_else(|| {
                std::fs::metadata(&results_path)
                    .and_then(|m| m.modified())
                    .ok()
                    .map(chrono::DateTime::<chrono::Utc>::from)
            });
        let label = if path.is_dir() {
            path.file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_else(|| path.display().to_string())
        } else {
            results_path.display().to_string()
        };
        Ok(Run {
            label,
            kind: results["kind"].as_str().unwrap_or_default().to_owned(),
            session_id: results["session_id"]
                .as_str()
                .unwrap_or_default()
                .to_owned(),
            results_path,
            results,
            machine,
            plan,
            started_at,
            session_path,
            config_path,
        })
    }

    /// A run from results already in memory (tests, generated histories).
    pub fn from_results(
        label: &str,
        results: serde_json::Value,
        machine: MachineIdentity,
        started_at: Option<chrono::DateTime<chrono::Utc>>,
    ) -> anyhow::Result<Run> {
        let results = Self::check_results(Path::new(label), results)?;
        Ok(Run {
            label: label.to_owned(),
            results_path: PathBuf::from(label),
            kind: results["kind"].as_str().unwrap_or_default().to_owned(),
            session_id: results["session_id"]
                .as_str()
                .unwrap_or_default()
                .to_owned(),
            results,
            machine,
            plan: None,
            started_at,
            session_path: None,
            config_path: None,
        })
    }

    fn parse_results(path: &Path, text: &str) -> anyhow::Result<serde_json::Value> {
        let results: serde_json::Value = serde_json::from_str(text)
            .with_context(|| format!("{}: not JSON (expected geocal-results/1)", path.display()))?;
        Self::check_results(path, results)
    }

    fn check_results(path: &Path, results: serde_json::Value) -> anyhow::Result<serde_json::Value> {
        let format = results.get("format").and_then(|f| f.as_str());
        if format != Some("geocal-results/1") {
            anyhow::bail!(
                "{}: key `format` is {}, expected \"geocal-results/1\"",
                path.display(),
                format.map_or("missing".to_string(), |f| format!("\"{f}\""))
            );
        }
        if !results.get("kind").is_some_and(|k| k.is_string()) {
            anyhow::bail!("{}: key `kind` missing or not a string", path.display());
        }
        Ok(results)
    }

    /// When the run started, as RFC 3339 (or "unknown").
    pub fn started_text(&self) -> String {
        self.started_at
            .map(|t| t.to_rfc3339_opts(chrono::SecondsFormat::Secs, true))
            .unwrap_or_else(|| "unknown".into())
    }
}

/// Every run folder directly under `dir` (a folder holding results.json), oldest first (by
/// start time, then name). Folders without results are left out; a results file that cannot
/// be read is an error naming it.
pub fn load_series(dir: &Path) -> anyhow::Result<Vec<Run>> {
    let entries = std::fs::read_dir(dir).with_context(|| {
        format!(
            "reading {} (expected a folder of run folders)",
            dir.display()
        )
    })?;
    let mut runs = Vec::new();
    for entry in entries {
        let entry = entry.with_context(|| format!("reading {}", dir.display()))?;
        let path = entry.path();
        if path.is_dir() && path.join(RESULTS_FILE).is_file() {
            runs.push(Run::load(&path)?);
        }
    }
    if runs.is_empty() {
        anyhow::bail!(
            "{}: no run folder (a folder with {RESULTS_FILE}) inside",
            dir.display()
        );
    }
    sort_by_time(&mut runs);
    Ok(runs)
}

/// Oldest first: by start time, then label.
pub fn sort_by_time(runs: &mut [Run]) {
    runs.sort_by(|a, b| (a.started_at, &a.label).cmp(&(b.started_at, &b.label)));
}

fn read_config(path: &Path) -> anyhow::Result<toml::Table> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    text.parse()
        .with_context(|| format!("{}: not TOML", path.display()))
}

fn text_of(value: &serde_json::Value) -> Option<String> {
    value
        .as_str()
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(str::to_owned)
}

/// SHA-256 of the value as JSON with every object's keys sorted.
pub fn fingerprint(value: &serde_json::Value) -> String {
    fn canonical(value: &serde_json::Value) -> serde_json::Value {
        match value {
            serde_json::Value::Object(fields) => {
                let mut sorted: Vec<_> = fields.iter().collect();
                sorted.sort_by(|a, b| a.0.cmp(b.0));
                serde_json::Value::Object(
                    sorted
                        .into_iter()
                        .map(|(k, v)| (k.clone(), canonical(v)))
                        .collect(),
                )
            }
            serde_json::Value::Array(items) => {
                serde_json::Value::Array(items.iter().map(canonical).collect())
            }
            other => other.clone(),
        }
    }
    let text = serde_json::to_string(&canonical(value)).unwrap_or_default();
    format!("{:x}", Sha256::digest(text.as_bytes()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fingerprint_ignores_key_order() {
        let a = serde_json::json!({"a": 1, "b": {"c": [1, 2], "d": "x"}});
        let b = serde_json::json!({"b": {"d": "x", "c": [1, 2]}, "a": 1});
        assert_eq!(fingerprint(&a), fingerprint(&b));
        assert_ne!(fingerprint(&a), fingerprint(&serde_json::json!({"a": 2})));
    }

    #[test]
    fn identity_matches_by_name_and_serial() {
        let m = |n: &str, s: Option<&str>| MachineIdentity {
            name: Some(n.into()),
            serial: s.map(Into::into),
            id: None,
        };
        assert!(m("a", Some("1")).same_machine(&m("a", Some("1"))));
        assert!(!m("a", None).same_machine(&m("a", Some("1"))));
        assert!(!m("a", Some("1")).same_machine(&m("a", Some("2"))));
        assert!(!m("a", None).same_machine(&m("b", None)));
        assert!(!MachineIdentity::default().same_machine(&MachineIdentity::default()));
        // A declared id is the machine, whatever its name and serial.
        let with_id = |n: &str| MachineIdentity {
            id: Some("cell-4".into()),
            ..m(n, None)
        };
        assert!(with_id("old name").same_machine(&with_id("new name")));
    }

    #[test]
    fn machine_keys_are_ascii_and_tell_machines_apart() {
        let m = |n: &str, s: Option<&str>| MachineIdentity {
            name: Some(n.into()),
            serial: s.map(Into::into),
            id: None,
        };
        let fraese = m("Fräse 7", None).key();
        assert!(fraese.starts_with("m-fr-se-7-"), "{fraese}");
        assert!(m("0042", None).key().starts_with("m-0042-"));
        let (a, b) = (m("Bridge", Some("BR-1001")), m("Bridge", Some("BR-1002")));
        assert_ne!(a.key(), b.key());
        assert_eq!(a.key(), a.clone().key(), "stable");
        for key in [fraese, a.key(), MachineIdentity::default().key()] {
            assert!(
                key.starts_with("m-")
                    && key
                        .bytes()
                        .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == b'-'),
                "{key}"
            );
        }
        let long = m(&"x".repeat(200), None).key();
        assert_eq!(long.len(), 2 + KEY_SLUG_MAX + 1 + 8, "{long}");
    }

    #[test]
    fn loads_a_run_folder_with_its_config() {
        let dir = tempfile::tempdir().expect("tempdir");
        std::fs::write(
            dir.path().join(RESULTS_FILE),
            r#"{"format": "geocal-results/1", "kind": "hexapod", "session_id": "s1"}"#,
        )
        .expect("write");
        std::fs::write(
            dir.path().join("run-config.toml"),
            "kind = \"hexapod\"\n[machine]\nname = \"M1\"\nserial = \"SN-7\"\n[plan]\nposes = 3\n",
        )
        .expect("write");
        let run = Run::load(dir.path()).expect("load");
        assert_eq!(run.kind, "hexapod");
        assert_eq!(run.machine.label(), "M1 (serial SN-7)");
        assert_eq!(
            run.plan.as_ref().map(|p| p.source),
            Some(FingerprintSource::Config)
        );
        assert!(run.started_at.is_some());
        let bad = dir.path().join("bad.json");
        std::fs::write(&bad, r#"{"format": "other"}"#).expect("write");
        let e = format!("{:#}", Run::load(&bad).expect_err("refused"));
        assert!(e.contains("format") && e.contains("bad.json"), "{e}");
    }
}
