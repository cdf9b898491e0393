//! Evaluation of solved results for the report: uncertainty budgets and normalisation.

pub mod normalise;
pub mod tracer;
pub mod uncertainty;
