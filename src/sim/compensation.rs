//! The simulated machine's controller compensation (`[sim] compensation`): the tables loaded
//! as their controllers read them, applied to the commanded axis positions as the
//! controllers apply them (a verification run after `geocal compensate`).

use crate::compensate::{load_table, AppliedTable, CompensateError};
use crate::config::sim::SimCompensation;

#[derive(Debug, Clone, Default)]
pub struct SimControllerCompensation {
    tables: [Option<AppliedTable>; 3],
    /// Direction of each axis's last move (+1, −1; 0 before it moved): LinuxCNC keeps the
    /// column of the last motion while the joint stands still.
    approach: [f64; 3],
}

impl SimControllerCompensation {
    pub fn load(config: &[SimCompensation]) -> Result<Self, CompensateError> {
        let mut out = SimControllerCompensation::default();
        for c in config {
            let table = load_table(c.format, &c.file, &c.controller_axis_name())?;
            // The configuration's validation checked the axis name.
            if let Some(axis) = c.axis_index() {
                out.tables[axis] = Some(table);
            }
        }
        Ok(out)
    }

    pub fn is_empty(&self) -> bool {
        self.tables.iter().all(Option::is_none)
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

    /// The joint positions the controller drives to for the commanded axis positions.
    pub fn joint_positions_m(&self, commanded_m: [f64; 3]) -> [f64; 3] {
        std::array::from_fn(|k| match &self.tables[k] {
            Some(t) => t.joint_position_m(commanded_m[k], self.approach[k]),
            None => commanded_m[k],
        })
    }
}
