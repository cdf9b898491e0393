// Ceres Solver peer for `cargo bench --bench solve_session`: solves the same extracted
// multilateration problem geocal solves, from the same start, and reports the time of the
// solve alone (problem assembly and file reading excluded).
//
// Built by bench/build_ceres_peer.sh (needs Debian's libceres-dev). Usage:
//   ceres_multilateration PROBLEM.txt POINTS_OUT.txt [THREADS]
// PROBLEM.txt (whitespace separated, written by the bench):
//   n m s nobs
//   n lines: nominal point x y z            (the start of the points)
//   m lines: start station x y z
//   s lines: start homing distance, station of the segment
//   nobs lines: point segment length_m sigma_m
//   6 lines: point axis                       (coordinates held: the gauge)
// Prints one JSON line: {"time_s":..,"iterations":..,"chi2":..,"chi2_start":..,"converged":..}
// and writes the solved points (x y z per line) to POINTS_OUT.txt.

#include <ceres/ceres.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <map>
#include <set>
#include <vector>

namespace {

struct LengthResidual {
  LengthResidual(double length, double sigma) : length_(length), inv_sigma_(1.0 / sigma) {}

  template <typename T>
  bool operator()(const T* point, const T* station, const T* distance, T* residual) const {
    const T dx = station[0] - point[0];
    const T dy = station[1] - point[1];
    const T dz = station[2] - point[2];
    const T predicted = ceres::sqrt(dx * dx + dy * dy + dz * dz) - distance[0];
    residual[0] = (T(length_) - predicted) * T(inv_sigma_);
    return true;
  }

  double length_;
  double inv_sigma_;
};

}  // namespace

int main(int argc, char** argv) {
  if (argc < 3) {
    std::cerr << "usage: " << argv[0] << " PROBLEM.txt POINTS_OUT.txt [THREADS]\n";
    return 2;
  }
  const int threads = argc > 3 ? std::atoi(argv[3]) : 2;
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
  for (size_t k = 0; k < nobs; ++k) {
    auto* cost = new ceres::AutoDiffCostFunction<LengthResidual, 1, 3, 3, 1>(
        new LengthResidual(obs_length[k], obs_sigma[k]));
    const size_t seg = obs_segment[k];
    problem.AddResidualBlock(cost, nullptr, &points[3 * obs_point[k]],
                             &stations[3 * segment_station[seg]], &distances[seg]);
  }
  // The gauge: the same six coordinates held as in the SciPy comparison.
  for (const auto& [point, axes] : fixed) {
    problem.SetManifold(&points[3 * point], new ceres::SubsetManifold(3, axes));
  }
  // Points first: the Schur complement eliminates them, leaving stations and distances.
  auto* ordering = new ceres::ParameterBlockOrdering;
  for (size_t i = 0; i < n; ++i) ordering->AddElementToGroup(&points[3 * i], 0);
  for (size_t j = 0; j < m; ++j) ordering->AddElementToGroup(&stations[3 * j], 1);
  for (size_t k = 0; k < s; ++k) ordering->AddElementToGroup(&distances[k], 1);

  ceres::Solver::Options options;
  options.linear_solver_type = ceres::DENSE_SCHUR;
  options.linear_solver_ordering.reset(ordering);
  options.num_threads = threads;
  options.max_num_iterations = 100;
  // geocal stops at a relative cost decrease of 1e-12.
  options.function_tolerance = 1e-12;
  options.gradient_tolerance = 1e-14;
  options.parameter_tolerance = 1e-14;
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
      "\"termination\":\"%s\"}\n",
      time_s, static_cast<int>(summary.iterations.size()) - 1, 2.0 * summary.final_cost,
      2.0 * summary.initial_cost, summary.IsSolutionUsable() ? "true" : "false",
      ceres::TerminationTypeToString(summary.termination_type));
  return summary.IsSolutionUsable() ? 0 : 1;
}
