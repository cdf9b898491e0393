//! The simulated rotary table: its true axis (near the nominal, slightly tilted), its smooth
//! angular positioning error, and its motion in virtual time. The world turns the tracer with it.

use std::f64::consts::TAU;

use nalgebra::{Unit, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use serde::Serialize;

use crate::config::{RotaryPlanConfig, SimRotaryConfig};
use crate::plan::rotate_about_axis;

/// Angular positioning error: true angle − commanded angle = Σ a_k cos kθ + b_k sin kθ.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct AngleError {
    /// (k, a_k, b_k), radians.
    pub harmonics: Vec<(u32, f64, f64)>,
}

impl AngleError {
    /// Random harmonics 1..=count scaled so that the peak over a revolution is `peak_rad`.
    pub fn random(rng: &mut ChaCha8Rng, count: usize, peak_rad: f64) -> AngleError {
        let mut harmonics: Vec<(u32, f64, f64)> = (1..=count as u32)
            .map(|k| {
                // Lower harmonics dominate, as eccentricity and pitch errors of a worm gear do.
                let w = 1.0 / f64::from(k);
                (
                    k,
                    w * rng.random_range(-1.0..=1.0),
                    w * rng.random_range(-1.0..=1.0),
                )
            })
            .collect();
        let unscaled = AngleError {
            harmonics: harmonics.clone(),
        };
        let peak = (0..3600)
            .map(|i| unscaled.at(TAU * f64::from(i) / 3600.0).abs())
            .fold(0.0f64, f64::max);
        let scale = if peak > 0.0 { peak_rad / peak } else { 0.0 };
        for h in &mut harmonics {
            h.1 *= scale;
            h.2 *= scale;
        }
        AngleError { harmonics }
    }

    pub fn at(&self, commanded_rad: f64) -> f64 {
        self.harmonics
            .iter()
            .map(|&(k, a, b)| {
                let x = f64::from(k) * commanded_rad;
                a * x.cos() + b * x.sin()
            })
            .sum()
    }
}

/// The table's error motions, periodic in its true angle θ (radial and axial harmonics 2-4,
/// tilt 2-3: a circle through the pivots absorbs harmonics 0 and 1 of a radial or axial motion): the axis moves radially
/// by a 2-vector in the plane (e1, e2) and axially along n, and tilts by a 2-vector (about a
/// line through the axis point). The pivot moves by axial·n + radial + tilt × (pivot − axis
/// point).
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct ErrorMotion {
    /// (k, cos coefficient, sin coefficient): radial and tilt in (e1, e2), axial along n.
    pub radial_m: Vec<(u32, [f64; 2], [f64; 2])>,
    pub axial_m: Vec<(u32, f64, f64)>,
    pub tilt_rad: Vec<(u32, [f64; 2], [f64; 2])>,
}

impl ErrorMotion {
    /// Coefficients drawn in ±size/k (metres of pivot displacement; the tilt's scaled by the
    /// pivot's distance from the axis point).
    pub fn random(rng: &mut ChaCha8Rng, size_m: f64, arm_m: f64) -> ErrorMotion {
        let mut draw = |scale: f64| scale * rng.random_range(-1.0..=1.0);
        let mut radial_m = Vec::new();
        let mut axial_m = Vec::new();
        let mut tilt_rad = Vec::new();
        for k in 2..=4u32 {
            let s = size_m / f64::from(k);
            radial_m.push((k, [draw(s), draw(s)], [draw(s), draw(s)]));
            axial_m.push((k, draw(s), draw(s)));
            // Tilts of harmonics 2-3 only: their pivot moves reach harmonic 4 (k ± 1).
            if k <= 3 {
                let t = s / arm_m.max(1e-3);
                tilt_rad.push((k, [draw(t), draw(t)], [draw(t), draw(t)]));
            }
        }
        ErrorMotion {
            radial_m,
            axial_m,
            tilt_rad,
        }
    }

    /// The pivot's displacement at true table angle θ; `arm` = pivot − axis point.
    pub fn displacement_m(
        &self,
        angle_rad: f64,
        n: &Vector3<f64>,
        arm: &Vector3<f64>,
    ) -> Vector3<f64> {
        let (e1, e2) = plane_basis(n);
        let harmonic = |k: u32, c: f64, s: f64| {
            let x = f64::from(k) * angle_rad;
            c * x.cos() + s * x.sin()
        };
        let in_plane = |terms: &[(u32, [f64; 2], [f64; 2])]| {
            terms.iter().fold(Vector3::zeros(), |acc, &(k, c, s)| {
                acc + e1 * harmonic(k, c[0], s[0]) + e2 * harmonic(k, c[1], s[1])
            })
        };
        let axial: f64 = self
            .axial_m
            .iter()
            .map(|&(k, c, s)| harmonic(k, c, s))
            .sum();
        in_plane(&self.radial_m) + n * axial + in_plane(&self.tilt_rad).cross(arm)
    }
}

