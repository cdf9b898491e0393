//! Evaluations of solved calibrations against standards: the ISO 230-2 positioning figures
//! (`iso230_2`, pure) and where their deviations come from in a kind's results (`deviations`).

pub mod deviations;
pub mod iso230_2;

pub use deviations::{of_results, AxisIso, Iso230_2};
