//! `[operator]`.

use serde::{Deserialize, Serialize};

/// `[operator]`: how a real run's operator acknowledges prompts.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OperatorConfig {
    /// Read acknowledgements as lines from stdin even when it is not a terminal (a pipe
    /// from a supervising program); `geocal run --yes` sets it.
    #[serde(default)]
    pub piped_stdin: bool,
    /// Simulated and emulated runs ask the operator too (at the console, or over the
    /// daemon's API) before each station and reflector change, as a real run would: a
    /// rehearsal of the prompts, and how the prompt path is tested.
    #[serde(default)]
    pub rehearse: bool,
}
