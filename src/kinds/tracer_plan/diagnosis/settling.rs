//! The settling effect: an axis offset along the approach direction that decays after each
//! move, tested on the raw samples inside the dwell windows (their trend), not on the means.

use nalgebra::{Matrix3, Vector3};

use super::data::Data;
use super::effects::Geometry;
use super::stats::f_sf;
use crate::parallel;

/// Time constants searched (s); Bonferroni over them.
pub const TAU_GRID_S: [f64; 11] = [0.1, 0.15, 0.2, 0.3, 0.5, 0.7, 1.0, 1.5, 2.0, 3.0, 5.0];
/// Cross-validation folds over windows.
const FOLDS: usize = 5;

/// The settling model at one time constant on every usable window.
#[derive(Debug, Clone)]
pub struct SettlingFit {
    pub tau_s: f64,
    /// Offset per axis at arrival (m) and its standard deviation.
    pub s_m: [f64; 3],
    pub s_sigma_m: [f64; 3],
    /// Identifiable parameters (axes that moved into some window).
    pub df: usize,
    pub windows: usize,
    /// Within-window deviations (sample minus its window mean), independent ones.
    pub dof: usize,
    pub chi2_base: f64,
    pub chi2_drop: f64,
    /// F test, Bonferroni over the time constants.
    pub p_value: f64,
    /// Profiled BIC of the within-window block (time constant counted as a parameter).
    pub bic_delta: f64,
    /// RMS of the within-window deviations after the fit, and the held-out mean squares
    /// (window folds) without and with the effect.
    pub rms_after_m: f64,
    pub heldout_ms_base_m2: f64,
    pub heldout_ms_after_m2: f64,
    /// Per observation: the settling bias of its window mean (0 where not modelled).
    pub bias_m: Vec<f64>,
}

/// Per observation: the sign of each axis's move into its window (None for a pass's first
/// window, whose arrival preceded the homing, and for windows without raw samples).
fn moves(data: &Data) -> Vec<Option<[f64; 3]>> {
    let mut out = vec![None; data.obs.len()];
    for members in &data.passes {
        for pair in members.windows(2) {
            let (prev, i) = (&data.obs[pair[0]], pair[1]);
            if data.obs[i].home == i || data.windows[i].is_none() {
                continue;
            }
            let d: [f64; 3] = std::array::from_fn(|a| {
                let step = data.obs[i].axes_m[a] - prev.axes_m[a];
                if step.abs() > 1e-9 {
                    step.signum()
                } else {
                    0.0
                }
            });
            out[i] = Some(d);
        }
    }
    out
}

/// Rows of one window at time constant tau: whitened deviations d/σ and regressors
/// c_a·(e(t) − ē)/σ with c_a = −u_a·sign_a (a target shift δX changes the length by −u·δX),
/// and ē·c_a, the mean's bias per unit offset.
#[derive(Default)]
struct WindowRows {
    obs: usize,
    d: Vec<f64>,
    x: Vec<[f64; 3]>,
    mean_col: [f64; 3],
}

/// A window's rows at time constant `tau_s` into `out` (its buffers reused): window `i`,
/// whose axes moved into it with signs `sign`.
fn window_rows(
    data: &Data,
    geom: &Geometry,
    (i, sign): (usize, [f64; 3]),
    tau_s: f64,
    out: &mut WindowRows,
) {
    out.obs = i;
    out.d.clear();
    out.x.clear();
    let Some(w) = &data.windows[i] else {
        return;
    };
    let n = w.samples.len();
    let (u, _) = geom.beam(data, i);
    let c: [f64; 3] = std::array::from_fn(|a| -u[a] * sign[a]);
    let sigma = data.obs[i].sigma_m * (n as f64).sqrt();
    let decay = |t: f64| (-(t - w.arrival_s).max(0.0) / tau_s).exp();
    let e_mean = w.samples.iter().map(|(t, _)| decay(*t)).sum::<f64>() / n as f64;
    let y_mean = w.samples.iter().map(|s| s.1).sum::<f64>() / n as f64;
    for &(t, y) in &w.samples {
        let ek = decay(t);
        out.d.push((y - y_mean) / sigma);
        out.x
            .push(std::array::from_fn(|a| c[a] * (ek - e_mean) / sigma));
    }
    out.mean_col = std::array::from_fn(|a| c[a] * e_mean);
}

