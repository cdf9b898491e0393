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
}
