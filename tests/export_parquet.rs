//! `geocal export --format parquet` read by an outside engine: DuckDB (PyPI) reads the export
//! of three small simulated runs of two machines, and its numbers are checked against the
//! results files, the ISO 230-2 figures computed from the live results, the diagnosis and the
//! sessions' raw samples; the DuckDB queries of docs/fleet.md run against it; docs/fleet.md
//! lists every column of every table; a damaged results file is skipped with a warning.

use crate::common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use geocal::evaluate::iso230_2::UnitFigures;
use geocal::evaluate::of_results;
use geocal::export::rows::as_planned;
use geocal::export::schema::{Column, ColumnType, RUN_COLUMNS, TABLES};
use geocal::history::MachineIdentity;
use geocal::session::reader::read_session;
use serde_json::{json, Value};

const FLEET_DOC: &str = include_str!("../docs/fleet.md");

/// Two machines: the mill's two runs differ in their simulated machine (another seed: other
/// squareness), with small positioning errors; the bridge's one run has large ones (it fails
/// the docs' 6 µm ISO 230-2 E query) and a diagnosis. Names with a space, `/`, parentheses
/// and a non-ASCII letter check the partition escaping.
const MILL: &str = "Mill 3/A (simulated) é";
const BRIDGE: &str = "Bridge CMM 9";
const BRIDGE_SERIAL: &str = "SN 0042";

/// The demo (5 stations, 5 × 5 × 4 points: enough for the 21 errors, and a serpentine pass
/// reaches 3 x targets both ways for ISO 230-2), named and sized as asked.
fn config(machine: &str, seed: u64, positioning_m: f64) -> String {
    let text = common::DEMO
        .replace(
            "name = \"Bridge CMM 14-24-10 (simulated)\"",
            &format!("name = {machine:?}"),
        )
        .replace("seed = 20261121", &format!("seed = {seed}"))
        .replace(
            "positioning_m = 5e-6",
            &format!("positioning_m = {positioning_m:e}"),
        );
    assert!(text.contains(&format!("seed = {seed}")) && text.contains(&format!("{machine:?}")));
    // The bridge declares its serial (the mill does not).
    if machine == BRIDGE {
        text.replace(
            &format!("name = {machine:?}"),
            &format!("name = {machine:?}\nserial = {BRIDGE_SERIAL:?}"),
        )
    } else {
        text
    }
}

struct Run {
    dir: PathBuf,
    machine: &'static str,
    results: Value,
    iso: geocal::evaluate::deviations::Iso230_2,
}

fn geocal(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_geocal"))
        .args(args)
        .output()
        .expect("run geocal")
}

