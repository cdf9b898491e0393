//! The points level of the diagnosis: the solved points (one set per pass, full covariance)
//! fitted by the machine's quasi-rigid 21-error model; whitened residuals, χ², and where they depart.

pub use crate::diagnose::lengths::{PointDeparture, PointsGap, PointsLevel, TargetOffsetTest};

use std::collections::BTreeMap;
use std::sync::Arc;

use nalgebra::{DMatrix, DVector, Vector3};

use super::data::Data;
use super::effects::Geometry;
use super::fit::Fit;
use super::locate::{octant_key, WhereEntry};
use super::schur::Design;
use super::stats::{chi2_sf, Basis, EFFECT_RANK_TOL};
use crate::method::multilateration::point_observations;
use crate::model::kinematics::Structure;
use crate::solve::geometric_errors::{grid_from_points, whitened_design, DecompositionOptions};
use crate::solve::multilateration::{
    dense_point_covariance, dense_point_covariance_fits, generator, solve, LengthObservation,
    MultilaterationProblem, MultilaterationSolution, SolveOptions,
};

/// Relative singular value below which a direction of the (column-normalised) quasi-rigid
/// design counts as not identifiable, as in the decomposition.
const RANK_TOL: f64 = 1e-9;
/// Largest decomposition fitted (unknowns), as `geocal solve` bounds its dense decomposition.
const MAX_PARAMETERS: usize = 1500;

/// Score test of per-target constant shifts (targets after the first) against the points
/// level's model `basis`, on the whitened residuals `r_w` (whitening factor `l`).
fn target_offset_test(
    info: &[(String, usize, [f64; 3])],
    l: &DMatrix<f64>,
    basis: &Basis,
    r_w: &DVector<f64>,
    chi2: f64,
    dof: usize,
) -> Option<TargetOffsetTest> {
    let mut targets: Vec<&str> = info.iter().map(|i| i.0.as_str()).collect();
    targets.sort_unstable();
    targets.dedup();
    let shifted = &targets[1..];
    if shifted.is_empty() {
        return None;
    }
    let rows = 3 * info.len();
    let a = DMatrix::from_fn(rows, 3 * shifted.len(), |row, col| {
        let same_target = shifted[col / 3] == info[row / 3].0;
        if same_target && row % 3 == col % 3 {
            1.0
        } else {
            0.0
        }
    });
    let a_w = l.solve_lower_triangular(&a)?;
    // The rank is judged against the shifts' own whitened size before the projection (as a
    // lengths-level candidate's): a direction the model absorbs (with two targets the gauge
    // rotation takes ω × (o₂ − o₁), two of the three) leaves a rounding remainder that must
    // not count, nor be normalised up to a unit column.
    let reference = (0..a_w.ncols())
        .map(|c| a_w.column(c).norm())
        .fold(0.0, f64::max);
    let q_basis = Basis::new(&basis.project_off(&a_w), EFFECT_RANK_TOL, reference);
    let df = q_basis.rank();
    if df == 0 {
        return None;
    }
    let chi2_drop = (q_basis.u.transpose() * r_w).norm_squared();
    // Minimum-norm shifts (m): only their identifiable part (Frisch–Waugh: the projected
    // design's coefficients are those of the joint fit).
    let beta = q_basis.solve(r_w);
    let offsets_m = shifted
        .iter()
        .enumerate()
        .map(|(k, t)| {
            (
                t.to_string(),
                [beta[3 * k], beta[3 * k + 1], beta[3 * k + 2]],
            )
        })
        .collect();
    // Cov(β) = V S⁻² Vᵀ of the projected design.
    let sigma = |c: usize| {
        (0..df)
            .map(|k| (q_basis.vt[(k, c)] / q_basis.s[k]).powi(2))
            .sum::<f64>()
            .sqrt()
    };
    let offsets_sigma_m = shifted
        .iter()
        .enumerate()
        .map(|(k, t)| (t.to_string(), std::array::from_fn(|a| sigma(3 * k + a))))
        .collect();
    Some(TargetOffsetTest {
        df,
        offsets_sigma_m,
        chi2_drop,
        p_value: chi2_sf(chi2_drop, df as f64),
        bic_delta: -chi2_drop + df as f64 * (rows as f64).ln(),
        chi2_after: chi2 - chi2_drop,
        dof_after: dof.saturating_sub(df),
        offsets_m,
    })
}

