//! "Where": splits the whitened residual sum of squares into groups (station, time block,
//! approach direction, workspace octant, beam axis, pass) and tests each against the noise model.

pub use crate::diagnose::WhereEntry;

use super::data::Data;
use super::dense;
use super::effects::Geometry;
use super::fit::Fit;
use super::schur::{Reduced, Schur};
use super::stats::chi2_sf;
use crate::parallel;

/// Time blocks: enough that a ramp or a step is localised, few enough that each block holds
/// tens of lengths (the χ² test of a block needs more than a handful of degrees of freedom).
const TIME_BLOCKS: usize = 8;

/// A change point: pass group, position in the pass, score statistic.
type Step = (usize, usize, f64);

/// Threads the change-point search walks its passes on.
const MAX_STEP_THREADS: usize = 8;

/// The best single change point in any pass of `stations` (None = all): (pass group, position,
/// score χ²(1) statistic, number of positions tried). `res_w` is orthogonal to span(basis).
pub fn best_step(
    data: &Data,
    basis: &Fit,
    res_w: &nalgebra::DVector<f64>,
    station: Option<usize>,
) -> Option<(usize, usize, f64, usize)> {
    best_steps(data, basis, res_w, &[station]).pop().flatten()
}

/// [`best_step`] for each of `stations`, the fit's split form computed once.
pub fn best_steps(
    data: &Data,
    basis: &Fit,
    res_w: &nalgebra::DVector<f64>,
    stations: &[Option<usize>],
) -> Vec<Option<(usize, usize, f64, usize)>> {
    let basis = match basis {
        Fit::Structured(s) => s,
        Fit::Dense(d) => {
            return stations
                .iter()
                .map(|&station| dense::best_step(data, d.basis(), res_w, station))
                .collect()
        }
    };
    let w: Vec<f64> = data.obs.iter().map(|o| 1.0 / o.sigma_m).collect();
    let reduced = basis.reduced();
    let threads = parallel::threads(MAX_STEP_THREADS);
    // Each station's passes in up to `threads` consecutive runs, all runs on the cores.
    let mut runs: Vec<(usize, Vec<usize>)> = Vec::new();
    for (s, &station) in stations.iter().enumerate() {
        let passes: Vec<usize> = (0..data.passes.len())
            .filter(|&g| station.is_none_or(|st| data.obs[data.passes[g][0]].station == st))
            .collect();
        let size = passes.len().div_ceil(threads).max(1);
        runs.extend(passes.chunks(size).map(|run| (s, run.to_vec())));
    }
    let found = parallel::in_groups(&runs, threads, |(s, passes)| {
        (*s, best_step_in(data, basis, &reduced, &w, res_w, passes))
    });
    // The first best in pass order wins, as in one walk over a station's passes.
    let mut best: Vec<(Option<Step>, usize)> = vec![(None, 0); stations.len()];
    for (s, (step, tried)) in found {
        let (kept, count) = &mut best[s];
        *count += tried;
        if let Some(step) = step.filter(|f| kept.is_none_or(|b| f.2 > b.2)) {
            *kept = Some(step);
        }
    }
    best.into_iter()
        .map(|(step, tried)| step.map(|(g, k, stat)| (g, k, stat, tried)))
        .collect()
}

/// The best change point in `passes` (pass group, position, statistic) and how many positions
/// were tried.
fn best_step_in(
    data: &Data,
    basis: &Schur,
    reduced: &Reduced,
    w: &[f64],
    res_w: &nalgebra::DVector<f64>,
    passes: &[usize],
) -> (Option<Step>, usize) {
    let mut best: Option<Step> = None;
    let mut tried = 0;
    // The suffix indicator's projection on the model, |P v|², in the split form of the
    // column space: per point q_pᵀ M_p⁺ q_p (q_p = Σ v_i a_i over its rows) plus |Σ v_i ρ_i|².
    let mut q: Vec<nalgebra::Vector3<f64>> =
        vec![nalgebra::Vector3::zeros(); basis.design().n_points()];
    let (mut rho, mut entries) = (nalgebra::DVector::zeros(reduced.dim()), Vec::new());
    for &g in passes {
        let members = &data.passes[g];
        // Walk the split from the end: the step column is the suffix indicator (whitened).
        let mut rho_sum: Option<nalgebra::DVector<f64>> = None;
        let mut point_part = 0.0;
        let (mut cc, mut cr) = (0.0, 0.0);
        for k in (1..members.len()).rev() {
            let i = members[k];
            let (p, a) = basis.row_parts(reduced, i, &mut rho, &mut entries);
            let m = basis.m_pinv(p);
            let old = q[p];
            let new = old + a * w[i];
            point_part += new.dot(&(m * new)) - old.dot(&(m * old));
            q[p] = new;
            match rho_sum.as_mut() {
                Some(sum) => sum.axpy(w[i], &rho, 1.0),
                None => rho_sum = Some(&rho * w[i]),
            }
            cc += w[i] * w[i];
            cr += w[i] * res_w[i];
            tried += 1;
            let proj = point_part + rho_sum.as_ref().map_or(0.0, |s| s.norm_squared());
            let perp = cc - proj;
            // A step that the nominal model absorbs (e.g. the whole pass) is not a candidate.
            if perp <= 1e-6 * cc {
                continue;
            }
            let stat = cr * cr / perp;
            if best.is_none_or(|b| stat > b.2) {
                best = Some((g, k, stat));
            }
        }
        for &i in members {
            q[data.obs[i].point] = nalgebra::Vector3::zeros();
        }
    }
    (best, tried)
}

