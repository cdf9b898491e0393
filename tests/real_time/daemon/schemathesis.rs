//! Schemathesis (from PyPI) against a live daemon, with and without a token, every check
//! enabled: every answer must be one the OpenAPI document states, in the type it states, with
//! the body schema it states; no 5xx; schema-violating requests refused, bearer auth enforced.
//!
//! The daemon lets plans name no real port or host, so nothing a generated request submits can
//! move a machine; generated TOML is no valid plan and is refused before any job starts.
//! `/v1/events` and `/v1/devices/samples` are left out: they are endless streams, which a
//! per-request check cannot end.

use crate::common;

use std::path::Path;
use std::process::{Command, Stdio};

/// Run schemathesis against a daemon started with `extra` arguments; `token` is sent when set.
fn fuzz(dir: &Path, extra: &[&str], token: Option<&str>) {
    let config = dir.join("serve.toml");
    std::fs::write(
        &config,
        "allowed_ports = []\nallowed_hosts = []\n[devices]\nhold = false\n",
    )
    .expect("config");
    let mut daemon = Command::new(env!("CARGO_BIN_EXE_geocal"))
        .arg("serve")
        .arg("--config")
        .arg(&config)
        .arg("--data-dir")
        .arg(dir.join("data"))
        .args(["--listen", "127.0.0.1:0", "--live", "off"])
        .args(extra)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("spawn geocal serve");
    let (url, _) = common::daemon_banner(&mut daemon);

    let here = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/schemathesis");
    let mut command = Command::new("python3");
    command
        .args(["-m", "schemathesis.cli", "--no-color", "--config-file"])
        .arg(format!("{here}/schemathesis.toml"))
        .arg("run")
        .arg(format!("{url}/v1/openapi.json"))
        .args([
            "--checks",
            "all",
            "--max-examples",
            "20",
            "--seed",
            "23",
            "--workers",
            "1",
            "--exclude-path",
            "/v1/events",
            "--exclude-path",
            "/v1/devices/samples",
            "--request-timeout",
            "60",
        ])
        .current_dir(dir)
        .env("SCHEMATHESIS_HOOKS", "geocal_hooks")
        .env("PYTHONPATH", here);
    if let Some(token) = token {
        command.args(["--header", &format!("Authorization: Bearer {token}")]);
    }
    let output = command.output().expect("python3 -m schemathesis.cli");
    let _ = daemon.kill();
    let _ = daemon.wait();
    let stdout = String::from_utf8_lossy(&output.stdout);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        output.status.success(),
        "schemathesis found problems:\n{stdout}\n{stderr}"
    );
    let summary: Vec<&str> = stdout.lines().rev().take(12).collect();
    println!(
        "{}",
        summary.into_iter().rev().collect::<Vec<_>>().join("\n")
    );
}

#[test]
fn schemathesis_finds_nothing_without_a_token() {
    if !common::python_module_available("schemathesis", "'schemathesis>=4,<5'") {
        return;
    }
    let dir = tempfile::tempdir().expect("tempdir");
    fuzz(dir.path(), &[], None);
}

#[test]
fn schemathesis_finds_nothing_with_a_token() {
    if !common::python_module_available("schemathesis", "'schemathesis>=4,<5'") {
        return;
    }
    let dir = tempfile::tempdir().expect("tempdir");
    let token = "schemathesis-token-0123456789";
    let file = dir.path().join("token");
    std::fs::write(&file, token).expect("token");
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&file, std::fs::Permissions::from_mode(0o600)).expect("chmod");
    }
    fuzz(
        dir.path(),
        &["--token-file", file.to_str().expect("utf-8")],
        Some(token),
    );
}