/// The windows settling is tested on: those with raw samples that some axis moved into, with
/// the moves' signs.
fn usable_windows(data: &Data) -> Vec<(usize, [f64; 3])> {
    moves(data)
        .into_iter()
        .enumerate()
        .filter_map(|(i, sign)| Some((i, sign?)))
        .filter(|&(i, _)| data.windows[i].is_some())
        .collect()
}

/// A pass's first window follows the homing dwell, and the arrival before it is not in the
/// session: its settling amplitude is unknown. It gets its own amplitude k (fitted to its
/// trend at the shared time constant, e measured from the window's first sample), and its
/// mean's bias is k·ē. These nuisance fits do not enter the test.
fn home_biases(data: &Data, tau_s: f64, bias_m: &mut [f64]) {
    for (i, o) in data.obs.iter().enumerate() {
        let Some(w) = data.windows[i].as_ref().filter(|_| o.home == i) else {
            continue;
        };
        let n = w.samples.len() as f64;
        let e: Vec<f64> = w
            .samples
            .iter()
            .map(|(t, _)| (-(t - w.arrival_s).max(0.0) / tau_s).exp())
            .collect();
        let e_mean = e.iter().sum::<f64>() / n;
        let y_mean = w.samples.iter().map(|s| s.1).sum::<f64>() / n;
        let (mut xx, mut xy) = (0.0, 0.0);
        for (ek, (_, y)) in e.iter().zip(&w.samples) {
            xx += (ek - e_mean).powi(2);
            xy += (ek - e_mean) * (y - y_mean);
        }
        if xx > 0.0 {
            bias_m[i] = xy / xx * e_mean;
        }
    }
}

/// XᵀX, Xᵀd, dᵀd and the sample count of a set of windows' rows.
#[derive(Clone, Copy)]
struct Normal {
    xtx: Matrix3<f64>,
    xtd: Vector3<f64>,
    dtd: f64,
    n: usize,
}

impl Normal {
    fn zero() -> Normal {
        Normal {
            xtx: Matrix3::zeros(),
            xtd: Vector3::zeros(),
            dtd: 0.0,
            n: 0,
        }
    }

    fn add(&mut self, other: &Normal) {
        self.xtx += other.xtx;
        self.xtd += other.xtd;
        self.dtd += other.dtd;
        self.n += other.n;
    }
}

/// The normal equations of each fold's windows (window k in fold k mod `FOLDS`), built in one
/// pass: the full fit's and every fold's training set are sums of them.
fn fold_normals(
    data: &Data,
    geom: &Geometry,
    usable: &[(usize, [f64; 3])],
    tau_s: f64,
) -> [Normal; FOLDS] {
    let mut out = [Normal::zero(); FOLDS];
    let mut w = WindowRows::default();
    for (k, &window) in usable.iter().enumerate() {
        window_rows(data, geom, window, tau_s, &mut w);
        let part = &mut out[k % FOLDS];
        for (d, x) in w.d.iter().zip(&w.x) {
            let x = Vector3::from(*x);
            part.xtx += x * x.transpose();
            part.xtd += x * *d;
            part.dtd += d * d;
            part.n += 1;
        }
    }
    out
}

/// The sum of the folds' normal equations, fold `skip` left out.
fn sum_normals(parts: &[Normal; FOLDS], skip: Option<usize>) -> Normal {
    let mut sum = Normal::zero();
    for (f, part) in parts.iter().enumerate() {
        if Some(f) != skip {
            sum.add(part);
        }
    }
    sum
}

fn solve3(xtx: &Matrix3<f64>, xtd: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>, usize) {
    let eig = xtx.symmetric_eigen();
    let top = eig.eigenvalues.amax();
    let (mut s, mut var, mut rank) = (Vector3::zeros(), Vector3::zeros(), 0);
    for k in 0..3 {
        let l = eig.eigenvalues[k];
        if l > 1e-10 * top && l > 0.0 {
            let v = eig.eigenvectors.column(k);
            s += v * (v.dot(xtd) / l);
            var += v.component_mul(&v) / l;
            rank += 1;
        }
    }
    (s, var, rank)
}

/// Threads the time constants' walks over the raw samples run on.
const MAX_THREADS: usize = 2;

