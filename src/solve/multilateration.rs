//! Multilateration with a tracking interferometer: self-calibrates stations and homing distances
//! and estimates every target point by sparse Levenberg–Marquardt (Schur complement on points),
//! started from the stations resected to the nominal points (`resection`).

use nalgebra::{DMatrix, DVector, Matrix3, Matrix3x6, Matrix6, Vector3};

use super::resection::resect;
use crate::parallel::{in_groups, in_parallel, split_lengths};

/// One relative length: |station − point| − d(segment), measured by the tracer.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LengthObservation {
    pub point: usize,
    pub segment: usize,
    pub length_m: f64,
    /// The standard deviation the fit weighs this length with. With `path_sigma` the solver
    /// sets it from its geometry; what is given here only has to be positive.
    pub sigma_m: f64,
    /// σ as a function of the beam |station − point|, when the noise grows with the optical
    /// path (an interferometer's ppm term); None for a fixed `sigma_m`.
    pub path_sigma: Option<PathSigma>,
}

/// σ of a length whose noise grows with the beam: at_zero_beam_m + per_beam_m·|A − P|
/// (at_zero_beam_m holds the constant part and the tracer's dead path).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct PathSigma {
    pub at_zero_beam_m: f64,
    pub per_beam_m: f64,
}

impl PathSigma {
    pub fn sigma_m(&self, beam_m: f64) -> f64 {
        self.at_zero_beam_m + self.per_beam_m * beam_m
    }
}

impl MultilaterationProblem {
    /// Set every path-dependent σ from the beams of the given geometry; returns the largest
    /// relative change.
    /// The largest relative change of a path-dependent σ if it were evaluated at the given
    /// geometry (nothing is changed).
    fn path_sigma_change(&self, stations: &[Vector3<f64>], points: &[Vector3<f64>]) -> f64 {
        let mut largest: f64 = 0.0;
        for obs in &self.observations {
            if let Some(path) = obs.path_sigma {
                let station = stations[self.segments[obs.segment].station];
                let sigma = path.sigma_m((station - points[obs.point]).norm());
                largest = largest.max((sigma - obs.sigma_m).abs() / sigma);
            }
        }
        largest
    }

    fn set_path_sigmas(&mut self, stations: &[Vector3<f64>], points: &[Vector3<f64>]) -> f64 {
        let mut largest: f64 = 0.0;
        for obs in &mut self.observations {
            if let Some(path) = obs.path_sigma {
                let station = stations[self.segments[obs.segment].station];
                let sigma = path.sigma_m((station - points[obs.point]).norm());
                largest = largest.max((sigma - obs.sigma_m).abs() / sigma);
                obs.sigma_m = sigma;
            }
        }
        largest
    }

    /// The same problem with every σ fixed at its value for the given solution (no longer
    /// path dependent): what fits that must weigh alike use (robust rounds, the diagnosis).
    pub fn with_fixed_sigmas(&self, sigmas_m: &[f64]) -> MultilaterationProblem {
        let mut fixed = self.clone();
        for (obs, &sigma) in fixed.observations.iter_mut().zip(sigmas_m) {
            obs.sigma_m = sigma;
            obs.path_sigma = None;
        }
        fixed
    }
}

/// A beam segment (between two homings at point 0) and the station it belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Segment {
    pub station: usize,
}

/// n target points seen from m stations through S beam segments.
#[derive(Debug, Clone, PartialEq)]
pub struct MultilaterationProblem {
    /// Commanded positions of the n target points; also the datum of the result.
    pub nominal_points: Vec<Vector3<f64>>,
    /// One entry per station: an approximate position, or `None` for the closed-form start.
    pub station_hints: Vec<Option<Vector3<f64>>>,
    pub segments: Vec<Segment>,
    pub observations: Vec<LengthObservation>,
}

/// Levenberg–Marquardt controls.
#[derive(Debug, Clone, PartialEq)]
pub struct SolveOptions {
    pub max_iterations: usize,
    /// Converged when an accepted step lowers the cost by less than this fraction.
    pub tolerance: f64,
    /// Converged when no parameter moves by more than this.
    pub step_tolerance_m: f64,
    /// Initial Marquardt damping factor (multiplies the diagonal of the normal matrix) from
    /// the hints; a start the resection improved begins at no more than `NEAR_MINIMUM_LAMBDA`.
    pub initial_lambda: f64,
}

impl Default for SolveOptions {
    fn default() -> Self {
        Self {
            max_iterations: 100,
            tolerance: 1e-12,
            step_tolerance_m: 1e-13,
            initial_lambda: 1e-3,
        }
    }
}

/// Estimates in the inner-constraint gauge relative to the nominal points, with their
/// Cramér–Rao covariances (JᵀWJ)⁻¹ from the given sigmas.
#[derive(Debug, Clone, PartialEq)]
pub struct MultilaterationSolution {
    pub points: Vec<Vector3<f64>>,
    /// Per point, 3x3 covariance in the inner-constraint gauge (m²).
    pub point_covariance: Vec<Matrix3<f64>>,
    pub stations: Vec<Vector3<f64>>,
    pub station_covariance: Vec<Matrix3<f64>>,
    /// All stations jointly, 3m x 3m (x, y, z of station 0, then station 1, ...), in the same
    /// gauge: functions of several stations (e.g. angles between them) need the correlations.
    pub station_joint_covariance: DMatrix<f64>,
    /// Per segment, distance from the station to the homing point.
    pub segment_distance_m: Vec<f64>,
    pub segment_distance_sigma_m: Vec<f64>,
    /// Per observation, measured − predicted.
    pub residuals_m: Vec<f64>,
    /// Per observation, the σ the fit weighed it with (path-dependent ones at the solution).
    pub sigmas_m: Vec<f64>,
    pub residual_rms_m: f64,
    /// Σ (r/σ)²; expect about `dof` when the noise model holds.
    pub chi2: f64,
    /// Observations − (unknowns − 6 gauge freedoms).
    pub dof: usize,
    /// LM iterations (accepted and rejected steps).
    pub iterations: usize,
    pub converged: bool,
    pub gauge: &'static str,
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SolveError {
    /// The problem is malformed or has too little data; the message says which part.
    #[error("invalid multilateration problem: {0}")]
    InvalidInput(String),
    /// The data cannot determine the unknowns (degenerate geometry or start).
    #[error("multilateration is singular: {0}")]
    Singular(String),
}

/// How the datum of every solution is fixed (also in `MultilaterationSolution::gauge`).
pub const GAUGE_DESCRIPTION: &str = "Datum: inner constraints relative to the nominal points; \
the solution was moved by the rigid motion that best fits its points onto the nominal points, \
so the corrections (estimated - nominal) carry no net translation or rotation, and the \
covariances are S-transformed to the same gauge.";

fn invalid(msg: String) -> SolveError {
    SolveError::InvalidInput(msg)
}

/// Index bookkeeping built once per problem, so the iterations allocate nothing per observation.
struct Layout {
    n: usize,
    m: usize,
    /// Columns of the reduced (station + segment) system: 3m station coordinates, then S distances.
    nv: usize,
    /// Observation indices grouped by point (CSR with `point_obs_start`).
    obs_order: Vec<usize>,
    point_obs_start: Vec<usize>,
    /// Per point, the global reduced-system columns it couples to, ascending (CSR with
    /// `point_cols_start`); a point's W and Y rows hold its columns in this order (its local
    /// columns), so the elimination walks the lower triangle without a test.
    cols: Vec<usize>,
    point_cols_start: Vec<usize>,
    /// Per point, its local columns in order of first appearance among its observations (CSR
    /// with `point_cols_start`): the order every sum over a point's columns runs in, so the
    /// rounding does not depend on how the columns are stored.
    summation_order: Vec<usize>,
    /// Per point, runs of consecutive global columns as (first local column, length) (CSR
    /// with `point_runs_start`): the elimination updates each run as one contiguous slice.
    runs: Vec<(usize, usize)>,
    point_runs_start: Vec<usize>,
    /// Per entry of `obs_order`: local column of its station block (3 wide) and of its segment.
    obs_local_station: Vec<usize>,
    obs_local_segment: Vec<usize>,
    /// Threads the elimination and the covariance use (1 for small problems).
    threads: usize,
    /// Entries of `obs_order` grouped by station, ascending within each (CSR with
    /// `station_obs_start`): the order in which the serial sweep over the points meets them.
    station_obs: Vec<usize>,
    station_obs_start: Vec<usize>,
    /// The stations split into `threads` consecutive ranges of about equal observations.
    station_ranges: Vec<std::ops::Range<usize>>,
    /// Six point coordinates held during the iterations: (point, axis).
    fixed: [(usize, usize); 6],
}

impl Layout {
    fn k(&self, i: usize) -> usize {
        self.point_cols_start[i + 1] - self.point_cols_start[i]
    }
    /// Offset of point i's 3×k block in the flat W / Y buffers.
    fn w_offset(&self, i: usize) -> usize {
        3 * self.point_cols_start[i]
    }
    /// Point i's global columns, ascending (its local columns).
    fn point_cols(&self, i: usize) -> &[usize] {
        &self.cols[self.point_cols_start[i]..self.point_cols_start[i + 1]]
    }
    /// Point i's local columns in the order its sums run.
    fn summation(&self, i: usize) -> &[usize] {
        &self.summation_order[self.point_cols_start[i]..self.point_cols_start[i + 1]]
    }
    fn point_runs(&self, i: usize) -> &[(usize, usize)] {
        &self.runs[self.point_runs_start[i]..self.point_runs_start[i + 1]]
    }
    /// The points split into `self.threads` consecutive ranges of about equal work.
    fn point_ranges(&self) -> Vec<std::ops::Range<usize>> {
        consecutive_ranges(&self.point_cols_start, self.threads)
    }

    /// Per range of `point_ranges`: the range, its pieces of two buffers with one entry per
    /// point and of one laid out as W (a 3 × k block per point).
    #[allow(clippy::type_complexity)]
    fn split_by_points<'a, A, B, C>(
        &self,
        per_point: &'a mut [A],
        per_point_too: &'a mut [B],
        blocks: &'a mut [C],
    ) -> Vec<(
        std::ops::Range<usize>,
        &'a mut [A],
        &'a mut [B],
        &'a mut [C],
    )> {
        let ranges = self.point_ranges();
        let lens = || ranges.iter().map(|r| r.len());
        let block_lens = ranges
            .iter()
            .map(|r| self.w_offset(r.end) - self.w_offset(r.start));
        ranges
            .iter()
            .cloned()
            .zip(split_lengths(per_point, lens()))
            .zip(split_lengths(per_point_too, lens()))
            .zip(split_lengths(blocks, block_lens))
            .map(|(((range, a), b), c)| (range, a, b, c))
            .collect()
    }
}

/// Items 0..n (n = `starts.len() - 1`, item i owning `starts[i]..starts[i + 1]` of the work)
/// split into `parts` consecutive ranges of about equal work.
fn consecutive_ranges(starts: &[usize], parts: usize) -> Vec<std::ops::Range<usize>> {
    let n = starts.len() - 1;
    let total = starts[n];
    let mut ranges = Vec::with_capacity(parts);
    let mut start = 0;
    for t in 1..=parts {
        let end = if t == parts {
            n
        } else {
            let goal = total * t / parts;
            start + starts[start..n].partition_point(|&c| c < goal)
        };
        ranges.push(start..end);
        start = end;
    }
    ranges
}