/// Run `queries` (name → SQL) after `setup` with DuckDB; name → rows.
fn duckdb(
    setup: &[String],
    queries: &BTreeMap<String, String>,
) -> BTreeMap<String, Vec<Vec<Value>>> {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/duckdb_query.py");
    let mut child = Command::new("python3")
        .arg(&script)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("python3");
    let request = json!({"setup": setup, "queries": queries});
    {
        use std::io::Write;
        let mut stdin = child.stdin.take().expect("stdin");
        stdin
            .write_all(request.to_string().as_bytes())
            .expect("write request");
    }
    let output = child.wait_with_output().expect("python3 output");
    assert!(
        output.status.success(),
        "DuckDB failed (pip install duckdb?):\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let answer: Value = serde_json::from_slice(&output.stdout).expect("DuckDB answer JSON");
    answer
        .as_object()
        .expect("object")
        .iter()
        .map(|(name, a)| {
            let rows = a["rows"]
                .as_array()
                .expect("rows")
                .iter()
                .map(|r| r.as_array().expect("row").clone())
                .collect();
            (name.clone(), rows)
        })
        .collect()
}

/// The machine key of a machine with this name and serial (docs/fleet.md, "One machine").
fn key_of(name: &str, serial: Option<&str>) -> String {
    MachineIdentity {
        name: Some(name.to_owned()),
        serial: serial.map(str::to_owned),
        id: None,
    }
    .key()
}

fn q(name: &str, sql: String) -> (String, String) {
    (name.to_owned(), sql)
}

fn table(dest: &Path, name: &str) -> String {
    format!(
        "read_parquet('{}/{name}/**/*.parquet', hive_partitioning = true)",
        dest.display()
    )
}

fn f(v: &Value) -> Option<f64> {
    v.as_f64()
}

/// Equal to the last bit, or both null: the export carries the results' numbers unchanged.
fn same(got: &Value, want: &Value, what: &str) {
    assert_eq!(f(got), f(want), "{what}: DuckDB {got}, results {want}");
}

/// The DuckDB blocks of docs/fleet.md (`-- duckdb: <name>` first), `fleet/` pointing at `dest`.
fn doc_queries(dest: &Path) -> BTreeMap<String, String> {
    let mut out = BTreeMap::new();
    for block in FLEET_DOC.split("```sql\n").skip(1) {
        let body = block.split("```").next().unwrap_or_default();
        let Some(name) = body
            .lines()
            .next()
            .and_then(|l| l.strip_prefix("-- duckdb: "))
        else {
            continue;
        };
        out.insert(
            name.trim().to_owned(),
            body.replace("'fleet/", &format!("'{}/", dest.display())),
        );
    }
    out
}

/// docs/fleet.md lists every column of every table, with its type and nullability as the code
/// writes them, in order.
#[test]
fn fleet_doc_lists_every_column() {
    let type_name = |t: ColumnType| match t {
        ColumnType::Int32 => "int32",
        ColumnType::Int64 => "int64",
        ColumnType::Float64 => "double",
        ColumnType::Bool => "boolean",
        ColumnType::Utf8 => "string",
        ColumnType::Utf8List => "list<string>",
        ColumnType::TimestampUs => "timestamp (µs, UTC)",
        ColumnType::Date => "date",
    };
    let sections = TABLES
        .iter()
        .map(|def| (format!("### `{}`", def.name), def.own_columns))
        .chain([("### Every table: the run's columns".to_owned(), RUN_COLUMNS)]);
    for (heading, columns) in sections {
        let columns: &[Column] = columns;
        let section = FLEET_DOC
            .split(&heading)
            .nth(1)
            .unwrap_or_else(|| panic!("docs/fleet.md has no section {heading}"));
        let section = section.split("\n### ").next().unwrap_or_default();
        let documented: Vec<(String, String, String)> = section
            .lines()
            .filter(|l| l.starts_with("| `"))
            .map(|l| {
                let cells: Vec<&str> = l.split('|').map(str::trim).collect();
                (
                    cells[1].trim_matches('`').to_owned(),
                    cells[2].to_owned(),
                    cells[3].to_owned(),
                )
            })
            .collect();
        let code: Vec<(String, String, String)> = columns
            .iter()
            .map(|c| {
                (
                    c.name.to_owned(),
                    type_name(c.kind).to_owned(),
                    if c.nullable { "yes" } else { "no" }.to_owned(),
                )
            })
            .collect();
        assert_eq!(documented, code, "docs/fleet.md, {heading}");
    }
}

#[test]
fn duckdb_reads_the_export_as_the_results_say() {
    let work = tempfile::tempdir().expect("tempdir");
    let fleet = work.path().join("runs");
    let mut runs = Vec::new();
    for (name, machine, text) in [
        ("mill-1", MILL, config(MILL, 11, 1e-6)),
        ("mill-2", MILL, config(MILL, 12, 1e-6)),
        ("bridge-1", BRIDGE, config(BRIDGE, 13, 3e-5)),
    ] {
        let dir = fleet.join(name);
        let (output, _) = common::run_with_truth(&text, &dir);
        let session = read_session(&output.session_path).expect("session");
        let iso = of_results(&output.results, &session).expect("ISO 230-2");
        let results: Value =
            serde_json::from_slice(&std::fs::read(&output.results_path).expect("results"))
                .expect("results JSON");
        runs.push(Run {
            dir,
            machine,
            results,
            iso,
        });
    }
    let bridge = &runs[2];
    let (diagnosis, _) = geocal::kinds::diagnosis::diagnose_file_detailed(
        &bridge.dir.join("session.mcap"),
        &Default::default(),
    )
    .expect("diagnosis");
    std::fs::write(
        bridge.dir.join("diagnosis.json"),
        serde_json::to_string_pretty(&diagnosis).expect("diagnosis JSON"),
    )
    .expect("write diagnosis");

    let dest = work.path().join("fleet");
    let out = geocal(&[
        "export",
        "--format",
        "parquet",
        fleet.to_str().expect("path"),
        "--out",
        dest.to_str().expect("path"),
        "--raw",
    ]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stdout}\n{stderr}");
    assert!(stdout.contains("3 runs exported, 0 skipped"), "{stdout}");
    // Hive partitions by machine key: ASCII, nothing to escape.
    let mill_key = key_of(MILL, None);
    assert!(mill_key.starts_with("m-mill-3-a-simulated-"), "{mill_key}");
    assert!(
        dest.join(format!("runs/machine_key={mill_key}")).is_dir(),
        "{stdout}"
    );

    let session_of = |r: &Run| r.results["session_id"].as_str().expect("id").to_owned();
    let mut queries: BTreeMap<String, String> = [
        q(
            "runs",
            format!(
                "SELECT session_id, machine, kind, schema_version, chi2_per_dof, dof, \
                 residual_rms_m, raw_samples, iso230_2_note, date = CAST(timezone('UTC', started_at) AS DATE), \
                 machine_serial, structure FROM {} ORDER BY session_id",
                table(&dest, "runs")
            ),
        ),
        q(
            "parameters",
            format!(
                "SELECT session_id, name, value, sigma, unit, identifiable, machine FROM {} \
                 ORDER BY session_id, name",
                table(&dest, "parameters")
            ),
        ),
        q(
            "error_functions",
            format!(
                "SELECT session_id, axis, error_function, position, value, sigma, unit, parameter \
                 FROM {} ORDER BY session_id, axis, error_function, position",
                table(&dest, "error_functions")
            ),
        ),
        q(
            "points",
            format!(
                "SELECT session_id, target, point, error_x_m, error_y_m, error_z_m, sigma_x_m, \
                 sigma_y_m, sigma_z_m, nominal_x_m FROM {} ORDER BY session_id, target, point",
                table(&dest, "points")
            ),
        ),
        q(
            "iso",
            format!(
                "SELECT session_id, axis, unit, systematic_error, reversal, mean_error, \
                 systematic_error_up, runs_up, runs_down, targets FROM {} \
                 ORDER BY session_id, axis",
                table(&dest, "iso230_2")
            ),
        ),
        q(
            "diagnoses",
            format!(
                "SELECT session_id, verdict, selected, noise_floor_m, gap_rms_m, machine FROM {}",
                table(&dest, "diagnoses")
            ),
        ),
        q(
            "raw",
            format!(
                "SELECT session_id, tracer, count(*), sum(length_m), min(seq), max(seq), \
                 min(log_time_ns), bool_and(epoch_us(log_time) = log_time_ns // 1000) FROM {} \
                 GROUP BY session_id, tracer ORDER BY session_id, tracer",
                table(&dest, "tracer_samples")
            ),
        ),
        q(
            "metadata",
            format!(
                "SELECT DISTINCT decode(key), decode(value) FROM parquet_kv_metadata('{}/*/*/*.parquet') \
                 WHERE decode(key) LIKE 'geocal.%' ORDER BY 1, 2",
                dest.display()
            ),
        ),
    ]
    .into_iter()
    .collect();
    let docs = doc_queries(&dest);
    for name in [
        "squareness_drift",
        "iso_e_failed",
        "verdicts",
        "runs_per_machine",
    ] {
        let sql = docs
            .get(name)
            .unwrap_or_else(|| panic!("docs/fleet.md has no `-- duckdb: {name}` query"));
        queries.insert(format!("doc_{name}"), sql.clone());
    }
    let setup_block: String = docs
        .get("setup")
        .expect("docs/fleet.md has a `-- duckdb: setup` block")
        .lines()
        .filter(|l| !l.starts_with("--"))
        .collect::<Vec<_>>()
        .join("\n");
    let setup: Vec<String> = setup_block
        .split(';')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(str::to_owned)
        .collect();
    let answers = duckdb(&setup, &queries);

    // runs: one per run, with the results' fit figures.
    let runs_rows = &answers["runs"];
    assert_eq!(runs_rows.len(), 3);
    for r in &runs {
        let id = session_of(r);
        let row = runs_rows
            .iter()
            .find(|row| row[0] == json!(id))
            .unwrap_or_else(|| panic!("run {id} exported"));
        assert_eq!(row[1], json!(r.machine));
        assert_eq!(row[2], r.results["kind"]);
        assert_eq!(row[3], json!(2), "schema version");
        same(&row[4], &r.results["chi2_per_dof"], "chi2_per_dof");
        assert_eq!(row[5], r.results["dof"]);
        same(&row[6], &r.results["residual_rms_m"], "residual_rms_m");
        assert!(row[8].is_null(), "ISO 230-2 of {id}: {}", row[8]);
        assert_eq!(row[9], json!(true), "date is the start's date");
        let serial = (r.machine == BRIDGE).then_some(BRIDGE_SERIAL);
        assert_eq!(row[10], json!(serial), "the declared serial");
        assert_eq!(row[11], json!("FYXZ"));
    }

    // parameters: every station coordinate and squareness with its σ, from results.json.
    let params = &answers["parameters"];
    for r in &runs {
        let id = session_of(r);
        let find = |name: &str| {
            params
                .iter()
                .find(|p| p[0] == json!(id) && p[1] == json!(name))
                .unwrap_or_else(|| panic!("parameter {name} of {id}"))
        };
        for (name, s) in r.results["geometric_errors"]["squareness"]
            .as_object()
            .expect("squareness")
        {
            let row = find(name);
            same(&row[2], &s["value_rad"], name);
            same(&row[3], &s["sigma_rad"], name);
            assert_eq!(row[4], json!("rad"));
            assert_eq!(row[5], s["identifiable"]);
            assert_eq!(row[6], json!(r.machine));
        }
        for station in r.results["stations"].as_array().expect("stations") {
            for (k, axis) in ["x", "y", "z"].iter().enumerate() {
                let row = find(&format!(
                    "station.{}.{axis}",
                    station["id"].as_str().expect("id")
                ));
                same(&row[2], &station["position_m"][k], "station");
                same(&row[3], &station["sigma_m"][k], "station σ");
            }
        }
    }

    // error_functions: every value of every function at every grid position.
    let functions = &answers["error_functions"];
    let mut expected_functions = 0;
    for r in &runs {
        let id = session_of(r);
        for (axis, a) in r.results["geometric_errors"]["axes"]
            .as_object()
            .expect("axes")
        {
            let positions = a["positions_m"].as_array().expect("positions");
            for (name, e) in a["errors"].as_object().expect("errors") {
                for (i, position) in positions.iter().enumerate() {
                    expected_functions += 1;
                    let row = functions
                        .iter()
                        .find(|row| {
                            row[0] == json!(id)
                                && row[1] == json!(axis)
                                && row[2] == json!(name)
                                && f(&row[3]).map(as_planned) == f(position).map(as_planned)
                        })
                        .unwrap_or_else(|| panic!("{name} of {id} at {position}"));
                    let planned = f(&row[3]).expect("position");
                    assert_eq!(
                        planned,
                        as_planned(planned),
                        "{name} at {position}: as planned"
                    );
                    same(&row[4], &e["values"][i], name);
                    same(&row[5], &e["sigma"][i], name);
                    assert_eq!(row[6], e["unit"]);
                }
            }
        }
    }
    assert_eq!(functions.len(), expected_functions);

    // points: the volumetric errors and their σ.
    let points = &answers["points"];
    let mut expected_points = 0;
    for r in &runs {
        let id = session_of(r);
        for p in r.results["points"].as_array().expect("points") {
            expected_points += 1;
            let row = points
                .iter()
                .find(|row| row[0] == json!(id) && row[1] == p["target"] && row[2] == p["point"])
                .expect("point exported");
            for k in 0..3 {
                same(&row[3 + k], &p["error_m"][k], "error_m");
                same(&row[6 + k], &p["sigma_m"][k], "sigma_m");
            }
            same(&row[9], &p["nominal_m"][0], "nominal_m");
        }
    }
    assert_eq!(points.len(), expected_points);

    // iso230_2: the figures of the live results (not through the results file).
    let iso_rows = &answers["iso"];
    let mut expected_iso = 0;
    let mut failed_e: Vec<(String, String)> = Vec::new();
    let mut passed_e = 0;
    for r in &runs {
        let id = session_of(r);
        for a in &r.iso.axes {
            expected_iso += 1;
            let row = iso_rows
                .iter()
                .find(|row| row[0] == json!(id) && row[1] == json!(a.axis))
                .unwrap_or_else(|| panic!("ISO 230-2 {} of {id}", a.axis));
            let UnitFigures::Metres(figures) = &a.evaluation.figures else {
                panic!("a linear axis");
            };
            let bi = figures.bidirectional.as_ref().expect("both directions");
            assert_eq!(row[2], json!("m"));
            assert_eq!(f(&row[3]), Some(bi.systematic_error), "E of {}", a.axis);
            assert_eq!(f(&row[4]), Some(bi.reversal));
            assert_eq!(f(&row[5]), Some(bi.mean_error));
            assert_eq!(f(&row[6]), figures.up.as_ref().map(|u| u.systematic_error));
            assert_eq!(row[7], json!(a.evaluation.runs_up));
            assert_eq!(row[8], json!(a.evaluation.runs_down));
            assert_eq!(row[9], json!(a.evaluation.targets));
            if bi.systematic_error > 6e-6 {
                failed_e.push((id.clone(), a.axis.clone()));
            } else {
                passed_e += 1;
            }
        }
    }
    assert_eq!(iso_rows.len(), expected_iso);
    println!("ISO 230-2 E > 6 µm: {failed_e:?}; {passed_e} axes within");
    assert!(
        !failed_e.is_empty() && passed_e > 0,
        "the docs' E query should split these runs: {failed_e:?}, {passed_e} within"
    );

    // diagnoses: the bridge's verdict.
    let diagnoses = &answers["diagnoses"];
    assert_eq!(diagnoses.len(), 1);
    assert_eq!(diagnoses[0][0], json!(diagnosis.session_id));
    assert_eq!(
        diagnoses[0][1],
        json!(geocal::export::rows::verdict(&diagnosis))
    );
    assert_eq!(diagnoses[0][2], json!(diagnosis.selected));
    assert_eq!(f(&diagnoses[0][3]), Some(diagnosis.noise_floor_m));
    assert_eq!(f(&diagnoses[0][4]), Some(diagnosis.gap.rms_m));
    assert_eq!(diagnoses[0][5], json!(BRIDGE));

    // tracer_samples: every raw sample of every session, as the session reader reads them.
    let raw = &answers["raw"];
    assert_eq!(raw.len(), 3, "{raw:?}");
    for r in &runs {
        let id = session_of(r);
        let session = read_session(&r.dir.join("session.mcap")).expect("session");
        for (tracer, samples) in &session.tracers {
            let row = raw
                .iter()
                .find(|row| row[0] == json!(id) && row[1] == json!(tracer))
                .expect("raw samples exported");
            assert_eq!(row[2], json!(samples.len()));
            let sum: f64 = samples.iter().map(|s| s.msg.length_m).sum();
            let got = f(&row[3]).expect("sum");
            assert!(
                (got - sum).abs() <= 1e-9 * sum.abs().max(1.0),
                "{got} vs {sum}"
            );
            assert_eq!(row[4], json!(samples.iter().map(|s| s.msg.seq).min()));
            assert_eq!(row[5], json!(samples.iter().map(|s| s.msg.seq).max()));
            assert_eq!(row[6], json!(samples.iter().map(|s| s.log_time_ns).min()));
            assert_eq!(row[7], json!(true), "log_time is log_time_ns to the µs");
        }
    }

    // Every file says its schema version and table.
    let metadata = &answers["metadata"];
    assert!(metadata.contains(&vec![json!("geocal.schema_version"), json!("2")]));
    for name in [
        "runs",
        "parameters",
        "error_functions",
        "points",
        "iso230_2",
        "diagnoses",
        "tracer_samples",
    ] {
        assert!(
            metadata.contains(&vec![json!("geocal.table"), json!(name)]),
            "{metadata:?}"
        );
    }

    // docs/fleet.md: squareness drift this quarter: the mill's two runs, change = last − first.
    let drift = &answers["doc_squareness_drift"];
    println!("squareness drift: {drift:?}");
    let (first, last) = (&runs[0].results, &runs[1].results);
    let identifiable: Vec<(&String, &Value)> = last["geometric_errors"]["squareness"]
        .as_object()
        .expect("squareness")
        .iter()
        .filter(|(_, s)| s["identifiable"] == json!(true))
        .collect();
    assert_eq!(drift.len(), identifiable.len(), "{drift:?}");
    for row in drift {
        assert_eq!(
            row[0],
            json!(mill_key),
            "only the mill has two runs: {row:?}"
        );
        assert_eq!(row[1], json!(MILL));
        assert_eq!(row[3], json!(2));
        let name = row[2].as_str().expect("name");
        let want = last["geometric_errors"]["squareness"][name]["value_rad"]
            .as_f64()
            .expect("value")
            - first["geometric_errors"]["squareness"][name]["value_rad"]
                .as_f64()
                .expect("value");
        assert_eq!(f(&row[4]), Some(want), "{name}");
    }
    let largest = drift
        .iter()
        .map(|row| f(&row[4]).expect("change").abs())
        .fold(0.0, f64::max);
    assert_eq!(
        f(&drift[0][4]).map(f64::abs),
        Some(largest),
        "ordered by |change|"
    );

    // docs/fleet.md: ISO 230-2 E beyond 6 µm: exactly the axes the live figures put there.
    let mut got: Vec<(String, String)> = answers["doc_iso_e_failed"]
        .iter()
        .map(|row| {
            (
                row[3].as_str().expect("session").to_owned(),
                row[4].as_str().expect("axis").to_owned(),
            )
        })
        .collect();
    got.sort();
    failed_e.sort();
    assert_eq!(got, failed_e);

    // docs/fleet.md: verdicts per machine.
    let bridge_key = key_of(BRIDGE, Some(BRIDGE_SERIAL));
    assert_eq!(
        answers["doc_verdicts"],
        vec![vec![
            json!(bridge_key),
            json!(BRIDGE),
            json!(BRIDGE_SERIAL),
            json!(geocal::export::rows::verdict(&diagnosis)),
            json!(1)
        ]]
    );
    // docs/fleet.md: runs per machine and kind, with their parameters.
    let parameters_of = |r: &Run| {
        params
            .iter()
            .filter(|p| p[0] == json!(session_of(r)))
            .count()
    };
    let mut want = vec![
        vec![
            json!(bridge_key),
            json!(BRIDGE),
            json!(BRIDGE_SERIAL),
            json!("multilateration"),
            json!(1),
            json!(parameters_of(&runs[2])),
        ],
        vec![
            json!(mill_key),
            json!(MILL),
            Value::Null,
            json!("multilateration"),
            json!(2),
            json!(parameters_of(&runs[0]) + parameters_of(&runs[1])),
        ],
    ];
    want.sort_by_key(|row| row[0].to_string());
    assert_eq!(answers["doc_runs_per_machine"], want);
    // The history's names are the export's: every parameter compare and trend follow is a
    // parameter or an error function of the export, by the same name.
    let exported_names = |session: &str| -> Vec<String> {
        params
            .iter()
            .filter(|p| p[0] == json!(session))
            .map(|p| p[1].as_str().expect("name").to_owned())
            .chain(
                functions
                    .iter()
                    .filter(|e| e[0] == json!(session))
                    .map(|e| e[7].as_str().expect("parameter").to_owned()),
            )
            .collect()
    };
    for r in &runs {
        let names = exported_names(&session_of(r));
        for p in geocal::history::parameters::parameters(&r.results).parameters {
            assert!(names.contains(&p.id), "{} not exported", p.id);
        }
    }

    // The daemon's catalog: a succeeded run job and a diagnose job of it (the diagnosis in
    // the diagnose job's folder); a failed run job is left out.
    let data = work.path().join("daemon");
    {
        use geocal::serve::catalog::{Catalog, JobState, JobType, NewJob};
        let mut catalog = Catalog::open(&data).expect("catalog");
        let mut add = |job_type, source_job, state| {
            let id = catalog
                .add(&NewJob {
                    job_type,
                    kind: "multilateration",
                    submitted_by: "test",
                    config_sha256: None,
                    source_job,
                })
                .expect("add job");
            catalog.start(id).expect("start");
            catalog.finish(id, state, None).expect("finish");
            id
        };
        let run_job = add(JobType::Run, None, JobState::Succeeded);
        let diagnose_job = add(JobType::Diagnose, Some(run_job), JobState::Succeeded);
        let failed_job = add(JobType::Run, None, JobState::Failed);
        let catalog = Catalog::open(&data).expect("catalog");
        for file in ["results.json", "session.mcap", "run-config.toml"] {
            std::fs::create_dir_all(catalog.dir_of(run_job)).expect("mkdir");
            std::fs::copy(bridge.dir.join(file), catalog.dir_of(run_job).join(file)).expect("copy");
        }
        std::fs::create_dir_all(catalog.dir_of(diagnose_job)).expect("mkdir");
        std::fs::copy(
            bridge.dir.join("diagnosis.json"),
            catalog.dir_of(diagnose_job).join("diagnosis.json"),
        )
        .expect("copy");
        // The failed job's folder holds results a reader must not take as a run.
        std::fs::create_dir_all(catalog.dir_of(failed_job)).expect("mkdir");
        std::fs::copy(
            runs[0].dir.join("results.json"),
            catalog.dir_of(failed_job).join("results.json"),
        )
        .expect("copy");
        let catalog_dest = work.path().join("catalog-fleet");
        let out = geocal(&[
            "export",
            "--format",
            "parquet",
            "--catalog",
            data.to_str().expect("path"),
            "--out",
            catalog_dest.to_str().expect("path"),
        ]);
        let stdout = String::from_utf8_lossy(&out.stdout);
        assert!(
            out.status.success(),
            "{stdout}\n{}",
            String::from_utf8_lossy(&out.stderr)
        );
        assert!(stdout.contains("1 runs exported, 0 skipped"), "{stdout}");
        let answers = duckdb(
            &[],
            &[
                q(
                    "runs",
                    format!(
                        "SELECT session_id, job_id, machine FROM {}",
                        table(&catalog_dest, "runs")
                    ),
                ),
                q(
                    "diagnoses",
                    format!(
                        "SELECT session_id, verdict FROM {}",
                        table(&catalog_dest, "diagnoses")
                    ),
                ),
            ]
            .into_iter()
            .collect(),
        );
        assert_eq!(
            answers["runs"],
            vec![vec![
                json!(session_of(bridge)),
                json!(run_job),
                json!(BRIDGE)
            ]]
        );
        assert_eq!(
            answers["diagnoses"],
            vec![vec![
                json!(session_of(bridge)),
                json!(geocal::export::rows::verdict(&diagnosis))
            ]]
        );
    }

    // Bad input. A damaged results file: that run is skipped with a warning naming the file
    // (--strict: an error naming it). A run without its session: exported without ISO 230-2
    // figures or raw samples, the machine from its configuration. A session cut short (a
    // crash): its raw samples up to the cut, every one the session reader reads, and a warning.
    let bad = work.path().join("bad");
    for (name, run, files) in [
        ("good", &runs[0], &["results.json", "session.mcap"][..]),
        ("damaged", &runs[1], &["results.json", "session.mcap"][..]),
        (
            "results-only",
            &runs[1],
            &["results.json", "run-config.toml"][..],
        ),
        (
            "truncated",
            &runs[2],
            &["results.json", "session.mcap", "run-config.toml"][..],
        ),
    ] {
        let dir = bad.join(name);
        std::fs::create_dir_all(&dir).expect("mkdir");
        for file in files {
            std::fs::copy(run.dir.join(file), dir.join(file)).expect("copy");
        }
    }
    let damaged = bad.join("damaged/results.json");
    let text = std::fs::read(&damaged).expect("read");
    std::fs::write(&damaged, &text[..text.len() / 2]).expect("truncate");
    let cut = bad.join("truncated/session.mcap");
    let bytes = std::fs::read(&cut).expect("read");
    std::fs::write(&cut, &bytes[..bytes.len() * 2 / 3]).expect("cut");
    let cut_session = read_session(&cut).expect("a cut session reads up to its last chunk");
    let cut_samples: usize = cut_session.tracers.values().map(Vec::len).sum();
    let bad_dest = work.path().join("bad-fleet");
    let args = [
        "export",
        "--format",
        "parquet",
        bad.to_str().expect("path"),
        "--out",
        bad_dest.to_str().expect("path"),
        "--raw",
    ];
    let out = geocal(&args);
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stdout}\n{stderr}");
    assert!(stdout.contains("3 runs exported, 1 skipped"), "{stdout}");
    assert!(
        stderr.contains(&format!("warning: skipped {}", damaged.display()))
            && stderr.contains("not JSON"),
        "{stderr}"
    );
    assert!(
        stderr.contains(&format!(
            "warning: {}: raw samples exported up to byte",
            cut.display()
        )),
        "{stderr}"
    );
    let answers = duckdb(
        &[],
        &[
            q(
                "runs",
                format!(
                    "SELECT machine, session_id, iso230_2_note, structure, raw_samples FROM {} \
                     ORDER BY session_id",
                    table(&bad_dest, "runs")
                ),
            ),
            q(
                "raw",
                format!(
                    "SELECT session_id, count(*) FROM {} GROUP BY session_id",
                    table(&bad_dest, "tracer_samples")
                ),
            ),
        ]
        .into_iter()
        .collect(),
    );
    let alone_row = answers["runs"]
        .iter()
        .find(|row| row[1] == json!(session_of(&runs[1])))
        .expect("the run without a session is exported");
    assert_eq!(alone_row[0], json!(MILL));
    assert!(
        alone_row[2]
            .as_str()
            .is_some_and(|n| n.contains("no session"))
            && alone_row[3].is_null()
            && alone_row[4].is_null(),
        "{alone_row:?}"
    );
    assert!(cut_samples > 0, "the cut session keeps some samples");
    assert!(
        answers["raw"].contains(&vec![json!(session_of(&runs[2])), json!(cut_samples)]),
        "{:?}, {cut_samples} in the cut session",
        answers["raw"]
    );
    let mut strict = args.to_vec();
    strict.push("--strict");
    let out = geocal(&strict);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        stderr.contains(&damaged.display().to_string()) && stderr.contains("not JSON"),
        "{stderr}"
    );

    let verdict = geocal::export::rows::verdict(&diagnosis);
    engines_read_a_fleet_alike(work.path(), &runs, &failed_e, verdict, params);
}

