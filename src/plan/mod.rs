//! The measurement plan: a validated configuration expanded into points (grid order),
//! stations (placed by the operator or turned by a rotary table) and the visiting order of
//! each pass. Pure data; the sequencer executes it.

pub mod nc;

use nalgebra::{Rotation3, Unit, Vector3};
use serde::Serialize;

use crate::config::{AxisRange, Config, GridOrder, PassDirection};

/// Axis names in the order of `PlanPoint::axes_m`.
pub const AXES: [&str; 3] = ["x", "y", "z"];

#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct PlanPoint {
    pub index: usize,
    /// Commanded axis positions x, y, z, metres.
    pub axes_m: [f64; 3],
}

#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct PlanTarget {
    pub id: String,
    /// Reflector offset from the tool point, metres.
    pub offset_m: [f64; 3],
}

#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct PlanStation {
    pub id: String,
    pub hint_m: Option<[f64; 3]>,
    /// Set when the tracer stands on a rotary table: the table turns it to this station.
    pub rotation: Option<PlanRotation>,
}

#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct PlanRotation {
    /// Table id.
    pub table: String,
    /// Commanded absolute table angle, radians.
    pub commanded_rad: f64,
    /// The table is sent here first, so that it approaches `commanded_rad` from this side.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub via_rad: Option<f64>,
}

#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Plan {
    /// Measured one after another at every station.
    pub targets: Vec<PlanTarget>,
    /// Point 0 is the homing point.
    pub points: Vec<PlanPoint>,
    pub stations: Vec<PlanStation>,
    pub passes: Vec<PassDirection>,
    pub dwell_s: f64,
    pub max_dwell_s: f64,
    pub stillstand_window_s: f64,
    pub stillstand_tolerance_m: f64,
}

impl Plan {
    /// Expand a validated configuration.
    pub fn from_config(config: &Config) -> Plan {
        let grid = &config.plan.grid;
        let points = grid_axes(&grid.x, &grid.y, &grid.z, grid.order)
            .into_iter()
            .enumerate()
            .map(|(index, axes_m)| PlanPoint { index, axes_m })
            .collect();
        Plan {
            targets: config
                .plan
                .targets
                .iter()
                .map(|id| PlanTarget {
                    id: id.clone(),
                    offset_m: config.target_offset(id).unwrap_or([0.0; 3]),
                })
                .collect(),
            points,
            stations: table_stations(config)
                .into_iter()
                .chain(config.plan.stations.iter().map(|s| PlanStation {
                    id: s.id.clone(),
                    hint_m: s.hint_m,
                    rotation: None,
                }))
                .collect(),
            passes: config.plan.passes.clone(),
            dwell_s: config.plan.dwell_s,
            max_dwell_s: config.plan.max_dwell_s,
            stillstand_window_s: config.plan.stillstand.window_s,
            stillstand_tolerance_m: config.plan.stillstand.tolerance_m,
        }
    }

    /// Commanded position of a target at a point: axes + target offset (machine frame).
    pub fn nominal_m(&self, point: usize, target: &PlanTarget) -> [f64; 3] {
        let axes = self.points[point].axes_m;
        std::array::from_fn(|k| axes[k] + target.offset_m[k])
    }

    /// Point indices visited in a pass after homing at point 0 (which comes first in both).
    pub fn pass_order(&self, direction: PassDirection) -> Vec<usize> {
        let n = self.points.len();
        match direction {
            PassDirection::Forward => (0..n).collect(),
            PassDirection::Backward => std::iter::once(0).chain((1..n).rev()).collect(),
        }
    }
}

/// The stations on the rotary table, in commanded order; each hint is the tracer's nominal
/// position turned about the nominal axis by the commanded angle.
fn table_stations(config: &Config) -> Vec<PlanStation> {
    let Some(rotary) = &config.plan.rotary else {
        return Vec::new();
    };
    let axis_point = Vector3::from(rotary.axis_point_m);
    let direction = Vector3::from(rotary.axis_direction);
    let tracer = Vector3::from(rotary.tracer_hint_m);
    rotary
        .visits()
        .into_iter()
        .enumerate()
        .map(|(k, visit)| {
            let hint = rotate_about_axis(&tracer, &axis_point, &direction, visit.commanded_rad);
            PlanStation {
                id: rotary.station_id(k),
                hint_m: Some([hint.x, hint.y, hint.z]),
                rotation: Some(PlanRotation {
                    table: rotary.table.clone(),
                    commanded_rad: visit.commanded_rad,
                    via_rad: visit.via_rad,
                }),
            }
        })
        .collect()
}

/// `p` turned by `angle_rad` (right-handed) about the axis through `axis_point` along `direction`.
pub fn rotate_about_axis(
    p: &Vector3<f64>,
    axis_point: &Vector3<f64>,
    direction: &Vector3<f64>,
    angle_rad: f64,
) -> Vector3<f64> {
    let Some(axis) = Unit::try_new(*direction, 1e-12) else {
        return *p;
    };
    axis_point + Rotation3::from_axis_angle(&axis, angle_rad) * (p - axis_point)
}

fn linspace(range: &AxisRange) -> Vec<f64> {
    if range.count == 1 {
        return vec![range.from];
    }
    let step = (range.to - range.from) / (range.count - 1) as f64;
    (0..range.count)
        .map(|i| range.from + step * i as f64 + step * range.spacing.shift_fraction(i, range.count))
        .collect()
}

