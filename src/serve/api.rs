//! The HTTP/JSON control API, versioned under `/v1`, with its OpenAPI document generated
//! from the handlers (`/v1/openapi.json`), Server-Sent Events and Prometheus metrics.

use std::convert::Infallible;
use std::net::SocketAddr;
use std::sync::Arc;

use axum::body::{Body, Bytes};
use axum::extract::{ConnectInfo, DefaultBodyLimit, Path, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::Extension;
use axum::{Json, Router};
use futures_util::{Stream, StreamExt};
use serde::{Deserialize, Serialize};
use tokio::sync::Semaphore;
use utoipa::{OpenApi, ToSchema};

use super::auth::{require_token, Token};
use super::catalog::{JobFile, JobRecord, JobState, JobType};
use super::guard::{check_host, json_errors, read_body, BodyLimits, HostCheck};
use super::jobs::{Daemon, JobError, ServerEvent, REPORT_FILE};
use super::layout::{AxisTravel, StationHint, StationLayout};
use super::library::{LibraryPlan, PlanLibrary};
use super::machines::{
    ComparisonSummary, HistoryEntry, MachineChange, MachineHistory, MachineView,
};
use super::prompts::PendingPrompt;
use super::samples::SampleBatch;
use super::schedule::{ScheduleView, ScheduledJob};
use super::status::{DeviceStatus, Progress};

/// A job as the API shows it.
#[derive(Debug, Clone, Serialize, serde::Deserialize, ToSchema)]
pub struct JobView {
    pub id: i64,
    /// The plan kind (multilateration, rotary_tracer, rotary_sphere, probe_install, hexapod).
    pub kind: String,
    #[serde(rename = "type")]
    pub job_type: JobType,
    pub state: JobState,
    pub progress: Progress,
    pub submitted_at: String,
    pub started_at: Option<String>,
    pub finished_at: Option<String>,
    pub submitted_by: String,
    pub config_sha256: Option<String>,
    pub source_job: Option<i64>,
    pub error: Option<String>,
    pub resume: bool,
    pub files: Vec<JobFile>,
}

/// A solve, diagnose or replay of an earlier job's session (`application/json`).
#[derive(Debug, Clone, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct SessionJob {
    #[serde(rename = "type")]
    pub job_type: SessionJobType,
    /// The job whose session to read.
    pub session_of: i64,
}

/// What a session job does (a run is submitted as a plan configuration instead).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum SessionJobType {
    Solve,
    Diagnose,
    Replay,
}

impl From<SessionJobType> for JobType {
    fn from(t: SessionJobType) -> JobType {
        match t {
            SessionJobType::Solve => JobType::Solve,
            SessionJobType::Diagnose => JobType::Diagnose,
            SessionJobType::Replay => JobType::Replay,
        }
    }
}

#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct Created {
    pub id: i64,
}

#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct StateReply {
    pub id: i64,
    pub state: JobState,
}

#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct ErrorBody {
    pub error: String,
}

#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct Health {
    pub status: String,
    pub version: String,
    pub accepting_jobs: bool,
    pub busy: bool,
}

/// An error as the API answers it: a status and `{"error": "..."}`.
pub struct ApiError(StatusCode, String);

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        (self.0, Json(ErrorBody { error: self.1 })).into_response()
    }
}

impl From<JobError> for ApiError {
    fn from(e: JobError) -> Self {
        let status = match &e {
            JobError::BadRequest(_) => StatusCode::BAD_REQUEST,
            JobError::NotFound(_) => StatusCode::NOT_FOUND,
            JobError::Conflict(_) => StatusCode::CONFLICT,
            JobError::ShuttingDown => StatusCode::SERVICE_UNAVAILABLE,
            JobError::Internal(e) => {
                tracing::error!("internal error: {e:#}");
                StatusCode::INTERNAL_SERVER_ERROR
            }
        };
        let message = match &e {
            JobError::Internal(e) => super::jobs::error_chain(e),
            other => other.to_string(),
        };
        ApiError(status, message)
    }
}

type ApiResult<T> = Result<T, ApiError>;

fn view(daemon: &Daemon, job: JobRecord) -> JobView {
    let progress = daemon.live_progress(job.id).unwrap_or(Progress {
        done: job.progress_done,
        total: job.progress_total,
        ..Progress::default()
    });
    JobView {
        id: job.id,
        kind: job.kind,
        job_type: job.job_type,
        state: job.state,
        progress,
        submitted_at: job.submitted_at,
        started_at: job.started_at,
        finished_at: job.finished_at,
        submitted_by: job.submitted_by,
        config_sha256: job.config_sha256,
        source_job: job.source_job,
        error: job.error,
        resume: job.resume,
        files: job.files,
    }
}