/// A copy of run folder `from` in `to` (the `files` it has), its configured machine renamed.
fn copy_run(from: &Path, to: &Path, files: &[&str], name: &str, serial: Option<&str>) {
    std::fs::create_dir_all(to).expect("mkdir");
    for file in files {
        std::fs::copy(from.join(file), to.join(file)).expect("copy");
        // The file's time too: a run without a session starts at its results file's time.
        let modified = std::fs::metadata(from.join(file))
            .and_then(|m| m.modified())
            .expect("file time");
        std::fs::File::options()
            .write(true)
            .open(to.join(file))
            .and_then(|f| f.set_modified(modified))
            .expect("set the file time");
    }
    rename_machine(to, name, serial);
}

/// Set the `[machine] name` and `serial` of the run folder's configuration.
fn rename_machine(dir: &Path, name: &str, serial: Option<&str>) {
    let path = dir.join("run-config.toml");
    let mut config: toml::Table = std::fs::read_to_string(&path)
        .expect("config")
        .parse()
        .expect("TOML");
    let machine = config
        .get_mut("machine")
        .and_then(|m| m.as_table_mut())
        .expect("[machine]");
    machine.insert("name".into(), name.into());
    match serial {
        Some(s) => machine.insert("serial".into(), s.into()),
        None => machine.remove("serial"),
    };
    std::fs::write(&path, toml::to_string(&config).expect("TOML")).expect("write config");
}

