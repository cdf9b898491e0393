//! The diagnosis's progress: (done, total) handed to a caller's hook (e.g. the Python
//! package's callback), the total fixed when the work starts, done never going back and
//! ending at the total.

use crate::progress_sink::ProgressSink;

/// Counts the units of work done against a total fixed at the start: the base fits and the
/// candidate evaluations of every round the selection may run, and the final steps. Work
/// that turns out not to be needed (the rounds after the selection stops) is counted done
/// when it is skipped, so `done` only grows and ends at `total`.
#[derive(Debug)]
pub struct Counter {
    hook: Option<ProgressSink>,
    done: u64,
    total: u64,
}

impl Counter {
    /// Starts at (0, total), reported at once.
    pub fn new(hook: Option<&ProgressSink>, total: u64) -> Counter {
        let counter = Counter {
            hook: hook.cloned(),
            done: 0,
            total,
        };
        counter.report();
        counter
    }

    fn report(&self) {
        if let Some(hook) = &self.hook {
            hook.report(self.done, self.total);
        }
    }

    /// `units` more done (never past the total).
    pub fn tick(&mut self, units: u64) {
        self.advance_to(self.done.saturating_add(units));
    }

    /// Done up to `done` (never back, never past the total).
    pub fn advance_to(&mut self, done: u64) {
        let done = done.min(self.total);
        if done > self.done {
            self.done = done;
            self.report();
        }
    }

    pub fn done(&self) -> u64 {
        self.done
    }

    /// Everything done: (total, total).
    pub fn finish(&mut self) {
        self.advance_to(self.total);
    }
}

/// Units of a forward selection over `candidates` effects: each round one base fit and one
/// evaluation per candidate left, at most one round per candidate plus the last.
pub fn selection_units(candidates: usize) -> u64 {
    let c = candidates as u64;
    (c + 1) + c * (c + 1) / 2
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::{Arc, Mutex};

    #[test]
    fn counts_only_forward_and_ends_at_the_total() {
        let calls = Arc::new(Mutex::new(Vec::new()));
        let seen = calls.clone();
        let hook = ProgressSink::new(move |d, t| seen.lock().expect("lock").push((d, t)));
        let mut counter = Counter::new(Some(&hook), 10);
        counter.tick(3);
        counter.advance_to(2);
        counter.tick(20);
        counter.finish();
        assert_eq!(
            *calls.lock().expect("lock"),
            vec![(0, 10), (3, 10), (10, 10)]
        );
        assert_eq!(selection_units(0), 1);
        // 3 candidates: rounds of 1 + 3, 1 + 2, 1 + 1, 1 + 0.
        assert_eq!(selection_units(3), 10);
    }
}
