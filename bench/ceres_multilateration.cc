// Ceres Solver peer for `cargo bench --bench solve_session`: solves the same extracted
// multilateration problem geocal solves, from the same start, and reports the time of the
// solve alone (problem assembly and file reading excluded). Written as fast as Ceres gets for
// this problem: analytic Jacobians, station and homing distance as one parameter block, points
// eliminated first by DENSE_SCHUR, and (given RADIUS) a first trust region large enough for
// Gauss-Newton steps: from the bench's start Ceres's default radius of 1e4 damps the network's
// weak directions and takes 9-14 iterations where 3 suffice.
//
// Built by bench/build_ceres_peer.sh (needs Debian's libceres-dev). Usage:
//   ceres_multilateration PROBLEM.txt POINTS_OUT.txt [THREADS [RADIUS]]
// PROBLEM.txt (whitespace separated, written by the bench):
//   n m s nobs
//   n lines: nominal point x y z            (the start of the points)
//   m lines: start station x y z
//   s lines: start homing distance, station of the segment
//   nobs lines: point segment length_m sigma_m
//   6 lines: point axis                       (coordinates held: the gauge)
// Prints one JSON line: {"time_s":..,"iterations":..,"chi2":..,"chi2_start":..,"converged":..,
// "fused":.., "ceres_total_s":.., ...} (the ceres_* fields: Ceres's own Solver::Summary times)
// and writes the solved points (x y z per line) to POINTS_OUT.txt.

#include <ceres/ceres.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <iostream>
#include <map>
#include <set>
#include <vector>

namespace {

// The analytic form of one length: residual = (length - (|S - X| - d)) / sigma.
// Jacobians: d/dS = -u / sigma, d/dd = +1 / sigma, d/dX = +u / sigma, u = (S - X) / |S - X|.
// When every station has one homing distance, station and distance are one block of 4
// (`FusedLength`): fewer blocks, the form a Ceres user writes for this problem.
class FusedLength : public ceres::SizedCostFunction<1, 4, 3> {
 public:
  FusedLength(double length, double sigma) : length_(length), inv_sigma_(1.0 / sigma) {}

  bool Evaluate(double const* const* parameters, double* residuals,
                double** jacobians) const override {
    const double* sd = parameters[0];
    const double* x = parameters[1];
    const double dx = sd[0] - x[0], dy = sd[1] - x[1], dz = sd[2] - x[2];
    const double r = std::sqrt(dx * dx + dy * dy + dz * dz);
    residuals[0] = (length_ - (r - sd[3])) * inv_sigma_;
    if (jacobians != nullptr) {
      const double k = inv_sigma_ / r;
      if (jacobians[0] != nullptr) {
        jacobians[0][0] = -dx * k;
        jacobians[0][1] = -dy * k;
        jacobians[0][2] = -dz * k;
        jacobians[0][3] = inv_sigma_;
      }
      if (jacobians[1] != nullptr) {
        jacobians[1][0] = dx * k;
        jacobians[1][1] = dy * k;
        jacobians[1][2] = dz * k;
      }
    }
    return true;
  }

 private:
  double length_;
  double inv_sigma_;
};

// The same length with station and distance as separate blocks (stations with several beam
// segments share their position).
class SplitLength : public ceres::SizedCostFunction<1, 3, 3, 1> {
 public:
  SplitLength(double length, double sigma) : length_(length), inv_sigma_(1.0 / sigma) {}

  bool Evaluate(double const* const* parameters, double* residuals,
                double** jacobians) const override {
    const double* x = parameters[0];
    const double* st = parameters[1];
    const double d = parameters[2][0];
    const double dx = st[0] - x[0], dy = st[1] - x[1], dz = st[2] - x[2];
    const double r = std::sqrt(dx * dx + dy * dy + dz * dz);
    residuals[0] = (length_ - (r - d)) * inv_sigma_;
    if (jacobians != nullptr) {
      const double k = inv_sigma_ / r;
      if (jacobians[0] != nullptr) {
        jacobians[0][0] = dx * k;
        jacobians[0][1] = dy * k;
        jacobians[0][2] = dz * k;
      }
      if (jacobians[1] != nullptr) {
        jacobians[1][0] = -dx * k;
        jacobians[1][1] = -dy * k;
        jacobians[1][2] = -dz * k;
      }
      if (jacobians[2] != nullptr) jacobians[2][0] = inv_sigma_;
    }
    return true;
  }

 private:
  double length_;
  double inv_sigma_;
};

}  // namespace