/// Below this many lower-triangle updates per elimination (Σ k²/2 over the points) threads
/// cost more than they save.
const THREADED_ELIMINATION_WORK: usize = 200_000;
const MAX_SOLVE_THREADS: usize = 8;

fn solve_threads(point_cols_start: &[usize]) -> usize {
    let work: usize = point_cols_start
        .windows(2)
        .map(|w| (w[1] - w[0]) * (w[1] - w[0] + 1) / 2)
        .sum();
    if work < THREADED_ELIMINATION_WORK {
        return 1;
    }
    crate::parallel::threads(MAX_SOLVE_THREADS)
}

fn validate(problem: &MultilaterationProblem) -> Result<(), SolveError> {
    let n = problem.nominal_points.len();
    let m = problem.station_hints.len();
    let s_count = problem.segments.len();
    if m < 4 {
        return Err(invalid(format!(
            "{m} stations given; multilateration needs at least 4"
        )));
    }
    if n < 4 {
        return Err(invalid(format!(
            "{n} points given; multilateration needs at least 4"
        )));
    }
    for (i, p) in problem.nominal_points.iter().enumerate() {
        if !p.iter().all(|v| v.is_finite()) {
            return Err(invalid(format!("nominal point {i} is not finite")));
        }
    }
    for (j, h) in problem.station_hints.iter().enumerate() {
        if let Some(h) = h {
            if !h.iter().all(|v| v.is_finite()) {
                return Err(invalid(format!("station hint {j} is not finite")));
            }
        }
    }
    for (s, seg) in problem.segments.iter().enumerate() {
        if seg.station >= m {
            return Err(invalid(format!(
                "segment {s} refers to station {} but there are only {m} stations",
                seg.station
            )));
        }
    }
    for (o, obs) in problem.observations.iter().enumerate() {
        if obs.point >= n {
            return Err(invalid(format!(
                "observation {o} refers to point {} but there are only {n} points",
                obs.point
            )));
        }
        if obs.segment >= s_count {
            return Err(invalid(format!(
                "observation {o} refers to segment {} but there are only {s_count} segments",
                obs.segment
            )));
        }
        if !obs.length_m.is_finite() {
            return Err(invalid(format!("observation {o} has a non-finite length")));
        }
        if !(obs.sigma_m.is_finite() && obs.sigma_m > 0.0) {
            return Err(invalid(format!(
                "observation {o} has sigma {} m; sigma must be positive and finite",
                obs.sigma_m
            )));
        }
    }
    // Distinct points per station and distinct stations per point.
    let mut seen_station_point = vec![false; m * n];
    let mut segment_used = vec![false; s_count];
    for obs in &problem.observations {
        let j = problem.segments[obs.segment].station;
        seen_station_point[j * n + obs.point] = true;
        segment_used[obs.segment] = true;
    }
    for j in 0..m {
        let count = seen_station_point[j * n..(j + 1) * n]
            .iter()
            .filter(|&&b| b)
            .count();
        if count < 4 {
            return Err(invalid(format!(
                "station {j} observes {count} distinct points; each station needs at least 4"
            )));
        }
    }
    for i in 0..n {
        let count = (0..m).filter(|&j| seen_station_point[j * n + i]).count();
        if count < 3 {
            return Err(invalid(format!(
                "point {i} is observed from {count} stations; each point needs at least 3"
            )));
        }
    }
    if let Some(s) = segment_used.iter().position(|&u| !u) {
        return Err(invalid(format!(
            "segment {s} has no observations, so its homing distance is undetermined"
        )));
    }
    let unknowns = 3 * n + 3 * m + s_count;
    let nobs = problem.observations.len();
    if nobs + 6 < unknowns {
        return Err(invalid(format!(
            "{nobs} observations for {unknowns} unknowns less 6 gauge freedoms; need at least {}",
            unknowns - 6
        )));
    }
    Ok(())
}

/// Three well-spread, non-collinear points and the 6 coordinates held fixed on them.
fn choose_gauge(points: &[Vector3<f64>]) -> Result<[(usize, usize); 6], SolveError> {
    let n = points.len() as f64;
    let centroid = points.iter().fold(Vector3::zeros(), |acc, p| acc + p) / n;
    let farthest = |from: &Vector3<f64>| {
        points
            .iter()
            .enumerate()
            .map(|(i, p)| (i, (p - from).norm_squared()))
            .fold((0, -1.0), |best, c| if c.1 > best.1 { c } else { best })
    };
    let (a, _) = farthest(&centroid);
    let (b, ab2) = farthest(&points[a]);
    let dir_ab = points[b] - points[a];
    let (c, area) = points
        .iter()
        .enumerate()
        .map(|(i, p)| (i, dir_ab.cross(&(p - points[a])).norm()))
        .fold((0, -1.0), |best, c| if c.1 > best.1 { c } else { best });
    if ab2 <= 0.0 || area <= 1e-6 * ab2 {
        return Err(SolveError::Singular(
            "the nominal points are collinear or coincident; the datum cannot be fixed".into(),
        ));
    }
    let normal = dir_ab.cross(&(points[c] - points[a]));
    let b_axis = dir_ab.iamax();
    let c_axis = normal.iamax();
    let b_free: Vec<usize> = (0..3).filter(|&k| k != b_axis).collect();
    Ok([
        (a, 0),
        (a, 1),
        (a, 2),
        (b, b_free[0]),
        (b, b_free[1]),
        (c, c_axis),
    ])
}

fn build_layout(problem: &MultilaterationProblem) -> Result<Layout, SolveError> {
    let n = problem.nominal_points.len();
    let m = problem.station_hints.len();
    let s_count = problem.segments.len();
    let nv = 3 * m + s_count;
    let mut counts = vec![0usize; n + 1];
    for obs in &problem.observations {
        counts[obs.point + 1] += 1;
    }
    for i in 0..n {
        counts[i + 1] += counts[i];
    }
    let point_obs_start = counts.clone();
    let mut fill = counts;
    let mut obs_order = vec![0usize; problem.observations.len()];
    for (o, obs) in problem.observations.iter().enumerate() {
        obs_order[fill[obs.point]] = o;
        fill[obs.point] += 1;
    }
    let mut cols = Vec::new();
    let mut point_cols_start = Vec::with_capacity(n + 1);
    let mut summation_order = Vec::new();
    let mut runs = Vec::new();
    let mut point_runs_start = Vec::with_capacity(n + 1);
    let mut obs_local_station = vec![0usize; obs_order.len()];
    let mut obs_local_segment = vec![0usize; obs_order.len()];
    // Marks: global column → column in order of first appearance for the current point
    // (usize::MAX = unset).
    let mut first_of = vec![usize::MAX; nv];
    let mut seen = Vec::new();
    let mut sorted_position = Vec::new();
    for i in 0..n {
        seen.clear();
        let obs_range = point_obs_start[i]..point_obs_start[i + 1];
        for e in obs_range.clone() {
            let obs = &problem.observations[obs_order[e]];
            let j = problem.segments[obs.segment].station;
            if first_of[3 * j] == usize::MAX {
                for a in 0..3 {
                    first_of[3 * j + a] = seen.len();
                    seen.push(3 * j + a);
                }
            }
            let sc = 3 * m + obs.segment;
            if first_of[sc] == usize::MAX {
                first_of[sc] = seen.len();
                seen.push(sc);
            }
            obs_local_station[e] = first_of[3 * j];
            obs_local_segment[e] = first_of[sc];
        }
        for &c in &seen {
            first_of[c] = usize::MAX;
        }
        // Local column = rank of the global column; the first-appearance order is kept for
        // the sums.
        let start = cols.len();
        point_cols_start.push(start);
        let mut order: Vec<usize> = (0..seen.len()).collect();
        order.sort_unstable_by_key(|&l| seen[l]);
        sorted_position.clear();
        sorted_position.resize(seen.len(), 0);
        for (position, &l) in order.iter().enumerate() {
            sorted_position[l] = position;
            cols.push(seen[l]);
        }
        summation_order.extend_from_slice(&sorted_position);
        for e in obs_range {
            obs_local_station[e] = sorted_position[obs_local_station[e]];
            obs_local_segment[e] = sorted_position[obs_local_segment[e]];
        }
        point_runs_start.push(runs.len());
        let point_cols = &cols[start..];
        let mut q = 0;
        while q < point_cols.len() {
            let mut len = 1;
            while q + len < point_cols.len() && point_cols[q + len] == point_cols[q] + len {
                len += 1;
            }
            runs.push((q, len));
            q += len;
        }
    }
    point_runs_start.push(runs.len());
    point_cols_start.push(cols.len());
    let fixed = choose_gauge(&problem.nominal_points)?;
    let threads = solve_threads(&point_cols_start);
    let station_of =
        |e: usize| problem.segments[problem.observations[obs_order[e]].segment].station;
    let mut station_obs_start = vec![0usize; m + 1];
    for e in 0..obs_order.len() {
        station_obs_start[station_of(e) + 1] += 1;
    }
    for j in 0..m {
        station_obs_start[j + 1] += station_obs_start[j];
    }
    let mut fill = station_obs_start.clone();
    let mut station_obs = vec![0usize; obs_order.len()];
    for e in 0..obs_order.len() {
        let j = station_of(e);
        station_obs[fill[j]] = e;
        fill[j] += 1;
    }
    let station_ranges = consecutive_ranges(&station_obs_start, threads);
    Ok(Layout {
        n,
        m,
        nv,
        obs_order,
        point_obs_start,
        threads,
        station_obs,
        station_obs_start,
        station_ranges,
        cols,
        point_cols_start,
        summation_order,
        runs,
        point_runs_start,
        obs_local_station,
        obs_local_segment,
        fixed,
    })
}

/// Closed-form start for one station from the linearised equations, taking X_i ≈ N_i:
/// −2 N_i·P − 2 l_i d_s + ρ_s = l_i² − N_i·N_i with ρ_s = P·P − d_s² free (one per segment).
fn closed_form_station(
    problem: &MultilaterationProblem,
    station: usize,
) -> Result<Vector3<f64>, SolveError> {
    let n = problem.nominal_points.len() as f64;
    // Centre the coordinates for conditioning.
    let centre = problem
        .nominal_points
        .iter()
        .fold(Vector3::zeros(), |acc, p| acc + p)
        / n;
    // A segment with fewer than 3 lengths adds 2 unknowns it cannot carry: leave it out here;
    // its distance is fitted afterwards from the station position.
    let mut per_segment = vec![0usize; problem.segments.len()];
    for o in &problem.observations {
        per_segment[o.segment] += 1;
    }
    let segs: Vec<usize> = (0..problem.segments.len())
        .filter(|&s| problem.segments[s].station == station && per_segment[s] >= 3)
        .collect();
    let rows: Vec<&LengthObservation> = problem
        .observations
        .iter()
        .filter(|o| segs.contains(&o.segment))
        .collect();
    let cols = 3 + 2 * segs.len();
    if rows.len() < cols {
        return Err(SolveError::Singular(format!(
            "station {station}: {} observations cannot give a closed-form start with {} segments; \
             give a station hint",
            rows.len(),
            segs.len()
        )));
    }
    let mut a = DMatrix::zeros(rows.len(), cols);
    let mut b = DVector::zeros(rows.len());
    for (r, obs) in rows.iter().enumerate() {
        let q = problem.nominal_points[obs.point] - centre;
        let k = segs.iter().position(|&s| s == obs.segment).unwrap_or(0);
        // Weighting by 1/sigma keeps the start sensible when sigmas differ a lot.
        let w = 1.0 / obs.sigma_m;
        for ax in 0..3 {
            a[(r, ax)] = -2.0 * q[ax] * w;
        }
        a[(r, 3 + 2 * k)] = -2.0 * obs.length_m * w;
        a[(r, 4 + 2 * k)] = w;
        b[r] = (obs.length_m * obs.length_m - q.norm_squared()) * w;
    }
    let svd = a.svd(true, true);
    let smax = svd.singular_values.max();
    let smin = svd.singular_values.min();
    if !(smax > 0.0 && smin > 1e-12 * smax) {
        return Err(SolveError::Singular(format!(
            "station {station}: the closed-form start is singular (points coplanar?); give a \
             station hint"
        )));
    }
    let x = svd
        .solve(&b, 0.0)
        .map_err(|e| SolveError::Singular(format!("station {station}: {e}")))?;
    let p = Vector3::new(x[0], x[1], x[2]) + centre;
    if !p.iter().all(|v| v.is_finite()) {
        return Err(SolveError::Singular(format!(
            "station {station}: closed-form start is not finite"
        )));
    }
    Ok(p)
}

