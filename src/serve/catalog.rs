//! The job catalog: an SQLite database in the data dir holding every job, its state and
//! times, who submitted it, its configuration's hash and the files it left with their SHA-256.

use std::path::{Path, PathBuf};

use anyhow::Context;
use rusqlite::{params, Connection, OptionalExtension};
use serde::Serialize;
use utoipa::ToSchema;

/// What a job does.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, serde::Deserialize, ToSchema)]
#[serde(rename_all = "lowercase")]
pub enum JobType {
    /// Run a plan configuration on its devices, record and solve it.
    Run,
    /// Solve the session of an earlier job again.
    Solve,
    /// Diagnose the session of an earlier job.
    Diagnose,
    /// Replay the session of an earlier job through the real sequencer.
    Replay,
}

impl JobType {
    pub fn as_str(self) -> &'static str {
        match self {
            JobType::Run => "run",
            JobType::Solve => "solve",
            JobType::Diagnose => "diagnose",
            JobType::Replay => "replay",
        }
    }

    fn parse(text: &str) -> Option<JobType> {
        [
            JobType::Run,
            JobType::Solve,
            JobType::Diagnose,
            JobType::Replay,
        ]
        .into_iter()
        .find(|t| t.as_str() == text)
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, serde::Deserialize, ToSchema)]
#[serde(rename_all = "lowercase")]
pub enum JobState {
    Queued,
    Running,
    Succeeded,
    Failed,
    Cancelled,
    /// Found running when the daemon started: it was killed; resume it.
    Interrupted,
}

impl JobState {
    pub const ALL: [JobState; 6] = [
        JobState::Queued,
        JobState::Running,
        JobState::Succeeded,
        JobState::Failed,
        JobState::Cancelled,
        JobState::Interrupted,
    ];

    pub fn as_str(self) -> &'static str {
        match self {
            JobState::Queued => "queued",
            JobState::Running => "running",
            JobState::Succeeded => "succeeded",
            JobState::Failed => "failed",
            JobState::Cancelled => "cancelled",
            JobState::Interrupted => "interrupted",
        }
    }

    fn parse(text: &str) -> Option<JobState> {
        JobState::ALL.into_iter().find(|s| s.as_str() == text)
    }

    /// A run in this state left a session that `resume` can continue.
    pub fn resumable(self) -> bool {
        matches!(self, JobState::Interrupted | JobState::Cancelled)
    }
}

/// A file a job left in its folder.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, serde::Deserialize, ToSchema)]
pub struct JobFile {
    pub name: String,
    pub bytes: u64,
    pub sha256: String,
}

/// One job as the catalog holds it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct JobRecord {
    pub id: i64,
    #[serde(rename = "type")]
    pub job_type: JobType,
    /// The plan kind (multilateration, rotary_tracer, ...).
    pub kind: String,
    pub state: JobState,
    /// RFC 3339 UTC.
    pub submitted_at: String,
    pub started_at: Option<String>,
    pub finished_at: Option<String>,
    /// Who or what submitted it: the peer address, or `schedule:<name>`.
    pub submitted_by: String,
    /// SHA-256 of the plan configuration as submitted (run jobs).
    pub config_sha256: Option<String>,
    /// The job whose session a solve, diagnose or replay job reads.
    pub source_job: Option<i64>,
    pub dir: PathBuf,
    pub error: Option<String>,
    pub progress_done: u64,
    pub progress_total: u64,
    /// Queued to continue its interrupted or cancelled run rather than start it.
    pub resume: bool,
    pub files: Vec<JobFile>,
}

/// A job to add.
pub struct NewJob<'a> {
    pub job_type: JobType,
    pub kind: &'a str,
    pub submitted_by: &'a str,
    pub config_sha256: Option<&'a str>,
    pub source_job: Option<i64>,
}

pub struct Catalog {
    connection: Connection,
    jobs_dir: PathBuf,
}

pub const CATALOG_FILE: &str = "catalog.sqlite";

pub fn now_rfc3339() -> String {
    time::OffsetDateTime::now_utc()
        .format(&time::format_description::well_known::Rfc3339)
        .unwrap_or_default()
}

