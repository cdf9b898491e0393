//! What the sequencer and the devices share with a run's caller: its progress, who answers
//! a real run's prompts, and the error of a cancelled run (`run::control::RunControl`).

use std::sync::Arc;

use geocal_drivers::Operator;

/// Builds the operator of a real run (default: the console's, `ConsoleOperator::stdin`).
pub type OperatorSource = Arc<dyn Fn() -> Box<dyn Operator> + Send + Sync>;

/// A run stopped by `run::control::RunControl::cancel`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("run cancelled (the session recorded so far is kept; resume it to finish the plan)")]
pub struct Cancelled;

/// Called after each point: gives the runtime a turn so that a cancel (the daemon's, Ctrl-C,
/// a progress callback's) is seen at once. Simulated devices answer without ever waiting, so
/// without it a simulated run would only notice a cancel when it ended.
pub async fn cancellation_point() {
    tokio::task::yield_now().await;
}
