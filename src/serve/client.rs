//! `geocal client`: submit a plan to a daemon, list and follow its jobs, acknowledge prompts,
//! fetch what a job left.

use std::io::BufRead;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::Context;
use reqwest::blocking::{Client as Http, RequestBuilder, Response};

use super::api::{Created, JobView};
use super::catalog::JobState;
use super::prompts::PendingPrompt;

pub struct Client {
    server: String,
    token: Option<String>,
    http: Http,
}

impl Client {
    /// A client of the daemon at `server` (`http://host:port`), with the token in
    /// `token_file` if given.
    pub fn new(server: &str, token_file: Option<&Path>) -> anyhow::Result<Client> {
        let token = match token_file {
            Some(path) => Some(
                std::fs::read_to_string(path)
                    .with_context(|| format!("reading the token file {}", path.display()))?
                    .trim()
                    .to_owned(),
            ),
            None => None,
        };
        let http = Http::builder()
            .connect_timeout(Duration::from_secs(10))
            .timeout(None)
            .build()
            .context("building the HTTP client")?;
        Ok(Client {
            server: server.trim_end_matches('/').to_owned(),
            token,
            http,
        })
    }

    fn request(&self, builder: RequestBuilder) -> anyhow::Result<Response> {
        let builder = match &self.token {
            Some(token) => builder.bearer_auth(token),
            None => builder,
        };
        let response = builder
            .send()
            .with_context(|| format!("reaching the daemon at {}", self.server))?;
        if response.status().is_success() {
            return Ok(response);
        }
        let status = response.status();
        let body = response.text().unwrap_or_default();
        let message = serde_json::from_str::<super::api::ErrorBody>(&body)
            .map(|e| e.error)
            .unwrap_or(body);
        anyhow::bail!("the daemon answered {status}: {message}")
    }

    fn url(&self, path: &str) -> String {
        format!("{}{path}", self.server)
    }

    pub fn submit(&self, config: &Path) -> anyhow::Result<i64> {
        let text =
            std::fs::read(config).with_context(|| format!("reading {}", config.display()))?;
        let created: Created = self
            .request(
                self.http
                    .post(self.url("/v1/jobs"))
                    .header(reqwest::header::CONTENT_TYPE, "application/toml")
                    .body(text),
            )?
            .json()
            .context("reading the daemon's answer")?;
        Ok(created.id)
    }

    pub fn jobs(&self) -> anyhow::Result<Vec<JobView>> {
        Ok(self.request(self.http.get(self.url("/v1/jobs")))?.json()?)
    }

    pub fn job(&self, id: i64) -> anyhow::Result<JobView> {
        Ok(self
            .request(self.http.get(self.url(&format!("/v1/jobs/{id}"))))?
            .json()?)
    }

    pub fn cancel(&self, id: i64) -> anyhow::Result<()> {
        self.request(self.http.post(self.url(&format!("/v1/jobs/{id}/cancel"))))?;
        Ok(())
    }

    pub fn resume(&self, id: i64) -> anyhow::Result<()> {
        self.request(self.http.post(self.url(&format!("/v1/jobs/{id}/resume"))))?;
        Ok(())
    }

    pub fn prompts(&self) -> anyhow::Result<Vec<PendingPrompt>> {
        Ok(self
            .request(self.http.get(self.url("/v1/prompts")))?
            .json()?)
    }

    pub fn ack(&self, prompt: u64) -> anyhow::Result<()> {
        self.request(
            self.http
                .post(self.url(&format!("/v1/prompts/{prompt}/ack"))),
        )?;
        Ok(())
    }

    /// Download `what` of job `id` (`results`, `session`, or a file name) to `out`.
    pub fn fetch(&self, id: i64, what: &str, out: &Path) -> anyhow::Result<u64> {
        let path = match what {
            "results" => format!("/v1/jobs/{id}/results"),
            "session" => format!("/v1/jobs/{id}/session"),
            "report" => format!("/v1/jobs/{id}/report"),
            name => format!("/v1/jobs/{id}/files/{name}"),
        };
        let mut response = self.request(self.http.get(self.url(&path)))?;
        let mut file =
            std::fs::File::create(out).with_context(|| format!("creating {}", out.display()))?;
        response
            .copy_to(&mut file)
            .with_context(|| format!("writing {}", out.display()))
    }

    /// Follow job `id` on the event stream until it ends, calling `line` with each change;
    /// its final state.
    pub fn follow(&self, id: i64, mut line: impl FnMut(&str)) -> anyhow::Result<JobView> {
        self.follow_events(id, |event, value| line(&describe(event, value)))
    }

    /// Follow job `id` until it ends, calling `on_event` with each of its events (name and
    /// data); its final state.
    pub fn follow_events(
        &self,
        id: i64,
        mut on_event: impl FnMut(&str, &serde_json::Value),
    ) -> anyhow::Result<JobView> {
        let response = self.request(self.http.get(self.url("/v1/events")))?;
        // The job may have ended before the stream opened.
        let job = self.job(id)?;
        if ended(job.state) {
            return Ok(job);
        }
        let mut event = String::new();
        for text in std::io::BufReader::new(response).lines() {
            let text = text.context("reading the event stream")?;
            if let Some(name) = text.strip_prefix("event:") {
                event = name.trim().to_owned();
            } else if let Some(data) = text.strip_prefix("data:") {
                let value: serde_json::Value =
                    serde_json::from_str(data.trim()).unwrap_or_default();
                let of_job = value.get("id").and_then(|v| v.as_i64()) == Some(id)
                    || value.pointer("/prompt/job").and_then(|v| v.as_i64()) == Some(id);
                if !of_job {
                    continue;
                }
                on_event(&event, &value);
                if event == "job" {
                    let state = value.get("state").and_then(|s| s.as_str()).unwrap_or("");
                    if ["succeeded", "failed", "cancelled", "interrupted"].contains(&state) {
                        return self.job(id);
                    }
                }
            }
        }
        // The stream closed (the daemon stopped): report where the job stands.
        self.job(id)
    }
}