impl Catalog {
    /// Open (or create) the catalog of `data_dir`.
    pub fn open(data_dir: &Path) -> anyhow::Result<Catalog> {
        let jobs_dir = data_dir.join("jobs");
        std::fs::create_dir_all(&jobs_dir)
            .with_context(|| format!("creating {}", jobs_dir.display()))?;
        let path = data_dir.join(CATALOG_FILE);
        let connection = Connection::open(&path)
            .with_context(|| format!("opening the job catalog {}", path.display()))?;
        connection
            .execute_batch(
                "PRAGMA journal_mode = WAL;
                 PRAGMA synchronous = FULL;
                 CREATE TABLE IF NOT EXISTS jobs (
                     id INTEGER PRIMARY KEY AUTOINCREMENT,
                     job_type TEXT NOT NULL,
                     kind TEXT NOT NULL,
                     state TEXT NOT NULL,
                     submitted_at TEXT NOT NULL,
                     started_at TEXT,
                     finished_at TEXT,
                     submitted_by TEXT NOT NULL,
                     config_sha256 TEXT,
                     source_job INTEGER,
                     error TEXT,
                     progress_done INTEGER NOT NULL DEFAULT 0,
                     progress_total INTEGER NOT NULL DEFAULT 0,
                     resume INTEGER NOT NULL DEFAULT 0
                 );
                 CREATE TABLE IF NOT EXISTS files (
                     job INTEGER NOT NULL REFERENCES jobs(id),
                     name TEXT NOT NULL,
                     bytes INTEGER NOT NULL,
                     sha256 TEXT NOT NULL,
                     PRIMARY KEY (job, name)
                 );",
            )
            .with_context(|| format!("preparing the job catalog {}", path.display()))?;
        Ok(Catalog {
            connection,
            jobs_dir,
        })
    }

    /// The folder of job `id`.
    pub fn dir_of(&self, id: i64) -> PathBuf {
        self.jobs_dir.join(id.to_string())
    }

    /// Jobs found running (the daemon was killed): mark them interrupted; their ids.
    pub fn mark_interrupted(&mut self) -> anyhow::Result<Vec<i64>> {
        let ids: Vec<i64> = {
            let mut statement = self
                .connection
                .prepare("SELECT id FROM jobs WHERE state = 'running' ORDER BY id")?;
            let rows = statement.query_map([], |row| row.get(0))?;
            rows.collect::<Result<_, _>>()?
        };
        self.connection.execute(
            "UPDATE jobs SET state = 'interrupted', finished_at = ?1,
                 error = 'the daemon stopped while the job ran'
             WHERE state = 'running'",
            params![now_rfc3339()],
        )?;
        Ok(ids)
    }