/// Submit a job: a plan configuration as TOML (`Content-Type: application/toml`) runs it; a
/// JSON `SessionJob` solves, diagnoses or replays an earlier job's session.
#[utoipa::path(post, path = "/v1/jobs",
    responses(
        (status = 201, body = Created),
        (status = 400, body = ErrorBody, description = "the configuration or session job is invalid: the error names the key"),
        (status = 404, body = ErrorBody, description = "the session job names no job"),
        (status = 408, body = ErrorBody, description = "the body did not arrive within the daemon's time-out"),
        (status = 409, body = ErrorBody, description = "the session job's source has no session"),
        (status = 413, body = ErrorBody, description = "the body is over the daemon's limit"),
        (status = 415, body = ErrorBody),
        (status = 503, body = ErrorBody, description = "the daemon is stopping")))]
async fn submit(
    State(daemon): State<Arc<Daemon>>,
    ConnectInfo(peer): ConnectInfo<SocketAddr>,
    headers: HeaderMap,
    body: Bytes,
) -> ApiResult<(StatusCode, Json<Created>)> {
    let content_type = headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
        .split(';')
        .next()
        .unwrap_or("")
        .trim()
        .to_ascii_lowercase();
    let by = peer.to_string();
    let id = match content_type.as_str() {
        "application/toml" | "text/toml" => {
            let text = std::str::from_utf8(&body).map_err(|e| {
                ApiError(
                    StatusCode::BAD_REQUEST,
                    format!("the body is not UTF-8: {e}"),
                )
            })?;
            let daemon = daemon.clone();
            let text = text.to_owned();
            blocking(move || daemon.submit_run(&text, &by)).await?
        }
        "application/json" => {
            let job: SessionJob = serde_json::from_slice(&body).map_err(|e| {
                ApiError(
                    StatusCode::BAD_REQUEST,
                    format!("the body is not a session job: {e}"),
                )
            })?;
            let daemon = daemon.clone();
            blocking(move || daemon.submit_on_session(job.job_type.into(), job.session_of, &by))
                .await?
        }
        other => {
            return Err(ApiError(
                StatusCode::UNSUPPORTED_MEDIA_TYPE,
                format!(
                    "Content-Type `{other}`: expected application/toml (a plan configuration) \
                     or application/json (a solve, diagnose or replay job)"
                ),
            ))
        }
    };
    Ok((StatusCode::CREATED, Json(Created { id })))
}

/// Run a catalog call off the async threads (it may check a plan or hash files).
async fn blocking<T: Send + 'static>(
    f: impl FnOnce() -> Result<T, JobError> + Send + 'static,
) -> ApiResult<T> {
    tokio::task::spawn_blocking(f)
        .await
        .map_err(|e| ApiError(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?
        .map_err(ApiError::from)
}

/// Every job, newest first.
#[utoipa::path(get, path = "/v1/jobs", responses((status = 200, body = Vec<JobView>)))]
async fn list_jobs(State(daemon): State<Arc<Daemon>>) -> ApiResult<Json<Vec<JobView>>> {
    let jobs = daemon.jobs()?;
    Ok(Json(jobs.into_iter().map(|j| view(&daemon, j)).collect()))
}

/// One job: state, progress (done/total, current station, ETA, last faults), files.
#[utoipa::path(get, path = "/v1/jobs/{id}", params(("id" = i64, Path)),
    responses((status = 200, body = JobView), (status = 404, body = ErrorBody)))]
async fn get_job(
    State(daemon): State<Arc<Daemon>>,
    Path(id): Path<i64>,
) -> ApiResult<Json<JobView>> {
    let job = daemon.job(id)?;
    Ok(Json(view(&daemon, job)))
}

/// Cancel a queued job, or a running one cleanly (flushed, resumable).
#[utoipa::path(post, path = "/v1/jobs/{id}/cancel", params(("id" = i64, Path)),
    responses((status = 202, body = StateReply), (status = 404, body = ErrorBody),
        (status = 409, body = ErrorBody)))]
async fn cancel_job(
    State(daemon): State<Arc<Daemon>>,
    Path(id): Path<i64>,
) -> ApiResult<(StatusCode, Json<StateReply>)> {
    let state = daemon.cancel(id)?;
    Ok((StatusCode::ACCEPTED, Json(StateReply { id, state })))
}

