//! Models: what a measurement predicts, with Jacobians. No solver and no I/O here.

pub mod hexapod;
pub mod kinematics;
pub mod probe_install;
pub mod rotary_sphere;
pub mod sphere_form;