/// Grid points with z slowest and x fastest; serpentine reverses every other row and layer
/// so that consecutive points are neighbours.
fn grid_axes(x: &AxisRange, y: &AxisRange, z: &AxisRange, order: GridOrder) -> Vec<[f64; 3]> {
    let (xs, ys, zs) = (linspace(x), linspace(y), linspace(z));
    let mut out = Vec::with_capacity(xs.len() * ys.len() * zs.len());
    let mut row = 0usize;
    for (layer, &zv) in zs.iter().enumerate() {
        let y_iter: Vec<f64> = if order == GridOrder::Serpentine && layer % 2 == 1 {
            ys.iter().rev().copied().collect()
        } else {
            ys.clone()
        };
        for yv in y_iter {
            let reverse_x = order == GridOrder::Serpentine && row % 2 == 1;
            row += 1;
            let x_iter: Box<dyn Iterator<Item = &f64>> = if reverse_x {
                Box::new(xs.iter().rev())
            } else {
                Box::new(xs.iter())
            };
            out.extend(x_iter.map(|&xv| [xv, yv, zv]));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::{RotaryPlanConfig, Spacing, DEFAULT_TABLE_OVERSHOOT_RAD};

    fn table(runs: Option<usize>, spacing: Spacing) -> RotaryPlanConfig {
        RotaryPlanConfig {
            table: "c".into(),
            axis_point_m: [0.0; 3],
            axis_direction: [0.0, 0.0, 1.0],
            tracer_hint_m: [0.2, 0.0, 0.0],
            angles_rad: None,
            start_rad: Some(0.1),
            step_rad: Some(0.5),
            count: Some(5),
            spacing,
            runs,
            overshoot_rad: None,
            station_prefix: "c".into(),
        }
    }

    #[test]
    fn table_cycle_alternates_runs_each_entered_through_its_overshoot() {
        let once = table(None, Spacing::Equal).visits();
        assert_eq!(once.len(), 5);
        assert!(once.iter().all(|v| v.via_rad.is_none()));
        let plan = table(Some(2), Spacing::PseudoRandom);
        let angles = plan.commanded_angles_rad();
        // The stepped form's ends stay; interior angles move less than a quarter step.
        assert_eq!((angles[0], angles[4]), (0.1, 0.1 + 4.0 * 0.5));
        for (k, a) in angles.iter().enumerate() {
            assert!((a - (0.1 + 0.5 * k as f64)).abs() <= 0.125, "{angles:?}");
        }
        assert!(angles.iter().zip(&angles[1..]).all(|(a, b)| b > a));
        let visits = plan.visits();
        assert_eq!(visits.len(), 20);
        for (run, chunk) in visits.chunks(5).enumerate() {
            let commanded: Vec<f64> = chunk.iter().map(|v| v.commanded_rad).collect();
            let (expected, side): (Vec<f64>, f64) = if run % 2 == 0 {
                (angles.clone(), -1.0)
            } else {
                (angles.iter().rev().copied().collect(), 1.0)
            };
            assert_eq!(commanded, expected, "run {run}");
            assert_eq!(
                chunk[0].via_rad,
                Some(expected[0] + side * DEFAULT_TABLE_OVERSHOOT_RAD)
            );
            assert!(chunk[1..].iter().all(|v| v.via_rad.is_none()));
        }
    }

    fn range(from: f64, to: f64, count: usize) -> AxisRange {
        AxisRange {
            from,
            to,
            count,
            spacing: Spacing::Equal,
        }
    }

    #[test]
    fn pseudo_random_spacing_keeps_the_ends_and_the_order() {
        let equal = linspace(&range(0.1, 1.3, 7));
        let spread = linspace(&AxisRange {
            spacing: Spacing::PseudoRandom,
            ..range(0.1, 1.3, 7)
        });
        assert_eq!(spread[0], 0.1);
        assert_eq!(spread[6], 1.3);
        let intervals: Vec<f64> = spread.windows(2).map(|p| p[1] - p[0]).collect();
        // Within ±1/4 of the interval each: every interval between 0.5 and 1.5 of 0.2.
        assert!(
            intervals
                .iter()
                .all(|&d| d > 0.1 - 1e-12 && d < 0.3 + 1e-12),
            "{intervals:?}"
        );
        let distinct = intervals
            .windows(2)
            .filter(|p| (p[0] - p[1]).abs() > 1e-4)
            .count();
        assert!(distinct >= 3, "intervals barely differ: {intervals:?}");
        assert!(equal
            .iter()
            .zip(&spread)
            .skip(1)
            .take(5)
            .all(|(a, b)| a != b));
    }

    #[test]
    fn serpentine_steps_between_neighbours() {
        let pts = grid_axes(
            &range(0.0, 1.0, 3),
            &range(0.0, 2.0, 3),
            &range(0.0, 1.0, 2),
            GridOrder::Serpentine,
        );
        assert_eq!(pts.len(), 18);
        for pair in pts.windows(2) {
            let moved: usize = (0..3).filter(|&k| pair[0][k] != pair[1][k]).count();
            assert_eq!(
                moved, 1,
                "consecutive points {pair:?} differ in more than one axis"
            );
        }
        let unique: std::collections::BTreeSet<String> =
            pts.iter().map(|p| format!("{p:?}")).collect();
        assert_eq!(unique.len(), 18);
    }

    #[test]
    fn raster_is_row_major() {
        let pts = grid_axes(
            &range(0.0, 1.0, 2),
            &range(0.0, 1.0, 2),
            &range(0.0, 0.0, 1),
            GridOrder::Raster,
        );
        assert_eq!(
            pts,
            vec![
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [0.0, 1.0, 0.0],
                [1.0, 1.0, 0.0]
            ]
        );
    }
}