/// Starting station positions: the hint where given, else the closed-form linearised solution.
pub fn initial_stations(problem: &MultilaterationProblem) -> Result<Vec<Vector3<f64>>, SolveError> {
    validate(problem)?;
    problem
        .station_hints
        .iter()
        .enumerate()
        .map(|(j, h)| match h {
            Some(p) => Ok(*p),
            None => closed_form_station(problem, j),
        })
        .collect()
}

/// Homing distances that best fit the lengths for given stations and points.
fn initial_segment_distances(
    problem: &MultilaterationProblem,
    stations: &[Vector3<f64>],
    points: &[Vector3<f64>],
) -> Vec<f64> {
    let s_count = problem.segments.len();
    let mut num = vec![0.0; s_count];
    let mut den = vec![0.0; s_count];
    for obs in &problem.observations {
        let j = problem.segments[obs.segment].station;
        let w = 1.0 / (obs.sigma_m * obs.sigma_m);
        num[obs.segment] += w * ((stations[j] - points[obs.point]).norm() - obs.length_m);
        den[obs.segment] += w;
    }
    num.iter().zip(&den).map(|(a, b)| a / b).collect()
}

#[derive(Clone)]
struct Params {
    points: Vec<Vector3<f64>>,
    stations: Vec<Vector3<f64>>,
    distances_m: Vec<f64>,
}

/// Half the weighted sum of squared residuals.
fn cost(problem: &MultilaterationProblem, p: &Params) -> f64 {
    let squared = |obs: &LengthObservation| {
        let j = problem.segments[obs.segment].station;
        let pred = (p.stations[j] - p.points[obs.point]).norm() - p.distances_m[obs.segment];
        let r = (obs.length_m - pred) / obs.sigma_m;
        r * r
    };
    let sum = |squares: &mut dyn Iterator<Item = f64>| squares.fold(0.0, |c, rr| c + rr);
    let observations = &problem.observations;
    if observations.len() < THREADED_COST_OBSERVATIONS {
        return 0.5 * sum(&mut observations.iter().map(squared));
    }
    // The squares on the threads, summed here in the observations' order as one thread would.
    let squares = in_groups(
        observations,
        crate::parallel::threads(MAX_SOLVE_THREADS),
        squared,
    );
    0.5 * sum(&mut squares.into_iter())
}

/// From this many observations the cost's squares are computed on the threads.
const THREADED_COST_OBSERVATIONS: usize = 20_000;

/// Normal equations JᵀWJ, JᵀWr in block form, and buffers for the reduced solve.
struct Normal {
    u: Vec<Matrix3<f64>>,
    gx: Vec<Vector3<f64>>,
    /// Per point, 3×k cross block with the reduced columns, row-major, flat.
    w: Vec<f64>,
    v: DMatrix<f64>,
    gv: DVector<f64>,
    // Work buffers.
    /// Per range of stations: its rows and columns of V and entries of g_v.
    station_parts: Vec<(DMatrix<f64>, DVector<f64>)>,
    uinv: Vec<Matrix3<f64>>,
    y: Vec<f64>,
    yg: Vec<Vector3<f64>>,
    a: DMatrix<f64>,
    b: DVector<f64>,
}

/// One observation's linearisation: the unit beam direction (point to station), its weight
/// 1/σ² and its residual (measured − predicted length).
struct ObsTerm {
    dir: Vector3<f64>,
    weight: f64,
    residual_m: f64,
}

impl ObsTerm {
    /// At the parameters `p`; None when the point sits on the station.
    fn at(problem: &MultilaterationProblem, obs: &LengthObservation, p: &Params) -> Option<Self> {
        let s = obs.segment;
        let diff = p.stations[problem.segments[s].station] - p.points[obs.point];
        let dist = diff.norm();
        (dist > 0.0 && dist.is_finite()).then(|| ObsTerm {
            dir: diff / dist,
            weight: 1.0 / (obs.sigma_m * obs.sigma_m),
            residual_m: obs.length_m - (dist - p.distances_m[s]),
        })
    }

    /// w · dir dirᵀ, the observation's block of the point's and the station's normal matrix.
    fn outer(&self) -> Matrix3<f64> {
        self.dir * self.dir.transpose() * self.weight
    }
}

impl Normal {
    fn new(layout: &Layout) -> Self {
        let wlen = 3 * layout.cols.len();
        Self {
            u: vec![Matrix3::zeros(); layout.n],
            gx: vec![Vector3::zeros(); layout.n],
            w: vec![0.0; wlen],
            v: DMatrix::zeros(layout.nv, layout.nv),
            gv: DVector::zeros(layout.nv),
            station_parts: layout
                .station_ranges
                .iter()
                .map(|_| {
                    (
                        DMatrix::zeros(layout.nv, layout.nv),
                        DVector::zeros(layout.nv),
                    )
                })
                .collect(),
            uinv: vec![Matrix3::zeros(); layout.n],
            y: vec![0.0; wlen],
            yg: vec![Vector3::zeros(); layout.n],
            a: DMatrix::zeros(layout.nv, layout.nv),
            b: DVector::zeros(layout.nv),
        }
    }

    /// The normal equations at `p`: per point its block U_i, gradient g_i and cross block W_i
    /// (the points split over the threads), then the stations' block V and gradient g_v (the
    /// stations split over the threads, each element summed in the serial sweep's order).
    fn build(
        &mut self,
        problem: &MultilaterationProblem,
        layout: &Layout,
        p: &Params,
    ) -> Result<(), SolveError> {
        self.build_points(problem, layout, p)?;
        self.build_stations(problem, layout, p);
        Ok(())
    }

    fn build_points(
        &mut self,
        problem: &MultilaterationProblem,
        layout: &Layout,
        p: &Params,
    ) -> Result<(), SolveError> {
        let parts = layout.split_by_points(&mut self.u, &mut self.gx, &mut self.w);
        let results = in_parallel(parts, |(range, us, gs, w)| {
            w.fill(0.0);
            let w_base = layout.w_offset(range.start);
            for (q, i) in range.enumerate() {
                let mut u = Matrix3::zeros();
                let mut g = Vector3::zeros();
                let k = layout.k(i);
                let off = layout.w_offset(i) - w_base;
                for e in layout.point_obs_start[i]..layout.point_obs_start[i + 1] {
                    let obs = &problem.observations[layout.obs_order[e]];
                    let Some(term) = ObsTerm::at(problem, obs, p) else {
                        let j = problem.segments[obs.segment].station;
                        return Err(SolveError::Singular(format!(
                            "point {i} coincides with station {j}"
                        )));
                    };
                    let (dir, wt, r) = (term.dir, term.weight, term.residual_m);
                    let uu = term.outer();
                    // d(pred)/dX = −dir, d(pred)/dP = dir, d(pred)/dd = −1.
                    u += uu;
                    g -= dir * (wt * r);
                    let ls = layout.obs_local_station[e];
                    let lg = layout.obs_local_segment[e];
                    for a in 0..3 {
                        for c in 0..3 {
                            w[off + a * k + ls + c] -= uu[(a, c)];
                        }
                        w[off + a * k + lg] += wt * dir[a];
                    }
                }
                // Held coordinates: decouple their row and column, unit diagonal, no gradient.
                for &(fp, ax) in &layout.fixed {
                    if fp == i {
                        for c in 0..3 {
                            u[(ax, c)] = 0.0;
                            u[(c, ax)] = 0.0;
                        }
                        u[(ax, ax)] = 1.0;
                        g[ax] = 0.0;
                        for c in 0..k {
                            w[off + ax * k + c] = 0.0;
                        }
                    }
                }
                us[q] = u;
                gs[q] = g;
            }
            Ok(())
        });
        results.into_iter().collect()
    }

    /// After `build_points`, which checked every observation's geometry.
    fn build_stations(&mut self, problem: &MultilaterationProblem, layout: &Layout, p: &Params) {
        let m = layout.m;
        let parts: Vec<_> = layout
            .station_ranges
            .iter()
            .zip(self.station_parts.iter_mut())
            .collect();
        in_parallel(parts, |(stations, (v, gv))| {
            for j in stations.clone() {
                let entries = &layout.station_obs
                    [layout.station_obs_start[j]..layout.station_obs_start[j + 1]];
                for &e in entries {
                    let obs = &problem.observations[layout.obs_order[e]];
                    let s = obs.segment;
                    // Made again as `build_points` made it (holding them all would cost the
                    // memory of the observations again).
                    let Some(term) = ObsTerm::at(problem, obs, p) else {
                        continue;
                    };
                    let (dir, wt, r) = (term.dir, term.weight, term.residual_m);
                    let uu = term.outer();
                    let sj = 3 * j;
                    let sc = 3 * m + s;
                    for a in 0..3 {
                        for c in 0..3 {
                            v[(sj + a, sj + c)] += uu[(a, c)];
                        }
                        v[(sj + a, sc)] -= wt * dir[a];
                        v[(sc, sj + a)] -= wt * dir[a];
                        gv[sj + a] += wt * r * dir[a];
                    }
                    v[(sc, sc)] += wt;
                    gv[sc] -= wt * r;
                }
            }
        });
        // Each range wrote only its own stations' and segments' elements (the rest stayed
        // zero), so the sum copies them exactly.
        self.v.fill(0.0);
        self.gv.fill(0.0);
        for (v, gv) in &mut self.station_parts {
            self.v += &*v;
            self.gv += &*gv;
            v.fill(0.0);
            gv.fill(0.0);
        }
    }

    /// Solves (H + λ diag H) δ = g by eliminating the points. On success, δ is in
    /// `dx` / `dv`; `Ok(false)` means the reduced matrix was not positive definite.
    fn solve_damped(
        &mut self,
        layout: &Layout,
        lambda: f64,
        dx: &mut [Vector3<f64>],
        dv: &mut DVector<f64>,
    ) -> Result<bool, SolveError> {
        let nv = layout.nv;
        self.a.copy_from(&self.v);
        self.b.copy_from(&self.gv);
        for c in 0..nv {
            self.a[(c, c)] *= 1.0 + lambda;
        }
        self.prepare_points(layout, lambda)?;
        self.eliminate_points(layout);
        let Some(chol) = self.a.clone().cholesky() else {
            return Ok(false);
        };
        let sol = chol.solve(&self.b);
        dv.copy_from(&sol);
        // Back-substitution, the points split over the threads (each point's step is its own).
        let ranges = layout.point_ranges();
        let parts: Vec<_> = ranges
            .iter()
            .cloned()
            .zip(split_lengths(dx, ranges.iter().map(|r| r.len())))
            .collect();
        let (y, yg) = (&self.y, &self.yg);
        in_parallel(parts, |(range, steps)| {
            for (d, i) in steps.iter_mut().zip(range) {
                let k = layout.k(i);
                let off = layout.w_offset(i);
                let cols = layout.point_cols(i);
                let mut t = yg[i];
                for a in 0..3 {
                    let row = &y[off + a * k..off + (a + 1) * k];
                    t[a] -= layout
                        .summation(i)
                        .iter()
                        .map(|&c| row[c] * sol[cols[c]])
                        .sum::<f64>();
                }
                *d = t;
            }
        });
        Ok(true)
    }

