//! `geocal._geocal`: the Rust core behind the Python package `geocal` (python/geocal/).
//! Every function calls the library function the command line calls and hands back its JSON
//! text exactly as the command line writes it, plus Arrow record batches for the tables;
//! the pure-Python package turns them into typed objects.

mod progress;
mod samples;

use std::path::{Path, PathBuf};

use arrow_array::RecordBatch;
use arrow_pyarrow::ToPyArrow;
use pyo3::exceptions::PyException;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use progress::Callback;

pyo3::create_exception!(
    _geocal,
    GeocalError,
    PyException,
    "A geocal command failed; the message is the command line's (its causes on `because:` lines)."
);

/// The command line's message for `e` (without its `error: ` prefix and final newline).
fn to_py_err(e: anyhow::Error) -> PyErr {
    let text = geocal::console::error_text(&e);
    let text = text.strip_prefix("error: ").unwrap_or(&text);
    GeocalError::new_err(text.trim_end().to_owned())
}

fn pyarrow(py: Python<'_>, batch: RecordBatch) -> PyResult<Bound<'_, PyAny>> {
    batch.to_pyarrow(py)
}

/// A results document's tables (parameters with σ, points, error functions) as the fleet
/// export builds them, without the export's run columns.
fn results_tables<'py>(py: Python<'py>, json: &str) -> PyResult<Bound<'py, PyDict>> {
    let value: serde_json::Value =
        serde_json::from_str(json).map_err(|e| to_py_err(anyhow::anyhow!("results JSON: {e}")))?;
    let tables = PyDict::new(py);
    for (name, batch) in samples::results_tables(&value).map_err(to_py_err)? {
        tables.set_item(name, pyarrow(py, batch)?)?;
    }
    Ok(tables)
}

/// read_session(path) -> dict: the session as `geocal solve` reads it.
#[pyfunction]
fn read_session<'py>(py: Python<'py>, path: PathBuf) -> PyResult<Bound<'py, PyDict>> {
    let read = py.detach(|| samples::read(&path)).map_err(to_py_err)?;
    let out = PyDict::new(py);
    out.set_item("header_json", read.header_json)?;
    out.set_item("events_json", read.events_json)?;
    out.set_item("losses_json", read.losses_json)?;
    for (group, batches) in read.devices {
        let by_id = PyDict::new(py);
        for (id, batch) in batches {
            by_id.set_item(id, pyarrow(py, batch)?)?;
        }
        out.set_item(group, by_id)?;
    }
    Ok(out)
}

fn solve_json(
    path: &Path,
    effects: &[String],
    callback: &Callback,
) -> anyhow::Result<(String, String)> {
    // Progress in bytes of the file read, plus one step for the solve after the read.
    let total = std::fs::metadata(path).map_or(0, |m| m.len()) + 1;
    let reader = callback.clone();
    let settings = geocal::kinds::diagnosis::solve_settings(
        path,
        effects,
        geocal::method::SolveSettings {
            read_progress: Some(geocal::session::reader::ReadProgress::new(
                move |done, _| {
                    reader.report(done, total);
                },
            )),
            ..Default::default()
        },
    )?;
    callback.report(0, total);
    let results = geocal::kinds::solve_file(path, &settings)?;
    callback.report(total, total);
    Ok((results.to_json_pretty(), results.report()))
}

/// solve(path, effects, progress) -> (results JSON, text report, tables)
#[pyfunction]
#[pyo3(signature = (path, effects=None, progress=None))]
fn solve<'py>(
    py: Python<'py>,
    path: PathBuf,
    effects: Option<Vec<String>>,
    progress: Option<Py<PyAny>>,
) -> PyResult<(String, String, Bound<'py, PyDict>)> {
    let callback = Callback::new(progress);
    let effects = effects.unwrap_or_default();
    let (json, text) = py
        .detach(|| solve_json(&path, &effects, &callback))
        .map_err(to_py_err)?;
    callback.raised()?;
    let tables = results_tables(py, &json)?;
    Ok((json, text, tables))
}

/// results_tables(json) -> tables of a results document (a run folder's results.json).
#[pyfunction(name = "results_tables")]
fn results_tables_of<'py>(py: Python<'py>, json: &str) -> PyResult<Bound<'py, PyDict>> {
    results_tables(py, json)
}

