//! Prometheus metrics in the OpenMetrics text format: jobs by state, samples recorded, faults
//! by kind, the recorder's queue depth.

use prometheus_client::encoding::text::encode;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::registry::Registry;

use super::jobs::Daemon;

type Labels = Vec<(String, String)>;

pub fn render(daemon: &Daemon) -> anyhow::Result<String> {
    let mut registry = Registry::with_prefix("geocal");
    let jobs = Family::<Labels, Gauge>::default();
    registry.register("jobs", "Jobs in the catalog by state", jobs.clone());
    for (state, n) in daemon.count_by_state()? {
        jobs.get_or_create(&vec![("state".into(), state.as_str().into())])
            .set(n as i64);
    }
    let counters = daemon.status.counters();
    let samples = Counter::<u64>::default();
    samples.inc_by(counters.samples);
    registry.register(
        "samples_recorded",
        "Device samples recorded since the daemon started",
        samples,
    );
    let faults = Family::<Labels, Counter>::default();
    registry.register(
        "faults",
        "Device faults since the daemon started, by kind",
        faults.clone(),
    );
    for (kind, n) in &counters.faults_by_kind {
        faults
            .get_or_create(&vec![("kind".into(), kind.clone())])
            .inc_by(*n);
    }
    let depth = Gauge::<i64>::default();
    depth.set(counters.recorder_queue_depth as i64);
    registry.register(
        "recorder_queue_depth",
        "Messages waiting for the session recorder when the last one was written",
        depth,
    );
    let depth_max = Gauge::<i64>::default();
    depth_max.set(counters.recorder_queue_depth_max as i64);
    registry.register(
        "recorder_queue_depth_max",
        "The most messages ever waiting for the session recorder",
        depth_max,
    );
    super::machines::register_metrics(&mut registry, &daemon.machines);
    let mut text = String::new();
    encode(&mut text, &registry)?;
    Ok(text)
}
