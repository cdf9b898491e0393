//! The rotary tracer's effect library for `geocal diagnose` (docs/diagnosis.md, "rotary_tracer"):
//! the tracer network's effects (`station_drift`, `air_refraction`, `length_step`, modelled by
//! the multilateration library), the tracer's eccentricity turning with the table (on the
//! lengths), and the table's error motions (on the solved table stations against their circle:
//! a free station absorbs any displacement of the pivot, so the lengths cannot show them).

use nalgebra::{DMatrix, DVector, Vector3};

use crate::method::tracer_effects::{
    BeamObservation, LengthEffect, NetworkSession, SolvedStations, StationResidual, StationsLevel,
    TracerNetworkDiagnosis,
};
use crate::solve::circle::fit_circle;

pub const TABLE_ERROR_MOTION: &str = "table_error_motion";
pub const TRACER_ECCENTRICITY: &str = "tracer_eccentricity";

/// The library, in the order candidates are listed.
pub const LIBRARY: &[&str] = &[
    TABLE_ERROR_MOTION,
    TRACER_ECCENTRICITY,
    "station_drift",
    "air_refraction",
    "length_step",
];

/// Highest harmonics of the table angle in `table_error_motion`: an error motion of harmonic
/// k (a radial motion of the axis, a 2-vector in the plane; a tilt) moves a pivot turning with
/// the table by harmonics k − 1 and k + 1 along its radius, so the outside recorders' and the
/// simulator's motions of harmonics 2-4 (tilts 2-3) reach radial 5 and axial 4. Fewer when the
/// table stations cannot carry them.
pub const MAX_RADIAL_HARMONIC: u32 = 5;
pub const MAX_AXIAL_HARMONIC: u32 = 4;

/// Degrees of freedom the stations level keeps beside the circle and the error motions.
const MIN_STATIONS_DOF: i64 = 4;

pub struct RotaryTracerDiagnosis;

pub static DIAGNOSIS: RotaryTracerDiagnosis = RotaryTracerDiagnosis;

/// The plan's axis direction (the commanded angles turn right-handed about it); z when the
/// header does not say.
fn plan_axis(session: &NetworkSession<'_>) -> Vector3<f64> {
    let axis = &session.header.plan["rotary"]["axis_direction"];
    let v = Vector3::from_fn(|k, _| axis[k].as_f64().unwrap_or(if k == 2 { 1.0 } else { 0.0 }));
    if v.norm() > 0.0 && v.iter().all(|c| c.is_finite()) {
        v.normalize()
    } else {
        Vector3::z()
    }
}

/// The table's plane: e1 = x projected on it (y when x lies along n), e2 = n × e1.
fn plane_basis(n: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>) {
    let x = if n.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let e1 = (x - n * n.dot(&x)).normalize();
    (e1, n.cross(&e1))
}

/// Per station of the session: its commanded table angle, None off the table.
fn table_angles(session: &NetworkSession<'_>) -> Vec<Option<f64>> {
    session
        .station_ids
        .iter()
        .map(|id| {
            session
                .rotations
                .iter()
                .find(|(s, _)| s == id)
                .map(|&(_, a)| a)
        })
        .collect()
}

/// The tracer's eccentricity (its beam pivot off its rotation centre), fixed in the tracer:
/// length error e·cos(az − φ0) + ez·sin(el) of the beam leaving the station. On the table the
/// tracer turns with it, so one (e cos φ0, e sin φ0, ez) in the table's frame serves every
/// table station: az = azimuth about the axis (from e1) less the commanded table angle, el
/// from the table's plane. A station off the table has its own, in machine azimuth.
#[derive(Debug)]
pub struct TurningEccentricity {
    axis: Vector3<f64>,
    angles: Vec<Option<f64>>,
    /// Column block of each station: 0 the table's, 1.. the off-table stations'.
    block: Vec<usize>,
    names: Vec<String>,
}

impl TurningEccentricity {
    pub fn of(session: &NetworkSession<'_>) -> Result<TurningEccentricity, String> {
        let angles = table_angles(session);
        if angles.iter().all(Option::is_none) {
            return Err("no station stood on the table (no `rotation` events)".into());
        }
        let mut names: Vec<String> = ["e_cos_phi0_m", "e_sin_phi0_m", "ez_m"]
            .iter()
            .map(|n| format!("table.{n}"))
            .collect();
        let mut block = Vec::new();
        for (id, angle) in session.station_ids.iter().zip(&angles) {
            if angle.is_some() {
                block.push(0);
            } else {
                block.push(names.len() / 3);
                names.extend(
                    ["e_cos_phi0_m", "e_sin_phi0_m", "ez_m"]
                        .iter()
                        .map(|n| format!("{id}.{n}")),
                );
            }
        }
        Ok(TurningEccentricity {
            axis: plan_axis(session),
            angles,
            block,
            names,
        })
    }
}