    /// Per point: U_i⁻¹ of the damped block, U_i⁻¹ g_i and Y_i = U_i⁻¹ W_i (points split over
    /// the threads; each point's figures are its own).
    fn prepare_points(&mut self, layout: &Layout, lambda: f64) -> Result<(), SolveError> {
        let parts = layout.split_by_points(&mut self.uinv, &mut self.yg, &mut self.y);
        let (u, gx, w) = (&self.u, &self.gx, &self.w);
        let results = in_parallel(parts, |(range, uinv, yg, y)| {
            let base = layout.w_offset(range.start);
            for (p, i) in range.enumerate() {
                let mut ud = u[i];
                for c in 0..3 {
                    ud[(c, c)] *= 1.0 + lambda;
                }
                let Some(inv) = ud.try_inverse() else {
                    return Err(SolveError::Singular(format!(
                        "point {i}: its 3x3 normal block is singular (stations collinear with it?)"
                    )));
                };
                uinv[p] = inv;
                yg[p] = inv * gx[i];
                let k = layout.k(i);
                let off = layout.w_offset(i);
                let (w0, w1, w2) = (
                    &w[off..off + k],
                    &w[off + k..off + 2 * k],
                    &w[off + 2 * k..off + 3 * k],
                );
                for a in 0..3 {
                    let row = &mut y[off - base + a * k..off - base + (a + 1) * k];
                    for (c, y) in row.iter_mut().enumerate() {
                        *y = inv[(a, 0)] * w0[c] + inv[(a, 1)] * w1[c] + inv[(a, 2)] * w2[c];
                    }
                }
            }
            Ok(())
        });
        results.into_iter().collect()
    }

    /// A −= Σ W_iᵀ Y_i (its lower triangle only: `a`'s upper triangle is left stale, and only
    /// the Cholesky factorisation reads `a`) and b −= Σ W_iᵀ U_i⁻¹ g_i. The columns of A are
    /// split over the threads; each walks every point in order, so every element sees the
    /// same updates in the same order whatever the threads.
    fn eliminate_points(&mut self, layout: &Layout) {
        let nv = layout.nv;
        // Column c of the lower triangle holds nv − c elements: equal shares of that work.
        let total = nv * (nv + 1) / 2;
        let mut bounds = vec![0];
        let mut done = 0;
        for c in 0..nv {
            done += nv - c;
            if done * layout.threads >= total * bounds.len() && bounds.len() < layout.threads {
                bounds.push(c + 1);
            }
        }
        bounds.push(nv);
        bounds.dedup();
        let spans: Vec<_> = bounds.windows(2).map(|b| b[0]..b[1]).collect();
        let parts: Vec<_> = spans
            .iter()
            .cloned()
            .zip(split_lengths(
                self.a.as_mut_slice(),
                spans.iter().map(|s| s.len() * nv),
            ))
            .zip(split_lengths(
                self.b.as_mut_slice(),
                spans.iter().map(|s| s.len()),
            ))
            .collect();
        let (w, y, yg) = (&self.w, &self.y, &self.yg);
        in_parallel(parts, |((span, a), b)| {
            for (i, yg) in yg.iter().enumerate() {
                eliminate_point(layout, i, w, y, yg, span.clone(), a, b);
            }
        });
    }
}

/// Point i's share of the elimination in the columns `span` of A (`a`: those columns,
/// column-major; `b`: those entries).
#[allow(clippy::too_many_arguments)]
fn eliminate_point(
    layout: &Layout,
    i: usize,
    w: &[f64],
    y: &[f64],
    yg: &Vector3<f64>,
    span: std::ops::Range<usize>,
    a: &mut [f64],
    b: &mut [f64],
) {
    let k = layout.k(i);
    let off = layout.w_offset(i);
    let nv = layout.nv;
    let cols = layout.point_cols(i);
    let runs = layout.point_runs(i);
    let (y0, y1, y2) = (
        &y[off..off + k],
        &y[off + k..off + 2 * k],
        &y[off + 2 * k..off + 3 * k],
    );
    let first = cols.partition_point(|&c| c < span.start);
    let last = cols.partition_point(|&c| c < span.end);
    let mut run = 0;
    for r in first..last {
        let gr = cols[r];
        let w0 = w[off + r];
        let w1 = w[off + k + r];
        let w2 = w[off + 2 * k + r];
        if w0 == 0.0 && w1 == 0.0 && w2 == 0.0 {
            continue;
        }
        // The update is symmetric and the Cholesky factorisation reads only the lower
        // triangle: half the work, the same factor. Column gr, rows gc >= gr (the local
        // columns from r on), one run of consecutive rows at a time.
        let column = &mut a[(gr - span.start) * nv..(gr - span.start + 1) * nv];
        while runs[run].0 + runs[run].1 <= r {
            run += 1;
        }
        for &(run_start, len) in &runs[run..] {
            let (from, to) = (run_start.max(r), run_start + len);
            let g = cols[from];
            let rows = &mut column[g..g + (to - from)];
            for (((dst, a0), a1), a2) in rows
                .iter_mut()
                .zip(&y0[from..to])
                .zip(&y1[from..to])
                .zip(&y2[from..to])
            {
                *dst -= w0 * a0 + w1 * a1 + w2 * a2;
            }
        }
        b[gr - span.start] -= w0 * yg[0] + w1 * yg[1] + w2 * yg[2];
    }
}

/// Best-fit rigid motion (Kabsch, no scale): R, t minimising Σ |R x_i + t − y_i|².
pub fn best_fit_rigid(
    from: &[Vector3<f64>],
    to: &[Vector3<f64>],
) -> Option<(Matrix3<f64>, Vector3<f64>)> {
    if from.len() != to.len() || from.is_empty() {
        return None;
    }
    let n = from.len() as f64;
    let cx = from.iter().fold(Vector3::zeros(), |a, p| a + p) / n;
    let cy = to.iter().fold(Vector3::zeros(), |a, p| a + p) / n;
    let mut h = Matrix3::zeros();
    for (x, y) in from.iter().zip(to) {
        h += (x - cx) * (y - cy).transpose();
    }
    let svd = h.svd(true, true);
    let u = svd.u?;
    let vt = svd.v_t?;
    let d = (vt.transpose() * u.transpose()).determinant().signum();
    let r = vt.transpose() * Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, d)) * u.transpose();
    Some((r, cy - r * cx))
}

/// Rigid-motion generators of a position q (translation, then small rotation about `centre`).
pub(crate) fn generator(q: &Vector3<f64>, centre: &Vector3<f64>) -> Matrix3x6<f64> {
    let p = q - centre;
    let mut g = Matrix3x6::zeros();
    g.fixed_view_mut::<3, 3>(0, 0)
        .copy_from(&Matrix3::identity());
    // ω × p = −[p]× ω
    g.fixed_view_mut::<3, 3>(0, 3)
        .copy_from(&(-p.cross_matrix()));
    g
}

/// Largest problem (unknowns) for which `dense_point_covariance` answers.
pub const MAX_DENSE_COVARIANCE_UNKNOWNS: usize = 1500;

/// Whether `dense_point_covariance` can answer for this problem: known before solving it.
pub fn dense_point_covariance_fits(problem: &MultilaterationProblem) -> bool {
    3 * problem.station_hints.len() + problem.segments.len() + 3 * problem.nominal_points.len()
        <= MAX_DENSE_COVARIANCE_UNKNOWNS
}

/// The full covariance of all points (3n x 3n, point-major) in the inner-constraint datum,
/// including the correlations between points that shared stations cause; `None` when the
/// problem has more than `MAX_DENSE_COVARIANCE_UNKNOWNS` unknowns (dense algebra).
/// A generalised inverse of the normal matrix, then the S-transform to inner constraints on
/// points: any generalised inverse gives the same result once S-transformed, when the rigid
/// motions are the normal matrix's only null directions. The points are eliminated block by
/// block (`by_elimination`); a problem where that cannot be shown to hold takes the
/// pseudo-inverse of the whole normal matrix (`by_eigen`).
pub fn dense_point_covariance(
    problem: &MultilaterationProblem,
    solution: &MultilaterationSolution,
) -> Option<DMatrix<f64>> {
    let (m, s, n) = unknown_counts(solution);
    if 3 * m + s + 3 * n > MAX_DENSE_COVARIANCE_UNKNOWNS {
        return None;
    }
    let q = by_elimination(problem, solution).or_else(|| by_eigen(problem, solution))?;
    inner_constraint(problem, solution, &q)
}

/// The S-transform of a generalised inverse `q` of the normal matrix onto the inner
/// constraint of the points (T q Tᵀ with T = I − g (eᵀg)⁻¹ eᵀ on the points' rows, g the
/// rigid motions at the solution and e at the nominal points; e has no stations' rows, so the
/// stations' part of `q` drops out). None when eᵀg is singular.
fn inner_constraint(
    problem: &MultilaterationProblem,
    solution: &MultilaterationSolution,
    q: &DMatrix<f64>,
) -> Option<DMatrix<f64>> {
    let n = solution.points.len();
    let centre = problem.nominal_points.iter().sum::<Vector3<f64>>() / n as f64;
    let mut g = DMatrix::<f64>::zeros(3 * n, 6);
    let mut e = DMatrix::<f64>::zeros(3 * n, 6);
    for i in 0..n {
        g.view_mut((3 * i, 0), (3, 6))
            .copy_from(&generator(&solution.points[i], &centre));
        e.view_mut((3 * i, 0), (3, 6))
            .copy_from(&generator(&problem.nominal_points[i], &centre));
    }
    let k = &g * (e.transpose() * &g).try_inverse()?;
    let tq = q - &k * (e.transpose() * q);
    Some(&tq - (&tq * &e) * k.transpose())
}

/// (stations, segments, points) of a solution.
fn unknown_counts(solution: &MultilaterationSolution) -> (usize, usize, usize) {
    (
        solution.stations.len(),
        solution.segment_distance_m.len(),
        solution.points.len(),
    )
}

/// Rows of one length's whitened Jacobian: (station j's 3 columns, segment column, point's 3).
fn whitened_row(
    problem: &MultilaterationProblem,
    solution: &MultilaterationSolution,
    k: usize,
) -> (usize, Vector3<f64>, f64) {
    let obs = &problem.observations[k];
    let sigma_m = solution.sigmas_m[k];
    let j = problem.segments[obs.segment].station;
    let d = solution.stations[j] - solution.points[obs.point];
    (j, d / d.norm() / sigma_m, -1.0 / sigma_m)
}