    /// Add a queued job; its id (the daemon's, never the client's).
    pub fn add(&mut self, job: &NewJob<'_>) -> anyhow::Result<i64> {
        self.connection.execute(
            "INSERT INTO jobs (job_type, kind, state, submitted_at, submitted_by,
                 config_sha256, source_job)
             VALUES (?1, ?2, 'queued', ?3, ?4, ?5, ?6)",
            params![
                job.job_type.as_str(),
                job.kind,
                now_rfc3339(),
                job.submitted_by,
                job.config_sha256,
                job.source_job
            ],
        )?;
        Ok(self.connection.last_insert_rowid())
    }

    pub fn get(&self, id: i64) -> anyhow::Result<Option<JobRecord>> {
        let job = self
            .connection
            .query_row(&format!("{SELECT_JOB} WHERE id = ?1"), params![id], |row| {
                self.record(row)
            })
            .optional()?;
        match job {
            Some(mut job) => {
                job.files = self.files(id)?;
                Ok(Some(job))
            }
            None => Ok(None),
        }
    }

    /// Every job, newest first.
    pub fn list(&self) -> anyhow::Result<Vec<JobRecord>> {
        let mut statement = self
            .connection
            .prepare(&format!("{SELECT_JOB} ORDER BY id DESC"))?;
        let rows = statement.query_map([], |row| self.record(row))?;
        let mut jobs: Vec<JobRecord> = rows.collect::<Result<_, _>>()?;
        for job in &mut jobs {
            job.files = self.files(job.id)?;
        }
        Ok(jobs)
    }

    /// The oldest queued job.
    pub fn next_queued(&self) -> anyhow::Result<Option<JobRecord>> {
        self.first_queued("state = 'queued'")
    }

    /// The oldest queued run (a job on the machine's devices).
    pub fn next_queued_run(&self) -> anyhow::Result<Option<JobRecord>> {
        self.first_queued("state = 'queued' AND job_type = 'run'")
    }

    /// The oldest queued solve, diagnosis or replay whose session is complete: one whose
    /// source job is still queued or running waits for it (its file is still being written).
    pub fn next_queued_on_session(&self) -> anyhow::Result<Option<JobRecord>> {
        self.first_queued(
            "state = 'queued' AND job_type != 'run' AND NOT EXISTS (
                 SELECT 1 FROM jobs AS source WHERE source.id = jobs.source_job
                     AND source.state IN ('queued', 'running'))",
        )
    }

    fn first_queued(&self, condition: &str) -> anyhow::Result<Option<JobRecord>> {
        let job = self
            .connection
            .query_row(
                &format!("{SELECT_JOB} WHERE {condition} ORDER BY id LIMIT 1"),
                [],
                |row| self.record(row),
            )
            .optional()?;
        Ok(job)
    }

    pub fn count_by_state(&self) -> anyhow::Result<Vec<(JobState, u64)>> {
        let mut out = Vec::new();
        for state in JobState::ALL {
            let n: i64 = self.connection.query_row(
                "SELECT COUNT(*) FROM jobs WHERE state = ?1",
                params![state.as_str()],
                |row| row.get(0),
            )?;
            out.push((state, n.max(0) as u64));
        }
        Ok(out)
    }

    pub fn start(&mut self, id: i64) -> anyhow::Result<()> {
        self.connection.execute(
            "UPDATE jobs SET state = 'running', started_at = ?2, finished_at = NULL,
                 error = NULL WHERE id = ?1",
            params![id, now_rfc3339()],
        )?;
        Ok(())
    }

    pub fn finish(&mut self, id: i64, state: JobState, error: Option<&str>) -> anyhow::Result<()> {
        self.connection.execute(
            "UPDATE jobs SET state = ?2, finished_at = ?3, error = ?4, resume = 0 WHERE id = ?1",
            params![id, state.as_str(), now_rfc3339(), error],
        )?;
        Ok(())
    }

    /// Queue an interrupted or cancelled run to continue where it stopped.
    pub fn queue_resume(&mut self, id: i64) -> anyhow::Result<()> {
        self.connection.execute(
            "UPDATE jobs SET state = 'queued', resume = 1, error = NULL, finished_at = NULL
             WHERE id = ?1",
            params![id],
        )?;
        Ok(())
    }

    pub fn set_progress(&mut self, id: i64, done: u64, total: u64) -> anyhow::Result<()> {
        self.connection.execute(
            "UPDATE jobs SET progress_done = ?2, progress_total = ?3 WHERE id = ?1",
            params![id, done as i64, total as i64],
        )?;
        Ok(())
    }

    /// Record (or update) the files in the job's folder with their size and SHA-256.
    pub fn record_files(&mut self, id: i64) -> anyhow::Result<Vec<JobFile>> {
        let dir = self.dir_of(id);
        let mut files = Vec::new();
        if let Ok(entries) = std::fs::read_dir(&dir) {
            for entry in entries.flatten() {
                let path = entry.path();
                if !path.is_file() {
                    continue;
                }
                let name = entry.file_name().to_string_lossy().into_owned();
                let (bytes, sha256) = hash_file(&path)?;
                files.push(JobFile {
                    name,
                    bytes,
                    sha256,
                });
            }
        }
        files.sort_by(|a, b| a.name.cmp(&b.name));
        let transaction = self.connection.transaction()?;
        transaction.execute("DELETE FROM files WHERE job = ?1", params![id])?;
        for file in &files {
            transaction.execute(
                "INSERT INTO files (job, name, bytes, sha256) VALUES (?1, ?2, ?3, ?4)",
                params![id, file.name, file.bytes as i64, file.sha256],
            )?;
        }
        transaction.commit()?;
        Ok(files)
    }

    fn files(&self, id: i64) -> anyhow::Result<Vec<JobFile>> {
        let mut statement = self
            .connection
            .prepare("SELECT name, bytes, sha256 FROM files WHERE job = ?1 ORDER BY name")?;
        let rows = statement.query_map(params![id], |row| {
            Ok(JobFile {
                name: row.get(0)?,
                bytes: row.get::<_, i64>(1)?.max(0) as u64,
                sha256: row.get(2)?,
            })
        })?;
        Ok(rows.collect::<Result<_, _>>()?)
    }

    fn record(&self, row: &rusqlite::Row<'_>) -> rusqlite::Result<JobRecord> {
        let id: i64 = row.get(0)?;
        let text = |i: usize| -> rusqlite::Result<String> { row.get(i) };
        let bad = |i: usize, what: &str, value: String| {
            rusqlite::Error::FromSqlConversionFailure(
                i,
                rusqlite::types::Type::Text,
                format!("job {id}: unknown {what} `{value}`").into(),
            )
        };
        let job_type = text(1)?;
        let state = text(3)?;
        Ok(JobRecord {
            id,
            job_type: JobType::parse(&job_type).ok_or_else(|| bad(1, "type", job_type))?,
            kind: text(2)?,
            state: JobState::parse(&state).ok_or_else(|| bad(3, "state", state))?,
            submitted_at: text(4)?,
            started_at: row.get(5)?,
            finished_at: row.get(6)?,
            submitted_by: text(7)?,
            config_sha256: row.get(8)?,
            source_job: row.get(9)?,
            error: row.get(10)?,
            progress_done: row.get::<_, i64>(11)?.max(0) as u64,
            progress_total: row.get::<_, i64>(12)?.max(0) as u64,
            resume: row.get::<_, i64>(13)? != 0,
            dir: self.dir_of(id),
            files: Vec::new(),
        })
    }
}

