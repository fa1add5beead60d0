// Chi-square goodness-of-fit tests for the sampling tests (renderfarm_testing, not part of the
// worker).
#pragma once

#include <cmath>
#include <functional>
#include <string>
#include <vector>

namespace rf {
namespace testing {

// Critical value of the chi-square distribution with `dof` degrees of freedom at significance
// 1e-3, by the Wilson-Hilferty approximation (accurate to a few percent for dof >= 3).
inline double chi2_critical(int dof) {
  const double k = dof, z = 3.09;
  const double t = 1.0 - 2.0 / (9.0 * k) + z * std::sqrt(2.0 / (9.0 * k));
  return k * t * t * t;
}

// P(X >= statistic) for X chi-square distributed with `dof` degrees of freedom: the regularized
// upper incomplete gamma function Q(dof / 2, statistic / 2).
double chi2_p_value(double statistic, int dof);

struct ChiSquareResult {
  double statistic = 0.0;
  int dof = 0;           // cells used (after pooling) - 1
  double p_value = 0.0;  // of the statistic; 0 if the test could not be made
  double zero_pdf_samples = 0.0;  // samples in cells whose integrated pdf is 0
  bool passed = false;
  std::string message;   // why it failed (empty if passed), with the figures
};

// A sampling routine against its pdf, in the manner of Mitsuba's test_warp (ChiSquareTest):
// samples are counted in a grid of cells over the unit square of the test's coordinates, the
// expected counts are the pdf integrated over each cell, cells of expected count below 5 are
// pooled (with the next smallest ones until the pool reaches 5), Pearson's statistic gives a
// p-value, and the test fails below the significance level, when too few cells remain, or as
// soon as one sample lands in a cell where the pdf is 0.
class ChiSquareTest {
 public:
  // nx x ny cells over [0, 1)^2 (ny = 1: one-dimensional).
  explicit ChiSquareTest(int nx, int ny = 1);

  // A sample at (x, y) of the unit square (coordinates outside are clamped to the edge cells).
  void add_sample(double x, double y = 0.5);

  // The expected counts: `density` (with respect to dx dy on the unit square) integrated over
  // each cell by the midpoint rule on sub x sub points, times sample_count (every sample drawn,
  // including those that gave none).
  void integrate(const std::function<double(double x, double y)>& density, int sub,
                 double sample_count);

  std::vector<double>& observed() { return observed_; }
  std::vector<double>& expected() { return expected_; }

  ChiSquareResult run(double significance = 1e-3) const;

 private:
  int nx_, ny_;
  std::vector<double> observed_, expected_;
};

}  // namespace testing
}  // namespace rf
