//! Unmodelled effects of the simulated world (`[sim.effects]`): each switchable and sized, applied
//! through two hooks of `SimWorld` (the optical distance the tracer sees and the actual axes).

use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

pub use crate::config::sim::{
    EccentricitySwitch, EffectSwitch, EffectsConfig, PeriodicSwitch, SettlingSwitch,
    TargetOffsetSwitch,
};
use crate::config::SimEnvironmentConfig;

/// Reference air of the tracer's wavelength (Edlén): 20 °C, 1013.25 hPa, 50 %RH.
pub const REFERENCE_AIR_TEMP_K: f64 = 293.15;
pub const REFERENCE_PRESSURE_PA: f64 = 101_325.0;
pub const REFERENCE_HUMIDITY_PCT: f64 = 50.0;

/// Refractive index change n − n_ref of air from the Edlén sensitivities near the reference
/// (−0.93 ppm/K, +0.27 ppm/hPa, −0.008 ppm/%RH); linear is within 1 % over ±3 K.
pub fn edlen_dn(air_temp_k: f64, pressure_pa: f64, humidity_pct: f64) -> f64 {
    1e-6 * (-0.93 * (air_temp_k - REFERENCE_AIR_TEMP_K)
        + 0.27 * (pressure_pa - REFERENCE_PRESSURE_PA) / 100.0
        - 0.008 * (humidity_pct - REFERENCE_HUMIDITY_PCT))
}

/// The simulated air temperature at device time t (also what the environment sensor logs).
pub fn air_temp_k(env: &SimEnvironmentConfig, t_s: f64) -> f64 {
    env.air_temp_k + env.temp_swing_k * (2.0 * std::f64::consts::PI * t_s / env.temp_period_s).sin()
}

/// A material temperature sensor's value at t (`base_k`: its mean): the structure follows the
/// air's swing at half the amplitude and an eighth of a period late (its thermal lag).
pub fn material_temp_k(env: &SimEnvironmentConfig, base_k: f64, t_s: f64) -> f64 {
    use std::f64::consts::{FRAC_PI_4, TAU};
    base_k + 0.5 * env.temp_swing_k * (TAU * t_s / env.temp_period_s - FRAC_PI_4).sin()
}

/// Reference temperature of machine scales and lengths (ISO 1): 20 °C.
pub const REFERENCE_MATERIAL_TEMP_K: f64 = 293.15;

/// The effects' drawn parameters and the little state they need (approach, station start).
#[derive(Debug, Clone)]
pub struct SimEffects {
    config: EffectsConfig,
    env: SimEnvironmentConfig,
    /// Per station: drift velocity, m/s.
    drift_m_s: Vec<Vector3<f64>>,
    /// Per station: (e, φ0, ez).
    eccentricity: Vec<(f64, f64, f64)>,
    /// The tracer on a rotary table: φ0 in the table's frame (it turns with the table).
    table_eccentricity_phi0: f64,
    /// Target drift velocity, m/s.
    thermal_drift_m_s: Vector3<f64>,
    /// Per station: error of the declared dead path (uncompensated), metres.
    dead_path_m: Vec<f64>,
    /// The tracer's declared dead path: the air acts on it as on the measured length.
    declared_dead_path_m: f64,
    /// Per axis: settling offset at the end of a move, metres.
    settling_m: [f64; 3],
    /// Sign of each axis's last move (0: it did not move) and when that move ends.
    moved: [f64; 3],
    move_end_s: f64,
    seed: u64,
    /// Full reversal span B per axis, metres.
    reversal_m: [f64; 3],
    /// (station, moves into its pass at which the fringe is lost, step size).
    step: (usize, usize, f64),
    step_time_s: Option<f64>,
    approach: [f64; 3],
    station: usize,
    station_start_s: f64,
    moves_in_station: usize,
}

