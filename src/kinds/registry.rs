//! The plan kinds and what every command needs of one: the `Kind` trait, and `KINDS`, the
//! only list that names them. The commands (`run`, `run --resume`, `check`, `solve`,
//! `simulate`) find a configuration's or a session's kind here and call it; none of them
//! names a kind.

use std::path::{Path, PathBuf};

use anyhow::Context;

use crate::config::kind_config;
use crate::config::PlanKind;
use crate::method::{self, MethodError, Results, SolveSettings};
pub use crate::run::replay::ReplaySequence;
use crate::run::RunOptions;
use crate::session::reader::{read_session, Completeness, Session};

/// What a run of any kind leaves behind.
pub struct KindRunOutput {
    pub session_path: std::path::PathBuf,
    pub results_path: std::path::PathBuf,
    pub results: Results,
    /// What was recorded, for the closing line ("12000 samples", "540 probe readings").
    pub recorded: String,
}

/// A plan check of any kind: its JSON and its text report.
pub struct KindCheck {
    pub json: serde_json::Value,
    pub text: String,
}

/// Choices on the command line that every kind's run accepts.
#[derive(Debug, Clone, Default)]
pub struct RunFlags {
    /// Answer the operator's prompts from a pipe instead of a terminal (`--yes`). The console
    /// passes it to the run as its operator (`RunControl::operator`), never as configuration.
    pub assume_yes: bool,
}

/// Everything a command needs of a plan kind.
pub trait Kind: Sync {
    /// The `kind` in configuration files, session headers and results.
    fn name(&self) -> &'static str;

    /// Parse and validate the configuration at `path`, check the plan and predict its
    /// uncertainties (`geocal check`).
    fn check(&self, path: &Path) -> anyhow::Result<KindCheck>;

    /// Run the configuration at `path` on its devices (simulated, emulated or real, as it
    /// declares), record the session and solve it (`geocal run`).
    fn run(
        &self,
        path: &Path,
        options: &RunOptions,
        flags: &RunFlags,
    ) -> anyhow::Result<KindRunOutput>;

    /// Continue the interrupted run recorded in `dir` (`geocal run --resume DIR`). Every
    /// built-in kind resumes; a kind that cannot says so.
    fn resume(
        &self,
        _dir: &Path,
        _config: Option<&Path>,
        _options: &RunOptions,
    ) -> anyhow::Result<KindRunOutput> {
        anyhow::bail!(
            "a {} run cannot be resumed: start it again with `geocal run CONFIG`",
            self.name()
        )
    }

    /// Solve a recorded session of this kind (`geocal solve`).
    fn solve(&self, session: &Session, settings: &SolveSettings) -> Result<Results, MethodError>;

    /// Solve the session file at `path` streamed (its tracer samples never held whole), with
    /// the results `solve` gives of the whole read. None when this kind does not stream or
    /// the file cannot be streamed exactly (damaged, cut short, repaired): it is read whole.
    fn solve_streamed(
        &self,
        _path: &Path,
        _settings: &SolveSettings,
    ) -> Option<Result<Results, MethodError>> {
        None
    }

    /// For a kind with its own sequencer: how `geocal replay` re-runs it against a recording
    /// (None: the kind replays through the tracer sequencer, `replay::replay`).
    fn own_replay(&self) -> Option<ReplaySequence> {
        None
    }

    /// Whether `geocal diagnose` has effect models for this kind's sessions.
    fn diagnosable(&self) -> bool {
        false
    }