/// diagnose(path, progress) -> (diagnosis JSON, text)
#[pyfunction]
#[pyo3(signature = (path, progress=None))]
fn diagnose(
    py: Python<'_>,
    path: PathBuf,
    progress: Option<Py<PyAny>>,
) -> PyResult<(String, String)> {
    let callback = Callback::new(progress);
    let (json, text) = py
        .detach(|| -> anyhow::Result<(String, String)> {
            let hook = callback.clone();
            let options = geocal::diagnose::DiagnoseOptions {
                progress: Some(geocal::progress_sink::ProgressSink::new(
                    move |done, total| {
                        hook.report(done, total);
                    },
                )),
                ..Default::default()
            };
            let (diagnosis, _) = geocal::kinds::diagnosis::diagnose_file_detailed(&path, &options)?;
            Ok((
                serde_json::to_string_pretty(&diagnosis)?,
                geocal::diagnose::text(&diagnosis),
            ))
        })
        .map_err(to_py_err)?;
    callback.raised()?;
    Ok((json, text))
}

/// check(config) -> (plan check JSON, text)
#[pyfunction]
fn check(py: Python<'_>, config: PathBuf) -> PyResult<(String, String)> {
    py.detach(|| -> anyhow::Result<(String, String)> {
        let kinds = geocal::kinds::Registry::standard();
        let check = kinds.of_config(&config)?.check(&config)?;
        Ok((serde_json::to_string_pretty(&check.json)?, check.text))
    })
    .map_err(to_py_err)
}

/// compare(a, b, alpha, tolerance_m, tolerance_rad, tolerance_other) -> (JSON, text)
#[pyfunction]
#[pyo3(signature = (a, b, alpha=0.05, tolerance_m=None, tolerance_rad=None, tolerance_other=None))]
fn compare(
    py: Python<'_>,
    a: PathBuf,
    b: PathBuf,
    alpha: f64,
    tolerance_m: Option<f64>,
    tolerance_rad: Option<f64>,
    tolerance_other: Option<f64>,
) -> PyResult<(String, String)> {
    use geocal::history::compare::{CompareOptions, Tolerances};
    py.detach(|| -> anyhow::Result<(String, String)> {
        let a = geocal::history::load::Run::load(&a)?;
        let b = geocal::history::load::Run::load(&b)?;
        let options = CompareOptions {
            alpha,
            tolerances: Tolerances {
                m: tolerance_m,
                rad: tolerance_rad,
                other: tolerance_other,
            },
        };
        let comparison = geocal::history::compare::compare(&a, &b, &options)?;
        Ok((
            serde_json::to_string_pretty(&comparison)?,
            geocal::history::compare::text(&comparison),
        ))
    })
    .map_err(to_py_err)
}

/// run(config, out, truth, progress) -> dict: the run's paths, results JSON, text, tables
#[pyfunction]
#[pyo3(signature = (config, out, truth=None, progress=None))]
fn run<'py>(
    py: Python<'py>,
    config: PathBuf,
    out: PathBuf,
    truth: Option<PathBuf>,
    progress: Option<Py<PyAny>>,
) -> PyResult<Bound<'py, PyDict>> {
    let callback = Callback::new(progress);
    let cancel = tokio_util::sync::CancellationToken::new();
    let output = py
        .detach(|| -> anyhow::Result<_> {
            let kind = geocal::kinds::Registry::standard().of_config(&config)?;
            let control = geocal::run::control::RunControl {
                cancel: cancel.clone(),
                progress: Some(callback.sink(cancel.clone())),
                ..Default::default()
            };
            let options = geocal::run::RunOptions {
                out_dir: out,
                truth,
                progress: false,
                settings: Default::default(),
                control,
            };
            let output = kind.run(&config, &options, &Default::default())?;
            Ok((
                output.session_path,
                output.results_path,
                output.results.to_json_pretty(),
                output.results.report(),
                output.recorded,
            ))
        })
        .map_err(to_py_err);
    // A callback that raised (Ctrl-C included) cancelled the run: its exception wins.
    callback.raised()?;
    let (session_path, results_path, json, text, recorded) = output?;
    let out = PyDict::new(py);
    out.set_item("session_path", session_path)?;
    out.set_item("results_path", results_path)?;
    out.set_item("results_json", &json)?;
    out.set_item("text", text)?;
    out.set_item("recorded", recorded)?;
    out.set_item("tables", results_tables(py, &json)?)?;
    Ok(out)
}

#[pymodule]
fn _geocal(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("GeocalError", m.py().get_type::<GeocalError>())?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add_function(wrap_pyfunction!(read_session, m)?)?;
    m.add_function(wrap_pyfunction!(solve, m)?)?;
    m.add_function(wrap_pyfunction!(results_tables_of, m)?)?;
    m.add_function(wrap_pyfunction!(diagnose, m)?)?;
    m.add_function(wrap_pyfunction!(check, m)?)?;
    m.add_function(wrap_pyfunction!(compare, m)?)?;
    m.add_function(wrap_pyfunction!(run, m)?)?;
    Ok(())
}