/// A pass point and its (target, plan point, nominal): what the group tests need of a point.
pub type PointMeta<'a> = (&'a PassPoint, &'a (String, usize, [f64; 3]));

/// One fitted point of the per-pass problem and its bookkeeping.
pub struct PassPoint {
    /// Problem point of `data` and pass.
    pub point: usize,
    pub pass: usize,
    pub approach: [f64; 3],
}

/// The points solved per pass with their full covariance (3n x 3n, point-major).
pub struct PerPass {
    pub pass_points: Vec<PassPoint>,
    /// Pass point of each observation of `data`.
    pub point_of: Vec<usize>,
    /// (target, plan point, nominal) of each pass point.
    pub info: Vec<(String, usize, [f64; 3])>,
    pub solution: MultilaterationSolution,
    pub cov: DMatrix<f64>,
}

/// Solve the lengths `lengths_m` (one per observation of `data`) with one unknown point per
/// (plan point, pass): passes then show as such (reversal, drift).
pub fn per_pass_points(data: &Data, lengths_m: &[f64]) -> Result<PerPass, String> {
    let mut index: BTreeMap<(usize, usize), usize> = BTreeMap::new();
    let mut pass_points: Vec<PassPoint> = Vec::new();
    let mut observations = Vec::with_capacity(data.obs.len());
    let mut point_of = Vec::with_capacity(data.obs.len());
    for (o, &length_m) in data.obs.iter().zip(lengths_m) {
        let k = *index.entry((o.point, o.pass)).or_insert_with(|| {
            pass_points.push(PassPoint {
                point: o.point,
                pass: o.pass,
                approach: std::array::from_fn(|a| o.approach_sign(a)),
            });
            pass_points.len() - 1
        });
        point_of.push(k);
        observations.push(LengthObservation {
            point: k,
            segment: o.segment,
            length_m,
            sigma_m: o.sigma_m,
            path_sigma: None,
        });
    }
    let problem = MultilaterationProblem {
        nominal_points: pass_points
            .iter()
            .map(|p| data.problem.nominal_points[p.point])
            .collect(),
        station_hints: data.problem.station_hints.clone(),
        segments: data.problem.segments.clone(),
        observations,
    };
    let too_large = || "the per-pass problem is too large for the dense point covariance";
    if !dense_point_covariance_fits(&problem) {
        return Err(too_large().into());
    }
    let solution = solve(&problem, &SolveOptions::default())
        .map_err(|e| format!("the per-pass multilateration: {e}"))?;
    let cov = dense_point_covariance(&problem, &solution).ok_or_else(|| too_large().to_string())?;
    let info = pass_points
        .iter()
        .map(|p| data.points[p.point].clone())
        .collect();
    Ok(PerPass {
        pass_points,
        point_of,
        info,
        solution,
        cov,
    })
}

/// How effects (`effects`: their columns, one row per observation, metres per unit parameter)
/// move the per-pass points: the part of each effect the free geometry absorbs, J⁺·P_J·A
/// (whitened, linearised at the per-pass optimum), points rows, in the points' datum (inner
/// constraints on the nominal points, as their covariance), whitened by `l`: an orthonormal
/// basis of the directions that move the points by more than EFFECT_RANK_TOL of the absorbed
/// signal's size in noise units (not only the stations or the gauge: the vertical
/// eccentricity is a station height). An effect fitted on the lengths leaves its estimate's uncertainty in the
/// points along these columns; the points level fits them as free columns (the limit of an
/// uncertain nuisance), so its test holds whatever the effect's size and however well the
/// lengths determine it.
fn effect_point_response(
    data: &Data,
    per_pass: &PerPass,
    effects: &DMatrix<f64>,
    l: &DMatrix<f64>,
) -> Option<DMatrix<f64>> {
    let (k_inner, reference) = effect_point_move(data, per_pass, effects)?;
    let k_w = l.solve_lower_triangular(&k_inner)?;
    // Mahalanobis size of the points' move against the absorbed signal's size (whitened
    // lengths): directions below EFFECT_RANK_TOL of it move only stations or the gauge.
    Some(Basis::new(&k_w, EFFECT_RANK_TOL, reference).u)
}

