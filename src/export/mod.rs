//! `geocal export` (docs/fleet.md): the results of every run of a folder or of the daemon's
//! catalog, and on request their raw tracer samples, as Parquet tables partitioned Hive-style
//! by machine key, for the engines analysts already use (Spark, DuckDB, polars, pandas).

pub mod rows;
pub mod schema;
pub mod table;
pub mod write;

use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::Context;
use arrow_array::builder::{
    BooleanBuilder, Float64Builder, Int64Builder, StringBuilder, TimestampMicrosecondBuilder,
};
use arrow_array::{ArrayRef, RecordBatch};
use serde_json::Value;

use crate::session::file_stream::{self as stream, StreamEnd};
use schema::{DIAGNOSES, ISO230_2, RUNS, TRACER_SAMPLES};
use table::{Cell, RunCells, Table};

pub const RESULTS_FILE: &str = "results.json";
pub const DIAGNOSIS_FILE: &str = "diagnosis.json";
/// Raw samples per record batch (and so at most per row group).
const RAW_BATCH_ROWS: usize = 65_536;

/// Where the runs come from.
#[derive(Debug, Clone)]
pub enum Source {
    /// A run folder (results.json inside), or a folder of run folders.
    Dir(PathBuf),
    /// The daemon's data folder (its catalog.sqlite and jobs/).
    Catalog(PathBuf),
}

#[derive(Debug, Clone, Default)]
pub struct ExportOptions {
    /// Also write every raw tracer sample (table `tracer_samples`).
    pub raw: bool,
    /// A run that cannot be exported fails the export instead of being skipped.
    pub strict: bool,
}

/// One run to export: its results file, and what lies beside it.
#[derive(Debug, Clone, PartialEq)]
pub struct RunInput {
    pub results: PathBuf,
    pub session: PathBuf,
    pub diagnosis: Option<PathBuf>,
    /// The daemon's job id (catalog export).
    pub job_id: Option<i64>,
}

impl RunInput {
    /// The run of folder `dir`: its results.json, session.mcap and diagnosis.json.
    pub fn of_dir(dir: &Path) -> RunInput {
        RunInput {
            results: dir.join(RESULTS_FILE),
            session: dir.join(crate::run::resume::SESSION_FILE),
            diagnosis: Some(dir.join(DIAGNOSIS_FILE)).filter(|p| p.is_file()),
            job_id: None,
        }
    }
}

/// What one run contributed.
#[derive(Debug, Clone, PartialEq)]
pub struct RunExported {
    pub results: PathBuf,
    pub session_id: String,
    pub run_id: String,
    /// The machine as people name it, and its key (its partition).
    pub machine: String,
    pub machine_key: String,
    /// Rows per table.
    pub rows: Vec<(&'static str, usize)>,
    pub files: Vec<PathBuf>,
}

/// A run left out, and why.
#[derive(Debug, Clone, PartialEq)]
pub struct RunSkipped {
    pub results: PathBuf,
    pub reason: String,
}

#[derive(Debug, Clone, Default, PartialEq)]
pub struct ExportSummary {
    pub exported: Vec<RunExported>,
    pub skipped: Vec<RunSkipped>,
    /// Warnings that did not stop a run (raw samples cut short, ISO figures not computed).
    pub warnings: Vec<String>,
}

impl ExportSummary {
    pub fn text(&self) -> String {
        let mut out = String::new();
        for r in &self.exported {
            let rows: Vec<String> = r
                .rows
                .iter()
                .filter(|(_, n)| *n > 0)
                .map(|(t, n)| format!("{n} {t}"))
                .collect();
            out += &format!(
                "{}: machine {:?} ({}), session {} (run {}): {}\n",
                r.results.display(),
                r.machine,
                r.machine_key,
                r.session_id,
                r.run_id,
                rows.join(", ")
            );
        }
        out += &format!(
            "{} runs exported, {} skipped\n",
            self.exported.len(),
            self.skipped.len()
        );
        out
    }
}

/// The runs of a folder: the folder itself when it holds results.json, else every folder in
/// it that does (one level down), in name order.
pub fn runs_in_dir(dir: &Path) -> anyhow::Result<Vec<RunInput>> {
    if !dir.is_dir() {
        anyhow::bail!(
            "{}: not a folder (expected a run folder or a folder of run folders)",
            dir.display()
        );
    }
    if dir.join(RESULTS_FILE).is_file() {
        return Ok(vec![RunInput::of_dir(dir)]);
    }
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("reading {}", dir.display()))?
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| p.is_dir() && p.join(RESULTS_FILE).is_file())
        .collect();
    dirs.sort();
    if dirs.is_empty() {
        anyhow::bail!(
            "{}: no {RESULTS_FILE} in it or in any folder in it",
            dir.display()
        );
    }
    Ok(dirs.iter().map(|d| RunInput::of_dir(d)).collect())
}