    /// For a kind whose session is a tracer network: its effect library and models in the
    /// diagnosis of the lengths (None: the multilateration's library as it is).
    fn tracer_diagnosis(
        &self,
    ) -> Option<&'static dyn method::tracer_effects::TracerNetworkDiagnosis> {
        None
    }

    /// Whether this kind hands `geocal diagnose` and `geocal solve --effects` a residual
    /// model with its effect library (`residual_model`).
    fn has_residual_model(&self) -> bool {
        false
    }

    /// The session's residual model (measured quantities against the nominal model, their
    /// labels) and the kind's effect library (docs/diagnosis.md).
    fn residual_model(
        &self,
        _session: &Session,
    ) -> anyhow::Result<Box<dyn crate::method::diagnosis::ResidualModel>> {
        anyhow::bail!("a {} session has no residual model", self.name())
    }

    /// Host the configuration's device emulators on their own (`geocal simulate`).
    fn simulate(
        &self,
        _path: &Path,
        _options: &crate::kinds::tracer_plan::simulate::SimulateOptions,
    ) -> anyhow::Result<()> {
        anyhow::bail!(
            "geocal simulate hosts the tracer emulator of multilateration and rotary_tracer \
             plans; a {} plan has none",
            self.name()
        )
    }

    /// The kind's summary and sections of `geocal report`, from its results.json
    /// (docs/report.md). By default: the results JSON as it is.
    fn report(&self, results: &serde_json::Value) -> anyhow::Result<crate::document::KindReport> {
        Ok(crate::document::KindReport::raw(self.name(), results))
    }

    /// What a run of this kind counts in its progress (points, postures, poses …).
    fn progress_unit(&self) -> &'static str {
        "points"
    }

    /// Whether the report gives ISO 230-2 positioning figures for this kind's sessions: the
    /// network solve of a tracer kind yields per-run positioning deviations.
    fn reports_iso230_2(&self) -> bool {
        false
    }

    /// Whether this kind's results carry error functions with uncertainty budgets that the
    /// report checks against the declared tolerances (`evaluated_errors`).
    fn has_error_functions(&self) -> bool {
        false
    }

    /// The kind's error functions evaluated with their uncertainty budgets, and the results'
    /// geometric errors they come from, for the report's tolerance verdict (None: none in
    /// these results).
    fn evaluated_errors(
        &self,
        _results: &serde_json::Value,
        _session: &Session,
        _config: Option<&crate::config::Config>,
    ) -> anyhow::Result<Option<EvaluatedErrors>> {
        Ok(None)
    }

    /// The kind's uncertainty budget in `geocal report` (docs/uncertainty.md), from its
    /// results, the recorded session and the run's configuration (`run-config.toml` beside
    /// the results; None when absent). By default none.
    fn uncertainty(
        &self,
        _results: &serde_json::Value,
        _session: &Session,
        _config: Option<&Path>,
    ) -> anyhow::Result<Vec<crate::document::Section>> {
        Ok(Vec::new())
    }
}

/// A kind's error functions with their uncertainty budgets (`Kind::evaluated_errors`).
pub struct EvaluatedErrors {
    pub evaluation: crate::evaluate::tracer::TracerEvaluation,
    /// The results' geometric errors the functions come from.
    pub geometric: serde_json::Value,
}

/// Every plan kind geocal knows.
pub static KINDS: &[&dyn Kind] = &[
    &super::multilateration::Multilateration,
    &super::rotary_tracer::RotaryTracer,
    &super::rotary_sphere::RotarySphere,
    &super::probe_install::ProbeInstall,
    &super::hexapod::Hexapod,
];

/// A list of kinds to dispatch through: `Registry::standard()` holds `KINDS`; a program or
/// a test with a kind of its own adds it with `with`.
#[derive(Clone)]
pub struct Registry {
    kinds: Vec<&'static dyn Kind>,
}

impl Registry {
    /// Every plan kind geocal knows.
    pub fn standard() -> Registry {
        Registry {
            kinds: KINDS.to_vec(),
        }
    }

    /// This registry and `kind` (which replaces a kind of the same name).
    pub fn with(mut self, kind: &'static dyn Kind) -> Registry {
        self.kinds.retain(|k| k.name() != kind.name());
        self.kinds.push(kind);
        self
    }

    /// The names of every kind, for error messages.
    pub fn names(&self) -> String {
        self.kinds
            .iter()
            .map(|k| k.name())
            .collect::<Vec<_>>()
            .join(", ")
    }

