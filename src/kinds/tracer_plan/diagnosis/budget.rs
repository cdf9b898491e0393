//! The memory a diagnosis needs, estimated from the session's size before any of its work, and
//! a clear refusal of a request the machine cannot hold (rather than an allocation failure).

use crate::diagnose::engine::MAX_FOLD_THREADS;
use crate::parallel;

use super::data::Data;
use super::effects::{EffectModel, LIBRARY};

const F64: u64 = 8;
/// Margin over the estimate for the allocator and what the sum leaves out (vectors of single
/// lengths, the points level's bounded dense blocks).
const MARGIN: f64 = 1.5;

#[derive(Debug, thiserror::Error)]
#[error(
    "diagnosing {lengths} lengths ({points} points, {stations} stations) needs about \
     {needed_mib} MiB, more than the {available_mib} MiB available ({available_from}); diagnose a \
     shorter session, or on a machine with more free memory"
)]
pub struct TooLarge {
    pub lengths: usize,
    pub points: usize,
    pub stations: usize,
    pub needed_mib: u64,
    pub available_mib: u64,
    /// Where the available figure comes from (`MemAvailable` in /proc/meminfo, or the option).
    pub available_from: String,
}

/// Bytes the diagnosis of `data` allocates at its peak (beyond the session and its extracted
/// data, already in memory): a few fits at once (points eliminated: a 3 × 3 block per point
/// and the reduced system of stations, segments and effects), the design with every effect of
/// the library accepted (the worst case), the folds downdated from the full fit (each length's
/// place in its point's block, the reduced system's part per point shared by the folds), the
/// candidate under evaluation (sparse, its projection's coefficients per point and over the
/// global columns), and leave one station out.
pub fn estimate_bytes(data: &Data) -> u64 {
    let n = data.obs.len() as u64;
    let points = data.problem.nominal_points.len() as u64;
    let segments = data.problem.segments.len() as u64;
    let widths: Vec<u64> = LIBRARY
        .iter()
        .map(|&k| EffectModel::plain(k).param_names(data).len() as u64)
        .collect();
    let all_effects: u64 = widths.iter().sum();
    let widest = widths.iter().copied().max().unwrap_or(0);
    let stations = data.station_ids.len() as u64;
    let global = 3 * stations + segments + all_effects;
    // One fit: row lists (3 words per row), the points' blocks, the reduced system and its
    // eigen-decomposition, the null-space basis.
    let fit = 3 * n * F64
        + 9 * points * F64
        + 4 * global * global * F64
        + 8 * (3 * points + global) * F64;
    // The full fit, leave one station out's on its threads, a fold refitted.
    let threads = parallel::threads(MAX_FOLD_THREADS) as u64;
    let fits = (2 + threads) * fit;
    // The design: 7 words of geometry per row and the accepted effects' columns.
    let design = n * (7 + all_effects) * F64;
    // The folds' downdates: every length is held out once, with its point's block and
    // positions in its fold (12 words), and the reduced system's part per point, shared.
    let reduced = 3 * points * global * F64;
    let downdates = n * 12 * F64 + reduced;
    // The candidate: its rows' entries (up to 3 and a start, 5 words a row), its projection's
    // coefficients (per point and over the global columns, twice while the second pass runs)
    // and the blocks of its projected rows on the threads. A fold that must be refitted makes
    // the columns dense: counted, as the worst case.
    let candidates = 5 * n * F64 + 2 * (3 * points + global) * widest * F64 + n * widest * F64;
    // Leave one station out: its held lengths against the reduced system, on its threads.
    let held = n.div_ceil(stations.max(1));
    let loso = threads * 3 * held * global * F64;
    // A candidate's evaluation and leave one station out come one after another: the larger
    // of them is what the peak holds.
    let phase = candidates.max(loso);
    ((fits + design + downdates + phase) as f64 * MARGIN) as u64
}

/// `MemAvailable` of /proc/meminfo in bytes, when the system reports it.
pub fn available_bytes() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    text.lines()
        .find_map(|l| l.strip_prefix("MemAvailable:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
        .map(|kib| kib * 1024)
}

/// Refuse, before any work, a diagnosis estimated to need more than `limit` bytes (None: the
/// machine's available memory; no check where the system does not report it).
pub fn check(data: &Data, limit: Option<u64>) -> Result<(), TooLarge> {
    let (available, source) = match limit {
        Some(l) => (l, "the memory limit of the options".to_string()),
        None => match available_bytes() {
            Some(a) => (a, "MemAvailable in /proc/meminfo".to_string()),
            None => return Ok(()),
        },
    };
    let needed = estimate_bytes(data);
    if needed <= available {
        return Ok(());
    }
    Err(TooLarge {
        lengths: data.obs.len(),
        points: data.problem.nominal_points.len(),
        stations: data.station_ids.len(),
        needed_mib: needed.div_ceil(1 << 20),
        available_mib: available >> 20,
        available_from: source,
    })
}

/// Returns the heap's free pages to the system. Reading a session frees many small blocks (its
/// measurements' strings and maps) inside the heap, where the allocator keeps them resident;
/// the diagnosis's large matrices are mapped apart from them, so without this the resident
/// memory carries the reading's peak through every later stage.
pub fn return_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only releases free memory of glibc's own heap.
    unsafe {
        libc::malloc_trim(0);
    }
}