/// The per-pass points' move under each effect column (metres per unit parameter, rows
/// point-major x, y, z, in the points' inner-constraint datum), and the size of the largest
/// absorbed signal in whitened lengths (the reference of the rank cut). See
/// `effect_point_response`.
pub(crate) fn effect_point_move(
    data: &Data,
    per_pass: &PerPass,
    effects: &DMatrix<f64>,
) -> Option<(DMatrix<f64>, f64)> {
    let n = per_pass.pass_points.len();
    let w = DVector::from_iterator(data.obs.len(), data.obs.iter().map(|o| 1.0 / o.sigma_m));
    let whiten = |m: &DMatrix<f64>| DMatrix::from_fn(m.nrows(), m.ncols(), |i, c| m[(i, c)] * w[i]);
    let a_w = whiten(effects);
    // The geometry's fit on the solve's structure (points eliminated block by block): the
    // steps' gauge, whatever it is, is taken off by the S-transform below.
    let geom = Geometry::from_solution(&per_pass.solution);
    let design = Design::with_points(data, &geom, |i| per_pass.point_of[i]);
    let geometry = Fit::new(Arc::new(design), (0..data.obs.len()).collect());
    let absorbed = &a_w - geometry.project_off(&a_w);
    let reference = (0..absorbed.ncols())
        .map(|c| absorbed.column(c).norm())
        .fold(0.0, f64::max);
    let steps = geometry.solve_columns(absorbed);
    let k = steps.rows(0, 3 * n).into_owned();
    // S-transform to the inner-constraint datum of the points' covariance: the rigid motion
    // (at the solved points) that the minimum-norm step carries is removed as there.
    let nominal: Vec<Vector3<f64>> = per_pass
        .pass_points
        .iter()
        .map(|p| data.problem.nominal_points[p.point])
        .collect();
    let centre = nominal.iter().sum::<Vector3<f64>>() / n as f64;
    let mut g = DMatrix::<f64>::zeros(3 * n, 6);
    let mut e = DMatrix::<f64>::zeros(3 * n, 6);
    for (i, (solved, nominal)) in per_pass.solution.points.iter().zip(&nominal).enumerate() {
        g.view_mut((3 * i, 0), (3, 6))
            .copy_from(&generator(solved, &centre));
        e.view_mut((3 * i, 0), (3, 6))
            .copy_from(&generator(nominal, &centre));
    }
    let etg_inv = (e.transpose() * &g).try_inverse()?;
    let k_inner = &k - &g * (etg_inv * (e.transpose() * &k));
    Some((k_inner, reference))
}

/// Residuals r (m, stacked point-major x, y, z) with covariance C; the χ² of a group of rows
/// is rᵀ C⁺ r over the group (pseudo-inverse: the rows the model fits exactly drop out).
fn group_chi2(e: &DVector<f64>, c: &DMatrix<f64>, rows: &[usize]) -> (f64, f64) {
    let sub = DMatrix::from_fn(rows.len(), rows.len(), |a, b| c[(rows[a], rows[b])]);
    let v = DVector::from_fn(rows.len(), |a, _| e[rows[a]]);
    let eigen = sub.symmetric_eigen();
    let largest = eigen.eigenvalues.amax();
    let (mut stat, mut dof) = (0.0, 0.0);
    for (k, &lambda) in eigen.eigenvalues.iter().enumerate() {
        if lambda > 1e-9 * largest && lambda > 0.0 {
            stat += eigen.eigenvectors.column(k).dot(&v).powi(2) / lambda;
            dof += 1.0;
        }
    }
    (stat, dof)
}