impl LengthEffect for TurningEccentricity {
    fn name(&self) -> &'static str {
        TRACER_ECCENTRICITY
    }

    fn param_names(&self) -> Vec<String> {
        self.names.clone()
    }

    fn absolute(&self, obs: &[BeamObservation]) -> DMatrix<f64> {
        let (e1, e2) = plane_basis(&self.axis);
        let mut f = DMatrix::zeros(obs.len(), self.names.len());
        for (i, o) in obs.iter().enumerate() {
            let b = o.beam;
            let (az, el) = match self.angles.get(o.station).copied().flatten() {
                Some(angle) => (
                    b.dot(&e2).atan2(b.dot(&e1)) - angle,
                    b.dot(&self.axis).clamp(-1.0, 1.0).asin(),
                ),
                None => (b.y.atan2(b.x), b.z.clamp(-1.0, 1.0).asin()),
            };
            let c = 3 * self.block.get(o.station).copied().unwrap_or(0);
            f[(i, c)] = az.cos();
            f[(i, c + 1)] = az.sin();
            f[(i, c + 2)] = el.sin();
        }
        f
    }
}

impl TracerNetworkDiagnosis for RotaryTracerDiagnosis {
    fn library(&self) -> &'static [&'static str] {
        LIBRARY
    }

    fn length_effect(
        &self,
        name: &str,
        session: &NetworkSession<'_>,
    ) -> Option<Result<Box<dyn LengthEffect>, String>> {
        (name == TRACER_ECCENTRICITY)
            .then(|| TurningEccentricity::of(session).map(|e| Box::new(e) as Box<dyn LengthEffect>))
    }

    fn stations_effect(&self) -> Option<&'static str> {
        Some(TABLE_ERROR_MOTION)
    }

    fn stations_level(
        &self,
        session: &NetworkSession<'_>,
        stations: &SolvedStations<'_>,
    ) -> Result<Option<StationsLevel>, String> {
        table_error_motion(session, stations)
    }

    fn station_label(&self, session: &NetworkSession<'_>, station: &str) -> Option<String> {
        let angle = session
            .rotations
            .iter()
            .find(|(s, _)| s == station)
            .map(|&(_, a)| a)?;
        Some(format!("{station} at {:.1}°", angle.to_degrees()))
    }
}

/// Pseudo-inverse of a symmetric positive semi-definite matrix (eigenvalues below 1e-12 of
/// the largest dropped) and its rank.
fn psd_pinv(m: &DMatrix<f64>) -> (DMatrix<f64>, usize) {
    let eig = m.clone().symmetric_eigen();
    let top = eig.eigenvalues.iter().copied().fold(0.0f64, f64::max);
    let mut inv = DMatrix::zeros(m.nrows(), m.ncols());
    let mut rank = 0;
    for (k, &l) in eig.eigenvalues.iter().enumerate() {
        if l > 1e-12 * top && l > 0.0 {
            let v = eig.eigenvectors.column(k);
            inv += (v * v.transpose()) / l;
            rank += 1;
        }
    }
    (inv, rank)
}

/// Generalised least squares of y on X with weight W = C⁺: (β, Cov β, residual, χ², rank X).
struct Gls {
    beta: DVector<f64>,
    cov: DMatrix<f64>,
    residual: DVector<f64>,
    chi2: f64,
    rank: usize,
}

fn gls(y: &DVector<f64>, x: &DMatrix<f64>, weight: &DMatrix<f64>) -> Gls {
    let normal = x.transpose() * weight * x;
    let (cov, rank) = psd_pinv(&normal);
    let beta = &cov * (x.transpose() * weight * y);
    let residual = y - x * &beta;
    let chi2 = (residual.transpose() * weight * &residual)[(0, 0)];
    Gls {
        beta,
        cov,
        residual,
        chi2,
        rank,
    }
}

