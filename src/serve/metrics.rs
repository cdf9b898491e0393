//! Prometheus metrics in the OpenMetrics text format: jobs by state, samples recorded, faults
//! by kind, the recorder's queue depth, the heap in use.

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
    if let Some(bytes) = heap_in_use_bytes() {
        let heap = Gauge::<i64>::default();
        heap.set(i64::try_from(bytes).unwrap_or(i64::MAX));
        registry.register(
            "heap_in_use_bytes",
            "Bytes the daemon has allocated and not freed (glibc's malloc, every arena)",
            heap,
        );
    }
    super::machines::register_metrics(&mut registry, &daemon.machines);
    let mut text = String::new();
    encode(&mut text, &registry)?;
    Ok(text)
}

/// Bytes allocated and not yet freed, from glibc's allocator statistics over all its arenas.
/// Unlike the resident memory, which keeps pages the allocator holds free for reuse, this
/// moves with what the daemon holds: memory that grows with a recording shows here at once.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
pub fn heap_in_use_bytes() -> Option<u64> {
    // SAFETY: mallinfo2 takes no arguments, only reads the allocator's statistics under its
    // arenas' locks, and returns a plain struct by value (glibc 2.33 and later).
    let info = unsafe { libc::mallinfo2() };
    // Small and large (mmap-ed) allocations in use.
    Some((info.uordblks + info.hblkhd) as u64)
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
pub fn heap_in_use_bytes() -> Option<u64> {
    None
}