/// Continue an interrupted or cancelled run at its first unfinished point.
#[utoipa::path(post, path = "/v1/jobs/{id}/resume", params(("id" = i64, Path)),
    responses((status = 202, body = StateReply), (status = 404, body = ErrorBody),
        (status = 409, body = ErrorBody, description = "the job is not an interrupted or cancelled run"),
        (status = 503, body = ErrorBody, description = "the daemon is stopping")))]
async fn resume_job(
    State(daemon): State<Arc<Daemon>>,
    Path(id): Path<i64>,
) -> ApiResult<(StatusCode, Json<StateReply>)> {
    let d = daemon.clone();
    blocking(move || d.resume(id)).await?;
    Ok((
        StatusCode::ACCEPTED,
        Json(StateReply {
            id,
            state: JobState::Queued,
        }),
    ))
}

/// The job's results (geocal-results/1).
#[utoipa::path(get, path = "/v1/jobs/{id}/results", params(("id" = i64, Path)),
    responses((status = 200, content_type = "application/json", description = "geocal-results/1"),
        (status = 404, body = ErrorBody)))]
async fn job_results(
    State(daemon): State<Arc<Daemon>>,
    Path(id): Path<i64>,
) -> ApiResult<Response> {
    job_file(&daemon, id, "results.json", "application/json").await
}

/// The job's recorded session (MCAP).
#[utoipa::path(get, path = "/v1/jobs/{id}/session", params(("id" = i64, Path)),
    responses((status = 200, content_type = "application/octet-stream", description = "the session's MCAP file"),
        (status = 404, body = ErrorBody)))]
async fn job_session(
    State(daemon): State<Arc<Daemon>>,
    Path(id): Path<i64>,
) -> ApiResult<Response> {
    job_file(&daemon, id, "session.mcap", "application/octet-stream").await
}

/// The job's report (`geocal report` of its folder: one self-contained HTML page).
#[utoipa::path(get, path = "/v1/jobs/{id}/report", params(("id" = i64, Path)),
    responses((status = 200, content_type = "text/html", description = "the report"),
        (status = 404, body = ErrorBody)))]
async fn job_report(State(daemon): State<Arc<Daemon>>, Path(id): Path<i64>) -> ApiResult<Response> {
    job_file(&daemon, id, REPORT_FILE, "text/html; charset=utf-8").await
}

/// Any file the job left (its report, diagnosis, plan, log), by the name its file list gives.
#[utoipa::path(get, path = "/v1/jobs/{id}/files/{name}", params(("id" = i64, Path), ("name" = String, Path)),
    responses((status = 200, description = "the file (its type from its extension)"), (status = 404, body = ErrorBody)))]
async fn job_named_file(
    State(daemon): State<Arc<Daemon>>,
    Path((id, name)): Path<(i64, String)>,
) -> ApiResult<Response> {
    let content_type = match name.rsplit_once('.').map(|(_, ext)| ext) {
        Some("json") => "application/json",
        Some("html") => "text/html; charset=utf-8",
        Some("svg") => "image/svg+xml",
        Some("toml") | Some("log") | Some("md") | Some("txt") => "text/plain; charset=utf-8",
        _ => "application/octet-stream",
    };
    job_file(&daemon, id, &name, content_type).await
}

/// Stream `name` from job `id`'s folder. Only names in the job's file list (as the catalog
/// recorded them, or as the folder lists them now) are served: no client-chosen paths.
async fn job_file(daemon: &Daemon, id: i64, name: &str, content_type: &str) -> ApiResult<Response> {
    let job = daemon.job(id)?;
    let mut listed = false;
    if let Ok(mut entries) = tokio::fs::read_dir(&job.dir).await {
        while let Ok(Some(entry)) = entries.next_entry().await {
            if entry.file_name().to_str() == Some(name)
                && entry.file_type().await.is_ok_and(|t| t.is_file())
            {
                listed = true;
                break;
            }
        }
    }
    if !listed {
        return Err(ApiError(
            StatusCode::NOT_FOUND,
            format!("job {id} has no file `{name}` (yet)"),
        ));
    }
    let file = tokio::fs::File::open(job.dir.join(name))
        .await
        .map_err(|e| ApiError(StatusCode::NOT_FOUND, format!("job {id}: {name}: {e}")))?;
    let body = Body::from_stream(tokio_util::io::ReaderStream::new(file));
    Ok(([(header::CONTENT_TYPE, content_type.to_owned())], body).into_response())
}