/// Fit the points solved from `lengths_m` (one per observation of `data`; the recorded lengths,
/// or lengths with fitted effects removed) against the quasi-rigid 21-error model. Err says
/// why the points level cannot be computed for this session.
/// `effects`: the columns of effects fitted with the per-pass geometry (none: zero columns).
pub fn points_level(
    data: &Data,
    lengths_m: &[f64],
    effects: &DMatrix<f64>,
    alpha: f64,
) -> Result<(PointsLevel, Vec<WhereEntry>), String> {
    let per_pass = per_pass_points(data, lengths_m)?;
    let PerPass {
        pass_points,
        info,
        solution,
        cov,
        ..
    } = &per_pass;
    let axes: Vec<Option<[f64; 3]>> = pass_points
        .iter()
        .map(|p| data.point_axes_m[p.point])
        .collect();
    let obs = point_observations(&data.machine, info, &axes, solution)?;
    let structure = Structure::parse(&data.machine.structure).map_err(|e| e.to_string())?;
    let options = DecompositionOptions::default();
    let grid = grid_from_points(&obs, options.grid_tolerance_m);
    let parameters = 6 * grid.iter().map(Vec::len).sum::<usize>() + 9;
    let equations = 3 * obs.len();
    if parameters > MAX_PARAMETERS || 2 * parameters > equations {
        return Err(format!(
            "the points are not on an axis grid the 21-error model can test: {parameters} \
             unknowns for {equations} equations (needs at most {MAX_PARAMETERS} and at most half)"
        ));
    }
    let wd =
        whitened_design(&structure, &grid, &obs, Some(cov), &options).map_err(|e| e.to_string())?;
    // The model with the selected effects' point response as free columns, whitened alike.
    let response_w = if effects.ncols() > 0 {
        effect_point_response(data, &per_pass, effects, &wd.l)
            .ok_or("the selected effects' point response is singular")?
    } else {
        DMatrix::zeros(wd.x.nrows(), 0)
    };
    let mut x = DMatrix::zeros(wd.x.nrows(), wd.x.ncols() + response_w.ncols());
    x.columns_mut(0, wd.x.ncols()).copy_from(&wd.x);
    x.columns_mut(wd.x.ncols(), response_w.ncols())
        .copy_from(&response_w);
    // Column-normalised so that the rank cut treats metres and radians alike.
    let mut xn = x;
    for mut col in xn.column_iter_mut() {
        let n = col.norm();
        if n > 0.0 {
            col /= n;
        }
    }
    let basis = Basis::new(&xn, RANK_TOL, 1.0);
    let r_w = basis.project_off_vec(&wd.y);
    let chi2 = r_w.norm_squared();
    let rows = equations;
    let dof = rows.saturating_sub(basis.rank());
    let e = &wd.l * &r_w;
    // Cov(e) = L (I − U Uᵀ) Lᵀ.
    let lu = &wd.l * &basis.u;
    let c = &wd.l * wd.l.transpose() - &lu * lu.transpose();
    let gap = PointsGap {
        chi2,
        dof,
        chi2_per_dof: chi2 / dof.max(1) as f64,
        p_value: chi2_sf(chi2, dof as f64),
        rms_m: (e.norm_squared() / rows as f64).sqrt(),
        floor_m: (c.trace().max(0.0) / rows as f64).sqrt(),
        points: pass_points.len(),
        rank: basis.rank(),
    };

    let meta: Vec<PointMeta> = pass_points.iter().zip(info).collect();
    let out = test_groups(&e, &c, &meta, alpha, "");
    let departures = point_departures(&e, &c, &meta, alpha);
    let target_offset = target_offset_test(info, &wd.l, &basis, &r_w, chi2, dof);
    Ok((
        PointsLevel {
            gap,
            departures,
            target_offset,
        },
        out,
    ))
}

