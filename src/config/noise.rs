//! The declared noise model of a tracer (SESSION_FORMAT.md): what every σ of a length follows from.

use serde::Serialize;

use crate::session::messages::SessionHeader;
use crate::solve::multilateration::PathSigma;

/// Per-sample noise of a tracer: sigma = noise_m + noise_ppm * 1e-6 * L_abs, with L_abs the
/// absolute optical path |station − target| + dead_path_m. The ppm part (air turbulence, index
/// and wavelength uncertainty) grows with the whole beam, not with the relative counter
/// length, which is near 0 at the homing point while the beam is metres long.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct NoiseModel {
    pub noise_m: f64,
    pub noise_ppm: f64,
    /// The tracer's declared dead path: optical path the counter does not see.
    pub dead_path_m: f64,
}

impl NoiseModel {
    /// σ of one sample with the beam `beam_m` = |station − target| long.
    pub fn sample_sigma_m(&self, beam_m: f64) -> f64 {
        self.noise_m + self.noise_ppm * 1e-6 * (beam_m.abs() + self.dead_path_m)
    }

    /// σ of the mean of `samples` samples, as a function of the beam length.
    pub fn mean_sigma(&self, samples: usize) -> PathSigma {
        let root_n = (samples.max(1) as f64).sqrt();
        PathSigma {
            at_zero_beam_m: self.sample_sigma_m(0.0) / root_n,
            per_beam_m: self.noise_ppm * 1e-6 / root_n,
        }
    }

    /// The tracer's declared noise model from the session header, if complete.
    pub fn from_header(header: &SessionHeader, tracer_id: &str) -> Option<NoiseModel> {
        let device = header.devices.iter().find(|d| d.id == tracer_id)?;
        Some(NoiseModel {
            noise_m: device.noise_m?,
            noise_ppm: device.noise_ppm.unwrap_or(0.0),
            dead_path_m: device.dead_path_m.unwrap_or(0.0),
        })
    }
}
