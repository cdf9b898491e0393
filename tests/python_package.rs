//! The Python package (python/, docs/python.md): its wheel built with maturin into this
//! target directory with the dev profile (the geocal build of this test run is reused: only
//! pyo3 and the binding compile), installed into a fresh virtual environment, and its pytest
//! suite (python/tests/) run there: every function against the command line, the sessions'
//! Arrow arrays against the `mcap` package, the example notebook through nbclient. A second
//! environment without site packages shows the wheel imports with only Python.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

/// The Python modules the suite uses (pip package names where they differ).
const TEST_MODULES: &[(&str, &str)] = &[
    ("pytest", "pytest"),
    ("numpy", "numpy"),
    ("pyarrow", "pyarrow"),
    ("pandas", "pandas"),
    ("polars", "polars"),
    ("matplotlib", "matplotlib"),
    ("mcap", "mcap"),
    ("nbformat", "nbformat"),
    ("nbclient", "nbclient"),
    ("ipykernel", "ipykernel"),
];

/// Why the suite cannot run here, if it cannot: in CI (which installs all of it) a failure.
fn missing() -> Option<String> {
    let maturin = Command::new("maturin").arg("--version").output();
    if !maturin.is_ok_and(|o| o.status.success()) {
        return Some("maturin is not installed (pip install maturin)".into());
    }
    let imports: Vec<&str> = TEST_MODULES.iter().map(|(m, _)| *m).collect();
    let found = Command::new("python3")
        .args(["-c", &format!("import {}", imports.join(", "))])
        .output();
    if !found.is_ok_and(|o| o.status.success()) {
        let packages: Vec<&str> = TEST_MODULES.iter().map(|(_, p)| *p).collect();
        return Some(format!(
            "python3 cannot import the test modules (pip install {})",
            packages.join(" ")
        ));
    }
    None
}

fn run(what: &str, command: &mut Command) {
    let started = Instant::now();
    let status = command
        .status()
        .unwrap_or_else(|e| panic!("{what}: cannot start: {e}"));
    assert!(status.success(), "{what} failed ({status})");
    println!("{what}: {:.1} s", started.elapsed().as_secs_f64());
}

fn wheel_in(dir: &Path) -> PathBuf {
    let wheels: Vec<PathBuf> = std::fs::read_dir(dir)
        .expect("wheel folder")
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "whl"))
        .collect();
    assert_eq!(
        wheels.len(),
        1,
        "one wheel in {}: {wheels:?}",
        dir.display()
    );
    wheels[0].clone()
}

#[test]
fn python_package_passes_its_suite() {
    if let Some(why) = missing() {
        assert!(
            std::env::var_os("CI").is_none(),
            "CI must test the Python package, but {why}"
        );
        println!("skipped: {why}");
        return;
    }
    let repo = Path::new(env!("CARGO_MANIFEST_DIR"));
    // target/ (this test's own temporary folder is target/tmp).
    let target = Path::new(env!("CARGO_TARGET_TMPDIR"))
        .parent()
        .expect("target dir");
    let work = tempfile::tempdir().expect("temp dir");
    let wheels = work.path().join("wheels");
    run(
        "maturin build (dev profile, this target dir)",
        Command::new("maturin")
            .args([
                "build",
                "--profile",
                "dev",
                "--interpreter",
                "python3",
                "--out",
            ])
            .arg(&wheels)
            .arg("--manifest-path")
            .arg(repo.join("python/Cargo.toml"))
            .env("CARGO_TARGET_DIR", target),
    );
    let wheel = wheel_in(&wheels);
    // The test-side packages come from the system Python (CI installs them once); only the
    // wheel goes into the environment.
    let venv = work.path().join("venv");
    let bare = work.path().join("bare");
    // Environments without their own pip (ensurepip took seconds each): the system's pip
    // installs the wheel into them.
    for (env, site) in [(&venv, true), (&bare, false)] {
        let mut command = Command::new("python3");
        command.args(["-m", "venv", "--without-pip"]);
        if site {
            command.arg("--system-site-packages");
        }
        run("venv", command.arg(env));
        run(
            "pip install the wheel",
            Command::new("python3")
                .args(["-m", "pip", "--python"])
                .arg(env.join("bin/python"))
                .args([
                    "install",
                    "--quiet",
                    "--disable-pip-version-check",
                    "--no-index",
                    "--no-deps",
                ])
                .arg(&wheel),
        );
    }
    run(
        "pytest python/tests",
        Command::new(venv.join("bin/python"))
            .args([
                "-m",
                "pytest",
                "-q",
                "-p",
                "no:cacheprovider",
                "--durations=5",
            ])
            .arg(repo.join("python/tests"))
            // Not the repository: `import geocal` must find the installed wheel.
            .current_dir(work.path())
            .env("GEOCAL_BIN", env!("CARGO_BIN_EXE_geocal"))
            .env("GEOCAL_REPO", repo)
            .env("GEOCAL_SESSIONS", repo.join("../shared/sessions"))
            .env("GEOCAL_WHEEL", &wheel)
            .env("GEOCAL_BARE_PYTHON", bare.join("bin/python")),
    );
}