/// The plane of the table (normal n): e1 = x projected on it (y when x is along n), e2 = n × e1.
pub fn plane_basis(n: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>) {
    let x = if n.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let e1 = (x - n * n.dot(&x)).normalize();
    (e1, n.cross(&e1))
}

/// The table's truth and its motion state.
#[derive(Debug, Clone)]
pub struct SimTable {
    pub id: String,
    /// A point on the true axis (the nominal point moved by the axis offset), metres.
    pub axis_point_m: Vector3<f64>,
    pub axis_direction: Unit<Vector3<f64>>,
    /// Where the tracer stands at true table angle 0, metres.
    pub tracer_base_m: Vector3<f64>,
    pub error: AngleError,
    /// Radial, axial and tilt error motions (`[sim.effects] table_error_motion`), if on.
    pub error_motion: Option<ErrorMotion>,
    /// Reversal (backlash): the table stands half of it beyond the command in the direction of
    /// its last move, radians.
    pub reversal_rad: f64,
    /// Sign of the last move's direction (0 before any move).
    approach: f64,
    /// Scatter of each positioning, and its own random stream (a plan's true angles follow
    /// from the commands in order: `world::table_true_angles`).
    repeatability: Option<(Normal<f64>, ChaCha8Rng)>,
    /// The scatter drawn for the current positioning, radians.
    scatter_rad: f64,
    speed_rad_s: f64,
    settle_s: f64,
    commanded_rad: f64,
    from_true_rad: f64,
    to_true_rad: f64,
    start_s: f64,
    move_s: f64,
}

