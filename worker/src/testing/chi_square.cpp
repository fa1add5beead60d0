#include "testing/chi_square.h"

#include <algorithm>
#include <cstdio>
#include <utility>

namespace rf {
namespace testing {

namespace {

// Regularized lower incomplete gamma P(a, x) by its series (converges fast for x < a + 1).
double gamma_p_series(double a, double x) {
  double term = 1.0 / a, sum = term;
  for (int n = 1; n < 10000; ++n) {
    term *= x / (a + n);
    sum += term;
    if (std::fabs(term) < std::fabs(sum) * 1e-15) break;
  }
  return sum * std::exp(-x + a * std::log(x) - std::lgamma(a));
}

// Regularized upper incomplete gamma Q(a, x) by its continued fraction (x >= a + 1), evaluated
// by the modified Lentz method.
double gamma_q_fraction(double a, double x) {
  const double tiny = 1e-300;
  double b = x + 1.0 - a, c = 1.0 / tiny, d = 1.0 / b, h = d;
  for (int i = 1; i < 10000; ++i) {
    const double an = -i * (i - a);
    b += 2.0;
    d = an * d + b;
    if (std::fabs(d) < tiny) d = tiny;
    c = b + an / c;
    if (std::fabs(c) < tiny) c = tiny;
    d = 1.0 / d;
    const double delta = d * c;
    h *= delta;
    if (std::fabs(delta - 1.0) < 1e-15) break;
  }
  return std::exp(-x + a * std::log(x) - std::lgamma(a)) * h;
}

}  // namespace

double chi2_p_value(double statistic, int dof) {
  if (dof < 1) return 0.0;
  if (!(statistic > 0.0)) return 1.0;
  const double a = 0.5 * dof, x = 0.5 * statistic;
  return x < a + 1.0 ? 1.0 - gamma_p_series(a, x) : gamma_q_fraction(a, x);
}

ChiSquareTest::ChiSquareTest(int nx, int ny)
    : nx_(nx), ny_(ny), observed_(size_t(nx) * size_t(ny), 0.0),
      expected_(size_t(nx) * size_t(ny), 0.0) {}

void ChiSquareTest::add_sample(double x, double y) {
  const int ix = std::min(nx_ - 1, std::max(0, int(x * nx_)));
  const int iy = std::min(ny_ - 1, std::max(0, int(y * ny_)));
  observed_[size_t(iy) * size_t(nx_) + size_t(ix)] += 1.0;
}

void ChiSquareTest::integrate(const std::function<double(double, double)>& density, int sub,
                              double sample_count) {
  const double cell_fraction = 1.0 / (double(nx_) * ny_ * sub * sub);
  for (int iy = 0; iy < ny_; ++iy)
    for (int ix = 0; ix < nx_; ++ix) {
      double mass = 0.0;
      for (int a = 0; a < sub; ++a)
        for (int b = 0; b < sub; ++b)
          mass += density((ix + (a + 0.5) / sub) / nx_, (iy + (b + 0.5) / sub) / ny_) *
                  cell_fraction;
      expected_[size_t(iy) * size_t(nx_) + size_t(ix)] = mass * sample_count;
    }
}

ChiSquareResult ChiSquareTest::run(double significance) const {
  constexpr double kMinExpected = 5.0;
  ChiSquareResult r;
  // Cells by increasing expected count; cells where the pdf is 0 must stay empty.
  std::vector<std::pair<double, double>> cells;  // (expected, observed)
  for (size_t i = 0; i < observed_.size(); ++i) {
    if (expected_[i] > 0.0)
      cells.emplace_back(expected_[i], observed_[i]);
    else
      r.zero_pdf_samples += observed_[i];
  }
  std::stable_sort(cells.begin(), cells.end(),
                   [](const auto& a, const auto& b) { return a.first < b.first; });
  // Pool the low cells, smallest first, into cells of expected count >= kMinExpected; a rest
  // below it joins the last cell.
  std::vector<std::pair<double, double>> pooled;
  double pool_e = 0.0, pool_o = 0.0;
  for (const auto& [e, o] : cells) {
    pool_e += e;
    pool_o += o;
    if (pool_e >= kMinExpected) {
      pooled.emplace_back(pool_e, pool_o);
      pool_e = pool_o = 0.0;
    }
  }
  if (pool_e > 0.0) {
    if (pooled.empty()) {
      pooled.emplace_back(pool_e, pool_o);
    } else {
      pooled.back().first += pool_e;
      pooled.back().second += pool_o;
    }
  }
  for (const auto& [e, o] : pooled) r.statistic += (o - e) * (o - e) / e;
  r.dof = int(pooled.size()) - 1;
  r.p_value = chi2_p_value(r.statistic, r.dof);
  char buf[256];
  if (r.zero_pdf_samples > 0.0) {
    std::snprintf(buf, sizeof buf, "%.0f samples in cells where the pdf is 0",
                  r.zero_pdf_samples);
  } else if (r.dof < 1) {
    std::snprintf(buf, sizeof buf, "too few cells of expected count >= %.0f (%d)", kMinExpected,
                  r.dof + 1);
  } else if (r.p_value < significance) {
    std::snprintf(buf, sizeof buf,
                  "chi-square %.4g with %d degrees of freedom: p-value %.3g below %.3g",
                  r.statistic, r.dof, r.p_value, significance);
  } else {
    r.passed = true;
    return r;
  }
  r.message = buf;
  return r;
}

}  // namespace testing
}  // namespace rf
