//! Every example config in `config/` (the simulated plans of every kind; the controller
//! examples in its subfolders need real devices or run in real time), run with `--truth` at
//! its seed, gives the results and
//! truth it gave when the digests in `tests/data/results_digests.json` were stored: a change
//! that should not change behaviour (a refactor) is shown not to, byte for byte.
//!
//! The session id holds the wall-clock start, so it is blanked before hashing. After an
//! intended change of results, store the new digests with
//! `GEOCAL_STORE_DIGESTS=1 cargo test --test integration results_digests::` and say why in the commit.

use std::collections::BTreeMap;
use std::path::Path;
use std::process::{Command, Stdio};

use sha2::{Digest, Sha256};

fn digest_of(path: &Path, blank_session_id: bool) -> String {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let mut json: serde_json::Value =
        serde_json::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    if blank_session_id {
        if let Some(id) = json.get_mut("session_id") {
            *id = serde_json::Value::String(String::new());
        }
    }
    let canonical = serde_json::to_vec(&json).expect("serialise");
    format!("{:x}", Sha256::digest(&canonical))
}

#[test]
fn example_configs_give_their_stored_results() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let stored_path = root.join("tests/data/results_digests.json");
    let mut configs: Vec<_> = std::fs::read_dir(root.join("config"))
        .expect("config/")
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|x| x == "toml"))
        .collect();
    configs.sort();
    assert!(configs.len() >= 5, "{} configs", configs.len());
    let mut found: BTreeMap<String, BTreeMap<String, String>> = BTreeMap::new();
    for config in &configs {
        let name = config
            .file_name()
            .expect("file name")
            .to_string_lossy()
            .into_owned();
        let dir = tempfile::tempdir().expect("tempdir");
        let out = dir.path().join("run");
        let truth = dir.path().join("truth.json");
        let status = Command::new(env!("CARGO_BIN_EXE_geocal"))
            .arg("run")
            .arg(config)
            .arg("--out")
            .arg(&out)
            .arg("--truth")
            .arg(&truth)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .status()
            .expect("run geocal");
        assert!(status.success(), "{name}: geocal run failed");
        found.insert(
            name,
            BTreeMap::from([
                ("results".into(), digest_of(&out.join("results.json"), true)),
                ("truth".into(), digest_of(&truth, false)),
            ]),
        );
    }
    if std::env::var_os("GEOCAL_STORE_DIGESTS").is_some() {
        let text = serde_json::to_string_pretty(&found).expect("serialise") + "\n";
        std::fs::write(&stored_path, text).expect("store digests");
        return;
    }
    let stored: BTreeMap<String, BTreeMap<String, String>> = serde_json::from_str(
        &std::fs::read_to_string(&stored_path).expect("tests/data/results_digests.json"),
    )
    .expect("stored digests parse");
    assert_eq!(
        found, stored,
        "results or truth of an example config changed (found, stored)"
    );
}