/// Every device seen by the daemon's runs: connected, last reading, signal, last error.
#[utoipa::path(get, path = "/v1/devices", responses((status = 200, body = Vec<DeviceStatus>)))]
async fn devices(State(daemon): State<Arc<Daemon>>) -> Json<Vec<DeviceStatus>> {
    Json(daemon.devices())
}

/// Operator prompts waiting for acknowledgement.
#[utoipa::path(get, path = "/v1/prompts", responses((status = 200, body = Vec<PendingPrompt>)))]
async fn prompts(State(daemon): State<Arc<Daemon>>) -> Json<Vec<PendingPrompt>> {
    Json(daemon.prompts.list())
}

/// Acknowledge a prompt (what Enter does at the console).
#[utoipa::path(post, path = "/v1/prompts/{id}/ack", params(("id" = u64, Path)),
    responses((status = 204), (status = 404, body = ErrorBody)))]
async fn ack_prompt(
    State(daemon): State<Arc<Daemon>>,
    Path(id): Path<u64>,
) -> ApiResult<StatusCode> {
    if daemon.prompts.acknowledge(id) {
        Ok(StatusCode::NO_CONTENT)
    } else {
        Err(ApiError(
            StatusCode::NOT_FOUND,
            format!("no prompt {id} is waiting"),
        ))
    }
}

/// Job states, progress, stations, faults and prompts as Server-Sent Events (the event name
/// is the `type`).
#[utoipa::path(get, path = "/v1/events",
    responses((status = 200, content_type = "text/event-stream", body = ServerEvent),
        (status = 403, body = ErrorBody, description = "a browser asked for another web origin's page"),
        (status = 503, body = ErrorBody, description = "max_streams event streams are open")))]
async fn events(
    State(daemon): State<Arc<Daemon>>,
    Extension(streams): Extension<StreamSlots>,
    headers: HeaderMap,
) -> ApiResult<Sse<impl Stream<Item = Result<Event, Infallible>>>> {
    let slot = streams.open(&headers)?;
    let stream = tokio_stream::wrappers::BroadcastStream::new(daemon.events.subscribe())
        .filter_map(|event| async move {
            let event = event.ok()?;
            Event::default().event(event.name()).json_data(&event).ok()
        })
        .map(move |event| {
            let _held = &slot;
            Ok(event)
        })
        // Open streams must not hold up a shutdown.
        .take_until(daemon.shutdown.clone().cancelled_owned());
    Ok(Sse::new(stream).keep_alive(KeepAlive::default()))
}

/// The running job's device readings as Server-Sent Events: `samples`, one device's readings
/// since its previous message (at most 20 messages a second per device, each with up to 200
/// samples); `lagged`, `{"messages": n}` when this client read too slowly and lost the n
/// oldest messages. Counted against `max_streams` with `/v1/events`.
#[utoipa::path(get, path = "/v1/devices/samples",
    responses((status = 200, content_type = "text/event-stream", body = SampleBatch),
        (status = 403, body = ErrorBody, description = "a browser asked for another web origin's page"),
        (status = 503, body = ErrorBody, description = "max_streams event streams are open")))]
async fn device_samples(
    State(daemon): State<Arc<Daemon>>,
    Extension(streams): Extension<StreamSlots>,
    headers: HeaderMap,
) -> ApiResult<Sse<impl Stream<Item = Result<Event, Infallible>>>> {
    use tokio_stream::wrappers::errors::BroadcastStreamRecvError;
    let slot = streams.open(&headers)?;
    let stream = tokio_stream::wrappers::BroadcastStream::new(daemon.samples.subscribe())
        .filter_map(|message| async move {
            match message {
                Ok(batch) => Event::default().event("samples").json_data(&*batch).ok(),
                Err(BroadcastStreamRecvError::Lagged(lost)) => Event::default()
                    .event("lagged")
                    .json_data(serde_json::json!({ "messages": lost }))
                    .ok(),
            }
        })
        .map(move |event| {
            let _held = &slot;
            Ok(event)
        })
        .take_until(daemon.shutdown.clone().cancelled_owned());
    Ok(Sse::new(stream).keep_alive(KeepAlive::default()))
}

/// The event streams' own slots (`max_streams`) and their number.
#[derive(Clone)]
pub struct StreamSlots(Arc<Semaphore>, usize);

