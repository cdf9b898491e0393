//! Twin comparison: a recording diagnosed against its simulated twin (a second session, or a
//! config simulated with the recording's solved stations and effects off), lengths and points.

pub use crate::diagnose::lengths::{TwinPointsGap, TwinReport};

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use nalgebra::{DMatrix, DVector};

use super::data::Data;
use super::points::{effect_point_move, per_pass_points, point_departures, test_groups, PointMeta};
use super::stats::{chi2_sf, Basis, EFFECT_RANK_TOL};
use super::{
    diagnose_data, hcat, DataDiagnosis, DiagnoseError, DiagnoseOptions, Diagnosis,
    StandardisedResiduals,
};
use crate::config::{Config, DriverKind};
use crate::session::reader::{read_session, Session};
use crate::solve::multilateration::{solve, SolveOptions};

/// Noise seed of a twin simulated from a config: its own draws, the config's machine.
const TWIN_NOISE_SEED: u64 = 0x5457_494e; // "TWIN"

/// Key of a length across two sessions of the same plan.
type LengthKey = (String, String, usize, usize, usize);

fn length_keys(data: &Data) -> Vec<LengthKey> {
    let mut seen: BTreeMap<(String, String, usize, usize), usize> = BTreeMap::new();
    data.obs
        .iter()
        .map(|o| {
            let (target, point, _) = &data.points[o.point];
            let base = (
                data.station_ids[o.station].clone(),
                target.clone(),
                *point,
                o.pass,
            );
            let k = seen.entry(base.clone()).or_insert(0);
            *k += 1;
            (base.0, base.1, base.2, base.3, *k - 1)
        })
        .collect()
}

/// Per-pass points of `lengths_m`, keyed by (target, plan point, pass): position, covariance
/// index and approach.
struct KeyedPoints {
    keys: BTreeMap<(String, usize, usize), usize>,
    per_pass: super::points::PerPass,
}

fn keyed_points(data: &Data, lengths_m: &[f64]) -> Result<KeyedPoints, String> {
    let per_pass = per_pass_points(data, lengths_m)?;
    let keys = per_pass
        .pass_points
        .iter()
        .zip(&per_pass.info)
        .enumerate()
        .map(|(k, (p, i))| ((i.0.clone(), i.1, p.pass), k))
        .collect();
    Ok(KeyedPoints { keys, per_pass })
}

/// The recording's points against the twin's: difference, joint covariance, bookkeeping.
fn compare_points(
    rec: &KeyedPoints,
    twin: &KeyedPoints,
) -> (DVector<f64>, DMatrix<f64>, Vec<(usize, usize)>) {
    let pairs: Vec<(usize, usize)> = rec
        .keys
        .iter()
        .filter_map(|(key, &a)| twin.keys.get(key).map(|&b| (a, b)))
        .collect();
    let n = pairs.len();
    let d = DVector::from_fn(3 * n, |r, _| {
        let (a, b) = pairs[r / 3];
        rec.per_pass.solution.points[a][r % 3] - twin.per_pass.solution.points[b][r % 3]
    });
    let c = DMatrix::from_fn(3 * n, 3 * n, |r, s| {
        let (a1, b1) = pairs[r / 3];
        let (a2, b2) = pairs[s / 3];
        rec.per_pass.cov[(3 * a1 + r % 3, 3 * a2 + s % 3)]
            + twin.per_pass.cov[(3 * b1 + r % 3, 3 * b2 + s % 3)]
    });
    (d, c, pairs)
}

/// Whitening W = Λ^-1/2 Vᵀ of a covariance on its informative directions (the 6 rigid
/// motions of the inner-constraint datum carry none): WᵀW is its pseudo-inverse.
fn whitening(c: &DMatrix<f64>) -> DMatrix<f64> {
    let eigen = c.clone().symmetric_eigen();
    let largest = eigen.eigenvalues.amax();
    let kept: Vec<usize> = (0..eigen.eigenvalues.len())
        .filter(|&k| eigen.eigenvalues[k] > 1e-9 * largest && eigen.eigenvalues[k] > 0.0)
        .collect();
    DMatrix::from_fn(kept.len(), c.nrows(), |r, col| {
        let k = kept[r];
        eigen.eigenvectors[(col, k)] / eigen.eigenvalues[k].sqrt()
    })
}