/// The runs of the daemon's catalog: every run job that succeeded, with the diagnosis of the
/// newest diagnose job of it when its own folder has none.
pub fn runs_in_catalog(data_dir: &Path) -> anyhow::Result<Vec<RunInput>> {
    use crate::serve::catalog::{Catalog, JobState, JobType, CATALOG_FILE};
    let path = data_dir.join(CATALOG_FILE);
    if !path.is_file() {
        anyhow::bail!(
            "{}: no job catalog there (expected the daemon's data folder, holding {CATALOG_FILE})",
            path.display()
        );
    }
    let jobs = Catalog::open(data_dir)?.list()?;
    let mut runs = Vec::new();
    for job in jobs.iter().rev() {
        if job.job_type != JobType::Run || job.state != JobState::Succeeded {
            continue;
        }
        let mut run = RunInput::of_dir(&job.dir);
        run.job_id = Some(job.id);
        if run.diagnosis.is_none() {
            // Newest first in the list: the first diagnose job of this run is the newest.
            run.diagnosis = jobs
                .iter()
                .filter(|d| {
                    d.job_type == JobType::Diagnose
                        && d.state == JobState::Succeeded
                        && d.source_job == Some(job.id)
                })
                .map(|d| d.dir.join(DIAGNOSIS_FILE))
                .find(|p| p.is_file());
        }
        runs.push(run);
    }
    Ok(runs)
}

/// Export every run of `source` to `dest`. A run that cannot be read is skipped with the
/// reason (named in the summary), or fails the export with `strict`.
pub fn export(
    source: &Source,
    dest: &Path,
    options: &ExportOptions,
) -> anyhow::Result<ExportSummary> {
    let runs = match source {
        Source::Dir(dir) => runs_in_dir(dir)?,
        Source::Catalog(dir) => runs_in_catalog(dir)?,
    };
    export_runs(&runs, dest, options)
}

pub fn export_runs(
    runs: &[RunInput],
    dest: &Path,
    options: &ExportOptions,
) -> anyhow::Result<ExportSummary> {
    let mut dataset = write::Dataset::open(dest)?;
    let mut summary = ExportSummary::default();
    // Session id → the results file it was exported from: a run copied twice goes once.
    let mut seen: std::collections::HashMap<String, PathBuf> = Default::default();
    for run in runs {
        match export_run(run, &mut dataset, options, &mut seen, &mut summary.warnings) {
            Ok(Some(done)) => summary.exported.push(done),
            Ok(None) => {}
            Err(e) if !options.strict => summary.skipped.push(RunSkipped {
                results: run.results.clone(),
                reason: format!("{e:#}"),
            }),
            Err(e) => {
                return Err(e.context(format!("exporting {}", run.results.display())));
            }
        }
    }
    dataset.finish()?;
    Ok(summary)
}

/// The ISO 230-2 figures the results and their session give, or why there are none.
fn iso_of(
    results: &Value,
    session: &Path,
) -> Result<crate::evaluate::deviations::Iso230_2, String> {
    use crate::evaluate::deviations::{rotary_axis, Iso230_2};
    let mut iso = Iso230_2::default();
    if results.get("stations").is_some() && results.get("points").is_some() {
        let network: crate::method::multilateration::MultilaterationResults =
            serde_json::from_value(results.clone())
                .map_err(|e| format!("the tracer network of the results does not parse: {e}"))?;
        // The per-pass deviations need the session's lengths (point extraction).
        let recorded = crate::session::reader::read_session(session).map_err(|e| e.to_string())?;
        iso = crate::evaluate::of_results(&crate::method::Results::new(network), &recorded)
            .map_err(|e| e.to_string())?;
    }
    if let Some(rotary) = results.get("rotary").filter(|r| r.is_object()) {
        iso.axes
            .push(rotary_axis(rotary).map_err(|e| e.to_string())?);
    }
    if iso.axes.is_empty() {
        return Err(if iso.notes.is_empty() {
            "the results hold no positioning deviations".to_owned()
        } else {
            iso.notes.join("; ")
        });
    }
    Ok(iso)
}