impl StreamSlots {
    /// A slot for a stream (held for as long as it runs, apart from the request slots); a
    /// browser reading for another origin's page gets none (a stream is read, not changed,
    /// but its data is the machine's).
    fn open(&self, headers: &HeaderMap) -> ApiResult<tokio::sync::OwnedSemaphorePermit> {
        if super::guard::from_another_origin(headers) {
            return Err(ApiError(
                StatusCode::FORBIDDEN,
                "a stream for another web origin's page is refused".into(),
            ));
        }
        self.0.clone().try_acquire_owned().map_err(|_| {
            ApiError(
                StatusCode::SERVICE_UNAVAILABLE,
                format!(
                    "{} event streams are open, the daemon's max_streams: close one",
                    self.1
                ),
            )
        })
    }
}

/// After the Host and token checks: the connection is admitted (no longer pushed out by
/// newer waiting ones) and its request takes one of the `max_connections` slots while its
/// handler runs. Slots are never taken by a request that was refused.
async fn admit(
    State(slots): State<Arc<Semaphore>>,
    request: axum::extract::Request,
    next: axum::middleware::Next,
) -> Response {
    if let Some(admission) = request.extensions().get::<super::http::Admission>() {
        admission.0.admit();
    }
    let Ok(_slot) = slots.acquire().await else {
        return ApiError(StatusCode::SERVICE_UNAVAILABLE, "stopping".into()).into_response();
    };
    next.run(request).await
}

/// Every machine with a succeeded run (by configured name): its kinds, runs and last run.
#[utoipa::path(get, path = "/v1/machines", responses((status = 200, body = Vec<MachineView>)))]
async fn list_machines(State(daemon): State<Arc<Daemon>>) -> ApiResult<Json<Vec<MachineView>>> {
    let d = daemon.clone();
    blocking(move || Ok(super::machines::machines(d.jobs()?)))
        .await
        .map(Json)
}

/// A machine's succeeded runs, oldest first, each with its comparison with the run before
/// (scheduled runs).
#[utoipa::path(get, path = "/v1/machines/{name}/history", params(("name" = String, Path)),
    responses((status = 200, body = MachineHistory), (status = 404, body = ErrorBody),
        (status = 409, body = ErrorBody, description = "the name is shared by several machines: the message names their keys")))]
async fn machine_history(
    State(daemon): State<Arc<Daemon>>,
    Path(name): Path<String>,
) -> ApiResult<Json<MachineHistory>> {
    machine_query(daemon, move |jobs| super::machines::history(jobs, &name))
        .await
        .map(Json)
}

/// A machine's trend over its runs of the kind of its last run (geocal-trend/1): each
/// parameter over time with its σ and band, and the events found (step, drift, outside
/// tolerance).
#[utoipa::path(get, path = "/v1/machines/{name}/trend", params(("name" = String, Path)),
    responses((status = 200, content_type = "application/json", description = "geocal-trend/1"),
        (status = 404, body = ErrorBody),
        (status = 409, body = ErrorBody, description = "fewer than 2 runs of its last kind, or the name is shared by several machines")))]
async fn machine_trend(
    State(daemon): State<Arc<Daemon>>,
    Path(name): Path<String>,
) -> ApiResult<Json<serde_json::Value>> {
    let config = daemon.config.history.clone();
    machine_query(daemon, move |jobs| {
        super::machines::trend(jobs, &name, &config)
    })
    .await
    .map(Json)
}