/// The gap of the differences `d` (covariance `c`, whitened by `w`).
fn points_gap(d: &DVector<f64>, c: &DMatrix<f64>, w: &DMatrix<f64>) -> TwinPointsGap {
    let chi2 = (w * d).norm_squared();
    let dof = w.nrows();
    let rows = d.len().max(1) as f64;
    TwinPointsGap {
        chi2,
        dof,
        chi2_per_dof: chi2 / dof.max(1) as f64,
        p_value: chi2_sf(chi2, dof as f64),
        rms_m: (d.norm_squared() / rows).sqrt(),
        floor_m: (c.trace().max(0.0) / rows).sqrt(),
        points: d.len() / 3,
    }
}

/// Columns of a constant shift of each target's points after the first (`targets`: the
/// target of each point, 3 rows per point).
fn target_shift_columns(targets: &[&str]) -> DMatrix<f64> {
    let mut names: Vec<&str> = targets.to_vec();
    names.sort_unstable();
    names.dedup();
    let shifted = names.get(1..).unwrap_or_default();
    DMatrix::from_fn(3 * targets.len(), 3 * shifted.len(), |row, col| {
        f64::from(u8::from(
            shifted[col / 3] == targets[row / 3] && row % 3 == col % 3,
        ))
    })
}

/// Fit the columns `a` to `d` (whitened by `w`) as free parameters and remove them; returns
/// the number of directions fitted: those whose Mahalanobis size exceeds EFFECT_RANK_TOL of
/// the largest (or of `reference`).
fn remove_columns(
    d: &mut DVector<f64>,
    w: &DMatrix<f64>,
    a: &DMatrix<f64>,
    reference: f64,
) -> usize {
    if a.ncols() == 0 {
        return 0;
    }
    let basis = Basis::new(&(w * a), EFFECT_RANK_TOL, reference);
    let beta = basis.solve(&(w * &*d));
    *d -= a * beta;
    basis.rank()
}

/// Diagnose `recording` against `twin`: every matched recorded length has the twin's residual
/// (its departure from the nominal model: whatever the simulation puts there beyond the
/// geometry) removed and both noise models in its sigma; then the usual where/which/how far.
/// The points of both (per pass) are compared directly, before and after the selected effects.
pub fn diagnose_against_twin(
    recording: &Session,
    twin: &Session,
    source: &str,
    options: &DiagnoseOptions,
) -> Result<Diagnosis, DiagnoseError> {
    Ok(diagnose_against_twin_detailed(recording, twin, source, options)?.0)
}