/// Held-out: each station's two components predicted from the others (the best linear
/// unbiased prediction, correlations through the shared points included), in units of its
/// prediction covariance; the RMS over stations of √(z²/2).
fn heldout_ratio(y: &DVector<f64>, x: &DMatrix<f64>, c: &DMatrix<f64>, m: usize) -> f64 {
    let mut z2 = 0.0;
    let mut counted = 0;
    for j in 0..m {
        let held = [2 * j, 2 * j + 1];
        let kept: Vec<usize> = (0..2 * m).filter(|r| !held.contains(r)).collect();
        let pick = |rows: &[usize], cols: &[usize], a: &DMatrix<f64>| {
            DMatrix::from_fn(rows.len(), cols.len(), |r, k| a[(rows[r], cols[k])])
        };
        let all_cols: Vec<usize> = (0..x.ncols()).collect();
        let (c_kk, c_hk, c_hh) = (
            pick(&kept, &kept, c),
            pick(&held, &kept, c),
            pick(&held, &held, c),
        );
        let (w_kk, _) = psd_pinv(&c_kk);
        let x_k = pick(&kept, &all_cols, x);
        let x_h = pick(&held, &all_cols, x);
        let y_k = DVector::from_fn(kept.len(), |r, _| y[kept[r]]);
        let y_h = DVector::from_fn(2, |r, _| y[held[r]]);
        let fit = gls(&y_k, &x_k, &w_kk);
        let gain = &c_hk * &w_kk;
        let predicted = &x_h * &fit.beta + &gain * &fit.residual;
        let e = y_h - predicted;
        let lever = &x_h - &gain * &x_k;
        let var = (&c_hh - &gain * c_hk.transpose()) + &lever * &fit.cov * lever.transpose();
        let (w, rank) = psd_pinv(&var);
        if rank == 0 {
            continue;
        }
        z2 += (e.transpose() * w * &e)[(0, 0)] / rank as f64;
        counted += 1;
    }
    (z2 / counted.max(1) as f64).sqrt()
}