/// A query over the catalog's machines, answered off the async runtime: no machine → 404, a
/// shared name or too few runs → 409.
async fn machine_query<T: Send + 'static>(
    daemon: Arc<Daemon>,
    query: impl FnOnce(Vec<super::catalog::JobRecord>) -> Result<T, super::machines::MachineError>
        + Send
        + 'static,
) -> ApiResult<T> {
    use super::machines::MachineError;
    let answer = tokio::task::spawn_blocking(move || {
        let jobs = daemon
            .jobs()
            .map_err(|e| MachineError::Internal(anyhow::anyhow!("{e}")))?;
        query(jobs)
    })
    .await
    .map_err(|e| ApiError(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?;
    match answer {
        Ok(value) => Ok(value),
        Err(e @ MachineError::NoMachine(_)) => Err(ApiError(StatusCode::NOT_FOUND, e.to_string())),
        Err(e @ (MachineError::NotEnough(_) | MachineError::Ambiguous(_))) => {
            Err(ApiError(StatusCode::CONFLICT, e.to_string()))
        }
        Err(MachineError::Internal(e)) => {
            tracing::error!("internal error: {e:#}");
            Err(ApiError(
                StatusCode::INTERNAL_SERVER_ERROR,
                super::jobs::error_chain(&e),
            ))
        }
    }
}

/// The plan library's plans (the daemon's `plan_library`; none without one).
#[utoipa::path(get, path = "/v1/plans", responses((status = 200, body = Vec<LibraryPlan>)))]
async fn list_plans(State(daemon): State<Arc<Daemon>>) -> ApiResult<Json<Vec<LibraryPlan>>> {
    let d = daemon.clone();
    blocking(move || {
        Ok(match &d.config.plan_library {
            Some(dir) => PlanLibrary::open(dir).map_err(JobError::Internal)?.list(),
            None => Vec::new(),
        })
    })
    .await
    .map(Json)
}

/// Submit plan `name` of the plan library as a run job (as `POST /v1/jobs` with its text).
#[utoipa::path(post, path = "/v1/plans/{name}/submit", params(("name" = String, Path)),
    responses((status = 201, body = Created),
        (status = 400, body = ErrorBody, description = "the plan is invalid: the error names the key"),
        (status = 404, body = ErrorBody, description = "the library offers no such plan"),
        (status = 503, body = ErrorBody, description = "the daemon is stopping")))]
async fn submit_library_plan(
    State(daemon): State<Arc<Daemon>>,
    ConnectInfo(peer): ConnectInfo<SocketAddr>,
    Path(name): Path<String>,
) -> ApiResult<(StatusCode, Json<Created>)> {
    let d = daemon.clone();
    let wanted = name.clone();
    let text = blocking(move || match &d.config.plan_library {
        Some(dir) => Ok(PlanLibrary::open(dir)
            .map_err(JobError::Internal)?
            .read(&wanted)),
        None => Ok(None),
    })
    .await?
    .ok_or_else(|| {
        ApiError(
            StatusCode::NOT_FOUND,
            format!("the plan library offers no plan `{name}`"),
        )
    })?;
    let d = daemon.clone();
    let id = blocking(move || d.submit_run(&text, &peer.to_string())).await?;
    Ok((StatusCode::CREATED, Json(Created { id })))
}

/// Every schedule: its expression and zone, its next run and its last job.
#[utoipa::path(get, path = "/v1/schedules", responses((status = 200, body = Vec<ScheduleView>)))]
async fn list_schedules(State(daemon): State<Arc<Daemon>>) -> ApiResult<Json<Vec<ScheduleView>>> {
    let d = daemon.clone();
    blocking(move || {
        Ok(super::schedule::overview(
            &d.config.schedule,
            &d.config.base_dir,
            chrono::Utc::now(),
            &d.jobs()?,
        ))
    })
    .await
    .map(Json)
}

/// Where a run's stations go: the machine's travel and the plan's station hints (empty for a
/// plan without stations).
#[utoipa::path(get, path = "/v1/jobs/{id}/layout", params(("id" = i64, Path)),
    responses((status = 200, body = StationLayout), (status = 404, body = ErrorBody)))]
async fn job_layout(
    State(daemon): State<Arc<Daemon>>,
    Path(id): Path<i64>,
) -> ApiResult<Json<StationLayout>> {
    let d = daemon.clone();
    blocking(move || {
        let job = d.job(id)?;
        Ok(std::fs::read_to_string(job.dir.join("plan.toml"))
            .map(|text| super::layout::of_plan(&text))
            .unwrap_or_default())
    })
    .await
    .map(Json)
}

#[utoipa::path(get, path = "/v1/health", responses((status = 200, body = Health)))]
async fn health(State(daemon): State<Arc<Daemon>>) -> Json<Health> {
    Json(Health {
        status: "ok".into(),
        version: env!("CARGO_PKG_VERSION").into(),
        accepting_jobs: !daemon.shutdown.is_cancelled(),
        busy: daemon.is_busy(),
    })
}

/// Prometheus metrics: jobs by state, samples recorded, faults by kind, recorder queue depth.
#[utoipa::path(get, path = "/metrics",
    responses((status = 200, content_type = "application/openmetrics-text", description = "OpenMetrics text format (`version=1.0.0`)")))]