/// The points' block of a generalised inverse of the normal matrix, the points eliminated
/// block by block: M⁻¹ + F S⁺ Fᵀ with M the points' 3 × 3 blocks, F = M⁻¹ Cᵀ and S the
/// reduced matrix of the stations and segments. None when a point's block or S has a null
/// direction other than the 6 rigid motions (the pseudo-inverse of the whole matrix then).
fn by_elimination(
    problem: &MultilaterationProblem,
    solution: &MultilaterationSolution,
) -> Option<DMatrix<f64>> {
    let (m, s, n) = unknown_counts(solution);
    let r = 3 * m + s;
    let mut blocks = vec![Matrix3::<f64>::zeros(); n];
    let mut coupling = DMatrix::<f64>::zeros(r, 3 * n);
    let mut reduced = DMatrix::<f64>::zeros(r, r);
    for k in 0..problem.observations.len() {
        let (j, u, w_segment) = whitened_row(problem, solution, k);
        let obs = &problem.observations[k];
        let (p, seg) = (obs.point, 3 * m + obs.segment);
        let outer = u * u.transpose();
        blocks[p] += outer;
        for a in 0..3 {
            for b in 0..3 {
                reduced[(3 * j + a, 3 * j + b)] += outer[(a, b)];
                // Station × point: u (−u)ᵀ.
                coupling[(3 * j + a, 3 * p + b)] -= outer[(a, b)];
            }
            reduced[(3 * j + a, seg)] += u[a] * w_segment;
            reduced[(seg, 3 * j + a)] += u[a] * w_segment;
            // Segment × point: w_segment (−u)ᵀ.
            coupling[(seg, 3 * p + a)] -= w_segment * u[a];
        }
        reduced[(seg, seg)] += w_segment * w_segment;
    }
    let largest = blocks
        .iter()
        .map(|b| b.trace())
        .fold(reduced.trace(), f64::max);
    let mut inverses = Vec::with_capacity(n);
    for block in &blocks {
        if block.symmetric_eigen().eigenvalues.min() <= largest * 1e-12 {
            return None;
        }
        inverses.push(block.try_inverse()?);
    }
    // F = M⁻¹ Cᵀ (3n × r), S = A − C M⁻¹ Cᵀ.
    let mut f = DMatrix::<f64>::zeros(3 * n, r);
    for (p, inverse) in inverses.iter().enumerate() {
        let c_p = coupling.columns(3 * p, 3);
        f.rows_mut(3 * p, 3).copy_from(&(inverse * c_p.transpose()));
    }
    reduced -= &coupling * &f;
    let eigen = reduced.symmetric_eigen();
    let top = eigen.eigenvalues.amax();
    let kept: Vec<usize> = (0..r)
        .filter(|&k| eigen.eigenvalues[k] > top * 1e-12)
        .collect();
    // The rigid motions' 6 directions, and no other.
    if kept.len() + 6 != r {
        return None;
    }
    let mut v_scaled = DMatrix::<f64>::zeros(r, kept.len());
    for (c, &k) in kept.iter().enumerate() {
        v_scaled.set_column(
            c,
            &(eigen.eigenvectors.column(k) / eigen.eigenvalues[k].sqrt()),
        );
    }
    let fv = &f * v_scaled;
    let mut q = &fv * fv.transpose();
    for (p, inverse) in inverses.iter().enumerate() {
        let mut block = q.view_mut((3 * p, 3 * p), (3, 3));
        block += inverse;
    }
    Some(q)
}

/// The points' block of the pseudo-inverse of the whole normal matrix (its eigenvalues above
/// 1e-12 of the largest).
fn by_eigen(
    problem: &MultilaterationProblem,
    solution: &MultilaterationSolution,
) -> Option<DMatrix<f64>> {
    let (m, s, n) = unknown_counts(solution);
    let unknowns = 3 * m + s + 3 * n;
    let point_col = |i: usize| 3 * m + s + 3 * i;
    let mut normal = DMatrix::<f64>::zeros(unknowns, unknowns);
    let mut row = [0.0; 7];
    let mut cols = [0usize; 7];
    for k in 0..problem.observations.len() {
        let (j, u, w_segment) = whitened_row(problem, solution, k);
        let obs = &problem.observations[k];
        for a in 0..3 {
            cols[a] = 3 * j + a;
            row[a] = u[a];
            cols[3 + a] = point_col(obs.point) + a;
            row[3 + a] = -u[a];
        }
        cols[6] = 3 * m + obs.segment;
        row[6] = w_segment;
        for a in 0..7 {
            for b in 0..7 {
                normal[(cols[a], cols[b])] += row[a] * row[b];
            }
        }
    }
    let eigen = normal.symmetric_eigen();
    let largest = eigen.eigenvalues.amax();
    let mut pinv = DMatrix::<f64>::zeros(unknowns, unknowns);
    for (k, &lambda) in eigen.eigenvalues.iter().enumerate() {
        // The 6 rigid motions are the only null directions of a solvable problem.
        if lambda > largest * 1e-12 {
            let v = eigen.eigenvectors.column(k);
            pinv += v * v.transpose() / lambda;
        }
    }
    Some(
        pinv.view((point_col(0), point_col(0)), (3 * n, 3 * n))
            .into_owned(),
    )
}

/// Cramér–Rao covariance in the minimal-constraint gauge, S-transformed to inner constraints
/// relative to the nominal points, computed blockwise so the cost stays linear in n.
struct Covariance {
    points: Vec<Matrix3<f64>>,
    stations: Vec<Matrix3<f64>>,
    stations_joint: DMatrix<f64>,
    distance_var_m2: Vec<f64>,
}

fn covariance(
    problem: &MultilaterationProblem,
    layout: &Layout,
    normal: &mut Normal,
    p: &Params,
) -> Result<Covariance, SolveError> {
    let (n, m, nv) = (layout.n, layout.m, layout.nv);
    normal.build(problem, layout, p)?;
    let mut dx = vec![Vector3::zeros(); n];
    let mut dv = DVector::zeros(nv);
    if !normal.solve_damped(layout, 0.0, &mut dx, &mut dv)? {
        return Err(SolveError::Singular(
            "the station/segment system is not positive definite at the solution".into(),
        ));
    }
    // Held coordinates have zero variance in the minimal-constraint gauge.
    for &(i, ax) in &layout.fixed {
        normal.uinv[i][(ax, ax)] = 0.0;
    }
    let chol = normal.a.clone().cholesky().ok_or_else(|| {
        SolveError::Singular("reduced normal matrix is singular at the solution".into())
    })?;
    let ainv = chol.inverse();
    let centre = problem
        .nominal_points
        .iter()
        .fold(Vector3::zeros(), |a, q| a + q)
        / n as f64;
    // Z = Σ Y_iᵀ E_i (nv×6), EᵀG (6×6).
    let mut z = DMatrix::<f64>::zeros(nv, 6);
    let mut etg = Matrix6::<f64>::zeros();
    for i in 0..n {
        let e = generator(&problem.nominal_points[i], &centre);
        let g = generator(&p.points[i], &centre);
        etg += e.transpose() * g;
        let k = layout.k(i);
        let off = layout.w_offset(i);
        for (c, &gc) in layout.point_cols(i).iter().enumerate() {
            for q in 0..6 {
                z[(gc, q)] += (0..3)
                    .map(|a| normal.y[off + a * k + c] * e[(a, q)])
                    .sum::<f64>();
            }
        }
    }
    let kmat = etg.try_inverse().ok_or_else(|| {
        SolveError::Singular("the rigid-motion generators of the points are degenerate".into())
    })?;
    // M = A⁻¹ Z; B_v = Q_vx E = −M; B_x,i = U_i⁻¹ E_i + Y_i M.
    let mmat = &ainv * &z;
    // Row g of A⁻¹ as a contiguous column (A⁻¹ is not exactly symmetric in floating point).
    let ainv_t = ainv.transpose();
    let centre_ref = &centre;
    let (mmat_ref, ainv_t_ref, normal_ref) = (&mmat, &ainv_t, &*normal);
    // Per point, B_x,i and the covariance block Q_ii in the inner-constraint gauge; each
    // point's figures are its own, so the points are split over the threads.
    let per_point = in_parallel(layout.point_ranges(), |range| {
        let mut tmp = vec![0.0; 3 * nv];
        range
            .map(|i| {
                let e = generator(&problem.nominal_points[i], centre_ref);
                let b = point_b(layout, normal_ref, mmat_ref, &e, i);
                let q = point_block(layout, normal_ref, ainv_t_ref, i, &mut tmp);
                (b, q)
            })
            .collect::<Vec<_>>()
    });
    let mut c6 = Matrix6::<f64>::zeros();
    let mut bx = Vec::with_capacity(n);
    let mut blocks = Vec::with_capacity(n);
    for (i, (b, q)) in per_point.into_iter().flatten().enumerate() {
        let e = generator(&problem.nominal_points[i], &centre);
        c6 += e.transpose() * b;
        bx.push(b);
        blocks.push(q);
    }
    let kck = kmat * c6 * kmat.transpose();
    let inner = |q: Matrix3<f64>, g: &Matrix3x6<f64>, b: &Matrix3x6<f64>| {
        let gkb = g * kmat * b.transpose();
        q - gkb - gkb.transpose() + g * kck * g.transpose()
    };
    let points = blocks
        .iter()
        .zip(&bx)
        .enumerate()
        .map(|(i, (q, bxi))| inner(*q, &generator(&p.points[i], &centre), bxi))
        .collect();
    let station_g: Vec<Matrix3x6<f64>> = p.stations.iter().map(|s| generator(s, &centre)).collect();
    let station_b: Vec<Matrix3x6<f64>> = (0..m)
        .map(|j| Matrix3x6::from_fn(|a, c| -mmat[(3 * j + a, c)]))
        .collect();
    let mut stations_joint = DMatrix::<f64>::zeros(3 * m, 3 * m);
    for j in 0..m {
        for l in 0..m {
            let q = ainv.fixed_view::<3, 3>(3 * j, 3 * l).into_owned();
            let (gj, gl) = (&station_g[j], &station_g[l]);
            let (bj, bl) = (&station_b[j], &station_b[l]);
            let block = q - gj * kmat * bl.transpose() - bj * kmat.transpose() * gl.transpose()
                + gj * kck * gl.transpose();
            stations_joint
                .fixed_view_mut::<3, 3>(3 * j, 3 * l)
                .copy_from(&block);
        }
    }
    let stations = (0..m)
        .map(|j| {
            inner(
                ainv.fixed_view::<3, 3>(3 * j, 3 * j).into_owned(),
                &station_g[j],
                &station_b[j],
            )
        })
        .collect();
    // Homing distances are invariant under rigid motions: no S-transform correction.
    let distance_var_m2 = (3 * m..nv).map(|c| ainv[(c, c)]).collect();
    Ok(Covariance {
        points,
        stations,
        stations_joint,
        distance_var_m2,
    })
}

/// B_x,i = U_i⁻¹ E_i + Y_i M (M = A⁻¹ Z).
fn point_b(
    layout: &Layout,
    normal: &Normal,
    mmat: &DMatrix<f64>,
    e: &Matrix3x6<f64>,
    i: usize,
) -> Matrix3x6<f64> {
    let k = layout.k(i);
    let off = layout.w_offset(i);
    let cols = layout.point_cols(i);
    let mut b = normal.uinv[i] * e;
    for a in 0..3 {
        let ya = &normal.y[off + a * k..off + (a + 1) * k];
        for q in 0..6 {
            b[(a, q)] += layout
                .summation(i)
                .iter()
                .map(|&c| ya[c] * mmat[(cols[c], q)])
                .sum::<f64>();
        }
    }
    b
}