/// [`diagnose_against_twin`] with the standardised residuals of the twin-corrected lengths.
pub fn diagnose_against_twin_detailed(
    recording: &Session,
    twin: &Session,
    source: &str,
    options: &DiagnoseOptions,
) -> Result<(Diagnosis, StandardisedResiduals), DiagnoseError> {
    let rec = Data::from_session(recording)?;
    let tw = Data::from_session(twin)?;
    let twin_fit = solve(&tw.problem, &SolveOptions::default())?;
    let twin_index: BTreeMap<LengthKey, usize> = length_keys(&tw)
        .into_iter()
        .enumerate()
        .map(|(i, k)| (k, i))
        .collect();
    let mut data = rec.clone();
    let mut matched = 0;
    for (i, key) in length_keys(&rec).iter().enumerate() {
        if let Some(&j) = twin_index.get(key) {
            matched += 1;
            let sigma = rec.obs[i].sigma_m.hypot(tw.obs[j].sigma_m);
            let length = rec.obs[i].length_m - twin_fit.residuals_m[j];
            data.obs[i].length_m = length;
            data.obs[i].sigma_m = sigma;
            data.problem.observations[i].length_m = length;
            data.problem.observations[i].sigma_m = sigma;
        }
    }
    let unmatched = rec.obs.len() - matched;
    // The recording's calibration was solved on its own lengths: the corrected ones are
    // solved again.
    data.nominal = None;
    let DataDiagnosis {
        mut diagnosis,
        effect_m,
        effect_columns,
        residuals,
        mut progress,
    } = diagnose_data(&mut data, options)?;

    let recorded: Vec<f64> = rec.obs.iter().map(|o| o.length_m).collect();
    let twin_lengths: Vec<f64> = tw.obs.iter().map(|o| o.length_m).collect();
    let mut report = TwinReport {
        session_id: tw.session_id.clone(),
        source: source.into(),
        matched_lengths: matched,
        unmatched_lengths: unmatched,
        points_before: None,
        points_after: None,
        departures: Vec::new(),
    };
    match (
        keyed_points(&rec, &recorded),
        keyed_points(&tw, &twin_lengths),
    ) {
        (Ok(rp), Ok(tp)) => {
            let (d, c, pairs) = compare_points(&rp, &tp);
            let meta: Vec<PointMeta> = pairs
                .iter()
                .map(|&(a, _)| (&rp.per_pass.pass_points[a], &rp.per_pass.info[a]))
                .collect();
            diagnosis
                .where_
                .extend(test_groups(&d, &c, &meta, options.alpha, " vs twin"));
            report.departures = point_departures(&d, &c, &meta, options.alpha);
            report.points_before = Some(points_gap(&d, &c, &whitening(&c)));
            let corrected: Vec<f64> = recorded.iter().zip(&effect_m).map(|(l, e)| l - e).collect();
            if let Ok(after) = keyed_points(&rec, &corrected) {
                let (mut d, c, pairs) = compare_points(&after, &tp);
                let w = whitening(&c);
                // The selected lengths-level effects' estimates are uncertain and move the
                // points along their response: fitted as free columns (as the points level
                // does). target_offset is a points-level effect, not in the lengths'
                // contribution: when it is named, each target's (after the first) constant
                // shift is fitted too.
                let rows: Vec<usize> = pairs.iter().flat_map(|&(a, _)| 3 * a..3 * a + 3).collect();
                let (response, reference) = if effect_columns.ncols() > 0 {
                    effect_point_move(&rec, &after.per_pass, &effect_columns)
                        .map(|(k, reference)| (k.select_rows(&rows), reference))
                        .unwrap_or_else(|| (DMatrix::zeros(rows.len(), 0), 0.0))
                } else {
                    (DMatrix::zeros(rows.len(), 0), 0.0)
                };
                let shifts = if diagnosis.selected.iter().any(|s| s == "target_offset") {
                    let targets: Vec<&str> = pairs
                        .iter()
                        .map(|&(a, _)| after.per_pass.info[a].0.as_str())
                        .collect();
                    target_shift_columns(&targets)
                } else {
                    DMatrix::zeros(rows.len(), 0)
                };
                let columns = hcat(&response, &shifts);
                let df = if columns.ncols() > 0 {
                    remove_columns(&mut d, &w, &columns, reference)
                } else {
                    0
                };
                let mut gap = points_gap(&d, &c, &w);
                if df > 0 {
                    gap.dof = gap.dof.saturating_sub(df);
                    gap.chi2_per_dof = gap.chi2 / gap.dof.max(1) as f64;
                    gap.p_value = chi2_sf(gap.chi2, gap.dof as f64);
                }
                if gap.p_value < options.alpha {
                    diagnosis.unexplained = true;
                    diagnosis.notes.push(format!(
                        "the recording's points still depart from the twin's after the selected effects: chi2/dof {:.2} (p = {:.1e})",
                        gap.chi2_per_dof, gap.p_value
                    ));
                }
                report.points_after = Some(gap);
            }
        }
        (Err(why), _) | (_, Err(why)) => diagnosis
            .notes
            .push(format!("points not compared with the twin: {why}")),
    }
    diagnosis.notes.push(format!(
        "against the twin {} ({source}): {matched} lengths matched, {unmatched} diagnosed against the model alone",
        tw.session_id
    ));
    diagnosis.twin = Some(report);
    progress.finish();
    Ok((diagnosis, residuals))
}