/// Groups of rows of point residuals `e` (covariance `c`, point-major x, y, z), tested against
/// the noise model: region (octant of the nominal point), component, approach, pass, target.
/// `suffix` is appended to each key.
pub fn test_groups(
    e: &DVector<f64>,
    c: &DMatrix<f64>,
    meta: &[PointMeta],
    alpha: f64,
    suffix: &str,
) -> Vec<WhereEntry> {
    let total_m2 = e.norm_squared().max(f64::MIN_POSITIVE);
    let n = meta.len();
    let pass_points: Vec<&PassPoint> = meta.iter().map(|m| m.0).collect();
    let info: Vec<&(String, usize, [f64; 3])> = meta.iter().map(|m| m.1).collect();
    let all_rows = |keep: &dyn Fn(usize) -> bool| -> Vec<usize> {
        (0..n)
            .filter(|&k| keep(k))
            .flat_map(|k| 3 * k..3 * k + 3)
            .collect()
    };
    let nominal = |k: usize| info[k].2;
    let centre: [f64; 3] =
        std::array::from_fn(|a| (0..n).map(|k| nominal(k)[a]).sum::<f64>() / n.max(1) as f64);
    let mut groups: Vec<(&str, String, Vec<usize>)> = Vec::new();
    for octant in 0..8 {
        let key = octant_key(octant);
        let members =
            all_rows(&|k| (0..3).all(|a| (nominal(k)[a] > centre[a]) == (octant >> a & 1 == 1)));
        groups.push(("region", key, members));
    }
    for (a, axis) in ["x", "y", "z"].iter().enumerate() {
        groups.push((
            "axis",
            format!("{axis} component"),
            (0..n).map(|k| 3 * k + a).collect(),
        ));
    }
    for (a, axis) in ["x", "y", "z"].iter().enumerate() {
        for (s, sign) in [(1.0, "+"), (-1.0, "-")] {
            let members = all_rows(&|k| pass_points[k].approach[a] == s);
            groups.push(("direction", format!("{axis}{sign}"), members));
        }
    }
    let max_pass = pass_points.iter().map(|p| p.pass).max().unwrap_or(0);
    if max_pass > 0 {
        for p in 0..=max_pass {
            groups.push((
                "pass",
                format!("pass {p}"),
                all_rows(&|k| pass_points[k].pass == p),
            ));
        }
    }
    let mut targets: Vec<&String> = info.iter().map(|i| &i.0).collect();
    targets.sort();
    targets.dedup();
    if targets.len() > 1 {
        for t in targets {
            groups.push(("target", t.clone(), all_rows(&|k| &info[k].0 == t)));
        }
    }
    groups.retain(|g| !g.2.is_empty());
    let tests = groups.len() as f64;
    let mut out = Vec::new();
    for (group, key, members) in &groups {
        let (stat, gdof) = group_chi2(e, c, members);
        let p = (chi2_sf(stat, gdof) * tests).min(1.0);
        if p < alpha {
            let ss: f64 = members.iter().map(|&r| e[r].powi(2)).sum();
            out.push(WhereEntry {
                level: "points".into(),
                group: (*group).into(),
                key: format!("{key}{suffix}"),
                share: ss / total_m2,
                rms_m: (ss / members.len() as f64).sqrt(),
                p_value: p,
            });
        }
    }
    out.sort_by(|a, b| b.share.total_cmp(&a.share));
    out
}

/// Single points whose 3 residual components fail the noise model (Bonferroni over points).
pub fn point_departures(
    e: &DVector<f64>,
    c: &DMatrix<f64>,
    meta: &[PointMeta],
    alpha: f64,
) -> Vec<PointDeparture> {
    let n = meta.len();
    let mut departures: Vec<PointDeparture> = (0..n)
        .filter_map(|k| {
            let (stat, gdof) = group_chi2(e, c, &[3 * k, 3 * k + 1, 3 * k + 2]);
            let p = (chi2_sf(stat, gdof) * n as f64).min(1.0);
            (p < alpha).then(|| PointDeparture {
                target: meta[k].1 .0.clone(),
                point: meta[k].1 .1,
                pass: meta[k].0.pass,
                nominal_m: meta[k].1 .2,
                residual_m: [e[3 * k], e[3 * k + 1], e[3 * k + 2]],
                chi2: stat,
                p_value: p,
            })
        })
        .collect();
    departures.sort_by(|a, b| b.chi2.total_cmp(&a.chi2));
    departures
}