impl SimEffects {
    /// Draw every effect's parameters from their own seeded stream (changing one effect's
    /// switch does not move the others, nor the truth machine or the noise).
    pub fn new(
        config: &EffectsConfig,
        env: &SimEnvironmentConfig,
        seed: u64,
        stations: usize,
        moves_per_station: usize,
    ) -> SimEffects {
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x4546_4645_4354_5321);
        let unit = |rng: &mut ChaCha8Rng| loop {
            let v = Vector3::from_fn(|_, _| rng.random_range(-1.0..1.0));
            let n: f64 = v.norm();
            if (0.2..=1.0).contains(&n) {
                return v / n;
            }
        };
        let drift_m_s = (0..stations)
            .map(|_| unit(&mut rng) * config.station_drift.size)
            .collect();
        let sign = |rng: &mut ChaCha8Rng| if rng.random_bool(0.5) { 1.0 } else { -1.0 };
        let eccentricity = (0..stations)
            .map(|_| {
                let phi = rng.random_range(0.0..std::f64::consts::TAU);
                let ez = config.tracer_eccentricity.z_size_m * sign(&mut rng);
                (config.tracer_eccentricity.size_m, phi, ez)
            })
            .collect();
        let reversal_m = std::array::from_fn(|_| {
            config.reversal.size * rng.random_range(0.5..1.0) * sign(&mut rng)
        });
        let step_station = rng.random_range(0..stations.max(1));
        let lo = (moves_per_station / 5).max(1);
        let hi = (4 * moves_per_station / 5).max(lo + 1);
        let step_move = rng.random_range(lo..hi);
        let step = (
            step_station,
            step_move,
            config.length_step.size * sign(&mut rng),
        );
        // Effects added later draw after the first five, so those keep their values.
        let thermal_drift_m_s = unit(&mut rng) * config.thermal_drift.size;
        let dead_path_m = (0..stations)
            .map(|_| config.dead_path.size * rng.random_range(0.5..1.0))
            .collect();
        let settling_m =
            std::array::from_fn(|_| config.settling.size_m * rng.random_range(0.5..1.0));
        // Its own stream: drawing it leaves every other effect's values as they were.
        let table_eccentricity_phi0 = ChaCha8Rng::seed_from_u64(seed ^ 0x5441_424c_4545_4343)
            .random_range(0.0..std::f64::consts::TAU);
        SimEffects {
            table_eccentricity_phi0,
            config: *config,
            env: env.clone(),
            drift_m_s,
            eccentricity,
            thermal_drift_m_s,
            dead_path_m,
            declared_dead_path_m: 0.0,
            settling_m,
            moved: [0.0; 3],
            move_end_s: 0.0,
            seed,
            reversal_m,
            step,
            step_time_s: None,
            approach: [0.0; 3],
            station: 0,
            station_start_s: 0.0,
            moves_in_station: 0,
        }
    }

    /// The tracer's declared dead path, part of the optical path the air refraction acts on.
    pub fn with_declared_dead_path(mut self, dead_path_m: f64) -> SimEffects {
        self.declared_dead_path_m = dead_path_m;
        self
    }

    /// The tracer's eccentricity on a rotary table (e, φ0 in the table's frame, ez), if on.
    pub fn table_eccentricity(&self) -> Option<(f64, f64, f64)> {
        let c = &self.config.tracer_eccentricity;
        c.enabled
            .then_some((c.size_m, self.table_eccentricity_phi0, c.z_size_m))
    }

    /// The tracer now stands at `station` (the operator has finished placing it).
    pub fn on_station(&mut self, station: usize, now_s: f64) {
        self.station = station;
        self.station_start_s = now_s;
        self.moves_in_station = 0;
    }

    /// A move starts (and ends at `end_s`): remember each axis's approach direction
    /// (persistent when it does not move) and which axes move.
    pub fn on_move(&mut self, from: [f64; 3], to: [f64; 3], now_s: f64, end_s: f64) {
        for k in 0..3 {
            let d = to[k] - from[k];
            // `from` is the end of the motion profile, equal to the last target only up to
            // rounding: an axis counts as moved from a nanometre on (commanded moves are mm).
            self.moved[k] = 0.0;
            if d.abs() > 1e-9 {
                self.approach[k] = d.signum();
                self.moved[k] = d.signum();
            }
        }
        self.move_end_s = end_s;
        self.moves_in_station += 1;
        if self.config.length_step.enabled
            && self.station == self.step.0
            && self.moves_in_station == self.step.1
            && self.step_time_s.is_none()
        {
            self.step_time_s = Some(now_s);
        }
    }

    /// The reflector's true offset for a configured one: off by `size_m` in a direction drawn
    /// from the seed and the configured offset (each target its own, the same every mount).
    pub fn actual_offset_m(&self, offset_m: [f64; 3]) -> [f64; 3] {
        let c = &self.config.target_offset;
        if !c.enabled {
            return offset_m;
        }
        let key = offset_m
            .iter()
            .fold(self.seed ^ 0x5441_5247_4554_4f46, |h, v| {
                (h ^ v.to_bits()).wrapping_mul(0x0100_0000_01b3)
            });
        let mut rng = ChaCha8Rng::seed_from_u64(key);
        let dir = loop {
            let v = Vector3::from_fn(|_, _| rng.random_range(-1.0..1.0));
            let n: f64 = v.norm();
            if (0.2..=1.0).contains(&n) {
                break v / n;
            }
        };
        std::array::from_fn(|k| offset_m[k] + c.size_m * dir[k])
    }

    /// Where the axes really are at t: commanded, scaled by the material's expansion, plus
    /// the reversal offset of the approach direction.
    pub fn actual_axes_m(&self, axes_m: [f64; 3], t_s: f64) -> [f64; 3] {
        let c = &self.config;
        let mut out = c.local_bump.displace(axes_m);
        if c.thermal_expansion.enabled && !self.env.material_temp_k.is_empty() {
            let sensors = &self.env.material_temp_k;
            let mean_k = sensors
                .iter()
                .map(|&m| material_temp_k(&self.env, m, t_s))
                .sum::<f64>()
                / sensors.len() as f64;
            let scale = c.thermal_expansion.size * (mean_k - REFERENCE_MATERIAL_TEMP_K);
            for a in &mut out {
                *a *= 1.0 + scale;
            }
        }
        if c.reversal.enabled {
            for (k, a) in out.iter_mut().enumerate() {
                *a += 0.5 * self.reversal_m[k] * self.approach[k];
            }
        }
        if c.settling.enabled && c.settling.tau_s > 0.0 {
            // Full lag while moving, then the exponential decay.
            let decay = (-(t_s - self.move_end_s).max(0.0) / c.settling.tau_s).exp();
            for (k, a) in out.iter_mut().enumerate() {
                *a -= self.moved[k] * self.settling_m[k] * decay;
            }
        }
        out
    }

    /// The distance the tracer at `station` (nominally at `station_m`) reads to `target_m` at
    /// time t: geometry with drift, plus the length errors of eccentricity, air and fringes.
    /// Homing zeroes whatever this contains at the homing time. `table_frame`: the tracer
    /// stands on a rotary table (its axis n and true angle θ), so its eccentricity turns with
    /// the table: azimuth about n (from e1 = x projected on the table's plane) less θ,
    /// elevation from the table's plane.
    pub fn distance_m(
        &self,
        station: usize,
        station_m: &Vector3<f64>,
        target_m: &Vector3<f64>,
        t_s: f64,
        table_frame: Option<(Vector3<f64>, f64)>,
    ) -> f64 {
        let c = &self.config;
        let mut p = *station_m;
        if c.station_drift.enabled {
            if let Some(w) = self.drift_m_s.get(station) {
                p += w * (t_s - self.station_start_s).max(0.0);
            }
        }
        let mut target = *target_m;
        if c.thermal_drift.enabled {
            target += self.thermal_drift_m_s * t_s.max(0.0);
        }
        let v = target - p;
        let d = v.norm();
        let mut err = 0.0;
        if c.tracer_eccentricity.enabled && d > 0.0 {
            if let Some(&(e, phi0, ez)) = self.eccentricity.get(station) {
                let (az, el, phi0, ez) = match table_frame {
                    Some((n, angle)) => {
                        let (e1, e2) = crate::sim::rotary::plane_basis(&n);
                        let az = v.dot(&e2).atan2(v.dot(&e1)) - angle;
                        let el = (v.dot(&n) / d).clamp(-1.0, 1.0).asin();
                        (
                            az,
                            el,
                            self.table_eccentricity_phi0,
                            c.tracer_eccentricity.z_size_m,
                        )
                    }
                    None => (v.y.atan2(v.x), (v.z / d).asin(), phi0, ez),
                };
                err += e * (az - phi0).cos() + ez * el.sin();
            }
        }
        let dn = edlen_dn(
            air_temp_k(&self.env, t_s),
            self.env.pressure_pa,
            self.env.humidity_pct,
        );
        if c.air_refraction.enabled {
            err += c.air_refraction.size * dn * (d + self.declared_dead_path_m);
        }
        if c.dead_path.enabled {
            err += dn * self.dead_path_m.get(station).copied().unwrap_or(0.0);
        }
        if c.length_step.enabled && station == self.step.0 {
            if let Some(t0) = self.step_time_s {
                if t_s >= t0 {
                    err += self.step.2;
                }
            }
        }
        let pn = &c.periodic_nonlinearity;
        if pn.enabled && pn.period_m > 0.0 {
            err += pn.size_m * (std::f64::consts::TAU * d / pn.period_m).sin();
        }
        d + err
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn validate_names_the_key() {
        let mut c = EffectsConfig::default();
        assert!(c.validate().is_ok());
        c.dead_path.size = -1.0;
        let (key, why) = c.validate().err().unwrap_or_default();
        assert_eq!(key, "sim.effects.dead_path.size");
        assert!(why.contains(">= 0"), "{why}");
        c.dead_path.size = 1.0;
        c.settling = SettlingSwitch {
            enabled: true,
            size_m: 1e-6,
            tau_s: 0.0,
        };
        let (key, _) = c.validate().err().unwrap_or_default();
        assert_eq!(key, "sim.effects.settling.tau_s");
    }

    #[test]
    fn unknown_effect_keys_are_refused() {
        let text = "settling = { enabled = true, size_m = 1e-6, tau = 0.5 }";
        assert!(toml::from_str::<EffectsConfig>(text).is_err());
        let text = "thermal_expansion = { enabled = true, size = 2e-6 }";
        let c: EffectsConfig = toml::from_str(text).unwrap_or_default();
        assert!(c.thermal_expansion.enabled && c.any());
    }

    #[test]
    fn target_offset_is_fixed_per_configured_offset() {
        let config = EffectsConfig {
            target_offset: TargetOffsetSwitch {
                enabled: true,
                size_m: 1e-3,
            },
            ..Default::default()
        };
        let e = SimEffects::new(&config, &SimEnvironmentConfig::default(), 7, 3, 10);
        let o = [0.0, 0.0, -0.12];
        let a = e.actual_offset_m(o);
        assert_eq!(a, e.actual_offset_m(o));
        let d = Vector3::from(a) - Vector3::from(o);
        assert!((d.norm() - 1e-3).abs() < 1e-12);
        assert_ne!(a, e.actual_offset_m([0.0, 0.05, -0.12]));
    }
}