const SELECT_JOB: &str = "SELECT id, job_type, kind, state, submitted_at, started_at, \
     finished_at, submitted_by, config_sha256, source_job, error, progress_done, \
     progress_total, resume FROM jobs";

/// (size, lowercase hex SHA-256) of a file, read in blocks.
pub fn hash_file(path: &Path) -> anyhow::Result<(u64, String)> {
    use sha2::Digest;
    use std::io::Read;
    let mut file =
        std::fs::File::open(path).with_context(|| format!("reading {}", path.display()))?;
    let mut hasher = sha2::Sha256::new();
    let mut buffer = vec![0u8; 1 << 16];
    let mut bytes = 0u64;
    loop {
        let n = file
            .read(&mut buffer)
            .with_context(|| format!("reading {}", path.display()))?;
        if n == 0 {
            break;
        }
        bytes += n as u64;
        hasher.update(&buffer[..n]);
    }
    Ok((bytes, hex(&hasher.finalize())))
}

pub fn sha256_hex(data: &[u8]) -> String {
    use sha2::Digest;
    hex(&sha2::Sha256::digest(data))
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn jobs_survive_a_reopen_and_running_ones_become_interrupted() {
        let dir = tempfile::tempdir().unwrap();
        let mut catalog = Catalog::open(dir.path()).unwrap();
        let job = NewJob {
            job_type: JobType::Run,
            kind: "multilateration",
            submitted_by: "127.0.0.1:5000",
            config_sha256: Some("ab"),
            source_job: None,
        };
        let first = catalog.add(&job).unwrap();
        let second = catalog.add(&job).unwrap();
        assert!(second > first);
        catalog.start(first).unwrap();
        catalog.set_progress(first, 3, 10).unwrap();
        std::fs::create_dir_all(catalog.dir_of(first)).unwrap();
        std::fs::write(catalog.dir_of(first).join("plan.toml"), b"abc").unwrap();
        let files = catalog.record_files(first).unwrap();
        assert_eq!(files[0].bytes, 3);
        assert_eq!(
            files[0].sha256,
            "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
        );
        drop(catalog);

        let mut catalog = Catalog::open(dir.path()).unwrap();
        assert_eq!(catalog.mark_interrupted().unwrap(), vec![first]);
        let job = catalog.get(first).unwrap().unwrap();
        assert_eq!(job.state, JobState::Interrupted);
        assert_eq!((job.progress_done, job.progress_total), (3, 10));
        assert_eq!(job.files.len(), 1);
        assert_eq!(catalog.next_queued().unwrap().unwrap().id, second);
        catalog.queue_resume(first).unwrap();
        assert_eq!(catalog.next_queued().unwrap().unwrap().id, first);
        assert!(catalog.get(first).unwrap().unwrap().resume);
        assert!(catalog.get(999).unwrap().is_none());
    }

    #[test]
    fn runs_and_session_jobs_are_taken_in_their_own_lanes() {
        let dir = tempfile::tempdir().unwrap();
        let mut catalog = Catalog::open(dir.path()).unwrap();
        let new = |job_type, source_job| NewJob {
            job_type,
            kind: "multilateration",
            submitted_by: "test",
            config_sha256: None,
            source_job,
        };
        let recorded = catalog.add(&new(JobType::Run, None)).unwrap();
        let recording = catalog.add(&new(JobType::Run, None)).unwrap();
        let later_run = catalog.add(&new(JobType::Run, None)).unwrap();
        let on_recording = catalog.add(&new(JobType::Solve, Some(recording))).unwrap();
        let on_recorded = catalog
            .add(&new(JobType::Diagnose, Some(recorded)))
            .unwrap();
        catalog.start(recorded).unwrap();
        catalog.finish(recorded, JobState::Succeeded, None).unwrap();
        catalog.start(recording).unwrap();

        // The runs queue behind each other; a session job does not queue behind them, but
        // one on a session still being recorded waits for its run.
        assert_eq!(catalog.next_queued_run().unwrap().unwrap().id, later_run);
        assert_eq!(
            catalog.next_queued_on_session().unwrap().unwrap().id,
            on_recorded
        );
        catalog.start(on_recorded).unwrap();
        assert!(catalog.next_queued_on_session().unwrap().is_none());
        catalog
            .finish(recording, JobState::Succeeded, None)
            .unwrap();
        assert_eq!(
            catalog.next_queued_on_session().unwrap().unwrap().id,
            on_recording
        );
        assert_eq!(catalog.next_queued().unwrap().unwrap().id, later_run);
    }
}
