//! Operator prompts of the daemon's runs: a run's operator posts what to do and waits; the
//! panel beside the machine lists the pending prompts and acknowledges them over the API.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};

use async_trait::async_trait;
use geocal_drivers::{DeviceError, Operator};
use serde::Serialize;
use tokio::sync::oneshot;
use utoipa::ToSchema;

use crate::devices::operator::{mount_target_instruction, place_station_instruction};

/// A prompt waiting for the operator.
#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize, ToSchema)]
pub struct PendingPrompt {
    pub id: u64,
    pub job: i64,
    pub instruction: String,
    /// RFC 3339 UTC.
    pub prompted_at: String,
}

#[derive(Default)]
struct Pending {
    next_id: u64,
    waiting: BTreeMap<u64, (PendingPrompt, oneshot::Sender<()>)>,
}

/// Every pending prompt; `notify` tells the event stream of a new one.
#[derive(Clone)]
pub struct PromptBoard {
    pending: Arc<Mutex<Pending>>,
    notify: Arc<dyn Fn(&PendingPrompt) + Send + Sync>,
}

impl PromptBoard {
    pub fn new(notify: Arc<dyn Fn(&PendingPrompt) + Send + Sync>) -> PromptBoard {
        PromptBoard {
            pending: Arc::default(),
            notify,
        }
    }

    pub fn list(&self) -> Vec<PendingPrompt> {
        self.pending
            .lock()
            .map(|p| {
                p.waiting
                    .values()
                    .map(|(prompt, _)| prompt.clone())
                    .collect()
            })
            .unwrap_or_default()
    }

    /// Acknowledge prompt `id`: false when no such prompt waits.
    pub fn acknowledge(&self, id: u64) -> bool {
        let sender = self
            .pending
            .lock()
            .ok()
            .and_then(|mut p| p.waiting.remove(&id));
        match sender {
            Some((_, tx)) => tx.send(()).is_ok(),
            None => false,
        }
    }

    /// Drop the prompts of `job` (it ended): their runs see the operator gone.
    pub fn clear_job(&self, job: i64) {
        if let Ok(mut p) = self.pending.lock() {
            p.waiting.retain(|_, (prompt, _)| prompt.job != job);
        }
    }

    async fn ask(&self, job: i64, instruction: String) -> Result<(), DeviceError> {
        let (tx, rx) = oneshot::channel();
        let prompt = {
            let mut p = self
                .pending
                .lock()
                .map_err(|_| gone("prompt board poisoned"))?;
            p.next_id += 1;
            let prompt = PendingPrompt {
                id: p.next_id,
                job,
                instruction,
                prompted_at: super::catalog::now_rfc3339(),
            };
            p.waiting.insert(prompt.id, (prompt.clone(), tx));
            prompt
        };
        tracing::info!(
            job,
            prompt = prompt.id,
            "operator prompt: {}",
            prompt.instruction
        );
        (self.notify)(&prompt);
        rx.await
            .map_err(|_| gone("the job ended before the prompt was acknowledged"))
    }

    /// The operator of job `job`'s run.
    pub fn operator(&self, job: i64) -> Box<dyn Operator> {
        Box::new(DaemonOperator {
            board: self.clone(),
            job,
        })
    }
}

fn gone(message: &str) -> DeviceError {
    DeviceError::Disconnected {
        device: "operator".into(),
        message: message.into(),
    }
}

struct DaemonOperator {
    board: PromptBoard,
    job: i64,
}

#[async_trait]
impl Operator for DaemonOperator {
    async fn place_station(
        &mut self,
        index: usize,
        id: &str,
        hint_m: Option<[f64; 3]>,
    ) -> Result<(), DeviceError> {
        self.board
            .ask(self.job, place_station_instruction(index, id, hint_m))
            .await
    }

    async fn mount_target(&mut self, target: &str, offset_m: [f64; 3]) -> Result<(), DeviceError> {
        self.board
            .ask(self.job, mount_target_instruction(target, offset_m))
            .await
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn a_prompt_waits_for_its_acknowledgement() {
        let seen = Arc::new(Mutex::new(Vec::new()));
        let seen_by_notify = seen.clone();
        let board = PromptBoard::new(Arc::new(move |p: &PendingPrompt| {
            seen_by_notify.lock().unwrap().push(p.id);
        }));
        let mut operator = board.operator(7);
        let asking = tokio::spawn(async move { operator.mount_target("t1", [0.0; 3]).await });
        while board.list().is_empty() {
            tokio::task::yield_now().await;
        }
        let pending = board.list();
        assert_eq!(pending[0].job, 7);
        assert!(pending[0].instruction.contains("mount reflector t1"));
        assert!(!board.acknowledge(pending[0].id + 1));
        assert!(board.acknowledge(pending[0].id));
        asking.await.unwrap().unwrap();
        assert!(board.list().is_empty());
        assert_eq!(*seen.lock().unwrap(), vec![pending[0].id]);
    }

    #[tokio::test]
    async fn a_cleared_prompt_fails_its_run() {
        let board = PromptBoard::new(Arc::new(|_: &PendingPrompt| {}));
        let mut operator = board.operator(3);
        let asking = tokio::spawn(async move { operator.place_station(0, "s1", None).await });
        while board.list().is_empty() {
            tokio::task::yield_now().await;
        }
        board.clear_job(3);
        assert!(asking.await.unwrap().is_err());
    }
}