fn ended(state: JobState) -> bool {
    !matches!(state, JobState::Queued | JobState::Running)
}

/// An event of a followed job on the progress line: counts and stations update it, every
/// other event (state, fault, prompt) is a line of its own.
pub fn show_event(shown: &crate::progress::Progress, event: &str, value: &serde_json::Value) {
    match event {
        "progress" => {
            let count = |key: &str| value.pointer(key).and_then(|v| v.as_u64());
            if let Some(station) = value.pointer("/progress/station").and_then(|s| s.as_str()) {
                shown.station(station);
            }
            if let (Some(done), Some(total)) = (count("/progress/done"), count("/progress/total")) {
                shown.update(done, total);
            }
        }
        "station" => {
            if let Some(station) = value.get("station").and_then(|s| s.as_str()) {
                shown.station(station);
            }
        }
        _ => shown.println(&describe(event, value)),
    }
}

fn describe(event: &str, value: &serde_json::Value) -> String {
    let text = |pointer: &str| {
        value
            .pointer(pointer)
            .filter(|v| !v.is_null())
            .map(|v| v.as_str().map_or_else(|| v.to_string(), str::to_owned))
            .unwrap_or_default()
    };
    match event {
        "job" => format!("job {}: {} {}", text("/id"), text("/state"), text("/error"))
            .trim_end()
            .to_owned(),
        "progress" => format!(
            "job {}: {}/{} points{}",
            text("/id"),
            text("/progress/done"),
            text("/progress/total"),
            value
                .pointer("/progress/eta_s")
                .and_then(|v| v.as_f64())
                .map_or(String::new(), |eta| format!(", about {eta:.0} s left"))
        ),
        "station" => format!("job {}: station {}", text("/id"), text("/station")),
        "fault" => format!("job {}: fault {}", text("/id"), text("/message")),
        "prompt" => format!(
            "job {}: operator prompt {}: {} (acknowledge with `geocal client ack {}`)",
            text("/prompt/job"),
            text("/prompt/id"),
            text("/prompt/instruction"),
            text("/prompt/id")
        ),
        other => format!("{other}: {value}"),
    }
}

/// A followed job's end for a person at a terminal: its state and time, where its results
/// and report are (URL and the command that fetches them), its files and its error.
pub fn summary(job: &JobView, server: &str) -> String {
    let server = server.trim_end_matches('/');
    let time = |t: &Option<String>| {
        t.as_deref()
            .and_then(|t| chrono::DateTime::parse_from_rfc3339(t).ok())
    };
    let took = match (time(&job.started_at), time(&job.finished_at)) {
        (Some(start), Some(end)) => {
            let seconds = (end - start).num_milliseconds().max(0) as f64 / 1000.0;
            let minutes = (seconds / 60.0).floor();
            if minutes >= 1.0 {
                format!(" in {minutes:.0} min {:.0} s", seconds - 60.0 * minutes)
            } else {
                format!(" in {seconds:.1} s")
            }
        }
        _ => String::new(),
    };
    let mut lines = vec![format!(
        "job {} {}{took}: {} {} ({}/{} points), submitted by {}",
        job.id,
        job.state.as_str(),
        job.kind,
        job.job_type.as_str(),
        job.progress.done,
        job.progress.total,
        job.submitted_by
    )];
    if let Some(error) = &job.error {
        lines.push(format!("  {:<9}{error}", "error:"));
    }
    let has = |name: &str| job.files.iter().any(|f| f.name == name);
    for (what, file, route) in [
        ("results", "results.json", "results"),
        ("report", "report.html", "report"),
        ("session", "session.mcap", "session"),
    ] {
        if has(file) {
            lines.push(format!(
                "  {:<9}{server}/v1/jobs/{}/{route}  (geocal client fetch {} {what})",
                format!("{what}:"),
                job.id,
                job.id
            ));
        }
    }
    let others: Vec<&str> = job
        .files
        .iter()
        .map(|f| f.name.as_str())
        .filter(|name| !["results.json", "report.html", "session.mcap"].contains(name))
        .collect();
    if !others.is_empty() {
        lines.push(format!("  {:<9}{}", "files:", others.join(", ")));
    }
    lines.push(format!("  {:<9}{server}/#/jobs/{}", "console:", job.id));
    lines.join("\n")
}

/// One line per job for `geocal client jobs`.
pub fn job_line(job: &JobView) -> String {
    format!(
        "{:>5}  {:<8} {:<15} {:<11} {:>5}/{:<5} {}",
        job.id,
        job.job_type.as_str(),
        job.kind,
        job.state.as_str(),
        job.progress.done,
        job.progress.total,
        job.error.as_deref().unwrap_or("")
    )
}

/// Where `fetch` writes by default: the name the daemon uses.
pub fn default_fetch_path(id: i64, what: &str) -> PathBuf {
    let name = match what {
        "results" => "results.json",
        "session" => "session.mcap",
        "report" => "report.html",
        name => name,
    };
    PathBuf::from(format!("job-{id}-{name}"))
}
