//! Solvers: minimisers and the methods that wire a model to a solver. No device access.

pub mod chi2;
pub mod circle;
pub mod elastic_net;
pub mod genetic;
pub mod geometric_errors;
pub mod hexapod;
pub mod hexapod_weighted;
pub mod misfit;
pub mod multilateration;
pub mod probe_install;
mod resection;
pub mod robust;
pub mod rotary_sphere;