impl SimTable {
    /// The seeded truth of the table of `plan`; the tracer's true base is its hint moved by
    /// `station_hint_error_m` per coordinate.
    pub fn random(
        seed: u64,
        plan: &RotaryPlanConfig,
        sim: &SimRotaryConfig,
        station_hint_error_m: f64,
    ) -> SimTable {
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x524f_5441_5259_5442);
        let normal = |sd: f64| Normal::new(0.0, sd.max(0.0)).ok();
        let mut draw = |sd: f64| normal(sd).map_or(0.0, |n| n.sample(&mut rng));
        let axis_point_m = Vector3::from(plan.axis_point_m).map(|v| v + draw(sim.axis_offset_m));
        let nominal = Vector3::from(plan.axis_direction).normalize();
        // Tilt: a small random rotation vector perpendicular to the nominal direction.
        let helper = if nominal.x.abs() < 0.9 {
            Vector3::x()
        } else {
            Vector3::y()
        };
        let e1 = nominal.cross(&helper).normalize();
        let e2 = nominal.cross(&e1);
        let tilt = e1 * draw(sim.axis_tilt_rad) + e2 * draw(sim.axis_tilt_rad);
        let axis_direction = Unit::new_normalize(nominal + tilt);
        let tracer_base_m =
            Vector3::from(plan.tracer_hint_m).map(|v| v + draw(station_hint_error_m));
        let error = AngleError::random(&mut rng, sim.harmonics, sim.angle_error_rad);
        let start = error.at(0.0);
        SimTable {
            id: plan.table.clone(),
            axis_point_m,
            axis_direction,
            tracer_base_m,
            error,
            error_motion: None,
            reversal_rad: sim.reversal_rad,
            approach: 0.0,
            repeatability: (sim.repeatability_rad > 0.0)
                .then(|| Normal::new(0.0, sim.repeatability_rad).ok())
                .flatten()
                .map(|n| (n, ChaCha8Rng::seed_from_u64(seed ^ 0x5245_5045_4154_4142))),
            scatter_rad: 0.0,
            speed_rad_s: sim.speed_rad_s,
            settle_s: sim.settle_s,
            commanded_rad: 0.0,
            from_true_rad: start,
            to_true_rad: start,
            start_s: 0.0,
            move_s: 0.0,
        }
    }

    /// The true table angle reached when the table is in position at `commanded_rad`, having
    /// approached it from the side `approach` (+1, −1; 0 before any move).
    fn true_angle_rad(&self, commanded_rad: f64, approach: f64) -> f64 {
        commanded_rad
            + self.error.at(commanded_rad)
            + 0.5 * self.reversal_rad * approach
            + self.scatter_rad
    }

    /// The scatter of each positioning (standard deviation), radians.
    pub fn repeatability_rad(&self) -> f64 {
        self.repeatability
            .as_ref()
            .map_or(0.0, |(n, _)| n.std_dev())
    }

    /// The true angle at which the table comes to rest: the tracer positions of a plan's table
    /// stations follow from the commands alone (`start_rotation` at rest, in order).
    pub fn rest_angle_rad(&self) -> f64 {
        self.to_true_rad
    }

    /// The true table angle at `t_s` (a smooth move between rest angles).
    pub fn angle_at(&self, t_s: f64) -> f64 {
        if self.move_s <= 0.0 {
            return self.to_true_rad;
        }
        let tau = ((t_s - self.start_s) / self.move_s).clamp(0.0, 1.0);
        let s = tau - (TAU * tau).sin() / TAU;
        self.from_true_rad + (self.to_true_rad - self.from_true_rad) * s
    }

    /// The table with error motions of `size_m` drawn from their own stream of `seed`.
    pub fn with_error_motion(mut self, seed: u64, size_m: f64) -> SimTable {
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x4552_524f_524d_4f54);
        let arm = (self.tracer_base_m - self.axis_point_m).norm();
        self.error_motion = Some(ErrorMotion::random(&mut rng, size_m, arm));
        self
    }

    /// Where the tracer on the table is at true table angle `angle_rad`.
    pub fn tracer_at(&self, angle_rad: f64) -> Vector3<f64> {
        let turned = rotate_about_axis(
            &self.tracer_base_m,
            &self.axis_point_m,
            &self.axis_direction,
            angle_rad,
        );
        match &self.error_motion {
            Some(motion) => {
                let arm = turned - self.axis_point_m;
                turned + motion.displacement_m(angle_rad, &self.axis_direction, &arm)
            }
            None => turned,
        }
    }

    /// Start turning to `commanded_rad` at `now_s`; returns whether the table moves at all.
    pub fn start_rotation(&mut self, commanded_rad: f64, now_s: f64) -> bool {
        let from = self.angle_at(now_s);
        if commanded_rad != self.commanded_rad {
            self.approach = (commanded_rad - self.commanded_rad).signum();
            if let Some((normal, rng)) = self.repeatability.as_mut() {
                self.scatter_rad = normal.sample(rng);
            }
        }
        let to = self.true_angle_rad(commanded_rad, self.approach);
        self.commanded_rad = commanded_rad;
        self.from_true_rad = from;
        self.to_true_rad = to;
        self.start_s = now_s;
        let moves = (to - from).abs() > 0.0;
        // A cycloidal move peaks at twice the mean speed: keep the peak at the set speed.
        self.move_s = if moves {
            2.0 * (to - from).abs() / self.speed_rad_s
        } else {
            0.0
        };
        moves
    }

    /// The encoder angle once in position (the servo holds the encoder at the command; the
    /// positioning error lies between encoder and table), else None while moving or settling.
    pub fn in_position_at(&self, now_s: f64) -> Option<f64> {
        let settle = if self.move_s > 0.0 {
            self.settle_s
        } else {
            0.0
        };
        (now_s >= self.start_s + self.move_s + settle).then_some(self.commanded_rad)
    }

    /// What the encoder reads at `now_s` and whether the table is in position: the command
    /// once in position, else the true angle less the positioning error of the target.
    pub fn encoder_at(&self, now_s: f64) -> (f64, bool) {
        match self.in_position_at(now_s) {
            Some(encoder_rad) => (encoder_rad, true),
            None => (
                self.angle_at(now_s)
                    - self.error.at(self.commanded_rad)
                    - 0.5 * self.reversal_rad * self.approach
                    - self.scatter_rad,
                false,
            ),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A table plan of three listed angles, the tracer 0.15 m off the axis.
    fn listed_angles() -> RotaryPlanConfig {
        RotaryPlanConfig {
            table: "c".into(),
            axis_point_m: [0.3, 0.3, -0.3],
            axis_direction: [0.0, 0.0, 1.0],
            tracer_hint_m: [0.45, 0.3, -0.2],
            angles_rad: Some(vec![0.0, 0.5, 1.0]),
            start_rad: None,
            step_rad: None,
            count: None,
            spacing: Default::default(),
            runs: None,
            overshoot_rad: None,
            station_prefix: "c".into(),
        }
    }

    #[test]
    fn angle_error_has_the_configured_peak() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let e = AngleError::random(&mut rng, 4, 2.4e-5);
        let peak = (0..36_000)
            .map(|i| e.at(TAU * f64::from(i) / 36_000.0).abs())
            .fold(0.0f64, f64::max);
        assert!((peak - 2.4e-5).abs() < 1e-8, "peak {peak}");
        // Periodic in the angle.
        assert!((e.at(0.3) - e.at(0.3 + TAU)).abs() < 1e-15);
    }

    #[test]
    fn tracer_turns_about_the_true_axis() {
        let plan = RotaryPlanConfig {
            angles_rad: None,
            step_rad: Some(0.5),
            count: Some(4),
            ..listed_angles()
        };
        let mut table = SimTable::random(1, &plan, &SimRotaryConfig::default(), 0.01);
        assert!(table.in_position_at(0.0).is_some());
        assert!(table.start_rotation(0.5, 10.0));
        assert_eq!(table.in_position_at(10.1), None);
        // The true move is 0.5 rad plus the (arcsecond) positioning errors.
        let done_s = 10.0 + 2.0 * 0.5 / 0.2 + 2.0 + 1e-3;
        assert_eq!(table.in_position_at(done_s), Some(0.5));
        let angle = table.angle_at(done_s);
        assert!((angle - 0.5 - table.error.at(0.5)).abs() < 1e-15);
        // The tracer keeps its distance from the axis and its height along it.
        let n = table.axis_direction.into_inner();
        let arm = |p: Vector3<f64>| {
            let d = p - table.axis_point_m;
            (d - n * d.dot(&n), d.dot(&n))
        };
        let (r0, h0) = arm(table.tracer_at(0.0));
        let (r1, h1) = arm(table.tracer_at(angle));
        assert!((r0.norm() - r1.norm()).abs() < 1e-12);
        assert!((h0 - h1).abs() < 1e-12);
        assert!((r0.angle(&r1) - angle).abs() < 1e-9);
    }

    #[test]
    fn reversal_puts_the_table_beyond_the_command_in_the_direction_of_the_move() {
        let plan = listed_angles();
        let sim = SimRotaryConfig {
            reversal_rad: 2e-5,
            ..SimRotaryConfig::default()
        };
        let mut table = SimTable::random(1, &plan, &sim, 0.01);
        // At rest before any move: no reversal; a command to where it stands is no move.
        assert!(!table.start_rotation(0.0, 0.0));
        assert_eq!(table.rest_angle_rad(), table.error.at(0.0));
        let mut now = 1.0;
        let mut go = |table: &mut SimTable, c: f64| {
            table.start_rotation(c, now);
            now += 100.0;
            assert_eq!(table.in_position_at(now), Some(c));
            table.angle_at(now)
        };
        let up = go(&mut table, 0.5);
        assert!((up - (0.5 + table.error.at(0.5) + 1e-5)).abs() < 1e-15);
        go(&mut table, 0.6);
        let down = go(&mut table, 0.5);
        assert!((up - down - 2e-5).abs() < 1e-15, "B = {}", up - down);
        // The encoder holds the command in position; while moving it reads the table.
        table.start_rotation(1.0, now);
        let (encoder, in_position) = table.encoder_at(now + 1.0);
        assert!(!in_position);
        let expected = table.angle_at(now + 1.0) - table.error.at(1.0) - 1e-5;
        assert!((encoder - expected).abs() < 1e-15);
    }

    #[test]
    fn repeatability_scatters_each_positioning_and_a_resend_keeps_it() {
        let plan = listed_angles();
        let sim = SimRotaryConfig {
            repeatability_rad: 1e-5,
            ..SimRotaryConfig::default()
        };
        let mut table = SimTable::random(1, &plan, &sim, 0.01);
        assert_eq!(table.repeatability_rad(), 1e-5);
        let scatter: Vec<f64> = (0..400)
            .map(|k| {
                table.start_rotation(if k % 2 == 0 { 0.5 } else { 1.0 }, 0.0);
                let c = table.commanded_rad;
                let scatter = table.rest_angle_rad() - c - table.error.at(c);
                // Sending the same command again is no new positioning.
                table.start_rotation(c, 0.0);
                assert_eq!(table.rest_angle_rad() - c - table.error.at(c), scatter);
                scatter
            })
            .collect();
        let sd = (scatter.iter().map(|s| s * s).sum::<f64>() / scatter.len() as f64).sqrt();
        // 400 draws: the sample σ lies within ±15 % of 1e-5 with probability > 0.997.
        assert!((sd / 1e-5 - 1.0).abs() < 0.15, "sample σ {sd:e}");
    }
}
