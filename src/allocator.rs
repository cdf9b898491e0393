//! The allocator's arena limit: the reader's, the solve's and the diagnosis's work runs on
//! threads (in the daemon beside a recording), and glibc would give them up to 8 arenas per
//! core, each keeping freed memory resident: a peak that varies from run to run, and in the
//! daemon one that creeps.

/// Arenas geocal's threads share (as `MALLOC_ARENA_MAX=2`).
const ARENAS: i32 = 2;

/// Limits glibc's arenas, unless the user set `MALLOC_ARENA_MAX` (then that holds). Call
/// before any thread starts.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
pub fn limit_arenas() {
    if std::env::var_os("MALLOC_ARENA_MAX").is_some() {
        return;
    }
    // SAFETY: mallopt only sets an allocator parameter; M_ARENA_MAX takes any positive count.
    let done = unsafe { libc::mallopt(libc::M_ARENA_MAX, ARENAS) };
    if done == 0 {
        tracing::warn!("glibc refused M_ARENA_MAX = {ARENAS}: resident memory may creep");
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
pub fn limit_arenas() {}
