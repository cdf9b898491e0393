//! A machine's history: has it changed since the last calibration? Runs loaded with their
//! machine's identity (`load`), the parameters every results document carries with their σ
//! (`parameters`), two runs compared (`compare`), a series trended with its events (`trend`).

pub mod cli;
pub mod compare;
pub mod load;
pub mod names;
pub mod parameters;
pub mod stats;
pub mod trend;

pub use compare::{compare, CompareOptions, Comparison, Tolerances};
pub use load::{load_series, MachineIdentity, Run};
pub use trend::{trend, Trend, TrendOptions};
