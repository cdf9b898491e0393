//! Shared by the bench binaries: a counting global allocator (current and peak heap bytes)
//! and small helpers for timing and printing tables.
#![allow(dead_code)]

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use nalgebra::Vector3;

/// Wraps the system allocator and keeps the live heap size and its high-water mark, so a bench
/// can report the peak memory of one phase without an external profiler.
pub struct Counting;

static CURRENT: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

fn grew(by: usize) {
    let now = CURRENT.fetch_add(by, Ordering::Relaxed) + by;
    PEAK.fetch_max(now, Ordering::Relaxed);
}

fn shrank(by: usize) {
    CURRENT.fetch_sub(by, Ordering::Relaxed);
}

// SAFETY: every call is forwarded unchanged to `System`; the counters only observe sizes.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            grew(layout.size());
        }
        p
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        let p = unsafe { System.alloc_zeroed(layout) };
        if !p.is_null() {
            grew(layout.size());
        }
        p
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) };
        shrank(layout.size());
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            if new_size >= layout.size() {
                grew(new_size - layout.size());
            } else {
                shrank(layout.size() - new_size);
            }
        }
        p
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

/// Live heap bytes now.
pub fn heap_now() -> usize {
    CURRENT.load(Ordering::Relaxed)
}

/// Starts a new high-water mark at the current heap size; returns that size (the baseline).
pub fn reset_peak() -> usize {
    let now = CURRENT.load(Ordering::Relaxed);
    PEAK.store(now, Ordering::Relaxed);
    now
}

pub fn peak() -> usize {
    PEAK.load(Ordering::Relaxed)
}

/// Runs `f`, returning its value, its wall time and the heap peak above the heap at its start.
pub fn measure<T>(f: impl FnOnce() -> T) -> (T, Duration, usize) {
    let base = reset_peak();
    let t0 = Instant::now();
    let v = f();
    let dt = t0.elapsed();
    (v, dt, peak().saturating_sub(base))
}

pub fn median(mut v: Vec<Duration>) -> Duration {
    v.sort();
    v[v.len() / 2]
}

pub fn mib(bytes: usize) -> f64 {
    bytes as f64 / (1024.0 * 1024.0)
}

/// Seconds with a unit that keeps 3 significant digits readable in a table.
pub fn fmt_time(d: Duration) -> String {
    let s = d.as_secs_f64();
    if s >= 1.0 {
        format!("{s:.2} s")
    } else if s >= 1e-3 {
        format!("{:.1} ms", s * 1e3)
    } else {
        format!("{:.0} µs", s * 1e6)
    }
}

/// CPU time (user + system, all threads) the process has used so far, from /proc/self/stat
/// (Linux, 10 ms resolution). On a shared machine it says what a phase costs when wall time
/// is inflated by other load. None where /proc is unavailable.
pub fn cpu_time() -> Option<Duration> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the parenthesised command name; utime and stime are fields 14 and 15.
    let rest = &stat[stat.rfind(')')? + 2..];
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let utime: u64 = fields.get(11)?.parse().ok()?;
    let stime: u64 = fields.get(12)?.parse().ok()?;
    // USER_HZ is 100 on every mainstream Linux configuration.
    Some(Duration::from_millis((utime + stime) * 10))
}

/// Six coordinates of three well-spread points to hold for SciPy and Ceres (their problems
/// have the 6-dof gauge freedom too). The choice moves no cost: chi2 is gauge invariant.
pub fn gauge_coordinates(points: &[Vector3<f64>]) -> [(usize, usize); 6] {
    let centroid = points.iter().sum::<Vector3<f64>>() / points.len() as f64;
    let farthest = |from: Vector3<f64>| {
        (0..points.len())
            .max_by(|&a, &b| {
                (points[a] - from)
                    .norm_squared()
                    .total_cmp(&(points[b] - from).norm_squared())
            })
            .unwrap_or(0)
    };
    let a = farthest(centroid);
    let b = farthest(points[a]);
    let ab = points[b] - points[a];
    let c = (0..points.len())
        .max_by(|&x, &y| {
            ab.cross(&(points[x] - points[a]))
                .norm()
                .total_cmp(&ab.cross(&(points[y] - points[a])).norm())
        })
        .unwrap_or(0);
    let b_axis = ab.iamax();
    let b_free: Vec<usize> = (0..3).filter(|&k| k != b_axis).collect();
    let c_axis = ab.cross(&(points[c] - points[a])).iamax();
    [
        (a, 0),
        (a, 1),
        (a, 2),
        (b, b_free[0]),
        (b, b_free[1]),
        (c, c_axis),
    ]
}
