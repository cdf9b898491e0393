//! The multilateration's start: each station and its segments' homing distances fitted to the
//! lengths with the points held at their nominal positions (a resection). Held points fix the
//! frame, so a station's few unknowns converge in a few Gauss–Newton steps from hints
//! centimetres off; the joint fit started from the hints spends several steps leaving the
//! weak directions of the whole network (a station against its homing distance, the free
//! points' gauge) before it converges quadratically.

use nalgebra::{DMatrix, DVector, Vector3};

use super::multilateration::MultilaterationProblem;

/// Gauss–Newton steps per station at most; a station whose hint is centimetres off settles
/// in three or four.
const MAX_STEPS: usize = 8;
/// A station counts as settled once no unknown moves by more than this (m): far below what
/// the joint fit's first step resolves, far above rounding.
const SETTLED_STEP_M: f64 = 1e-9;

/// Stations and homing distances fitted to the lengths with `points` held. A station whose
/// normal equations are singular or nearly so (too few points, or points in a line) stays
/// where it stands, and so do its segments' distances; the caller keeps the result only if
/// it lowers the cost.
pub(super) fn resect(
    problem: &MultilaterationProblem,
    points: &[Vector3<f64>],
    stations: &mut [Vector3<f64>],
    distances_m: &mut [f64],
) {
    // Each station's segments, numbered from 3 after its own x, y, z.
    let mut local = vec![0usize; problem.segments.len()];
    let mut unknowns = vec![3usize; stations.len()];
    for (s, segment) in problem.segments.iter().enumerate() {
        local[s] = unknowns[segment.station];
        unknowns[segment.station] += 1;
    }
    let mut settled = vec![false; stations.len()];
    for _ in 0..MAX_STEPS {
        let mut normal: Vec<DMatrix<f64>> =
            unknowns.iter().map(|&u| DMatrix::zeros(u, u)).collect();
        let mut gradient: Vec<DVector<f64>> = unknowns.iter().map(|&u| DVector::zeros(u)).collect();
        for obs in &problem.observations {
            let j = problem.segments[obs.segment].station;
            if settled[j] {
                continue;
            }
            let beam = stations[j] - points[obs.point];
            let range = beam.norm();
            if range == 0.0 {
                continue;
            }
            let u = beam / range;
            let r = obs.length_m - (range - distances_m[obs.segment]);
            let w = 1.0 / (obs.sigma_m * obs.sigma_m);
            let k = local[obs.segment];
            let (n, g) = (&mut normal[j], &mut gradient[j]);
            // ∂(predicted length)/∂(station) = u, ∂/∂(distance) = −1.
            for a in 0..3 {
                for b in 0..3 {
                    n[(a, b)] += w * u[a] * u[b];
                }
                n[(a, k)] -= w * u[a];
                n[(k, a)] -= w * u[a];
                g[a] += w * u[a] * r;
            }
            n[(k, k)] += w;
            g[k] -= w * r;
        }
        let mut all_settled = true;
        for j in 0..stations.len() {
            if settled[j] {
                continue;
            }
            // A segment without lengths keeps its distance.
            for k in 3..unknowns[j] {
                if normal[j][(k, k)] == 0.0 {
                    normal[j][(k, k)] = 1.0;
                }
            }
            let Some(step) = well_posed_step(&normal[j], &gradient[j]) else {
                settled[j] = true;
                continue;
            };
            stations[j] += Vector3::new(step[0], step[1], step[2]);
            for (s, segment) in problem.segments.iter().enumerate() {
                if segment.station == j {
                    distances_m[s] += step[local[s]];
                }
            }
            settled[j] = step.amax() <= SETTLED_STEP_M;
            all_settled &= settled[j];
        }
        if all_settled {
            break;
        }
    }
}

/// Pivots of the Cholesky factor below this fraction of the largest mean a direction the
/// station's lengths do not determine (the points seen from it too few or in a line).
const SMALLEST_PIVOT_RATIO: f64 = 1e-7;