/// The octant's name by the sign of each axis from the mean, e.g. `x+y-z+`.
pub fn octant_key(octant: usize) -> String {
    (0..3)
        .map(|a| {
            format!(
                "{}{}",
                ["x", "y", "z"][a],
                if octant >> a & 1 == 1 { "+" } else { "-" }
            )
        })
        .collect()
}

/// Groups whose whitened residuals exceed the noise model (family-wise level `alpha`).
pub fn locate(
    data: &Data,
    geom: &Geometry,
    resid_m: &[f64],
    basis: &Fit,
    alpha: f64,
) -> Vec<WhereEntry> {
    let nobs = data.obs.len();
    let leverage = basis.leverages();
    let mut groups: Vec<(&str, String, Vec<usize>)> = Vec::new();
    for (j, id) in data.station_ids.iter().enumerate() {
        let members = (0..nobs).filter(|&i| data.obs[i].station == j).collect();
        groups.push(("station", id.clone(), members));
    }
    let (t0, t1) = data
        .obs
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |a, o| {
            (a.0.min(o.t_s), a.1.max(o.t_s))
        });
    let span = (t1 - t0).max(1e-9);
    for b in 0..TIME_BLOCKS {
        let lo = t0 + span * b as f64 / TIME_BLOCKS as f64;
        let hi = t0 + span * (b + 1) as f64 / TIME_BLOCKS as f64;
        let members = (0..nobs)
            .filter(|&i| {
                let t = data.obs[i].t_s;
                t >= lo && (t < hi || b + 1 == TIME_BLOCKS)
            })
            .collect();
        groups.push(("time", format!("{lo:.0}-{hi:.0} s"), members));
    }
    for (a, axis) in ["x", "y", "z"].iter().enumerate() {
        for (s, sign) in [(1.0, "+"), (-1.0, "-")] {
            let members = (0..nobs)
                .filter(|&i| data.obs[i].approach_sign(a) == s)
                .collect();
            groups.push(("direction", format!("{axis}{sign}"), members));
        }
    }
    let centre: [f64; 3] = std::array::from_fn(|a| {
        data.obs
            .iter()
            .map(|o| data.points[o.point].2[a])
            .sum::<f64>()
            / nobs.max(1) as f64
    });
    for octant in 0..8 {
        let key = octant_key(octant);
        let members = (0..nobs)
            .filter(|&i| {
                let nominal_m = data.points[data.obs[i].point].2;
                (0..3).all(|a| (nominal_m[a] > centre[a]) == (octant >> a & 1 == 1))
            })
            .collect();
        groups.push(("region", key, members));
    }
    for (a, axis) in ["x", "y", "z"].iter().enumerate() {
        let members = (0..nobs)
            .filter(|&i| geom.beam(data, i).0.iamax() == a)
            .collect();
        groups.push(("axis", format!("beam along {axis}"), members));
    }
    let max_pass = data.obs.iter().map(|o| o.pass).max().unwrap_or(0);
    for p in 0..=max_pass {
        let members = (0..nobs).filter(|&i| data.obs[i].pass == p).collect();
        groups.push(("pass", format!("pass {p}"), members));
    }
    groups.retain(|g| !g.2.is_empty());

    let total_m2: f64 = resid_m
        .iter()
        .map(|r| r * r)
        .sum::<f64>()
        .max(f64::MIN_POSITIVE);
    let tests = groups.len() + data.station_ids.len();
    let mut out = Vec::new();
    for (group, key, members) in &groups {
        let stat: f64 = members
            .iter()
            .map(|&i| (resid_m[i] / data.obs[i].sigma_m).powi(2))
            .sum();
        // A residual's variance is (1 − leverage) σ²: the group's expected χ² and its dof.
        let dof: f64 = members.iter().map(|&i| (1.0 - leverage[i]).max(0.0)).sum();
        let p = (chi2_sf(stat, dof) * tests as f64).min(1.0);
        if p < alpha {
            let ss: f64 = members.iter().map(|&i| resid_m[i].powi(2)).sum();
            out.push(WhereEntry {
                level: "lengths".into(),
                group: (*group).into(),
                key: key.clone(),
                share: ss / total_m2,
                rms_m: (ss / members.len() as f64).sqrt(),
                p_value: p,
            });
        }
    }
    // Change points in each station's passes (a fringe loss, a bump of the stand).
    let res_w = nalgebra::DVector::from_fn(nobs, |i, _| resid_m[i] / data.obs[i].sigma_m);
    let stations: Vec<Option<usize>> = (0..data.station_ids.len()).map(Some).collect();
    for (g, k, stat, tried) in best_steps(data, basis, &res_w, &stations)
        .into_iter()
        .flatten()
    {
        let p = (chi2_sf(stat, 1.0) * (tried * tests) as f64).min(1.0);
        if p < alpha {
            let members = &data.passes[g][k..];
            let ss: f64 = members.iter().map(|&i| resid_m[i].powi(2)).sum();
            out.push(WhereEntry {
                level: "lengths".into(),
                group: "time".into(),
                key: format!(
                    "change point in {} at {:.1} s",
                    data.pass_names[g], data.obs[members[0]].t_s
                ),
                share: ss / total_m2,
                rms_m: (ss / members.len() as f64).sqrt(),
                p_value: p,
            });
        }
    }
    out.sort_by(|a, b| b.share.total_cmp(&a.share));
    out
}
