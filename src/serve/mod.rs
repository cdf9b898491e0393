//! `geocal serve`: the acquisition daemon — a job catalog that survives crashes, workers
//! that run jobs (runs one at a time, session jobs beside them), the HTTP control API, and a
//! client that speaks to it.

pub mod api;
pub mod auth;
pub mod catalog;
pub mod client;
pub mod config;
pub mod console;
pub mod door;
pub mod guard;
pub mod http;
pub mod jobs;
pub mod layout;
pub mod library;
pub mod live;
pub mod live_guard;
pub mod machines;
pub mod metrics;
pub mod prompts;
pub mod samples;
pub mod schedule;
pub mod status;

use std::time::Duration;

use anyhow::Context;

pub use config::ServeConfig;

use crate::kinds::Registry;

/// Start the daemon and serve until SIGTERM or SIGINT: then stop taking jobs, cancel the
/// running one cleanly (its session flushed and resumable) and return.
pub fn serve(config: ServeConfig, registry: Registry) -> anyhow::Result<()> {
    crate::allocator::limit_arenas();
    let token = match &config.token_file {
        Some(path) => Some(auth::Token::load(path)?),
        None if !config.listen.ip().is_loopback() => anyhow::bail!(
            "listening on {} (beyond loopback) needs a bearer token: set token_file in the \
             daemon configuration (a file only its owner can read)",
            config.listen
        ),
        None => None,
    };
    let live_address = match config.live.trim() {
        "off" | "" => None,
        text => Some(live::parse_address(text)?),
    };
    // Beyond loopback the live view, like the API, needs the token to check.
    if let Some(address) = live_address.filter(|a| !a.ip().is_loopback()) {
        if token.is_none() {
            anyhow::bail!(
                "the live view on {address} (beyond loopback) needs the daemon's token_file, \
                 as the API does"
            );
        }
    }
    config.request_timeout()?;
    config.history.check()?;
    for (key, value) in [
        ("max_connections", config.max_connections),
        ("max_streams", config.max_streams),
    ] {
        if value == 0 {
            anyhow::bail!("{key} = 0: expected at least 1");
        }
    }
    if let Some(library) = &config.plan_library {
        library::PlanLibrary::open(library)?;
    }
    // A bad schedule refuses the start, like a bad key.
    schedule::Scheduler::new(&config.schedule, &config.base_dir, chrono::Utc::now())?;
    std::fs::create_dir_all(&config.data_dir)
        .with_context(|| format!("creating the data dir {}", config.data_dir.display()))?;
    // Bound before the live view starts, which needs the API's port (the console's origin).
    let listener = std::net::TcpListener::bind(config.listen)
        .with_context(|| format!("listening on {}", config.listen))?;
    listener
        .set_nonblocking(true)
        .context("making the listener non-blocking")?;
    let api_port = listener
        .local_addr()
        .context("reading the bound address")?
        .port();
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    let live = live_address
        .map(|address| {
            let access = live::LiveAccess {
                token: token.clone(),
                extra_origins: config.live_origins.clone(),
                console_port: Some(api_port),
            };
            live::LiveView::start_guarded(address, access).map(std::sync::Arc::new)
        })
        .transpose()?;
    let result = runtime.block_on(run(config, listener, registry, token, live.clone()));
    if let Some(live) = live {
        live.stop();
    }
    result
}