/// Simulate the twin of `recording` from `config_path`: the config's plan, machine and noise
/// model, the tracer stations where the recording's solve puts them, every effect off, noise
/// of its own seed. Writes `out_dir/session.mcap` and returns its path.
pub fn simulate_twin(
    recording: &Session,
    config_path: &Path,
    out_dir: &Path,
) -> anyhow::Result<PathBuf> {
    let mut config = Config::load(config_path)?;
    let Some(sim) = config.sim.as_mut() else {
        bail!(
            "{}: no [sim] section: the twin needs the simulated world's machine and noise model",
            config_path.display()
        );
    };
    sim.effects = Default::default();
    sim.station_hint_error_m = 0.0;
    sim.noise_seed = Some(sim.seed ^ TWIN_NOISE_SEED);
    config.hil = None;
    config.devices.tracer.driver = DriverKind::Sim;
    config.devices.machine.driver = DriverKind::Sim;
    if let Some(env) = config.devices.environment.as_mut() {
        env.driver = DriverKind::Sim;
    }
    let (results, _) =
        crate::method::multilateration::solve_detailed(recording, &Default::default())
            .context("solving the recording for its stations")?;
    for station in &mut config.plan.stations {
        let solved = results
            .stations
            .iter()
            .find(|s| s.id == station.id)
            .with_context(|| {
                format!(
                    "{}: plan station `{}` is not in the recording",
                    config_path.display(),
                    station.id
                )
            })?;
        station.hint_m = Some(solved.position_m);
    }
    let output = crate::kinds::tracer_plan::run::run(
        &config,
        &crate::run::RunOptions {
            out_dir: out_dir.to_path_buf(),
            truth: None,
            progress: false,
            settings: Default::default(),
            control: Default::default(),
        },
    )
    .with_context(|| format!("simulating the twin from {}", config_path.display()))?;
    Ok(output.session_path)
}

/// `geocal diagnose SESSION --twin TWIN`: TWIN is a session file, or a config (`.toml`) whose
/// simulated twin is written to `twin_dir` (a temporary directory when `None`).
pub fn diagnose_file_with_twin(
    path: &Path,
    twin: &Path,
    twin_dir: Option<&Path>,
    options: &DiagnoseOptions,
) -> anyhow::Result<Diagnosis> {
    Ok(diagnose_file_with_twin_detailed(path, twin, twin_dir, options)?.0)
}

/// [`diagnose_file_with_twin`] with the standardised residuals of the twin-corrected lengths.
pub fn diagnose_file_with_twin_detailed(
    path: &Path,
    twin: &Path,
    twin_dir: Option<&Path>,
    options: &DiagnoseOptions,
) -> anyhow::Result<(Diagnosis, StandardisedResiduals)> {
    let recording = read_session(path).with_context(|| format!("reading {}", path.display()))?;
    // Before simulating a twin: a kind without a diagnosis model fails here, clearly.
    super::data::check_kind(&recording.header.kind)
        .with_context(|| format!("diagnosing {}", path.display()))?;
    let is_config = twin.extension().is_some_and(|e| e == "toml");
    let (twin_session, source) = if is_config {
        // Without a directory given, a scratch one, removed when `scratch` drops (after the read).
        let scratch;
        let dir: &Path = match twin_dir {
            Some(d) => d,
            None => {
                scratch = tempfile::Builder::new()
                    .prefix("geocal-twin-")
                    .tempdir()
                    .context("creating a scratch directory for the twin")?;
                scratch.path()
            }
        };
        let twin_path = simulate_twin(&recording, twin, dir);
        let session = twin_path.and_then(|p| {
            read_session(&p).with_context(|| format!("reading the twin {}", p.display()))
        });
        (session?, "config")
    } else {
        let session =
            read_session(twin).with_context(|| format!("reading the twin {}", twin.display()))?;
        (session, "session")
    };
    diagnose_against_twin_detailed(&recording, &twin_session, source, options)
        .with_context(|| format!("diagnosing {} against {}", path.display(), twin.display()))
}