/// Export one run; None (with a warning) when its session was already exported from another
/// results file.
fn export_run(
    run: &RunInput,
    dataset: &mut write::Dataset,
    options: &ExportOptions,
    seen: &mut std::collections::HashMap<String, PathBuf>,
    warnings: &mut Vec<String>,
) -> anyhow::Result<Option<RunExported>> {
    // The run as the machine's history loads it: results, kind, machine identity (the
    // configured name and serial), start time.
    let loaded = crate::history::load::Run::load(&run.results)?;
    let results = &loaded.results;
    let session_id = loaded.session_id.clone();
    if session_id.is_empty() {
        anyhow::bail!(
            "{}: key `session_id` missing or not a string",
            run.results.display()
        );
    }
    if let Some(first) = seen.get(&session_id) {
        warnings.push(format!(
            "{}: the same run (session {session_id}) as {}: exported once, from the first",
            run.results.display(),
            first.display()
        ));
        return Ok(None);
    }
    seen.insert(session_id.clone(), run.results.clone());
    let kind = loaded.kind.clone();
    let machine = loaded.machine.label();
    let machine_key = loaded.machine.key();
    let run_id = write::run_id(&session_id);
    let started = loaded.started_at.ok_or_else(|| {
        anyhow::anyhow!(
            "{}: no start time (no session header beside it, no file time)",
            run.results.display()
        )
    })?;
    let started_ns = started.timestamp_nanos_opt().ok_or_else(|| {
        anyhow::anyhow!(
            "{}: start time {started} out of range",
            run.results.display()
        )
    })?;
    let days = i32::try_from(started_ns.div_euclid(86_400_000_000_000)).unwrap_or(i32::MAX);
    let run_cells: RunCells = vec![
        ("run_id", run_id.as_str().into()),
        ("session_id", session_id.as_str().into()),
        ("machine", loaded.machine.name.clone().into()),
        ("machine_serial", loaded.machine.serial.clone().into()),
        ("machine_id", loaded.machine.id.clone().into()),
        ("kind", kind.as_str().into()),
        ("started_at", Cell::TimeNs(started_ns)),
    ];
    let session = run.session.is_file().then_some(run.session.as_path());
    let structure = match session {
        Some(path) => {
            let header = stream::read_header(path)?;
            if header.session_id != session_id {
                anyhow::bail!(
                    "{}: session_id {session_id:?}, but the session beside it ({}) is {:?}",
                    run.results.display(),
                    path.display(),
                    header.session_id
                );
            }
            Some(header.machine.structure)
        }
        None => None,
    };
    let diagnosis = match &run.diagnosis {
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("reading {}", path.display()))?;
            let d: crate::diagnose::Diagnosis = serde_json::from_str(&text).with_context(|| {
                format!("{}: not a geocal-diagnosis/1 document", path.display())
            })?;
            if d.session_id != session_id {
                anyhow::bail!(
                    "{}: diagnosis of session {:?}, but the results are of {session_id:?}",
                    path.display(),
                    d.session_id
                );
            }
            Some(d)
        }
        None => None,
    };

    let mut tables: Vec<Table> = vec![
        rows::parameters(results, &run_cells),
        rows::error_functions(results, &run_cells),
        rows::points(results, &run_cells),
    ];
    let mut iso_note = None;
    let iso = match session {
        Some(path) => iso_of(results, path),
        None => Err(format!(
            "no session beside the results ({} missing)",
            run.session.display()
        )),
    };
    match iso {
        Ok(iso) => tables.push(rows::iso230_2(&iso, &run_cells)),
        Err(why) => {
            iso_note = Some(why);
            tables.push(Table::of_run(&ISO230_2, &run_cells));
        }
    }
    tables.push(match &diagnosis {
        Some(d) => rows::diagnosis(d, &run_cells),
        None => Table::of_run(&DIAGNOSES, &run_cells),
    });

    // (staged file, its place in the dataset)
    let mut files: Vec<(PathBuf, PathBuf)> = Vec::new();
    let mut row_counts = Vec::new();
    let raw_samples = if let (true, Some(session)) = (options.raw, session) {
        let staged = dataset.staged(&TRACER_SAMPLES, &run_id);
        let raw_table = Table::of_run(&TRACER_SAMPLES, &run_cells);
        let (n, end, skipped) = write_raw(session, &staged, &raw_table)?;
        if let StreamEnd::Cut { bytes_read, reason } = end {
            warnings.push(format!(
                "{}: raw samples exported up to byte {bytes_read} only ({reason}); `geocal \
                 repair` the session and export again for the rest",
                run.session.display()
            ));
        }
        if skipped > 0 {
            warnings.push(format!(
                "{}: {skipped} tracer samples do not parse and were not exported",
                run.session.display()
            ));
        }
        if n > 0 {
            let path = write::run_file(dataset.dest(), &TRACER_SAMPLES, &machine_key, &run_id);
            files.push((staged, path));
        }
        row_counts.push((TRACER_SAMPLES.name, n));
        Some(n)
    } else {
        if options.raw {
            warnings.push(format!(
                "{}: no session beside it: no raw samples",
                run.results.display()
            ));
        }
        None
    };

    let extraction = &results["extraction"];
    let misfit = &results["misfit"];
    let mut runs = Table::of_run(&RUNS, &run_cells);
    runs.push(vec![
        ("schema_version", Cell::Int(schema::SCHEMA_VERSION.into())),
        ("date", Cell::Days(days)),
        ("structure", structure.into()),
        ("source", run.results.display().to_string().into()),
        ("job_id", run.job_id.map_or(Cell::Null, Cell::Int)),
        ("chi2_per_dof", results["chi2_per_dof"].as_f64().into()),
        ("dof", results["dof"].as_i64().map_or(Cell::Null, Cell::Int)),
        ("residual_rms_m", results["residual_rms_m"].as_f64().into()),
        (
            "converged",
            results["converged"]
                .as_bool()
                .or_else(|| results["lm"]["converged"].as_bool())
                .map_or(Cell::Null, Cell::Bool),
        ),
        ("misfit", misfit.is_object().into()),
        ("misfit_sigma_scale", misfit["sigma_scale"].as_f64().into()),
        (
            "windows_used",
            extraction["windows_used"]
                .as_i64()
                .map_or(Cell::Null, Cell::Int),
        ),
        (
            "windows_dropped",
            extraction["windows_dropped"]
                .as_i64()
                .map_or(Cell::Null, Cell::Int),
        ),
        (
            "damaged_chunks",
            extraction["damaged_chunks"]
                .as_array()
                .map_or(Cell::Null, |a| a.len().into()),
        ),
        ("iso230_2_note", iso_note.clone().into()),
        ("raw_samples", raw_samples.map_or(Cell::Null, Cell::from)),
    ]);
    tables.insert(0, runs);
    if let Some(why) = &iso_note {
        if results.get("stations").is_some() {
            warnings.push(format!(
                "{}: no ISO 230-2 figures: {why}",
                run.results.display()
            ));
        }
    }
    for table in &tables {
        let staged = dataset.staged(table.def, &run_id);
        if write::write_batch(&staged, table.def, &table.to_batch()?)? {
            let path = write::run_file(dataset.dest(), table.def, &machine_key, &run_id);
            files.push((staged, path));
        }
        row_counts.push((table.def.name, table.len()));
    }
    dataset.publish(&run_id, &files)?;
    Ok(Some(RunExported {
        results: run.results.clone(),
        session_id,
        run_id,
        machine,
        machine_key,
        rows: row_counts,
        files: files.into_iter().map(|(_, path)| path).collect(),
    }))
}

