//! Grading a decomposition against a known (simulated) truth: the truth expressed in the
//! decomposition's datum, and the comparison of every identifiable value with its sigma.

use nalgebra::DVector;

use super::{
    apply_datum, build_system, first_step_columns, lsq, row_norm, select_columns,
    DecompositionOptions, Layout, PointObservation, Route, ESTIMABLE_TOL,
};
use crate::model::kinematics::{Axis, GeometricErrors, Squareness, Structure};

/// The truth as a full layout vector (all grid values, squareness, rigid motion 0).
fn truth_vector(layout: &Layout, grid: &[Vec<f64>; 3], t: &dyn GeometricErrors) -> DVector<f64> {
    let mut v = DVector::zeros(layout.len());
    for (a, axis) in Axis::ALL.iter().enumerate() {
        for (pos, &q) in grid[a].iter().enumerate() {
            let e = t.axis(*axis, q);
            for k in 0..3 {
                v[layout.axis(a, k, pos)] = e.linear_m[k];
                v[layout.axis(a, k + 3, pos)] = e.angular_rad[k];
            }
        }
    }
    let s = t.squareness();
    v[layout.square(0)] = s.xy_rad;
    v[layout.square(1)] = s.yz_rad;
    v[layout.square(2)] = s.zx_rad;
    v
}

/// The truth in the decomposition's datum: the parameters of the (datum-constrained, and for
/// the elastic-net route column-reduced) model that reproduce the truth's first-order error
/// field exactly; `None` where not estimable. Estimable values are unique, so this is the
/// datum conversion, independent of the solver's noise handling.
pub fn truth_in_datum(
    structure: &Structure,
    grid: &[Vec<f64>; 3],
    points: &[PointObservation],
    t: &dyn GeometricErrors,
    route: Route,
) -> Option<Vec<Option<f64>>> {
    let opts = DecompositionOptions::default();
    let sys = build_system(structure, grid, points, None, &opts).ok()?;
    let layout = &sys.layout;
    let f = &sys.x * truth_vector(layout, grid, t);
    let full = lsq(&sys.x, &f, opts.rank_tolerance).ok()?;
    let (fixed, null) = apply_datum(layout, &full.null);
    let mut out = vec![None; layout.len()];
    fixed.iter().for_each(|&j| out[j] = Some(0.0));
    let kept: Vec<usize> = (0..layout.len()).filter(|j| !fixed.contains(j)).collect();
    let cols = match route {
        Route::WeightedLeastSquares => kept.clone(),
        Route::ElasticNetQr => {
            let mut en = first_step_columns(&sys, &kept, &null, opts.rank_tolerance)
                .ok()?
                .en_cols;
            en.extend((0..6).map(|r| layout.rigid(r)));
            en
        }
    };
    let sol = lsq(&select_columns(&sys.x, &cols), &f, opts.rank_tolerance).ok()?;
    for (c, &j) in cols.iter().enumerate() {
        let free = match route {
            Route::WeightedLeastSquares => row_norm(&null, j) <= ESTIMABLE_TOL,
            Route::ElasticNetQr => row_norm(&sol.null, c) <= ESTIMABLE_TOL,
        };
        if free {
            out[j] = Some(sol.theta[c]);
        }
    }
    Some(out)
}

/// One identifiable value of a decomposition next to the truth in the same datum.
#[derive(Debug, Clone, PartialEq)]
pub struct Comparison {
    pub name: String,
    pub estimate: f64,
    pub sigma: f64,
    pub truth: f64,
}

impl Comparison {
    /// (estimate - truth) / sigma.
    pub fn normalised(&self) -> f64 {
        (self.estimate - self.truth) / self.sigma
    }
}

/// Every identifiable value (with a sigma > 0) of a decomposition, in its JSON form as results
/// carry it, beside the truth expressed in the decomposition's datum.
pub fn compare_with_truth(
    structure: &Structure,
    grid: &[Vec<f64>; 3],
    points: &[PointObservation],
    result: &serde_json::Value,
    truth: &dyn GeometricErrors,
) -> Result<Vec<Comparison>, String> {
    let route = match result["method"].as_str() {
        Some("weighted_least_squares") => Route::WeightedLeastSquares,
        Some("elastic_net+qr") => Route::ElasticNetQr,
        other => return Err(format!("unknown decomposition method {other:?}")),
    };
    let truth_d = truth_in_datum(structure, grid, points, truth, route)
        .ok_or("the truth cannot be expressed in the decomposition's datum")?;
    let layout = Layout::new(grid);
    let mut out = Vec::new();
    for (a, axis) in Axis::ALL.iter().enumerate() {
        let axis_json = &result["axes"][axis.letter().to_ascii_lowercase().to_string()];
        for (k, name) in axis.iso_names().iter().enumerate() {
            let f = &axis_json["errors"][*name];
            for pos in 0..layout.n_pos[a] {
                if let (Some(v), Some(s)) = (f["values"][pos].as_f64(), f["sigma"][pos].as_f64()) {
                    if s > 0.0 {
                        let t = truth_d[layout.axis(a, k, pos)].ok_or_else(|| {
                            format!("{name}[{pos}] is reported but not estimable")
                        })?;
                        out.push(Comparison {
                            name: format!("{name}[{pos}]"),
                            estimate: v,
                            sigma: s,
                            truth: t,
                        });
                    }
                }
            }
        }
    }
    for (s, name) in Squareness::ISO_NAMES.iter().enumerate() {
        let e = &result["squareness"][*name];
        if let (Some(v), Some(sg)) = (e["value_rad"].as_f64(), e["sigma_rad"].as_f64()) {
            let t = truth_d[layout.square(s)]
                .ok_or_else(|| format!("{name} is reported but not estimable"))?;
            out.push(Comparison {
                name: name.to_string(),
                estimate: v,
                sigma: sg,
                truth: t,
            });
        }
    }
    Ok(out)
}