async fn run(
    config: ServeConfig,
    listener: std::net::TcpListener,
    registry: Registry,
    token: Option<auth::Token>,
    live: Option<std::sync::Arc<live::LiveView>>,
) -> anyhow::Result<()> {
    let listener = tokio::net::TcpListener::from_std(listener)
        .with_context(|| format!("listening on {}", config.listen))?;
    let address = listener.local_addr().context("reading the bound address")?;
    let data_dir = config.data_dir.clone();
    let scheduler =
        schedule::Scheduler::new(&config.schedule, &config.base_dir, chrono::Utc::now())?;
    let live_line = live.as_ref().map_or(String::new(), |l| {
        format!(", live view on ws://{}", l.address())
    });
    let live_tap = live.map(|l| l as std::sync::Arc<dyn crate::session::tap::MessageTap>);
    let request_timeout = config.request_timeout()?;
    let host_check = token.is_none().then(|| guard::HostCheck {
        port: address.port(),
        names: config.allowed_host_names.clone(),
    });
    let options = api::ApiOptions {
        token,
        host_check,
        body: guard::BodyLimits {
            max_bytes: config.max_body_bytes,
            timeout: request_timeout,
        },
        request_slots: config.max_connections,
        stream_slots: config.max_streams,
    };
    let limits = http::Limits { request_timeout };
    let daemon = jobs::Daemon::open(config, registry, live_tap)?;
    let worker = tokio::spawn(daemon.clone().work());
    let schedules = tokio::spawn(run_schedules(daemon.clone(), scheduler));
    let samples = tokio::spawn(daemon.samples.clone().run(daemon.shutdown.clone()));

    let app = api::router(daemon.clone(), options);
    // The line tools and tests wait for: the API is up.
    if let Err(e) = crate::console::write_out(format_args!(
        "geocal serve: listening on http://{address}, data in {}{live_line}\n",
        data_dir.display()
    )) {
        tracing::warn!("writing the ready line to stdout: {e}");
    }
    tracing::info!(%address, data_dir = %data_dir.display(), "geocal serve ready");
    notify_systemd(&[sd_notify::NotifyState::Ready]);
    let watchdog = tokio::spawn(watchdog());

    let stopping = daemon.clone();
    let server = http::serve(listener, app, limits, async move {
        wait_for_signal().await;
        tracing::info!("stopping: no new jobs; cancelling the running one");
        notify_systemd(&[sd_notify::NotifyState::Stopping]);
        stopping.stop();
    });
    server.await;
    // The workers end once the cancelled jobs have ended (a run's session flushed and closed).
    if let Err(e) = worker.await {
        tracing::error!("job worker: {e}");
    }
    watchdog.abort();
    schedules.abort();
    samples.abort();
    tracing::info!("geocal serve stopped");
    Ok(())
}

/// Submit the schedules' plans when they come due, once a second.
async fn run_schedules(daemon: std::sync::Arc<jobs::Daemon>, mut scheduler: schedule::Scheduler) {
    if scheduler.is_empty() {
        return;
    }
    for (name, next) in scheduler.upcoming() {
        tracing::info!(schedule = name, next = ?next, "schedule loaded");
    }
    let mut tick = tokio::time::interval(Duration::from_secs(1));
    loop {
        tick.tick().await;
        if daemon.shutdown.is_cancelled() {
            return;
        }
        let busy = daemon.busy_reason();
        for firing in scheduler.due(chrono::Utc::now(), busy.as_deref()) {
            let name = firing.schedule.clone();
            match firing.decision {
                schedule::Decision::Skip { reason } => {
                    tracing::warn!(schedule = name, "schedule skipped: {reason}");
                }
                schedule::Decision::Submit => {
                    let daemon = daemon.clone();
                    let submitted = tokio::task::spawn_blocking(move || {
                        let text = std::fs::read_to_string(&firing.plan).map_err(|e| {
                            jobs::JobError::BadRequest(format!(
                                "reading {}: {e}",
                                firing.plan.display()
                            ))
                        })?;
                        daemon.submit_run(&text, &format!("schedule:{}", firing.schedule))
                    })
                    .await;
                    match submitted {
                        Ok(Ok(id)) => {
                            tracing::info!(schedule = name, job = id, "schedule submitted")
                        }
                        Ok(Err(e)) => {
                            tracing::error!(schedule = name, "schedule not submitted: {e}")
                        }
                        Err(e) => tracing::error!(schedule = name, "schedule task failed: {e}"),
                    }
                }
            }
        }
    }
}

async fn wait_for_signal() {
    let terminate = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut term) => {
                term.recv().await;
            }
            Err(e) => {
                tracing::error!("cannot listen for SIGTERM: {e}");
                std::future::pending::<()>().await;
            }
        }
    };
    tokio::select! {
        _ = terminate => {}
        _ = tokio::signal::ctrl_c() => {}
    }
}

fn notify_systemd(state: &[sd_notify::NotifyState<'_>]) {
    if let Err(e) = sd_notify::notify(false, state) {
        tracing::debug!("sd_notify: {e}");
    }
}

/// Tell systemd's watchdog the daemon lives, at half its interval, when it asks for that.
async fn watchdog() {
    let mut usec = 0u64;
    if !sd_notify::watchdog_enabled(false, &mut usec) || usec == 0 {
        return;
    }
    let period = Duration::from_micros(usec / 2);
    loop {
        notify_systemd(&[sd_notify::NotifyState::Watchdog]);
        tokio::time::sleep(period).await;
    }
}