int main(int argc, char** argv) {
  if (argc < 3) {
    std::cerr << "usage: " << argv[0] << " PROBLEM.txt POINTS_OUT.txt [THREADS [RADIUS]]\n";
    return 2;
  }
  const int threads = argc > 3 ? std::atoi(argv[3]) : 2;
  // The trust region's first radius (Ceres's default 1e4 when not given). A large one makes
  // the first steps Gauss-Newton steps, which this problem takes from its start.
  const double radius = argc > 4 ? std::atof(argv[4]) : 0.0;
  std::ifstream in(argv[1]);
  size_t n, m, s, nobs;
  if (!(in >> n >> m >> s >> nobs)) {
    std::cerr << argv[1] << ": cannot read the sizes line\n";
    return 1;
  }
  std::vector<double> points(3 * n), stations(3 * m), distances(s);
  std::vector<size_t> segment_station(s);
  for (auto& v : points) in >> v;
  for (auto& v : stations) in >> v;
  for (size_t k = 0; k < s; ++k) in >> distances[k] >> segment_station[k];
  std::vector<size_t> obs_point(nobs), obs_segment(nobs);
  std::vector<double> obs_length(nobs), obs_sigma(nobs);
  for (size_t k = 0; k < nobs; ++k) in >> obs_point[k] >> obs_segment[k] >> obs_length[k] >> obs_sigma[k];
  std::map<size_t, std::vector<int>> fixed;
  for (int k = 0; k < 6; ++k) {
    size_t point;
    int axis;
    in >> point >> axis;
    fixed[point].push_back(axis);
  }
  if (!in) {
    std::cerr << argv[1] << ": the file ends early\n";
    return 1;
  }

  ceres::Problem::Options problem_options;
  problem_options.cost_function_ownership = ceres::TAKE_OWNERSHIP;
  ceres::Problem problem(problem_options);
  // One homing distance per station: station and distance fused into one block of 4.
  std::vector<int> segments_of_station(m, 0);
  for (size_t k = 0; k < s; ++k) segments_of_station[segment_station[k]] += 1;
  bool fused = true;
  for (int c : segments_of_station) fused = fused && c == 1;
  std::vector<double> station_distance(fused ? 4 * m : 0);
  if (fused) {
    for (size_t k = 0; k < s; ++k) {
      const size_t j = segment_station[k];
      for (int a = 0; a < 3; ++a) station_distance[4 * j + a] = stations[3 * j + a];
      station_distance[4 * j + 3] = distances[k];
    }
  }
  for (size_t k = 0; k < nobs; ++k) {
    const size_t seg = obs_segment[k];
    double* point = &points[3 * obs_point[k]];
    if (fused) {
      problem.AddResidualBlock(new FusedLength(obs_length[k], obs_sigma[k]), nullptr,
                               &station_distance[4 * segment_station[seg]], point);
    } else {
      problem.AddResidualBlock(new SplitLength(obs_length[k], obs_sigma[k]), nullptr, point,
                               &stations[3 * segment_station[seg]], &distances[seg]);
    }
  }
  // The gauge: the same six coordinates held as in the SciPy comparison.
  for (const auto& [point, axes] : fixed) {
    problem.SetManifold(&points[3 * point], new ceres::SubsetManifold(3, axes));
  }
  // Points first: the Schur complement eliminates them, leaving stations and distances.
  auto* ordering = new ceres::ParameterBlockOrdering;
  for (size_t i = 0; i < n; ++i) ordering->AddElementToGroup(&points[3 * i], 0);
  if (fused) {
    for (size_t j = 0; j < m; ++j) ordering->AddElementToGroup(&station_distance[4 * j], 1);
  } else {
    for (size_t j = 0; j < m; ++j) ordering->AddElementToGroup(&stations[3 * j], 1);
    for (size_t k = 0; k < s; ++k) ordering->AddElementToGroup(&distances[k], 1);
  }

  ceres::Solver::Options options;
  options.linear_solver_type = ceres::DENSE_SCHUR;
  options.linear_solver_ordering.reset(ordering);
  options.num_threads = threads;
  options.max_num_iterations = 100;
  // geocal stops at a relative cost decrease of 1e-12.
  options.function_tolerance = 1e-12;
  options.gradient_tolerance = 1e-14;
  options.parameter_tolerance = 1e-14;
  if (radius > 0.0) {
    options.initial_trust_region_radius = radius;
    options.max_trust_region_radius = std::max(options.max_trust_region_radius, radius);
  }
  options.logging_type = ceres::SILENT;
  ceres::Solver::Summary summary;
  const auto t0 = std::chrono::steady_clock::now();
  ceres::Solve(options, &problem, &summary);
  const double time_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();

  std::ofstream out(argv[2]);
  out.precision(17);
  for (size_t i = 0; i < n; ++i) {
    out << points[3 * i] << ' ' << points[3 * i + 1] << ' ' << points[3 * i + 2] << '\n';
  }
  // Ceres' cost is half the sum of squared residuals.
  std::printf(
      "{\"time_s\":%.6f,\"iterations\":%d,\"chi2\":%.9f,\"chi2_start\":%.9f,\"converged\":%s,"
      "\"termination\":\"%s\",\"fused\":%s,\"ceres_total_s\":%.6f,\"ceres_preprocessor_s\":%.6f,"
      "\"ceres_minimizer_s\":%.6f,\"ceres_linear_solver_s\":%.6f,\"ceres_jacobian_s\":%.6f,"
      "\"ceres_residual_s\":%.6f,\"initial_trust_region_radius\":%g}\n",
      time_s, static_cast<int>(summary.iterations.size()) - 1, 2.0 * summary.final_cost,
      2.0 * summary.initial_cost, summary.IsSolutionUsable() ? "true" : "false",
      ceres::TerminationTypeToString(summary.termination_type), fused ? "true" : "false",
      summary.total_time_in_seconds, summary.preprocessor_time_in_seconds,
      summary.minimizer_time_in_seconds, summary.linear_solver_time_in_seconds,
      summary.jacobian_evaluation_time_in_seconds, summary.residual_evaluation_time_in_seconds,
      options.initial_trust_region_radius);
  return summary.IsSolutionUsable() ? 0 : 1;
}