/// Fit settling at every time constant of the grid and return the best (largest χ² drop),
/// or None when no window can show it (no raw samples, or no axis moved into a window).
pub fn evaluate(data: &Data, geom: &Geometry) -> Option<SettlingFit> {
    // Each window's rows are made again where needed rather than held for every window: the
    // raw samples of a large session would take several times their own memory.
    let usable = usable_windows(data);
    if usable.is_empty() {
        return None;
    }
    // Each time constant's normal equations (one walk over the raw samples), on the cores.
    let normals = parallel::in_groups(&TAU_GRID_S, parallel::threads(MAX_THREADS), |&tau_s| {
        fold_normals(data, geom, &usable, tau_s)
    });
    // The largest χ² drop, the first of equal ones.
    let mut best: Option<(usize, f64)> = None;
    for (t, parts) in normals.iter().enumerate() {
        let Normal { xtx, xtd, .. } = sum_normals(parts, None);
        let (s, _, df) = solve3(&xtx, &xtd);
        if df == 0 {
            return None;
        }
        let chi2_drop = s.dot(&xtd);
        if !best.is_some_and(|(_, b)| b >= chi2_drop) {
            best = Some((t, chi2_drop));
        }
    }
    let (t, _) = best?;
    Some(fit_at(data, geom, &usable, TAU_GRID_S[t], &normals[t]))
}

/// The settling fit at time constant `tau_s`, from its folds' normal equations `parts`.
fn fit_at(
    data: &Data,
    geom: &Geometry,
    usable: &[(usize, [f64; 3])],
    tau_s: f64,
    parts: &[Normal; FOLDS],
) -> SettlingFit {
    let Normal { xtx, xtd, dtd, n } = sum_normals(parts, None);
    let (s, var, df) = solve3(&xtx, &xtd);
    let chi2_drop = s.dot(&xtd);
    let windows = usable.len();
    let dof = n.saturating_sub(windows).max(df + 1);
    let chi2_after = (dtd - chi2_drop).max(f64::MIN_POSITIVE);
    let dof_after = (dof - df) as f64;
    let f_stat = (chi2_drop / df as f64) / (chi2_after / dof_after);
    let p_value = (f_sf(f_stat, df as f64, dof_after) * TAU_GRID_S.len() as f64).min(1.0);
    let bic_delta = dof as f64 * (chi2_after / dtd).ln() + (df + 1) as f64 * (dof as f64).ln();
    // Held out: each fold's windows scored by the fit on the other windows. In the same
    // walk, each window mean's bias and the residuals after the full fit.
    let fold_fits: Vec<Vector3<f64>> = (0..FOLDS)
        .map(|f| {
            let train = sum_normals(parts, Some(f));
            solve3(&train.xtx, &train.xtd).0
        })
        .collect();
    let (mut ms_base, mut ms_after, mut held, mut ss) = (0.0, 0.0, 0usize, 0.0);
    let mut bias_m = vec![0.0; data.obs.len()];
    let mut w = WindowRows::default();
    for (k, &window) in usable.iter().enumerate() {
        window_rows(data, geom, window, tau_s, &mut w);
        let sf = &fold_fits[k % FOLDS];
        let sigma = data.obs[w.obs].sigma_m * (w.d.len() as f64).sqrt();
        for (d, x) in w.d.iter().zip(&w.x) {
            let x = Vector3::from(*x);
            ms_base += (d * sigma).powi(2);
            ms_after += ((d - x.dot(sf)) * sigma).powi(2);
            ss += ((d - x.dot(&s)) * sigma).powi(2);
            held += 1;
        }
        bias_m[w.obs] = (0..3).map(|a| w.mean_col[a] * s[a]).sum();
    }
    home_biases(data, tau_s, &mut bias_m);
    let rms_after_m = (ss / n.max(1) as f64).sqrt();
    SettlingFit {
        tau_s,
        s_m: s.into(),
        s_sigma_m: var.map(f64::sqrt).into(),
        df,
        windows,
        dof,
        chi2_base: dtd,
        chi2_drop,
        p_value,
        bic_delta,
        rms_after_m,
        heldout_ms_base_m2: ms_base / held.max(1) as f64,
        heldout_ms_after_m2: ms_after / held.max(1) as f64,
        bias_m,
    }
}