    /// The kind called `name`.
    pub fn named(&self, name: &str) -> Option<&'static dyn Kind> {
        self.kinds.iter().copied().find(|k| k.name() == name)
    }

    /// The kind a configuration file declares (`kind = "..."`; none declared is
    /// multilateration).
    pub fn of_config(&self, path: &Path) -> anyhow::Result<&'static dyn Kind> {
        let text = kind_config::read(path)?;
        let declared = kind_config::declared_kind(&text);
        let name = declared
            .as_deref()
            .unwrap_or(PlanKind::Multilateration.as_str());
        self.named(name).with_context(|| {
            format!(
                "{}: kind = \"{name}\" is not a plan kind (known: {})",
                path.display(),
                self.names()
            )
        })
    }

    /// The kind of the interrupted run in `dir`: the given configuration's, else the one
    /// stored at run start, else the recorded session's.
    pub fn of_run_dir(
        &self,
        dir: &Path,
        config: Option<&Path>,
    ) -> anyhow::Result<&'static dyn Kind> {
        let stored = dir.join(crate::run::resume::CONFIG_FILE);
        if let Some(path) = config.or(stored.exists().then_some(stored.as_path())) {
            return self.of_config(path);
        }
        let session_path = dir.join(crate::run::resume::SESSION_FILE);
        let (session, _) =
            crate::session::reader::read_session_raw(&session_path).with_context(|| {
                format!(
                    "{} holds neither {} nor a readable {}: is it a run's output directory?",
                    dir.display(),
                    crate::run::resume::CONFIG_FILE,
                    crate::run::resume::SESSION_FILE
                )
            })?;
        let name = session.header.kind.as_str();
        self.named(name).with_context(|| {
            format!(
                "{}: kind \"{name}\" is not a plan kind (known: {})",
                session_path.display(),
                self.names()
            )
        })
    }

    /// Solve a session with the method of its kind.
    pub fn solve_session(
        &self,
        session: &Session,
        settings: &SolveSettings,
    ) -> Result<Results, MethodError> {
        let name = session.header.kind.as_str();
        match self.named(name) {
            Some(kind) => kind.solve(session, settings),
            None => Err(MethodError::UnknownKind(name.to_string(), self.names())),
        }
    }
}

/// The names of every kind, for error messages.
pub fn kind_names() -> String {
    Registry::standard().names()
}

/// The kind called `name`.
pub fn kind_named(name: &str) -> Option<&'static dyn Kind> {
    Registry::standard().named(name)
}

/// The kind a configuration file declares (`kind = "..."`; none declared is multilateration).
pub fn kind_of_config(path: &Path) -> anyhow::Result<&'static dyn Kind> {
    Registry::standard().of_config(path)
}

/// The kind of the interrupted run in `dir` (see `Registry::of_run_dir`).
pub fn kind_of_run_dir(dir: &Path, config: Option<&Path>) -> anyhow::Result<&'static dyn Kind> {
    Registry::standard().of_run_dir(dir, config)
}

/// Run the configuration at `path` if it declares one of the kinds with their own layout
/// (probe_install, hexapod), with the run's summary; None otherwise.
pub fn run_file(
    path: &Path,
    options: &RunOptions,
) -> anyhow::Result<Option<crate::run::RunOutput>> {
    let text = kind_config::read(path)?;
    match kind_config::declared_kind(&text).as_deref() {
        Some(super::probe_install::config::KIND) => {
            let config = super::probe_install::config::ProbeInstallConfig::load(path)?;
            super::probe_install::run::run(&config, options).map(Some)
        }
        Some(super::hexapod::config::KIND) => {
            let config = super::hexapod::config::HexapodConfig::load(path)?;
            super::hexapod::run::run(&config, options).map(Some)
        }
        _ => Ok(None),
    }
}

/// The plan check of the configuration at `path` if it declares one of the kinds with their
/// own layout (rotary_sphere, probe_install, hexapod); None otherwise. Validates it first.
pub fn kind_layout_plan_check(
    path: &Path,
) -> anyhow::Result<Option<method::plan_check_kinds::KindPlanCheck>> {
    use super::hexapod::config as hx;
    use super::probe_install::config as pi;
    use crate::kinds::rotary_sphere::config as rs;
    let text = kind_config::read(path)?;
    let check = match kind_config::declared_kind(&text).as_deref() {
        Some(rs::KIND) => super::rotary_sphere::check::check(&rs::RotarySphereConfig::load(path)?),
        Some(pi::KIND) => super::probe_install::check::check(&pi::ProbeInstallConfig::load(path)?),
        Some(hx::KIND) => super::hexapod::check::check(&hx::HexapodConfig::load(path)?),
        _ => return Ok(None),
    };
    check
        .map(Some)
        .map_err(|e| anyhow::anyhow!("{}: plan check: {e}", path.display()))
}

/// The text report of any kind's results: what an engineer reads at the end of a run.
pub fn report(results: &Results) -> String {
    results.report()
}