async fn metrics(State(daemon): State<Arc<Daemon>>) -> ApiResult<Response> {
    let text = super::metrics::render(&daemon)
        .map_err(|e| ApiError(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?;
    Ok((
        [(
            header::CONTENT_TYPE,
            "application/openmetrics-text; version=1.0.0; charset=utf-8",
        )],
        text,
    )
        .into_response())
}

#[derive(OpenApi)]
#[openapi(
    info(
        title = "geocal daemon",
        description = "Calibration jobs, devices, prompts and live events of `geocal serve`."
    ),
    paths(
        submit,
        list_jobs,
        get_job,
        cancel_job,
        resume_job,
        job_results,
        job_session,
        job_report,
        job_named_file,
        devices,
        prompts,
        ack_prompt,
        events,
        device_samples,
        list_plans,
        submit_library_plan,
        list_schedules,
        job_layout,
        health,
        metrics,
        list_machines,
        machine_history,
        machine_trend
    ),
    components(schemas(
        JobView,
        SessionJob,
        SessionJobType,
        Created,
        StateReply,
        ErrorBody,
        Health,
        JobFile,
        JobState,
        JobType,
        Progress,
        LibraryPlan,
        ScheduleView,
        ScheduledJob,
        StationLayout,
        AxisTravel,
        StationHint,
        DeviceStatus,
        crate::devices::held::HeldStatus,
        PendingPrompt,
        ServerEvent,
        SampleBatch,
        MachineView,
        MachineHistory,
        HistoryEntry,
        ComparisonSummary,
        MachineChange
    ))
)]
pub struct ApiDoc;

/// The OpenAPI document of this daemon as configured: bearer security only when a token is
/// set, and on every operation the answers any request may get (a path, header or body that
/// does not parse: 400; no or a wrong token: 401; a body too slow: 408, or too large: 413; a
/// Host not allowed: 421; 500).
pub fn openapi_document(options: &ApiOptions) -> utoipa::openapi::OpenApi {
    use utoipa::openapi::path::Operation;
    use utoipa::openapi::request_body::RequestBodyBuilder;
    use utoipa::openapi::schema::{ObjectBuilder, Type};
    use utoipa::openapi::security::{
        HttpAuthScheme, HttpBuilder, SecurityRequirement, SecurityScheme,
    };
    use utoipa::openapi::{ContentBuilder, Ref, Required, ResponseBuilder};

    let mut document = ApiDoc::openapi();
    let error = |description: &str| {
        ResponseBuilder::new()
            .description(description)
            .content(
                "application/json",
                ContentBuilder::new()
                    .schema(Some(Ref::from_schema_name("ErrorBody")))
                    .build(),
            )
            .build()
    };
    let mut common = vec![
        (
            "400",
            error("a path parameter, header or body that does not parse"),
        ),
        (
            "408",
            error("the body did not arrive within the daemon's time-out"),
        ),
        (
            "413",
            error("the declared or sent body is over the daemon's limit"),
        ),
        ("414", error("the request target is over 8 KiB")),
        (
            "431",
            error("the request's headers are over 64 KiB or more than 64"),
        ),
        ("500", error("an internal error")),
    ];
    if options.token.is_some() {
        common.push(("401", error("no bearer token, or another")));
    }
    if options.host_check.is_some() {
        common.push((
            "421",
            error("the Host header is not one the daemon answers to without a token"),
        ));
    }
    for item in document.paths.paths.values_mut() {
        let operations: [&mut Option<Operation>; 8] = [
            &mut item.get,
            &mut item.put,
            &mut item.post,
            &mut item.delete,
            &mut item.options,
            &mut item.head,
            &mut item.patch,
            &mut item.trace,
        ];
        for operation in operations.into_iter().flatten() {
            for (status, response) in &common {
                operation
                    .responses
                    .responses
                    .entry((*status).to_owned())
                    .or_insert_with(|| response.clone().into());
            }
        }
    }
    if let Some(submit) = document
        .paths
        .paths
        .get_mut("/v1/jobs")
        .and_then(|item| item.post.as_mut())
    {
        let toml = ObjectBuilder::new()
            .schema_type(Type::String)
            .description(Some("a plan configuration, as for `geocal run`"))
            .build();
        submit.request_body = Some(
            RequestBodyBuilder::new()
                .description(Some(
                    "a plan configuration as TOML runs it; a session job as JSON solves, \
                     diagnoses or replays an earlier job's session",
                ))
                .content(
                    "application/toml",
                    ContentBuilder::new().schema(Some(toml)).build(),
                )
                .content(
                    "application/json",
                    ContentBuilder::new()
                        .schema(Some(Ref::from_schema_name("SessionJob")))
                        .build(),
                )
                .required(Some(Required::True))
                .build(),
        );
    }
    // The named files' types follow their extensions.
    if let Some(file) = document
        .paths
        .paths
        .get_mut("/v1/jobs/{id}/files/{name}")
        .and_then(|item| item.get.as_mut())
    {
        let mut found =
            ResponseBuilder::new().description("the file (its type from its extension)");
        for content_type in [
            "application/json",
            "text/html",
            "image/svg+xml",
            "text/plain",
            "application/octet-stream",
        ] {
            found = found.content(content_type, ContentBuilder::new().build());
        }
        file.responses
            .responses
            .insert("200".into(), found.build().into());
    }
    if options.token.is_some() {
        let components = document.components.get_or_insert_with(Default::default);
        components.add_security_scheme(
            "bearer",
            SecurityScheme::Http(HttpBuilder::new().scheme(HttpAuthScheme::Bearer).build()),
        );
        document.security = Some(vec![SecurityRequirement::new(
            "bearer",
            Vec::<String>::new(),
        )]);
    }
    document
}

