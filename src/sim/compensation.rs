//! The simulated machine's controller compensation (`[sim] compensation`): the tables loaded
//! as their controllers read them, applied to the commanded axis positions as the
//! controllers apply them (a verification run after `geocal compensate`).

use crate::compensate::applied::{load_cross_tables, CrossTable};
use crate::compensate::{load_table, AppliedTable, CompensateError};
use crate::config::sim::SimCompensation;

#[derive(Debug, Clone, Default)]
pub struct SimControllerCompensation {
    tables: [Option<AppliedTable>; 3],
    /// SINUMERIK `$AN_CEC` tables: each adds to its compensation axis a value of its base
    /// axis's position setpoint; several on one axis sum (K3).
    cross: Vec<CrossTable>,
    /// Direction of each axis's last move (+1, −1; 0 before it moved): LinuxCNC keeps the
    /// column of the last motion while the joint stands still, and a direction-dependent
    /// cross table acts after moves of its base axis in its direction.
    approach: [f64; 3],
}

impl SimControllerCompensation {
    pub fn load(config: &[SimCompensation]) -> Result<Self, CompensateError> {
        let mut out = SimControllerCompensation::default();
        for c in config {
            if c.is_cross() {
                out.cross
                    .extend(load_cross_tables(&c.file, &c.machine_axis_names())?);
                continue;
            }
            let table = load_table(c.format, &c.file, &c.controller_axis_name())?;
            // The configuration's validation checked the axis name.
            if let Some(axis) = c.axis_index() {
                out.tables[axis] = Some(table);
            }
        }
        Ok(out)
    }

    pub fn is_empty(&self) -> bool {
        self.tables.iter().all(Option::is_none) && self.cross.is_empty()
    }

    /// A move from `from` to `to` starts: the direction each moving axis approaches in.
    pub fn on_move(&mut self, from: [f64; 3], to: [f64; 3]) {
        for k in 0..3 {
            let d = to[k] - from[k];
            if d.abs() > 1e-9 {
                self.approach[k] = d.signum();
            }
        }
    }

    /// The sum of the cross tables' values on each axis at the commanded positions.
    fn cross_values_m(&self, commanded_m: [f64; 3]) -> [f64; 3] {
        let mut sum = [0.0; 3];
        for c in &self.cross {
            if c.table.acts(self.approach[c.base]) {
                sum[c.compensated] += c.table.value_m(commanded_m[c.base]);
            }
        }
        sum
    }

    /// The joint positions the controller drives to for the commanded axis positions. A
    /// SINUMERIK axis is in position when its compensated actual value, encoder value plus
    /// `$AA_ENC_COMP` plus the cross tables' sum, equals the command.
    pub fn joint_positions_m(&self, commanded_m: [f64; 3]) -> [f64; 3] {
        let cross = self.cross_values_m(commanded_m);
        std::array::from_fn(|k| {
            let q = commanded_m[k] - cross[k];
            match &self.tables[k] {
                Some(t) => t.joint_position_m(q, self.approach[k]),
                None => q,
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::compensate::sinumerik::{CecTable, EncCompTable};

    #[test]
    fn cross_and_encoder_tables_sum_on_the_compensated_axis() {
        let ramp = |input: &str, output: &str| CecTable {
            values_mm: vec![0.0, 0.010],
            input_axis: input.into(),
            output_axis: output.into(),
            step_mm: 1000.0,
            min_mm: 0.0,
            max_mm: 1000.0,
            direction: 0,
        };
        let encoder = AppliedTable::Sinumerik(EncCompTable {
            values_mm: vec![0.002, 0.002],
            step_mm: 1000.0,
            min_mm: 0.0,
            max_mm: 1000.0,
        });
        // y on x and y on z, +10 µm per metre each; y's encoder table a constant +2 µm.
        let mut c = SimControllerCompensation {
            tables: [None, Some(encoder), None],
            cross: vec![
                CrossTable {
                    index: 0,
                    base: 0,
                    compensated: 1,
                    table: ramp("X1", "Y1"),
                },
                CrossTable {
                    index: 1,
                    base: 2,
                    compensated: 1,
                    table: ramp("Z1", "Y1"),
                },
            ],
            approach: [0.0; 3],
        };
        let j = c.joint_positions_m([0.5, 0.3, 2.0]);
        // x 0.5 m: +5 µm; z beyond the table: its last value, +10 µm; encoder +2 µm.
        assert!(
            (j[1] - (0.3 - 5e-6 - 10e-6 - 2e-6)).abs() < 1e-12,
            "{}",
            j[1]
        );
        assert_eq!((j[0], j[2]), (0.5, 2.0));
        // A table for the − direction of x acts only after x moved −.
        c.cross[0].table.direction = -1;
        c.on_move([0.0; 3], [0.5, 0.0, 0.0]);
        let j = c.joint_positions_m([0.5, 0.3, 2.0]);
        assert!((j[1] - (0.3 - 10e-6 - 2e-6)).abs() < 1e-12, "{}", j[1]);
        c.on_move([0.6, 0.0, 0.0], [0.5, 0.0, 0.0]);
        let j = c.joint_positions_m([0.5, 0.3, 2.0]);
        assert!((j[1] - (0.3 - 17e-6)).abs() < 1e-12, "{}", j[1]);
    }
}
