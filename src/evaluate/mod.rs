//! What a report states beside a solved result: the ISO 230-2 positioning figures
//! (`iso230_2`, pure) and their deviations from a kind's results (`deviations`), GUM
//! uncertainty budgets (`uncertainty`, `tracer`; a kind's budgets as a report section:
//! `budget_section`) and the normalisation to 20 °C (`normalise`).

pub mod budget_section;
pub mod deviations;
pub mod iso230_2;
pub mod normalise;
pub mod tracer;
pub mod uncertainty;

pub use deviations::{of_results, of_results_extracted, AxisIso, Iso230_2};