/// Q_ii = U_i⁻¹ + Y_i A⁻¹ Y_iᵀ over the point's columns only, in the minimal-constraint
/// gauge. `ainv_t`: A⁻¹ transposed; `tmp`: scratch of 3·nv.
fn point_block(
    layout: &Layout,
    normal: &Normal,
    ainv_t: &DMatrix<f64>,
    i: usize,
    tmp: &mut [f64],
) -> Matrix3<f64> {
    let (k, nv) = (layout.k(i), layout.nv);
    let off = layout.w_offset(i);
    let cols = layout.point_cols(i);
    let order = layout.summation(i);
    let y = &normal.y[off..off + 3 * k];
    // tmp_c[r1] = Σ_r2 A⁻¹[(g(r2), g(r1))] · Y[c][r2], r2 in summation order: each element
    // gets the terms of that sum in that order, the rows r1 a run of columns at a time.
    let (t0, rest) = tmp[..3 * k].split_at_mut(k);
    let (t1, t2) = rest.split_at_mut(k);
    for t in [&mut *t0, &mut *t1, &mut *t2] {
        t.fill(-0.0);
    }
    let ainv_t = ainv_t.as_slice();
    for &r2 in order {
        let row = &ainv_t[cols[r2] * nv..(cols[r2] + 1) * nv];
        let (c0, c1, c2) = (y[r2], y[k + r2], y[2 * k + r2]);
        for &(start, len) in layout.point_runs(i) {
            let g = cols[start];
            let span = start..start + len;
            for (((&x, d0), d1), d2) in row[g..g + len]
                .iter()
                .zip(&mut t0[span.clone()])
                .zip(&mut t1[span.clone()])
                .zip(&mut t2[span])
            {
                *d0 += x * c0;
                *d1 += x * c1;
                *d2 += x * c2;
            }
        }
    }
    let mut q = normal.uinv[i];
    for (c, t) in [&*t0, &*t1, &*t2].into_iter().enumerate() {
        for a in 0..3 {
            let ya = &y[a * k..(a + 1) * k];
            q[(a, c)] += order.iter().map(|&r1| ya[r1] * t[r1]).sum::<f64>();
        }
    }
    q
}

/// Moves points and stations by the rigid motion that best fits the points onto the nominal
/// points: that realises the inner constraints Σ(X−N) = 0, Σ N×(X−N) = 0.
fn align_to_nominal(problem: &MultilaterationProblem, p: &mut Params) -> Result<(), SolveError> {
    let limit = 1e-12 * p.points.len() as f64;
    // A second pass removes what rounding left of the first; a third is a safety margin.
    for _ in 0..3 {
        let (r, t) = best_fit_rigid(&p.points, &problem.nominal_points).ok_or_else(|| {
            SolveError::Singular("rigid alignment to the nominal points failed".into())
        })?;
        for x in p.points.iter_mut().chain(p.stations.iter_mut()) {
            *x = r * *x + t;
        }
        let (sum, moment) = inner_constraint_sums(&problem.nominal_points, &p.points);
        if sum.amax() < limit && moment.amax() < limit {
            break;
        }
    }
    Ok(())
}

/// Σ (X−N) in m and Σ N×(X−N) in m²: both vanish under the inner constraints.
fn inner_constraint_sums(
    nominal: &[Vector3<f64>],
    points: &[Vector3<f64>],
) -> (Vector3<f64>, Vector3<f64>) {
    let mut sum = Vector3::zeros();
    let mut moment = Vector3::zeros();
    for (x, nom) in points.iter().zip(nominal) {
        sum += x - nom;
        moment += nom.cross(&(x - nom));
    }
    (sum, moment)
}

/// Self-calibrating multilateration: stations, homing distances and points from relative lengths.
pub fn solve(
    problem: &MultilaterationProblem,
    options: &SolveOptions,
) -> Result<MultilaterationSolution, SolveError> {
    solve_on_threads(problem, options, None)
}

/// `solve` on the given number of threads (None: as many as the problem's size warrants and
/// the machine has); the result does not depend on it, bit for bit.
fn solve_on_threads(
    problem: &MultilaterationProblem,
    options: &SolveOptions,
    threads: Option<usize>,
) -> Result<MultilaterationSolution, SolveError> {
    let stations = initial_stations(problem)?;
    let mut layout = build_layout(problem)?;
    if let Some(threads) = threads {
        layout.threads = threads.max(1);
    }
    let points = problem.nominal_points.clone();
    // Path-dependent σ: set from the starting geometry, re-evaluated after every accepted
    // step that moved them by more than REWEIGHT_TOLERANCE (the first steps, while the
    // stations move from their hints), and checked once more at each solution.
    let path_dependent = problem.observations.iter().any(|o| o.path_sigma.is_some());
    let mut weighted = std::borrow::Cow::Borrowed(problem);
    if path_dependent {
        weighted.to_mut().set_path_sigmas(&stations, &points);
    }
    let distances_m = initial_segment_distances(&weighted, &stations, &points);
    let mut params = Params {
        points,
        stations,
        distances_m,
    };
    // The stations resected to the nominal points start the joint fit near its minimum,
    // where a Gauss–Newton step is right; from the hints alone it starts damped.
    let mut start_lambda = options.initial_lambda;
    let mut resected = params.clone();
    resect(
        &weighted,
        &resected.points,
        &mut resected.stations,
        &mut resected.distances_m,
    );
    if cost(&weighted, &resected) < cost(&weighted, &params) {
        params = resected;
        start_lambda = start_lambda.min(NEAR_MINIMUM_LAMBDA);
        if path_dependent {
            weighted
                .to_mut()
                .set_path_sigmas(&params.stations, &params.points);
        }
    }
    let mut normal = Normal::new(&layout);
    let (mut iterations, mut converged) = levenberg_marquardt(
        &mut weighted,
        path_dependent,
        &layout,
        &mut normal,
        &mut params,
        options,
        start_lambda,
    )?;
    for _ in 0..MAX_REWEIGHTS {
        if !path_dependent {
            break;
        }
        let change = weighted
            .to_mut()
            .set_path_sigmas(&params.stations, &params.points);
        if change <= REWEIGHT_TOLERANCE {
            break;
        }
        // A solution whose weights moved a little is still in the quadratic basin.
        let (more, done) = levenberg_marquardt(
            &mut weighted,
            path_dependent,
            &layout,
            &mut normal,
            &mut params,
            options,
            options.initial_lambda.min(NEAR_MINIMUM_LAMBDA),
        )?;
        iterations += more;
        converged = done;
    }
    let problem = weighted.as_ref();
    align_to_nominal(problem, &mut params)?;
    let cov = covariance(problem, &layout, &mut normal, &params)?;
    let mut residuals_m = Vec::with_capacity(problem.observations.len());
    let mut chi2 = 0.0;
    for obs in &problem.observations {
        let j = problem.segments[obs.segment].station;
        let pred = (params.stations[j] - params.points[obs.point]).norm()
            - params.distances_m[obs.segment];
        let r = obs.length_m - pred;
        chi2 += (r / obs.sigma_m).powi(2);
        residuals_m.push(r);
    }
    let nobs = residuals_m.len();
    let residual_rms_m = (residuals_m.iter().map(|r| r * r).sum::<f64>() / nobs as f64).sqrt();
    let unknowns = 3 * layout.n + layout.nv;
    Ok(MultilaterationSolution {
        points: params.points,
        point_covariance: cov.points,
        stations: params.stations,
        station_covariance: cov.stations,
        station_joint_covariance: cov.stations_joint,
        segment_distance_m: params.distances_m,
        segment_distance_sigma_m: cov
            .distance_var_m2
            .iter()
            .map(|v| v.max(0.0).sqrt())
            .collect(),
        residuals_m,
        sigmas_m: problem.observations.iter().map(|o| o.sigma_m).collect(),
        residual_rms_m,
        chi2,
        dof: nobs + 6 - unknowns,
        iterations,
        converged,
        gauge: GAUGE_DESCRIPTION,
    })
}

/// Rounds of re-evaluating path-dependent σ at the solution, and the relative change of any σ
/// below which the weights count as settled (χ² then moves by well under 0.1 %).
const MAX_REWEIGHTS: usize = 4;
const REWEIGHT_TOLERANCE: f64 = 1e-4;

/// The Marquardt factor to start from near the minimum: small enough that the network's weak
/// directions (a station against its homing distance) take their Gauss–Newton step at once.
/// A damping of 1e-3 there takes five more iterations on a 10 000-point session; a step that
/// raises the cost is refused and damped as always.
const NEAR_MINIMUM_LAMBDA: f64 = 1e-9;