/// The Gauss–Newton step N⁻¹g, or None when N is singular or nearly so.
fn well_posed_step(normal: &DMatrix<f64>, gradient: &DVector<f64>) -> Option<DVector<f64>> {
    let factor = normal.clone().cholesky()?;
    let pivots = factor.l_dirty().diagonal();
    let smallest = SMALLEST_PIVOT_RATIO * pivots.amax();
    if pivots.iter().any(|&p| p.is_nan() || p <= smallest) {
        return None;
    }
    let step = factor.solve(gradient);
    step.iter().all(|d| d.is_finite()).then_some(step)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solve::multilateration::tests::{stations5, synthetic};

    /// A noise-free problem whose lengths are those of the nominal points, with the stations'
    /// hints 3 cm off in each coordinate.
    fn nominal_lengths() -> (MultilaterationProblem, Vec<Vector3<f64>>, Vec<f64>) {
        let offset_m = 0.03;
        let stations = stations5();
        let mut syn = synthetic(3, [4, 4, 3], &stations, &[1, 3], 30e-9, false);
        let problem = &mut syn.problem;
        for obs in &mut problem.observations {
            let j = problem.segments[obs.segment].station;
            obs.length_m = (stations[j] - problem.nominal_points[obs.point]).norm()
                - syn.true_distances_m[obs.segment];
        }
        for (j, hint) in problem.station_hints.iter_mut().enumerate() {
            let sign = if j % 2 == 0 { 1.0 } else { -1.0 };
            *hint = Some(stations[j] + Vector3::new(offset_m, -sign * offset_m, sign * offset_m));
        }
        (syn.problem, stations, syn.true_distances_m)
    }

    /// The stations resected from their hints, the distances from zero.
    fn resected_from_the_hints(problem: &MultilaterationProblem) -> (Vec<Vector3<f64>>, Vec<f64>) {
        let mut stations: Vec<_> = problem.station_hints.iter().flatten().copied().collect();
        let mut distances = vec![0.0; problem.segments.len()];
        resect(
            problem,
            &problem.nominal_points,
            &mut stations,
            &mut distances,
        );
        (stations, distances)
    }

    #[test]
    fn stations_centimetres_off_settle_on_the_truth() {
        let (problem, truth, true_distances) = nominal_lengths();
        let (stations, distances) = resected_from_the_hints(&problem);
        for (j, (got, want)) in stations.iter().zip(&truth).enumerate() {
            assert!(
                (got - want).amax() < 1e-9,
                "station {j}: {got} against {want}"
            );
        }
        for (s, (got, want)) in distances.iter().zip(&true_distances).enumerate() {
            assert!(
                (got - want).abs() < 1e-9,
                "segment {s}: {got} against {want}"
            );
        }
    }

    #[test]
    fn a_station_whose_points_lie_in_a_line_keeps_its_start() {
        let (mut problem, _, _) = nominal_lengths();
        // Station 2 sees only points on the grid's first row (one line along x).
        let row: Vec<usize> = (0..problem.nominal_points.len())
            .filter(|&i| problem.nominal_points[i].y == 0.0 && problem.nominal_points[i].z == 0.0)
            .collect();
        assert!(row.len() >= 3);
        problem
            .observations
            .retain(|o| problem.segments[o.segment].station != 2 || row.contains(&o.point));
        let start: Vec<_> = problem.station_hints.iter().flatten().copied().collect();
        let (stations, distances) = resected_from_the_hints(&problem);
        assert_eq!(
            stations[2], start[2],
            "moved along a direction its lengths do not fix"
        );
        let s2 = problem
            .segments
            .iter()
            .position(|s| s.station == 2)
            .expect("segment");
        assert_eq!(distances[s2], 0.0);
        assert!(
            (stations[0] - start[0]).amax() > 0.01,
            "the others are resected"
        );
    }
}
