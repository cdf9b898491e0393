//! Connections not yet admitted — no request or handshake that passed the checks yet — are
//! what a peer without the token can open by the thousand. At most `cap` of them wait at
//! once, and a new one pushes out the oldest: a flood of idle connections cannot keep a real
//! client out, and it holds none of the slots admitted requests take.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, MutexGuard};

use tokio_util::sync::CancellationToken;

pub struct Waiting {
    cap: usize,
    state: Mutex<State>,
}

#[derive(Default)]
struct State {
    next: u64,
    entries: BTreeMap<u64, CancellationToken>,
}

impl Waiting {
    pub fn new(cap: usize) -> Arc<Waiting> {
        Arc::new(Waiting {
            cap: cap.max(1),
            state: Mutex::default(),
        })
    }

    fn state(&self) -> MutexGuard<'_, State> {
        // A panic while holding this lock leaves a consistent map.
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// A new connection waits; when `cap` already do, the oldest is pushed out.
    pub fn enter(self: &Arc<Self>) -> Entry {
        let token = CancellationToken::new();
        let mut state = self.state();
        while state.entries.len() >= self.cap {
            match state.entries.pop_first() {
                Some((_, oldest)) => oldest.cancel(),
                None => break,
            }
        }
        let id = state.next;
        state.next += 1;
        state.entries.insert(id, token.clone());
        Entry {
            id,
            token,
            waiting: self.clone(),
        }
    }

    /// Connections waiting now.
    pub fn len(&self) -> usize {
        self.state().entries.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// One waiting connection; dropping it (the connection closed) leaves the set.
pub struct Entry {
    id: u64,
    token: CancellationToken,
    waiting: Arc<Waiting>,
}

impl Entry {
    /// The connection passed the checks: it is no longer pushed out by newer ones.
    pub fn admit(&self) {
        self.waiting.state().entries.remove(&self.id);
    }

    /// Resolves when a newer connection pushed this one out.
    pub async fn pushed_out(&self) {
        self.token.cancelled().await
    }
}

impl Drop for Entry {
    fn drop(&mut self) {
        self.admit();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_oldest_waiting_connection_is_pushed_out_and_admitted_ones_stay() {
        let waiting = Waiting::new(2);
        let first = waiting.enter();
        let second = waiting.enter();
        second.admit();
        let third = waiting.enter();
        assert_eq!(waiting.len(), 2);
        assert!(!first.token.is_cancelled() && !third.token.is_cancelled());
        let fourth = waiting.enter();
        assert!(
            first.token.is_cancelled(),
            "the oldest waiting one is pushed out"
        );
        assert!(!second.token.is_cancelled(), "an admitted one is not");
        assert!(!third.token.is_cancelled() && !fourth.token.is_cancelled());
        drop(third);
        assert_eq!(waiting.len(), 1, "only the fourth waits");
        drop(first);
        drop(fourth);
        assert!(waiting.is_empty());
    }
}