/// Levenberg–Marquardt from `params` to convergence, damped by `lambda` at first; with
/// `reweight`, path-dependent σ are re-evaluated after an accepted step that moved them (each
/// step is judged with fixed σ). Returns the iterations taken and whether it converged.
fn levenberg_marquardt(
    weighted: &mut std::borrow::Cow<MultilaterationProblem>,
    reweight: bool,
    layout: &Layout,
    normal: &mut Normal,
    params: &mut Params,
    options: &SolveOptions,
    mut lambda: f64,
) -> Result<(usize, bool), SolveError> {
    let mut trial = params.clone();
    let mut dx = vec![Vector3::zeros(); layout.n];
    let mut dv = DVector::zeros(layout.nv);
    let mut current_cost = cost(weighted, params);
    let mut converged = current_cost == 0.0;
    let mut iterations = 0;
    let mut need_build = true;
    while !converged && iterations < options.max_iterations {
        iterations += 1;
        let problem: &MultilaterationProblem = weighted;
        if need_build {
            normal.build(problem, layout, params)?;
            need_build = false;
        }
        if !normal.solve_damped(layout, lambda, &mut dx, &mut dv)? {
            lambda *= 10.0;
            if lambda > 1e20 {
                return Err(SolveError::Singular(
                    "the reduced normal matrix stays indefinite under damping".into(),
                ));
            }
            continue;
        }
        let m = layout.m;
        let mut max_step: f64 = 0.0;
        for (i, d) in dx.iter().enumerate() {
            trial.points[i] = params.points[i] + d;
            max_step = max_step.max(d.amax());
        }
        for j in 0..m {
            let d = Vector3::new(dv[3 * j], dv[3 * j + 1], dv[3 * j + 2]);
            trial.stations[j] = params.stations[j] + d;
            max_step = max_step.max(d.amax());
        }
        for (s, dist) in trial.distances_m.iter_mut().enumerate() {
            *dist = params.distances_m[s] + dv[3 * m + s];
            max_step = max_step.max(dv[3 * m + s].abs());
        }
        let new_cost = cost(problem, &trial);
        if new_cost.is_finite() && new_cost < current_cost {
            let decrease = (current_cost - new_cost) / current_cost;
            std::mem::swap(params, &mut trial);
            current_cost = new_cost;
            need_build = true;
            let reweighted = reweight
                && weighted.path_sigma_change(&params.stations, &params.points)
                    > REWEIGHT_TOLERANCE;
            if reweighted {
                weighted
                    .to_mut()
                    .set_path_sigmas(&params.stations, &params.points);
                current_cost = cost(weighted, params);
            }
            // A tiny decrease only means convergence when the step was not heavily damped.
            let nearly_gauss_newton = lambda < 1.0;
            lambda = (lambda / 10.0).max(1e-15);
            if !reweighted
                && ((decrease <= options.tolerance && nearly_gauss_newton)
                    || max_step <= options.step_tolerance_m)
            {
                converged = true;
            }
        } else {
            // A rejected step below the resolution means we sit at the rounding floor.
            if max_step <= options.step_tolerance_m {
                converged = true;
            }
            lambda *= 10.0;
            if lambda > 1e20 {
                break;
            }
        }
    }
    Ok((iterations, converged))
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    use rand_distr::StandardNormal;

    pub(crate) struct Synthetic {
        pub(crate) problem: MultilaterationProblem,
        pub(crate) true_points: Vec<Vector3<f64>>,
        pub(crate) true_stations: Vec<Vector3<f64>>,
        pub(crate) true_distances_m: Vec<f64>,
    }

    pub(crate) fn stations5() -> Vec<Vector3<f64>> {
        vec![
            Vector3::new(-0.4, -0.4, 0.2),
            Vector3::new(1.8, -0.3, 0.9),
            Vector3::new(1.9, 2.8, 0.1),
            Vector3::new(-0.3, 2.9, 1.1),
            Vector3::new(0.7, 1.2, -0.5),
        ]
    }

    /// Grid over 1.4 x 2.4 x 1.0 m; point 0 (a corner) is the homing point. Stations listed in
    /// `two_segments` have their pass split by a beam break (re-homed with 1 µm repeatability).
    pub(crate) fn synthetic(
        seed: u64,
        grid: [usize; 3],
        stations: &[Vector3<f64>],
        two_segments: &[usize],
        sigma_m: f64,
        noisy: bool,
    ) -> Synthetic {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut nominal = Vec::new();
        let size = [1.4, 2.4, 1.0];
        for iz in 0..grid[2] {
            for iy in 0..grid[1] {
                for ix in 0..grid[0] {
                    let f = |i: usize, k: usize| size[k] * i as f64 / (grid[k] - 1) as f64;
                    nominal.push(Vector3::new(f(ix, 0), f(iy, 1), f(iz, 2)));
                }
            }
        }
        let true_points: Vec<Vector3<f64>> = nominal
            .iter()
            .map(|p| p + Vector3::from_fn(|_, _| rng.random_range(-4e-6..4e-6)))
            .collect();
        let n = nominal.len();
        let mut segments = Vec::new();
        let mut true_distances_m = Vec::new();
        let mut observations = Vec::new();
        for (j, pj) in stations.iter().enumerate() {
            let home = (pj - true_points[0]).norm();
            let parts = if two_segments.contains(&j) { 2 } else { 1 };
            for part in 0..parts {
                let s = segments.len();
                segments.push(Segment { station: j });
                let d = home + if part == 1 { 1e-6 } else { 0.0 };
                true_distances_m.push(d);
                let range = if parts == 1 {
                    0..n
                } else if part == 0 {
                    0..n / 2
                } else {
                    n / 2..n
                };
                for i in range {
                    let noise: f64 = if noisy {
                        rng.sample::<f64, _>(StandardNormal) * sigma_m
                    } else {
                        0.0
                    };
                    observations.push(LengthObservation {
                        point: i,
                        segment: s,
                        length_m: (pj - true_points[i]).norm() - d + noise,
                        sigma_m,
                        path_sigma: None,
                    });
                }
            }
        }
        Synthetic {
            problem: MultilaterationProblem {
                nominal_points: nominal,
                station_hints: stations.iter().map(|p| Some(*p)).collect(),
                segments,
                observations,
            },
            true_points,
            true_stations: stations.to_vec(),
            true_distances_m,
        }
    }

    struct Errors {
        point_ms_m2: f64,
        point_pred_ms_m2: f64,
        station_ms_m2: f64,
        station_pred_ms_m2: f64,
        max_point_m: f64,
        max_station_m: f64,
    }

    /// Errors after removing the rigid motion that best fits the estimate onto the truth.
    fn errors(sol: &MultilaterationSolution, syn: &Synthetic) -> Errors {
        let (r, t) = best_fit_rigid(&sol.points, &syn.true_points).expect("kabsch");
        let pe: Vec<Vector3<f64>> = sol
            .points
            .iter()
            .zip(&syn.true_points)
            .map(|(x, y)| r * x + t - y)
            .collect();
        let se: Vec<Vector3<f64>> = sol
            .stations
            .iter()
            .zip(&syn.true_stations)
            .map(|(x, y)| r * x + t - y)
            .collect();
        let n = pe.len() as f64;
        let m = se.len() as f64;
        Errors {
            point_ms_m2: pe.iter().map(|e| e.norm_squared()).sum::<f64>() / (3.0 * n),
            point_pred_ms_m2: sol.point_covariance.iter().map(|q| q.trace()).sum::<f64>()
                / (3.0 * n),
            station_ms_m2: se.iter().map(|e| e.norm_squared()).sum::<f64>() / (3.0 * m),
            station_pred_ms_m2: sol
                .station_covariance
                .iter()
                .map(|q| q.trace())
                .sum::<f64>()
                / (3.0 * m),
            max_point_m: pe.iter().map(|e| e.amax()).fold(0.0, f64::max),
            max_station_m: se.iter().map(|e| e.amax()).fold(0.0, f64::max),
        }
    }

    #[test]
    fn hints_centimetres_off_converge_in_gauss_newton_steps() {
        let syn = synthetic(11, [6, 6, 4], &stations5(), &[1, 3], 30e-9, true);
        let from_truth = solve(&syn.problem, &SolveOptions::default()).expect("solve");
        let mut off = syn.problem.clone();
        for (j, hint) in off.station_hints.iter_mut().enumerate() {
            let sign = if j % 2 == 0 { 1.0 } else { -1.0 };
            *hint = hint.map(|h| h + Vector3::new(0.03 * sign, 0.02, -0.025 * sign));
        }
        let sol = solve(&off, &SolveOptions::default()).expect("solve");
        assert!(sol.converged);
        // Resected, the start is within the quadratic basin: a step to the minimum, one to
        // the rounding floor, one to see the cost no longer falls.
        assert!(sol.iterations <= 4, "{} iterations", sol.iterations);
        for (a, b) in sol.points.iter().zip(&from_truth.points) {
            assert!((a - b).amax() < 1e-11, "{a} against {b}");
        }
    }

    #[test]
    fn synthetic_noisy_within_covariance() {
        let syn = synthetic(7, [5, 5, 4], &stations5(), &[1, 3], 30e-9, true);
        let sol = solve(&syn.problem, &SolveOptions::default()).expect("solve");
        assert!(sol.converged, "iterations {}", sol.iterations);
        let e = errors(&sol, &syn);
        let point_ratio = (e.point_ms_m2 / e.point_pred_ms_m2).sqrt();
        let station_ratio = (e.station_ms_m2 / e.station_pred_ms_m2).sqrt();
        assert!(point_ratio < 3.0, "point error ratio {point_ratio}");
        assert!(station_ratio < 3.0, "station error ratio {station_ratio}");
        for (s, d) in sol.segment_distance_m.iter().enumerate() {
            let z = (d - syn.true_distances_m[s]) / sol.segment_distance_sigma_m[s];
            assert!(z.abs() < 4.0, "segment {s}: {z} sigma");
        }
        // chi2 should be near its degrees of freedom.
        let chi2_ratio = sol.chi2 / sol.dof as f64;
        assert!((0.7..1.3).contains(&chi2_ratio), "chi2/dof {chi2_ratio}");
        assert_eq!(sol.residuals_m.len(), syn.problem.observations.len());
    }

    /// The elimination splits the reduced system's columns over the threads and the
    /// covariance the points: every figure is the same, bit for bit, on any number of threads.
    #[test]
    fn threads_give_the_same_solution_bit_for_bit() {
        let mut syn = synthetic(13, [5, 4, 3], &stations5(), &[1, 3], 30e-9, true);
        // A point seen from three stations only: its columns are not one run.
        syn.problem
            .observations
            .retain(|o| !(o.point == 7 && syn.problem.segments[o.segment].station == 2));
        let one = solve_on_threads(&syn.problem, &SolveOptions::default(), Some(1)).expect("1");
        for threads in [2, 3, 7] {
            let many = solve_on_threads(&syn.problem, &SolveOptions::default(), Some(threads))
                .expect("threads");
            assert_eq!(many, one, "{threads} threads");
        }
    }

    #[test]
    fn noise_free_is_recovered_exactly() {
        let syn = synthetic(3, [5, 5, 4], &stations5(), &[0, 2], 30e-9, false);
        let sol = solve(&syn.problem, &SolveOptions::default()).expect("solve");
        assert!(sol.converged);
        let e = errors(&sol, &syn);
        assert!(e.max_point_m < 1e-10, "point error {}", e.max_point_m);
        assert!(e.max_station_m < 1e-10, "station error {}", e.max_station_m);
        for (d, t) in sol.segment_distance_m.iter().zip(&syn.true_distances_m) {
            assert!((d - t).abs() < 1e-10);
        }
        assert!(sol.residual_rms_m < 1e-12);
    }

    /// The points eliminated block by block and the pseudo-inverse of the whole normal matrix
    /// give one covariance once S-transformed (two beam segments per station: segments too).
    #[test]
    fn dense_point_covariance_by_elimination_equals_the_pseudo_inverse() {
        let syn = synthetic(37, [4, 3, 3], &stations5(), &[2, 3], 30e-9, true);
        let sol = solve(&syn.problem, &SolveOptions::default()).expect("solve");
        let inner = |q: DMatrix<f64>| inner_constraint(&syn.problem, &sol, &q).expect("eᵀg");
        let eliminated = by_elimination(&syn.problem, &sol).expect("a solvable problem");
        let whole = by_eigen(&syn.problem, &sol).expect("pseudo-inverse");
        // The generalised inverses differ (gauge) before the transform, not after it.
        assert!((&eliminated - &whole).amax() > 1e-6 * whole.amax());
        let (a, b) = (inner(eliminated), inner(whole));
        assert!(
            (&a - &b).amax() <= 1e-9 * b.amax(),
            "{:e} of {:e}",
            (&a - &b).amax(),
            b.amax()
        );
    }

    #[test]
    fn dense_point_covariance_matches_the_blocks() {
        let syn = synthetic(31, [4, 4, 3], &stations5(), &[2], 30e-9, true);
        let sol = solve(&syn.problem, &SolveOptions::default()).expect("solve");
        let q = dense_point_covariance(&syn.problem, &sol).expect("small problem");
        for (i, block) in sol.point_covariance.iter().enumerate() {
            let dense = q.fixed_view::<3, 3>(3 * i, 3 * i);
            let scale = block.amax();
            assert!(
                (dense - block).amax() < 1e-6 * scale,
                "point {i}: dense {dense} vs block {block}"
            );
        }
        // Points are correlated through the shared stations: off-diagonal blocks are not zero.
        let cross = q.fixed_view::<3, 3>(0, 3 * 7).amax();
        assert!(
            cross > 1e-3 * sol.point_covariance[0].amax(),
            "cross covariance {cross}"
        );
    }

    #[test]
    fn monte_carlo_error_matches_covariance() {
        let seeds = 30;
        let (mut pe, mut pp, mut se, mut sp) = (0.0, 0.0, 0.0, 0.0);
        for seed in 0..seeds {
            let syn = synthetic(100 + seed, [4, 4, 2], &stations5(), &[4], 30e-9, true);
            let sol = solve(&syn.problem, &SolveOptions::default()).expect("solve");
            assert!(sol.converged);
            let e = errors(&sol, &syn);
            pe += e.point_ms_m2;
            pp += e.point_pred_ms_m2;
            se += e.station_ms_m2;
            sp += e.station_pred_ms_m2;
        }
        let point_ratio = (pe / pp).sqrt();
        let station_ratio = (se / sp).sqrt();
        eprintln!("monte carlo: point ratio {point_ratio:.3}, station ratio {station_ratio:.3}");
        assert!(
            (0.8..1.25).contains(&point_ratio),
            "point ratio {point_ratio}"
        );
        assert!(
            (0.8..1.25).contains(&station_ratio),
            "station ratio {station_ratio}"
        );
    }

    #[test]
    fn converges_to_same_solution_from_any_start() {
        let syn = synthetic(11, [4, 4, 3], &stations5(), &[1], 30e-9, true);
        let from_hints = solve(&syn.problem, &SolveOptions::default()).expect("hints");
        let mut no_hints = syn.problem.clone();
        no_hints.station_hints = vec![None; 5];
        let closed = initial_stations(&no_hints).expect("closed form");
        for (c, t) in closed.iter().zip(&syn.true_stations) {
            // The linearised start ignores the µm point deviations and the noise only.
            assert!(
                (c - t).norm() < 1e-3,
                "closed-form start off by {}",
                (c - t).norm()
            );
        }
        let from_none = solve(&no_hints, &SolveOptions::default()).expect("no hints");
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let mut off = syn.problem.clone();
        for h in off.station_hints.iter_mut().flatten() {
            let dir = Vector3::from_fn(|_, _| rng.sample::<f64, _>(StandardNormal)).normalize();
            *h += dir * 0.2;
        }
        let from_off = solve(&off, &SolveOptions::default()).expect("off hints");
        for other in [&from_none, &from_off] {
            assert!(other.converged);
            for (a, b) in from_hints.points.iter().zip(&other.points) {
                assert!((a - b).amax() < 1e-9, "points differ by {}", (a - b).amax());
            }
            for (a, b) in from_hints.stations.iter().zip(&other.stations) {
                assert!(
                    (a - b).amax() < 1e-9,
                    "stations differ by {}",
                    (a - b).amax()
                );
            }
            for (a, b) in from_hints
                .segment_distance_m
                .iter()
                .zip(&other.segment_distance_m)
            {
                assert!((a - b).abs() < 1e-9);
            }
        }
    }

    #[test]
    fn inner_constraints_hold() {
        let syn = synthetic(21, [5, 5, 4], &stations5(), &[], 30e-9, true);
        let sol = solve(&syn.problem, &SolveOptions::default()).expect("solve");
        let n = sol.points.len() as f64;
        let (sum, moment) = inner_constraint_sums(&syn.problem.nominal_points, &sol.points);
        assert!(sum.amax() < 1e-12 * n, "translation sum {sum}");
        assert!(moment.amax() < 1e-12 * n, "rotation sum {moment}");
        assert!(sol.gauge.contains("inner constraints"));
    }

    /// Dense reference: full Jacobian, a different minimal constraint (pseudo-inverse over the
    /// free parameters), dense S-transform. The inner-constraint covariance must not depend on
    /// which minimal constraint was used, so it must match the blockwise one.
    #[test]
    fn blockwise_covariance_matches_dense() {
        let syn = synthetic(31, [3, 3, 2], &stations5(), &[2], 30e-9, true);
        let p = &syn.problem;
        let sol = solve(p, &SolveOptions::default()).expect("solve");
        let (n, m, s) = (p.nominal_points.len(), 5, p.segments.len());
        let np = 3 * n + 3 * m + s;
        let mut h = DMatrix::<f64>::zeros(np, np);
        for obs in &p.observations {
            let j = p.segments[obs.segment].station;
            let diff = sol.stations[j] - sol.points[obs.point];
            let u = diff / diff.norm();
            let mut row = DVector::<f64>::zeros(np);
            for a in 0..3 {
                row[3 * obs.point + a] = -u[a];
                row[3 * n + 3 * j + a] = u[a];
            }
            row[3 * n + 3 * m + obs.segment] = -1.0;
            h += &row * row.transpose() / (obs.sigma_m * obs.sigma_m);
        }
        // Minimal constraint: hold point 0 xyz, point 2 (on the x axis) y z, point 3 z.
        let fixed = [0, 1, 2, 3 * 2 + 1, 3 * 2 + 2, 3 * 3 + 2];
        let free: Vec<usize> = (0..np).filter(|c| !fixed.contains(c)).collect();
        let hf = DMatrix::from_fn(free.len(), free.len(), |a, b| h[(free[a], free[b])]);
        let qf = hf.cholesky().expect("dense normal").inverse();
        let mut q = DMatrix::<f64>::zeros(np, np);
        for (a, &fa) in free.iter().enumerate() {
            for (b, &fb) in free.iter().enumerate() {
                q[(fa, fb)] = qf[(a, b)];
            }
        }
        let centre = Vector3::new(0.3, -0.2, 0.1);
        let mut g = DMatrix::<f64>::zeros(np, 6);
        let mut e = DMatrix::<f64>::zeros(np, 6);
        for i in 0..n {
            g.view_mut((3 * i, 0), (3, 6))
                .copy_from(&generator(&sol.points[i], &centre));
            e.view_mut((3 * i, 0), (3, 6))
                .copy_from(&generator(&p.nominal_points[i], &centre));
        }
        for j in 0..m {
            g.view_mut((3 * n + 3 * j, 0), (3, 6))
                .copy_from(&generator(&sol.stations[j], &centre));
        }
        let etg = e.transpose() * &g;
        let sm =
            DMatrix::<f64>::identity(np, np) - &g * etg.try_inverse().expect("etg") * e.transpose();
        let qi = &sm * q * sm.transpose();
        let et_q = e.transpose() * &qi;
        let scale = qi.amax();
        assert!(et_q.amax() < 1e-9 * scale, "EᵀQ = {}", et_q.amax());
        for i in 0..n {
            let d = qi.view((3 * i, 3 * i), (3, 3)) - sol.point_covariance[i];
            assert!(
                d.amax() < 1e-6 * sol.point_covariance[i].amax(),
                "point {i}: {d}"
            );
        }
        for j in 0..m {
            let c = 3 * n + 3 * j;
            let joint: Matrix3<f64> = sol
                .station_joint_covariance
                .fixed_view::<3, 3>(3 * j, 3 * j)
                .into_owned();
            assert!((joint - sol.station_covariance[j]).amax() < 1e-12 * joint.amax());
            for l in 0..sol.stations.len() {
                let cl = 3 * n + 3 * l;
                let d = qi.view((c, cl), (3, 3))
                    - sol.station_joint_covariance.view((3 * j, 3 * l), (3, 3));
                assert!(
                    d.amax() < 1e-6 * sol.station_covariance[j].amax(),
                    "stations {j},{l}: {d}"
                );
            }
            let d = qi.view((c, c), (3, 3)) - sol.station_covariance[j];
            assert!(
                d.amax() < 1e-6 * sol.station_covariance[j].amax(),
                "station {j}"
            );
        }
        for k in 0..s {
            let c = 3 * n + 3 * m + k;
            let sd = qi[(c, c)].sqrt();
            assert!((sd - sol.segment_distance_sigma_m[k]).abs() < 1e-6 * sd);
        }
    }

    #[test]
    fn closed_form_start_skips_short_segments() {
        let mut syn = synthetic(41, [4, 4, 3], &stations5(), &[], 30e-9, false);
        // A beam break right after re-homing: a third segment on station 0 with two lengths.
        let d = (syn.true_stations[0] - syn.true_points[0]).norm() + 2e-6;
        let s = syn.problem.segments.len();
        syn.problem.segments.push(Segment { station: 0 });
        syn.true_distances_m.push(d);
        for i in [5, 6] {
            syn.problem.observations.push(LengthObservation {
                point: i,
                segment: s,
                length_m: (syn.true_stations[0] - syn.true_points[i]).norm() - d,
                sigma_m: 30e-9,
                path_sigma: None,
            });
        }
        syn.problem.station_hints = vec![None; 5];
        let sol = solve(&syn.problem, &SolveOptions::default()).expect("solve");
        assert!(sol.converged);
        assert!(errors(&sol, &syn).max_point_m < 1e-10);
        assert!((sol.segment_distance_m[s] - d).abs() < 1e-10);
    }

    fn small_problem() -> MultilaterationProblem {
        synthetic(1, [3, 3, 2], &stations5(), &[], 30e-9, true).problem
    }

    fn message(p: &MultilaterationProblem) -> String {
        match solve(p, &SolveOptions::default()) {
            Err(e) => e.to_string(),
            Ok(_) => panic!("expected an error"),
        }
    }

    #[test]
    fn validation_errors_are_clear() {
        let mut p = small_problem();
        p.station_hints.truncate(3);
        p.segments.retain(|s| s.station < 3);
        p.observations.retain(|o| o.segment < 3);
        assert!(message(&p).contains("3 stations given; multilateration needs at least 4"));

        let mut p = small_problem();
        p.observations[5].point = 99;
        let msg = message(&p);
        assert!(msg.contains("observation 5 refers to point 99"), "{msg}");

        let mut p = small_problem();
        p.observations[2].sigma_m = 0.0;
        let msg = message(&p);
        assert!(msg.contains("observation 2 has sigma 0 m"), "{msg}");

        let mut p = small_problem();
        p.observations.retain(|o| !(o.segment == 1 && o.point > 2));
        let msg = message(&p);
        assert!(
            msg.contains("station 1 observes 3 distinct points"),
            "{msg}"
        );

        let mut p = small_problem();
        p.segments.push(Segment { station: 7 });
        assert!(message(&p).contains("segment 5 refers to station 7"));

        // Every point seen from exactly 3 of 4 stations: 3n lengths for 3n + 16 − 6 unknowns.
        let mut p = small_problem();
        p.station_hints.truncate(4);
        p.segments.truncate(4);
        p.observations
            .retain(|o| o.segment < 4 && o.segment != o.point % 4);
        let msg = message(&p);
        assert!(msg.contains("54 observations for 70 unknowns"), "{msg}");
    }

    #[test]
    fn degenerate_input_gives_errors_not_panics() {
        // All points coplanar and no hints: the closed-form start is singular.
        let mut p = small_problem();
        for q in p.nominal_points.iter_mut() {
            q.z = 0.0;
        }
        p.station_hints = vec![None; 5];
        assert!(matches!(
            solve(&p, &SolveOptions::default()),
            Err(SolveError::Singular(_))
        ));
        // All points collinear: no datum.
        let mut p = small_problem();
        for (i, q) in p.nominal_points.iter_mut().enumerate() {
            *q = Vector3::new(0.1 * i as f64, 0.0, 0.0);
        }
        assert!(solve(&p, &SolveOptions::default()).is_err());
    }

    /// 10 000 points x 16 stations; run with `cargo test --release -- --ignored large`.
    #[test]
    #[ignore]
    fn large_problem_timing() {
        let mut stations = Vec::new();
        for k in 0..16 {
            let a = k as f64 * std::f64::consts::TAU / 16.0;
            stations.push(Vector3::new(
                0.7 + 1.8 * a.cos(),
                1.2 + 2.2 * a.sin(),
                -0.3 + 0.1 * (k % 4) as f64 * 4.0,
            ));
        }
        let two: Vec<usize> = (0..16).step_by(2).collect();
        let syn = synthetic(9, [20, 25, 20], &stations, &two, 30e-9, true);
        let t0 = std::time::Instant::now();
        let sol = solve(&syn.problem, &SolveOptions::default()).expect("solve");
        eprintln!(
            "n={} m=16 obs={} time {:?} iterations {}",
            sol.points.len(),
            syn.problem.observations.len(),
            t0.elapsed(),
            sol.iterations
        );
        let e = errors(&sol, &syn);
        eprintln!("ratio {}", (e.point_ms_m2 / e.point_pred_ms_m2).sqrt());
        assert!(sol.converged);
    }
}