/// How the API guards itself (see `guard` and `auth`).
#[derive(Clone)]
pub struct ApiOptions {
    pub token: Option<Token>,
    /// The `Host` allow-list, used when no token guards the API.
    pub host_check: Option<HostCheck>,
    pub body: BodyLimits,
    /// Requests handled at once (`max_connections`).
    pub request_slots: usize,
    /// Event streams open at once (`max_streams`).
    pub stream_slots: usize,
}

async fn not_found() -> ApiError {
    ApiError(StatusCode::NOT_FOUND, "no such route".into())
}

/// Every route, behind the Host check, the token check and the body limits; every error
/// answer JSON.
pub fn router(daemon: Arc<Daemon>, options: ApiOptions) -> Router {
    let limit = options.body.max_bytes;
    let streams = options.stream_slots.clamp(1, Semaphore::MAX_PERMITS);
    let document = serde_json::to_string(&openapi_document(&options)).unwrap_or_default();
    let openapi = move || {
        let document = document.clone();
        async move { ([(header::CONTENT_TYPE, "application/json")], document) }
    };
    Router::new()
        .route("/v1/jobs", post(submit).get(list_jobs))
        .route("/v1/jobs/{id}", get(get_job))
        .route("/v1/jobs/{id}/cancel", post(cancel_job))
        .route("/v1/jobs/{id}/resume", post(resume_job))
        .route("/v1/jobs/{id}/results", get(job_results))
        .route("/v1/jobs/{id}/session", get(job_session))
        .route("/v1/jobs/{id}/report", get(job_report))
        .route("/v1/jobs/{id}/files/{name}", get(job_named_file))
        .route("/v1/devices", get(devices))
        .route("/v1/devices/samples", get(device_samples))
        .route("/v1/prompts", get(prompts))
        .route("/v1/prompts/{id}/ack", post(ack_prompt))
        .route("/v1/events", get(events))
        .route("/v1/machines", get(list_machines))
        .route("/v1/machines/{name}/history", get(machine_history))
        .route("/v1/machines/{name}/trend", get(machine_trend))
        .route("/v1/plans", get(list_plans))
        .route("/v1/plans/{name}/submit", post(submit_library_plan))
        .route("/v1/schedules", get(list_schedules))
        .route("/v1/jobs/{id}/layout", get(job_layout))
        .merge(super::console::routes(options.token.clone()))
        .route("/v1/health", get(health))
        .route("/v1/openapi.json", get(openapi))
        .route("/metrics", get(metrics))
        .fallback(not_found)
        .layer(DefaultBodyLimit::max(limit))
        .layer(Extension(StreamSlots(
            Arc::new(Semaphore::new(streams)),
            streams,
        )))
        .layer(axum::middleware::from_fn_with_state(
            options.body,
            read_body,
        ))
        .layer(axum::middleware::from_fn_with_state(
            Arc::new(Semaphore::new(
                options.request_slots.clamp(1, Semaphore::MAX_PERMITS),
            )),
            admit,
        ))
        .layer(axum::middleware::from_fn_with_state(
            Arc::new(options.token),
            require_token,
        ))
        .layer(axum::middleware::from_fn_with_state(
            Arc::new(options.host_check),
            check_host,
        ))
        .layer(axum::middleware::from_fn(super::guard::check_origin))
        .layer(axum::middleware::from_fn(json_errors))
        .with_state(daemon)
}