/// A run of another session from the results of `from` (results and configuration only: no
/// session, so no ISO 230-2 figures, and its time is the results file's, `age_s` ago).
fn results_only_run(
    from: &Path,
    to: &Path,
    session_suffix: &str,
    age_s: u64,
    name: &str,
    serial: Option<&str>,
) {
    copy_run(from, to, &["run-config.toml"], name, serial);
    let mut results: Value =
        serde_json::from_slice(&std::fs::read(from.join("results.json")).expect("results"))
            .expect("results JSON");
    let session = format!(
        "{}{session_suffix}",
        results["session_id"].as_str().expect("id")
    );
    results["session_id"] = json!(session);
    let path = to.join("results.json");
    std::fs::write(&path, serde_json::to_string(&results).expect("JSON")).expect("write");
    std::fs::File::options()
        .write(true)
        .open(&path)
        .and_then(|f| {
            f.set_modified(std::time::SystemTime::now() - std::time::Duration::from_secs(age_s))
        })
        .expect("set the results' time");
}

/// The Spark setup block and the `-- <engine>: <name>` SQL blocks of docs/fleet.md.
fn doc_blocks(engine: &str) -> BTreeMap<String, String> {
    let mut out = BTreeMap::new();
    for block in FLEET_DOC.split("```sql\n").skip(1) {
        let body = block.split("```").next().unwrap_or_default();
        if let Some(name) = body
            .lines()
            .next()
            .and_then(|l| l.strip_prefix(&format!("-- {engine}: ")))
        {
            out.insert(name.trim().to_owned(), body.to_owned());
        }
    }
    out
}