/// `table_error_motion` on the table stations: their radial and axial residuals against the
/// circle through them, linearised at that circle; the circle's own freedom (radius and
/// centre height: harmonic 0; centre and plane tilt: harmonic 1) as nuisance columns, the
/// error motions as harmonics 2..K of the commanded table angle in radial and axial (the
/// tangential part of a motion, a tilt's included, is the step angle itself: not seen apart
/// from it). Whitened by the stations' joint covariance.
fn table_error_motion(
    session: &NetworkSession<'_>,
    stations: &SolvedStations<'_>,
) -> Result<Option<StationsLevel>, String> {
    let angles = table_angles(session);
    let on_table: Vec<(usize, f64)> = angles
        .iter()
        .enumerate()
        .filter_map(|(j, a)| a.map(|a| (j, a)))
        .collect();
    let m = on_table.len();
    // Harmonics 2..K of each component, within what 2m values beside the circle's 6 carry.
    let dof_left = |radial: u32, axial: u32| {
        2 * m as i64 - 6 - 2 * (i64::from(radial) - 1) - 2 * (i64::from(axial) - 1)
    };
    let (mut top_radial, mut top_axial) = (MAX_RADIAL_HARMONIC, MAX_AXIAL_HARMONIC);
    while dof_left(top_radial, top_axial) < MIN_STATIONS_DOF && top_radial.max(top_axial) > 2 {
        if top_radial >= top_axial {
            top_radial -= 1;
        } else {
            top_axial -= 1;
        }
    }
    if dof_left(top_radial, top_axial) < MIN_STATIONS_DOF {
        return Err(format!(
            "{m} table stations: the table's error motions need at least 7 (harmonics 2 and up beside the circle)"
        ));
    }
    let points: Vec<Vector3<f64>> = on_table
        .iter()
        .map(|&(j, _)| stations.positions_m[j])
        .collect();
    let cov_p = DMatrix::from_fn(3 * m, 3 * m, |r, c| {
        stations.covariance_m2[(3 * on_table[r / 3].0 + r % 3, 3 * on_table[c / 3].0 + c % 3)]
    });
    let circle = fit_circle(&points, Some(&cov_p), None).map_err(|e| e.to_string())?;
    let mut n = circle.normal.into_inner();
    if n.dot(&plan_axis(session)) < 0.0 {
        n = -n;
    }
    // y: radial and axial residual of each station; J: their gradient in the station's position.
    let mut y = DVector::zeros(2 * m);
    let mut jac = DMatrix::zeros(2 * m, 3 * m);
    for (k, p) in points.iter().enumerate() {
        let d = p - circle.centre_m;
        let axial = d.dot(&n);
        let in_plane = d - n * axial;
        let radial_dir = in_plane / in_plane.norm().max(f64::MIN_POSITIVE);
        y[2 * k] = in_plane.norm() - circle.radius_m;
        y[2 * k + 1] = axial;
        for a in 0..3 {
            jac[(2 * k, 3 * k + a)] = radial_dir[a];
            jac[(2 * k + 1, 3 * k + a)] = n[a];
        }
    }
    let c = &jac * &cov_p * jac.transpose();
    let (weight, rank_c) = psd_pinv(&c);
    // Columns of harmonics `radial` of the radial rows and `axial` of the axial rows (order 0:
    // the constant).
    let harmonic_columns = |radial: std::ops::RangeInclusive<u32>,
                            axial: std::ops::RangeInclusive<u32>| {
        let mut columns: Vec<(usize, u32, bool)> = Vec::new();
        for (row, orders) in [(0, radial), (1, axial)] {
            for order in orders {
                columns.push((row, order, false));
                if order > 0 {
                    columns.push((row, order, true));
                }
            }
        }
        let mut x = DMatrix::zeros(2 * m, columns.len());
        for (k, &(_, theta)) in on_table.iter().enumerate() {
            for (c, &(row, order, sine)) in columns.iter().enumerate() {
                let (s, co) = (f64::from(order) * theta).sin_cos();
                x[(2 * k + row, c)] = if sine { s } else { co };
            }
        }
        x
    };
    let nuisance = harmonic_columns(0..=1, 0..=1);
    let motion = harmonic_columns(2..=top_radial, 2..=top_axial);
    let both = {
        let mut x = DMatrix::zeros(2 * m, nuisance.ncols() + motion.ncols());
        x.columns_mut(0, nuisance.ncols()).copy_from(&nuisance);
        x.columns_mut(nuisance.ncols(), motion.ncols())
            .copy_from(&motion);
        x
    };
    let before = gls(&y, &nuisance, &weight);
    let after = gls(&y, &both, &weight);
    let mut names = Vec::new();
    for (component, top) in [("radial", top_radial), ("axial", top_axial)] {
        for order in 2..=top {
            names.push(format!("{component}_cos{order}_m"));
            names.push(format!("{component}_sin{order}_m"));
        }
    }
    let offset = nuisance.ncols();
    let params = names
        .into_iter()
        .enumerate()
        .map(|(k, name)| {
            let c = offset + k;
            (name, after.beta[c], after.cov[(c, c)].max(0.0).sqrt())
        })
        .collect();
    let rms = |r: &DVector<f64>| (r.norm_squared() / r.len().max(1) as f64).sqrt();
    let station_rows = on_table
        .iter()
        .enumerate()
        .map(|(k, &(j, theta))| {
            let id = &session.station_ids[j];
            let e = DVector::from_vec(vec![before.residual[2 * k], before.residual[2 * k + 1]]);
            let block = DMatrix::from_fn(2, 2, |r, q| c[(2 * k + r, 2 * k + q)]);
            let (w, _) = psd_pinv(&block);
            StationResidual {
                station: id.clone(),
                label: format!("{id} at {:.1}°", theta.to_degrees()),
                residual_m: vec![e[0], e[1]],
                residual_after_m: vec![after.residual[2 * k], after.residual[2 * k + 1]],
                chi2: (e.transpose() * w * &e)[(0, 0)],
            }
        })
        .collect();
    Ok(Some(StationsLevel {
        model: format!(
            "the {m} table stations' radial and axial residuals against their circle (harmonics 0-1 of the table angle)"
        ),
        effect: TABLE_ERROR_MOTION,
        chi2: before.chi2,
        dof: rank_c.saturating_sub(before.rank),
        df: after.rank.saturating_sub(before.rank),
        chi2_drop: (before.chi2 - after.chi2).max(0.0),
        params,
        stations: station_rows,
        rms_m: rms(&before.residual),
        rms_after_m: rms(&after.residual),
        heldout_ratio: heldout_ratio(&y, &nuisance, &c, m),
        heldout_ratio_after: heldout_ratio(&y, &both, &c, m),
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plane_basis_is_right_handed_about_the_axis() {
        for n in [Vector3::z(), -Vector3::z(), Vector3::x()] {
            let (e1, e2) = plane_basis(&n);
            assert!((e1.cross(&e2) - n).norm() < 1e-12);
            assert!(e1.dot(&n).abs() < 1e-12);
        }
    }
}
