// Monte Carlo estimator bookkeeping shared by the renderer and its tests: Welford's running
// mean and M2 (the per-pixel statistics of a TileBuffer), Chan et al.'s merge of two such
// summaries, and the variance of an importance-sampling estimator by quadrature.
#pragma once

#include <cstdint>
#include <functional>

namespace rf {

// Running mean and sum of squared deviations (Welford 1962), numerically stable.
struct RunningStats {
  uint64_t n = 0;
  double mean = 0.0;
  double m2 = 0.0;
  void add(double x) {
    ++n;
    const double delta = x - mean;
    mean += delta / double(n);
    m2 += delta * (x - mean);
  }
  // Chan, Golub & LeVeque's parallel combination: the summary of the union of both samples.
  void merge(const RunningStats& o) {
    if (o.n == 0) return;
    if (n == 0) {
      *this = o;
      return;
    }
    const double total = double(n + o.n);
    const double delta = o.mean - mean;
    mean += delta * double(o.n) / total;
    m2 += o.m2 + delta * delta * double(n) * double(o.n) / total;
    n += o.n;
  }
  // Unbiased per-sample variance s^2 = M2 / (n - 1); 0 for n < 2.
  double sample_variance() const { return n > 1 ? m2 / double(n - 1) : 0.0; }
  // Estimated variance of the mean, s^2 / n.
  double variance_of_mean() const { return n > 1 ? sample_variance() / double(n) : 0.0; }
};

// Per-sample variance of the primary estimator h(X) / p(X), X ~ p, of I = integral of h over
// [a, b]: integral of h^2 / p minus I^2, by the midpoint rule with `steps` cells (cells where
// p = 0 must have h = 0, otherwise the estimator is biased; they are skipped).
inline double importance_sampling_variance(const std::function<double(double)>& h,
                                           const std::function<double(double)>& p, double a,
                                           double b, int steps = 200000) {
  const double dx = (b - a) / steps;
  double integral = 0.0, second = 0.0;
  for (int i = 0; i < steps; ++i) {
    const double x = a + (i + 0.5) * dx;
    const double hx = h(x), px = p(x);
    integral += hx * dx;
    if (px > 0.0) second += hx * hx / px * dx;
  }
  return second - integral * integral;
}

}  // namespace rf