fn sorted(rows: &Value) -> Vec<Value> {
    let mut rows = rows.as_array().cloned().unwrap_or_default();
    rows.sort_by_key(|r| r.to_string());
    rows
}

/// Two engines' answers agree: the same rows, numbers to the last bits (their sqrt and power
/// may round differently).
fn agree(a: &Value, b: &Value, what: &str) {
    let (a, b) = (sorted(a), sorted(b));
    assert_eq!(a.len(), b.len(), "{what}: {a:?} vs {b:?}");
    for (ra, rb) in a.iter().zip(&b) {
        let (ra, rb) = (ra.as_array().expect("row"), rb.as_array().expect("row"));
        assert_eq!(ra.len(), rb.len(), "{what}");
        for (x, y) in ra.iter().zip(rb) {
            match (x.as_f64(), y.as_f64()) {
                (Some(x), Some(y)) if x != y => assert!(
                    (x - y).abs() <= 1e-12 * x.abs().max(y.abs()),
                    "{what}: {ra:?} vs {rb:?}"
                ),
                _ if x.is_number() && y.is_number() => {}
                _ => assert_eq!(x, y, "{what}: {ra:?} vs {rb:?}"),
            }
        }
    }
}

/// The fleet an analyst would find hard: a non-ASCII machine name, an all-digit one, two
/// machines sharing a name (serials BR-1001 and BR-1002), a run copied twice, a re-export
/// after a rename over a `--raw` one with an interrupted export's leftovers; and a fleet
/// without diagnoses, ISO 230-2 figures or raw samples. Apache Spark (one local[2] session
/// for both, running docs/fleet.md's Spark setup and every Spark SQL block as written there),
/// DuckDB (the page's DuckDB blocks), polars and pyarrow read them alike, and the answers are
/// those of the results files.
fn engines_read_a_fleet_alike(
    work: &Path,
    runs: &[Run],
    failed_e: &[(String, String)],
    verdict: &str,
    params: &[Vec<Value>],
) {
    const FRAESE: &str = "Fräse 7";
    const DIGITS: &str = "0042";
    const SHARED: &str = "Bridge";
    let src = work.join("spark-runs");
    let multi = ["results.json", "session.mcap", "run-config.toml"];
    copy_run(&runs[0].dir, &src.join("a-fraese-1"), &multi, FRAESE, None);
    copy_run(&runs[1].dir, &src.join("a-fraese-2"), &multi, FRAESE, None);
    copy_run(
        &runs[1].dir,
        &src.join("a-fraese-2-copy"),
        &multi,
        FRAESE,
        None,
    );
    let with_diagnosis = [
        "results.json",
        "session.mcap",
        "run-config.toml",
        "diagnosis.json",
    ];
    copy_run(
        &runs[2].dir,
        &src.join("b-bridge-1001"),
        &with_diagnosis,
        SHARED,
        Some("BR-1001"),
    );
    results_only_run(
        &runs[0].dir,
        &src.join("c-bridge-1002-a"),
        "-br1002",
        120,
        "Old Bridge",
        Some("BR-1002"),
    );
    results_only_run(
        &runs[1].dir,
        &src.join("c-bridge-1002-b"),
        "-br1002",
        60,
        "Old Bridge",
        Some("BR-1002"),
    );
    results_only_run(&runs[1].dir, &src.join("d-0042"), "-0042", 60, DIGITS, None);
    let dest = work.join("spark-fleet");
    let export = |from: &Path, to: &Path, raw: bool| {
        let mut args = vec![
            "export",
            "--format",
            "parquet",
            from.to_str().expect("path"),
            "--out",
            to.to_str().expect("path"),
        ];
        if raw {
            args.push("--raw");
        }
        let out = geocal(&args);
        let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
        let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
        assert!(out.status.success(), "{stdout}\n{stderr}");
        (stdout, stderr)
    };
    let (stdout, stderr) = export(&src, &dest, true);
    assert!(stdout.contains("6 runs exported, 0 skipped"), "{stdout}");
    assert!(
        stderr.contains("a-fraese-2-copy/results.json: the same run (session")
            && stderr.contains("exported once"),
        "{stderr}"
    );
    let old_key = key_of("Old Bridge", Some("BR-1002"));
    assert!(dest
        .join(format!("parameters/machine_key={old_key}"))
        .is_dir());

    // The machine renamed; an interrupted export left a file in the staging folder; exported
    // again without --raw.
    for run in ["c-bridge-1002-a", "c-bridge-1002-b"] {
        rename_machine(&src.join(run), SHARED, Some("BR-1002"));
    }
    std::fs::create_dir_all(dest.join("_staging")).expect("staging folder");
    std::fs::write(
        dest.join("_staging/parameters.r-interrupted.parquet"),
        b"PAR1 half",
    )
    .expect("leftover");
    export(&src, &dest, false);
    for table in TABLES {
        let dir = dest.join(table.name);
        assert!(
            !dir.join(format!("machine_key={old_key}")).exists(),
            "{}",
            table.name
        );
        let entries: Vec<String> = std::fs::read_dir(&dir)
            .expect("table folder")
            .map(|e| e.expect("entry").file_name().to_string_lossy().into_owned())
            .collect();
        let empty = entries.iter().any(|e| e == "empty.parquet");
        assert!(
            empty != entries.iter().any(|e| e.starts_with("machine_key=")),
            "{}: {entries:?}",
            table.name
        );
        assert_eq!(
            empty,
            table.name == "tracer_samples",
            "{}: {entries:?}",
            table.name
        );
    }
    assert!(!dest.join("_staging").exists());
    // A fleet of results only: no diagnoses, ISO 230-2 figures or raw samples.
    let bare_src = work.join("spark-runs-bare");
    for run in ["c-bridge-1002-a", "c-bridge-1002-b", "d-0042"] {
        copy_run(
            &src.join(run),
            &bare_src.join(run),
            &["results.json", "run-config.toml"],
            if run == "d-0042" { DIGITS } else { SHARED },
            (run != "d-0042").then_some("BR-1002"),
        );
    }
    let bare = work.join("spark-fleet-bare");
    export(&bare_src, &bare, false);
    // A fleet of probe and hexapod runs only: no error functions, diagnoses or ISO 230-2
    // figures, no tracer.
    let (kind_dir, _) = kind_runs();
    let kinds_src = work.join("spark-runs-kinds");
    for kind in ["probe-install", "hexapod"] {
        copy_run(
            &kind_dir.join(kind),
            &kinds_src.join(kind),
            &["results.json", "session.mcap", "run-config.toml"],
            &format!("Cell {kind}"),
            None,
        );
    }
    let kinds = work.join("spark-fleet-kinds");
    export(&kinds_src, &kinds, false);

    let duckdb_setup: Vec<String> = doc_blocks("duckdb")
        .remove("setup")
        .expect("docs/fleet.md has a `-- duckdb: setup` block")
        .lines()
        .filter(|l| !l.starts_with("--"))
        .collect::<Vec<_>>()
        .join("\n")
        .split(';')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(str::to_owned)
        .collect();
    let mut duckdb_queries = doc_blocks("duckdb");
    duckdb_queries.remove("setup");
    let spark_queries = doc_blocks("spark");
    assert_eq!(
        spark_queries.keys().collect::<Vec<_>>(),
        duckdb_queries.keys().collect::<Vec<_>>(),
        "every question in both dialects"
    );
    let spark_setup = FLEET_DOC
        .split("```python\n")
        .skip(1)
        .map(|b| b.split("```").next().unwrap_or_default())
        .find(|b| b.contains("spark.read"))
        .expect("docs/fleet.md has the Spark setup block");
    let request = json!({
        "fleets": {"fleet": dest, "bare": bare, "kinds": kinds},
        "spark_setup": spark_setup,
        "spark_queries": spark_queries,
        "duckdb_setup": duckdb_setup,
        "duckdb_queries": duckdb_queries,
        "tables": TABLES.iter().map(|t| t.name).collect::<Vec<_>>(),
    });
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/fleet_engines.py");
    let started = std::time::Instant::now();
    let mut child = Command::new("python3")
        .arg(&script)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("python3");
    {
        use std::io::Write;
        let mut stdin = child.stdin.take().expect("stdin");
        stdin
            .write_all(request.to_string().as_bytes())
            .expect("write request");
    }
    let output = child.wait_with_output().expect("python3 output");
    assert!(
        output.status.success(),
        "Spark, DuckDB, polars or pyarrow failed (a JRE and pip install pyspark duckdb \
         polars pyarrow?):\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let answer: Value = serde_json::from_slice(&output.stdout).expect("answer JSON");
    println!(
        "engines: {:.1} s in all, {}",
        started.elapsed().as_secs_f64(),
        answer["timings"]
    );

    // Every engine reads every table alike: the same machine keys, names, serials and runs,
    // each run under one machine only, every machine column a string.
    for (fleet, a) in answer["fleets"].as_object().expect("fleets") {
        for table in TABLES {
            let spark = &a["summary"]["spark"][table.name];
            for engine in ["duckdb", "polars", "pyarrow"] {
                agree(
                    &a["summary"][engine][table.name],
                    spark,
                    &format!("{fleet} {} {engine}", table.name),
                );
            }
            for (engine, types) in a["types"].as_object().expect("types") {
                for column in ["machine_key", "machine", "machine_serial", "run_id"] {
                    let t = types[table.name][column]
                        .as_str()
                        .unwrap_or_default()
                        .to_lowercase();
                    assert!(
                        t == "string"
                            || t == "varchar"
                            || t == "str"
                            || t == "dictionary<values=string, indices=int32, ordered=0>",
                        "{fleet} {engine} {}.{column}: {t}",
                        table.name
                    );
                }
            }
        }
        for (query, spark) in a["spark"].as_object().expect("spark answers") {
            agree(
                &a["duckdb"][query],
                spark,
                &format!("{fleet} {query}: DuckDB and Spark"),
            );
        }
    }

    let fleet = &answer["fleets"]["fleet"];
    let session_of = |r: &Run| r.results["session_id"].as_str().expect("id").to_owned();
    let run_id = |session: &str| geocal::export::write::run_id(session);
    let (fraese, b1001, b1002, digits) = (
        key_of(FRAESE, None),
        key_of(SHARED, Some("BR-1001")),
        key_of(SHARED, Some("BR-1002")),
        key_of(DIGITS, None),
    );
    assert!(fraese.starts_with("m-fr-se-7-") && digits.starts_with("m-0042-") && b1001 != b1002);
    // runs: one row per run, under its machine, with its name as written.
    let mut want_runs = vec![
        json!([fraese, FRAESE, null, run_id(&session_of(&runs[0])), 1]),
        json!([fraese, FRAESE, null, run_id(&session_of(&runs[1])), 1]),
        json!([b1001, SHARED, "BR-1001", run_id(&session_of(&runs[2])), 1]),
        json!([
            b1002,
            SHARED,
            "BR-1002",
            run_id(&format!("{}-br1002", session_of(&runs[0]))),
            1
        ]),
        json!([
            b1002,
            SHARED,
            "BR-1002",
            run_id(&format!("{}-br1002", session_of(&runs[1]))),
            1
        ]),
        json!([
            digits,
            DIGITS,
            null,
            run_id(&format!("{}-0042", session_of(&runs[1]))),
            1
        ]),
    ];
    want_runs.sort_by_key(|r| r.to_string());
    assert_eq!(sorted(&fleet["summary"]["spark"]["runs"]), want_runs);
    // parameters: each run once (as many rows as its results give), after the rename.
    let source_of: BTreeMap<String, usize> = [
        (session_of(&runs[0]), 0),
        (session_of(&runs[1]), 1),
        (session_of(&runs[2]), 2),
        (format!("{}-br1002", session_of(&runs[0])), 0),
        (format!("{}-br1002", session_of(&runs[1])), 1),
        (format!("{}-0042", session_of(&runs[1])), 1),
    ]
    .into_iter()
    .map(|(session, i)| (run_id(&session), i))
    .collect();
    let rows_of = |session: &str| params.iter().filter(|p| p[0] == json!(session)).count();
    let parameters = sorted(&fleet["summary"]["spark"]["parameters"]);
    assert_eq!(parameters.len(), want_runs.len());
    for (row, run) in parameters.iter().zip(&want_runs) {
        assert_eq!(
            row.as_array().expect("row")[..4],
            run.as_array().expect("row")[..4],
            "{row}"
        );
        let source = source_of[row[3].as_str().expect("run id")];
        assert_eq!(row[4], json!(rows_of(&session_of(&runs[source]))), "{row}");
    }
    assert_eq!(
        fleet["summary"]["spark"]["tracer_samples"],
        json!([]),
        "a plain export removes the raw samples"
    );

    // docs/fleet.md's questions, answered by Spark as the results files say.
    let spark = &fleet["spark"];
    let identifiable: Vec<&String> = runs[1].results["geometric_errors"]["squareness"]
        .as_object()
        .expect("squareness")
        .iter()
        .filter(|(_, s)| s["identifiable"] == json!(true))
        .map(|(name, _)| name)
        .collect();
    let drift = spark["squareness_drift"].as_array().expect("drift");
    // Fräse 7 and the BR-1002 bridge have two runs each; the BR-1001 bridge one (the two
    // bridges are not one machine of three runs).
    assert_eq!(drift.len(), 2 * identifiable.len(), "{drift:?}");
    for row in drift {
        let name = row[2].as_str().expect("name");
        let machine = if row[0] == json!(fraese) {
            FRAESE
        } else {
            SHARED
        };
        assert!(row[0] == json!(fraese) || row[0] == json!(b1002), "{row}");
        assert_eq!(row[1], json!(machine), "the name as written");
        assert_eq!(row[3], json!(2));
        let value = |r: &Run| {
            r.results["geometric_errors"]["squareness"][name]["value_rad"]
                .as_f64()
                .expect("value")
        };
        assert_eq!(f(&row[4]), Some(value(&runs[1]) - value(&runs[0])), "{row}");
    }
    let mut e_failed: Vec<(String, String)> = spark["iso_e_failed"]
        .as_array()
        .expect("rows")
        .iter()
        .map(|row| {
            (
                row[3].as_str().expect("session").to_owned(),
                row[4].as_str().expect("axis").to_owned(),
            )
        })
        .collect();
    e_failed.sort();
    assert_eq!(e_failed, failed_e);
    assert_eq!(
        spark["verdicts"],
        json!([[b1001, SHARED, "BR-1001", verdict, 1]])
    );
    let per_machine: Vec<(Value, Value)> = spark["runs_per_machine"]
        .as_array()
        .expect("rows")
        .iter()
        .map(|r| (r[0].clone(), r[4].clone()))
        .collect();
    let mut want = vec![
        (json!(fraese), json!(2)),
        (json!(b1001), json!(1)),
        (json!(b1002), json!(2)),
        (json!(digits), json!(1)),
    ];
    want.sort_by_key(|(k, _)| k.to_string());
    assert_eq!(per_machine, want);

    // The fleet without diagnoses: the page's setup and questions work, with no rows where
    // there are none.
    let bare = &answer["fleets"]["bare"];
    for table in ["diagnoses", "iso230_2", "tracer_samples"] {
        assert_eq!(bare["summary"]["spark"][table], json!([]), "{table}");
    }
    assert_eq!(bare["spark"]["verdicts"], json!([]));
    assert_eq!(bare["spark"]["iso_e_failed"], json!([]));
    assert_eq!(
        bare["spark"]["squareness_drift"].as_array().map(Vec::len),
        Some(identifiable.len()),
        "the BR-1002 bridge's two runs"
    );

    // The probe and hexapod fleet: the page's setup and every question run; their
    // parameters are there, one run per machine, and no table has rows it cannot have.
    let kinds = &answer["fleets"]["kinds"];
    for table in ["error_functions", "diagnoses", "iso230_2", "tracer_samples"] {
        assert_eq!(kinds["summary"]["spark"][table], json!([]), "{table}");
    }
    let per_run: Vec<(Value, Value)> = kinds["summary"]["spark"]["parameters"]
        .as_array()
        .expect("parameters summary")
        .iter()
        .map(|row| (row[1].clone(), row[3].clone()))
        .collect();
    let machines: Vec<&Value> = per_run.iter().map(|(m, _)| m).collect();
    assert_eq!(
        machines,
        [json!("Cell hexapod"), json!("Cell probe-install")]
            .iter()
            .collect::<Vec<_>>(),
        "{per_run:?}"
    );
    assert_eq!(kinds["spark"]["verdicts"], json!([]));
    assert_eq!(kinds["spark"]["iso_e_failed"], json!([]));
}

/// Every other plan kind's example run exported: its parameters and error functions as its
/// results file holds them (found by the results' shape, docs/fleet.md).
/// The example run of every other plan kind, run once for the tests that read them: the
/// folder holding one run folder per kind, and each run's results.
fn kind_runs() -> &'static (PathBuf, BTreeMap<&'static str, Value>) {
    static RUNS: std::sync::OnceLock<(PathBuf, BTreeMap<&'static str, Value>)> =
        std::sync::OnceLock::new();
    RUNS.get_or_init(|| {
        let runs = Path::new(env!("CARGO_TARGET_TMPDIR"))
            .join(format!("export-kind-runs-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&runs);
        let configs = Path::new(env!("CARGO_MANIFEST_DIR")).join("config");
        let mut results = BTreeMap::new();
        for kind in ["rotary-sphere", "probe-install", "hexapod", "rotary-tracer"] {
            let dir = runs.join(kind);
            let config = configs.join(format!("{kind}.toml"));
            let out = geocal(&[
                "run",
                config.to_str().expect("path"),
                "--out",
                dir.to_str().expect("path"),
            ]);
            assert!(
                out.status.success(),
                "{}",
                String::from_utf8_lossy(&out.stderr)
            );
            let json: Value =
                serde_json::from_slice(&std::fs::read(dir.join("results.json")).expect("results"))
                    .expect("results JSON");
            results.insert(kind, json);
        }
        (runs, results)
    })
}

#[test]
fn every_kind_exports_what_its_results_hold() {
    let work = tempfile::tempdir().expect("tempdir");
    let (runs, results) = kind_runs();
    let dest = work.path().join("fleet");
    let out = geocal(&[
        "export",
        "--format",
        "parquet",
        runs.to_str().expect("path"),
        "--out",
        dest.to_str().expect("path"),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let answers = duckdb(
        &[],
        &[
            q(
                "parameters",
                format!(
                    "SELECT session_id, name, value, sigma, unit FROM {}",
                    table(&dest, "parameters")
                ),
            ),
            q(
                "error_functions",
                format!(
                    "SELECT session_id, axis, error_function, position, value, sigma, unit, \
                     parameter FROM {}",
                    table(&dest, "error_functions")
                ),
            ),
        ]
        .into_iter()
        .collect(),
    );
    let parameter = |r: &Value, name: &str| -> Vec<Value> {
        answers["parameters"]
            .iter()
            .find(|row| row[0] == r["session_id"] && row[1] == json!(name))
            .unwrap_or_else(|| panic!("parameter {name} of {}", r["kind"]))
            .clone()
    };
    let function = |r: &Value, axis: &Value, name: &str, position: &Value| -> Vec<Value> {
        answers["error_functions"]
            .iter()
            .find(|row| {
                row[0] == r["session_id"]
                    && row[1] == *axis
                    && row[2] == json!(name)
                    && row[3] == *position
            })
            .unwrap_or_else(|| panic!("{name} at {position} of {}", r["kind"]))
            .clone()
    };

    // The history's names are the export's, for every kind.
    for (kind, r) in results {
        let names: Vec<&Value> = answers["parameters"]
            .iter()
            .filter(|p| p[0] == r["session_id"])
            .map(|p| &p[1])
            .chain(
                answers["error_functions"]
                    .iter()
                    .filter(|e| e[0] == r["session_id"])
                    .map(|e| &e[7]),
            )
            .collect();
        let found = geocal::history::parameters::parameters(r).parameters;
        assert!(!found.is_empty(), "{kind}");
        for p in found {
            assert!(
                names.contains(&&json!(p.id)),
                "{kind}: {} ({}) not exported by that name",
                p.id,
                p.path
            );
        }
    }

    let probe = &results["probe-install"];
    for p in probe["parameters"].as_array().expect("parameters") {
        let row = parameter(probe, p["name"].as_str().expect("name"));
        same(&row[2], &p["value"], "probe parameter");
        same(&row[3], &p["sigma"], "probe parameter σ");
    }

    let sphere = &results["rotary-sphere"];
    for l in sphere["location"].as_array().expect("location") {
        let name = l["name"].as_str().expect("name");
        let row = parameter(sphere, name);
        same(&row[2], &l["value"], name);
        same(&row[3], &l["sigma"], name);
        let unit = if name.starts_with("EA") || name.starts_with("EB") {
            "rad"
        } else {
            "m"
        };
        assert_eq!(row[4], json!(unit), "{name}");
    }
    let names = sphere["motion_names"].as_array().expect("motion names");
    for m in sphere["motion"].as_array().expect("motion") {
        for (k, name) in names.iter().enumerate() {
            let row = function(
                sphere,
                &sphere["table"],
                name.as_str().expect("name"),
                &m["commanded_rad"],
            );
            same(&row[4], &m["errors"][k], "motion error");
            same(&row[5], &m["sigma"][k], "motion error σ");
        }
    }

    let hexapod = &results["hexapod"];
    for h in hexapod["hinges"].as_array().expect("hinges") {
        for (k, axis) in ["x", "y", "z"].iter().enumerate() {
            let row = parameter(hexapod, &format!("hinge.{}.base.{axis}", h["leg"]));
            same(&row[2], &h["base_m"][k], "base hinge");
            same(&row[3], &h["base_sigma_m"][k], "base hinge σ");
            let row = parameter(hexapod, &format!("hinge.{}.platform.{axis}", h["leg"]));
            same(&row[2], &h["platform_m"][k], "platform hinge");
        }
    }

    let tracer = &results["rotary-tracer"];
    let rotary = &tracer["rotary"];
    let table_id = rotary["table"].as_str().expect("table");
    let row = parameter(tracer, &format!("rotary_axis.{table_id}.radius_m"));
    same(&row[2], &rotary["radius_m"], "radius");
    same(&row[3], &rotary["radius_sigma_m"], "radius σ");
    for s in rotary["steps"].as_array().expect("steps") {
        let row = function(tracer, &rotary["table"], "step_error", &s["commanded_rad"]);
        same(&row[4], &s["error_rad"], "step error");
        same(&row[5], &s["sigma_rad"], "step error σ");
    }
}
