//! The rotary_tracer report: the tracer network, then the table's axis and step errors.

use std::fmt::Write;

use super::solve::{RotaryResult, RotaryTracerResults};
use crate::method::multilateration::MultilaterationResults;
use crate::method::report::{multilateration_text, um};
use crate::method::KindResults;

impl KindResults for RotaryTracerResults {
    fn report(&self) -> String {
        multilateration_text(&self.multilateration) + &rotary_text(&self.rotary)
    }

    fn tracer_network(&self) -> Option<&MultilaterationResults> {
        Some(&self.multilateration)
    }
}

/// Arcseconds per radian.
const ARCSEC_PER_RAD: f64 = 180.0 * 3600.0 / std::f64::consts::PI;

fn rotary_text(r: &RotaryResult) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "\n  rotary table {} (circle through the table stations):",
        r.table
    );
    let _ = writeln!(
        s,
        "    axis point  [{:.6}, {:.6}, {:.6}] m  σ [{:.2}, {:.2}, {:.2}] µm",
        r.axis_point_m[0],
        r.axis_point_m[1],
        r.axis_point_m[2],
        um(r.axis_point_sigma_m[0]),
        um(r.axis_point_sigma_m[1]),
        um(r.axis_point_sigma_m[2])
    );
    let _ = writeln!(
        s,
        "    axis dir.   [{:.7}, {:.7}, {:.7}]  σ [{:.2}, {:.2}, {:.2}] µrad",
        r.axis_direction[0],
        r.axis_direction[1],
        r.axis_direction[2],
        um(r.axis_direction_sigma[0]),
        um(r.axis_direction_sigma[1]),
        um(r.axis_direction_sigma[2])
    );
    let _ = writeln!(
        s,
        "    radius {:.6} m (σ {:.2} µm), stations off the circle: RMS {:.3} µm",
        r.radius_m,
        um(r.radius_sigma_m),
        um(r.circle_residual_rms_m)
    );
    let _ = writeln!(
        s,
        "    station   commanded [°]   measured [°]   error [\"]    σ [\"]   (from {})",
        r.reference_station
    );
    for step in &r.steps {
        let _ = writeln!(
            s,
            "    {:<8} {:>13.4} {:>14.6} {:>10.3} {:>8.3}",
            step.station,
            step.commanded_rad.to_degrees(),
            step.measured_rad.to_degrees(),
            step.error_rad * ARCSEC_PER_RAD,
            step.sigma_rad * ARCSEC_PER_RAD
        );
    }
    s
}