/// Solve a session with the method of its kind.
pub fn solve_session(session: &Session, settings: &SolveSettings) -> Result<Results, MethodError> {
    Registry::standard().solve_session(session, settings)
}

fn closing_count(n: u64, what: &str) -> String {
    format!("{n} {what}")
}

/// A run's output as any kind's: what was recorded, counted in samples.
pub(crate) fn from_run(output: crate::run::RunOutput) -> KindRunOutput {
    KindRunOutput {
        recorded: closing_count(output.summary.samples, "samples"),
        session_path: output.session_path,
        results_path: output.results_path,
        results: output.results,
    }
}

/// A kind-layout plan check as a `KindCheck`.
pub(crate) fn kind_layout_check(
    path: &Path,
    check: Result<method::plan_check_kinds::KindPlanCheck, impl std::fmt::Display>,
) -> anyhow::Result<KindCheck> {
    let check = check.map_err(|e| anyhow::anyhow!("{}: plan check: {e}", path.display()))?;
    Ok(KindCheck {
        json: serde_json::to_value(&check)?,
        text: method::plan_check_kinds::text(&check),
    })
}

/// Solve the finished session file exactly as `geocal solve` does; write results.json.
pub(crate) fn solve_and_write(
    session_path: &Path,
    options: &RunOptions,
) -> anyhow::Result<(Results, PathBuf)> {
    let results = solve_file(session_path, &options.settings)?;
    let results_path = options.out_dir.join("results.json");
    std::fs::write(&results_path, results.to_json_pretty())
        .with_context(|| format!("writing {}", results_path.display()))?;
    Ok((results, results_path))
}

/// Read a session file and solve it with the method of its kind.
pub fn solve_file(path: &Path, settings: &SolveSettings) -> anyhow::Result<Results> {
    // A clean session of a kind that streams: its tracer samples are never held whole.
    let kind = crate::session::file_stream::read_header(path)
        .ok()
        .and_then(|header| kind_named(&header.kind));
    // The streamed read reports its progress; a whole read only its end.
    let read_done = || {
        if let (Some(progress), Ok(meta)) = (&settings.read_progress, std::fs::metadata(path)) {
            progress.finish(meta.len());
        }
    };
    if let Some(solved) = kind.and_then(|kind| kind.solve_streamed(path, settings)) {
        read_done();
        return solved.with_context(|| format!("solving {}", path.display()));
    }
    let session = read_session(path).with_context(|| format!("reading {}", path.display()))?;
    read_done();
    solve_session(&session, settings).with_context(|| {
        let file = path.display();
        let damage = match (&session.completeness, session.damaged.len()) {
            (Completeness::Truncated { bytes_read, .. }, _) => format!(
                " (cut short after byte {bytes_read}: resume the run with \
                 `geocal run --resume DIR`, or run `geocal repair {file}`)"
            ),
            (_, 0) => String::new(),
            (_, n) => format!(" ({n} damaged chunks skipped, listed above)"),
        };
        format!("solving {file}{damage}")
    })
}

#[cfg(test)]
mod tests {
    use std::path::Path;
    use std::sync::{Arc, Mutex};

    use crate::session::reader::ReadProgress;

    /// `solve_file` passes the read's progress on, growing, and ends it at the file's size,
    /// also when the file is read whole (a cut copy).
    #[test]
    fn solving_a_file_reports_the_read_to_its_end() {
        let outside = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/outside");
        let whole = outside.join("outside-clean-7/session.mcap");
        let dir = tempfile::tempdir().expect("tempdir");
        let cut = dir.path().join("cut.mcap");
        let bytes = std::fs::read(&whole).expect("read");
        std::fs::write(&cut, &bytes[..bytes.len() - 100]).expect("write");
        for path in [whole, cut] {
            let len = std::fs::metadata(&path).expect("size").len();
            let seen = Arc::new(Mutex::new(Vec::<(u64, u64)>::new()));
            let log = seen.clone();
            let settings = super::SolveSettings {
                read_progress: Some(ReadProgress::new(move |done, total| {
                    log.lock().unwrap().push((done, total))
                })),
                ..Default::default()
            };
            super::solve_file(&path, &settings).expect("solved");
            let seen = seen.lock().unwrap().clone();
            assert_eq!(seen.last(), Some(&(len, len)), "{}", path.display());
            assert!(seen.windows(2).all(|w| w[0].0 < w[1].0), "{seen:?}");
        }
    }
}