/// Raw tracer samples in record batches, streamed from the session to the file.
struct RawBatch<'a> {
    /// The run's columns.
    run: &'a Table,
    tracer: StringBuilder,
    log_time: TimestampMicrosecondBuilder,
    log_time_ns: Int64Builder,
    seq: Int64Builder,
    t_s: Float64Builder,
    length_m: Float64Builder,
    signal: Float64Builder,
    tracking: BooleanBuilder,
    beam_segment: Int64Builder,
    rows: usize,
}

impl<'a> RawBatch<'a> {
    fn new(run: &'a Table) -> RawBatch<'a> {
        RawBatch {
            run,
            tracer: StringBuilder::new(),
            log_time: TimestampMicrosecondBuilder::new().with_timezone("UTC"),
            log_time_ns: Int64Builder::new(),
            seq: Int64Builder::new(),
            t_s: Float64Builder::new(),
            length_m: Float64Builder::new(),
            signal: Float64Builder::new(),
            tracking: BooleanBuilder::new(),
            beam_segment: Int64Builder::new(),
            rows: 0,
        }
    }

    fn push(&mut self, tracer: &str, log_time_ns: u64, s: &crate::session::messages::TracerSample) {
        self.tracer.append_value(tracer);
        let log_time_ns = i64::try_from(log_time_ns).unwrap_or(i64::MAX);
        self.log_time.append_value(log_time_ns.div_euclid(1000));
        self.log_time_ns.append_value(log_time_ns);
        self.seq
            .append_value(i64::try_from(s.seq).unwrap_or(i64::MAX));
        self.t_s.append_value(s.t_s);
        self.length_m.append_value(s.length_m);
        self.signal.append_value(s.signal);
        self.tracking.append_value(s.tracking);
        self.beam_segment.append_value(i64::from(s.beam_segment));
        self.rows += 1;
    }

    fn finish(&mut self) -> anyhow::Result<RecordBatch> {
        let rows = std::mem::take(&mut self.rows);
        let mut arrays: Vec<ArrayRef> = self.run.run_arrays(rows)?;
        arrays.extend::<[ArrayRef; 9]>([
            Arc::new(self.tracer.finish()),
            Arc::new(self.log_time.finish()),
            Arc::new(self.log_time_ns.finish()),
            Arc::new(self.seq.finish()),
            Arc::new(self.t_s.finish()),
            Arc::new(self.length_m.finish()),
            Arc::new(self.signal.finish()),
            Arc::new(self.tracking.finish()),
            Arc::new(self.beam_segment.finish()),
        ]);
        Ok(RecordBatch::try_new(TRACER_SAMPLES.schema(), arrays)?)
    }
}

/// Every tracer sample of `session` to `path`, a batch in memory at a time; (samples written,
/// how the stream ended, samples that did not parse).
fn write_raw(session: &Path, path: &Path, run: &Table) -> anyhow::Result<(usize, StreamEnd, u64)> {
    let mut file: Option<write::PartFile> = None;
    let mut batch = RawBatch::new(run);
    let mut written = 0usize;
    let mut skipped = 0u64;
    let flush =
        |batch: &mut RawBatch, file: &mut Option<write::PartFile>| -> anyhow::Result<usize> {
            if batch.rows == 0 {
                return Ok(0);
            }
            let records = batch.finish()?;
            if file.is_none() {
                *file = Some(write::PartFile::create(path, &TRACER_SAMPLES)?);
            }
            if let Some(f) = file.as_mut() {
                f.write(&records)?;
            }
            Ok(records.num_rows())
        };
    let end = stream::for_each_tracer_sample(session, &mut skipped, |tracer, log_time, sample| {
        batch.push(tracer, log_time, sample);
        if batch.rows >= RAW_BATCH_ROWS {
            written += flush(&mut batch, &mut file)?;
        }
        Ok(())
    })?;
    written += flush(&mut batch, &mut file)?;
    if let Some(f) = file {
        f.finish()?;
    }
    Ok((written, end, skipped))
}

/// `geocal export`'s arguments.
#[derive(Debug, Clone, clap::Args)]
pub struct ExportArgs {
    /// A run folder (results.json, session.mcap, diagnosis.json) or a folder of run folders.
    #[arg(
        value_name = "DIR",
        required_unless_present = "catalog",
        conflicts_with = "catalog"
    )]
    pub dir: Option<PathBuf>,
    /// Export the runs of the daemon's catalog instead: its data folder (default geocal-data).
    #[arg(long, value_name = "DATA_DIR", num_args = 0..=1, default_missing_value = "geocal-data")]
    pub catalog: Option<PathBuf>,
    /// The format: parquet.
    #[arg(long, default_value = "parquet")]
    pub format: String,
    /// The export's folder (one folder per table inside, partitioned machine_key=…).
    #[arg(long, value_name = "DEST")]
    pub out: PathBuf,
    /// Also export every raw tracer sample (table tracer_samples), streamed from the sessions.
    #[arg(long)]
    pub raw: bool,
    /// Fail on the first run that cannot be exported instead of skipping it with a warning.
    #[arg(long)]
    pub strict: bool,
}

/// `geocal export`: export, print what was written, warn about runs left out; an error when
/// no run could be exported.
pub fn command(args: &ExportArgs) -> anyhow::Result<()> {
    if args.format != "parquet" {
        anyhow::bail!("--format {}: expected parquet", args.format);
    }
    let source = match (&args.dir, &args.catalog) {
        (_, Some(data_dir)) => Source::Catalog(data_dir.clone()),
        (Some(dir), None) => Source::Dir(dir.clone()),
        (None, None) => anyhow::bail!("geocal export needs DIR or --catalog"),
    };
    let options = ExportOptions {
        raw: args.raw,
        strict: args.strict,
    };
    let summary = export(&source, &args.out, &options)?;
    for w in &summary.warnings {
        crate::console::write_err(format_args!("warning: {w}\n"));
    }
    for s in &summary.skipped {
        crate::console::write_err(format_args!(
            "warning: skipped {}: {}\n",
            s.results.display(),
            s.reason
        ));
    }
    crate::console::write_out(format_args!("{}", summary.text()))?;
    if summary.exported.is_empty() && !summary.skipped.is_empty() {
        anyhow::bail!(
            "no run could be exported ({} skipped)",
            summary.skipped.len()
        );
    }
    Ok(())
}
