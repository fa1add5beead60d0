// The chi-square harness itself: p-values against closed forms and tables, pooling, and the
// failures it must report (a wrong distribution, samples where the pdf is 0).
#include "testing/chi_square.h"

#include <gtest/gtest.h>

#include <cmath>
#include <random>

namespace rf {
namespace testing {
namespace {

TEST(ChiSquare, PValues) {
  // Two degrees of freedom: the survival function is exp(-x / 2).
  for (double x : {0.1, 1.0, 4.0, 13.8, 40.0})
    EXPECT_NEAR(chi2_p_value(x, 2), std::exp(-0.5 * x), 1e-12 * std::exp(-0.5 * x) + 1e-15) << x;
  // Critical values of standard tables (Abramowitz & Stegun 26.8).
  EXPECT_NEAR(chi2_p_value(3.841459, 1), 0.05, 1e-6);
  EXPECT_NEAR(chi2_p_value(23.209251, 10), 0.01, 1e-6);
  EXPECT_NEAR(chi2_p_value(149.449, 100), 0.001, 1e-5);
  EXPECT_DOUBLE_EQ(chi2_p_value(0.0, 5), 1.0);
  // The Wilson-Hilferty critical value at 1e-3 (chi2_critical) is close to the exact one.
  for (int dof : {10, 50, 200}) EXPECT_NEAR(chi2_p_value(chi2_critical(dof), dof), 1e-3, 2e-4);
}

TEST(ChiSquare, AcceptsTheRightDistributionAndRejectsAWrongOne) {
  // Samples of the density 2x on [0, 1) (x = sqrt(u)), tested against 2x and against 1.
  std::mt19937_64 rng(1);
  std::uniform_real_distribution<double> uni(0.0, 1.0);
  const int n = 100000;
  ChiSquareTest right(40), wrong(40);
  for (int i = 0; i < n; ++i) {
    const double x = std::sqrt(uni(rng));
    right.add_sample(x);
    wrong.add_sample(x);
  }
  right.integrate([](double x, double) { return 2.0 * x; }, 4, n);
  wrong.integrate([](double, double) { return 1.0; }, 4, n);
  const ChiSquareResult ok = right.run(), bad = wrong.run();
  EXPECT_TRUE(ok.passed) << ok.message;
  EXPECT_EQ(ok.dof, 39);
  EXPECT_FALSE(bad.passed);
  EXPECT_LT(bad.p_value, 1e-3);
}

TEST(ChiSquare, PoolsLowCellsAndFailsOnSamplesWherePdfIsZero) {
  // Expected counts 1, 1, 2, 3, 10, 20: the four smallest make one cell of 7.
  ChiSquareTest t(6);
  const double expected[] = {1, 1, 2, 3, 10, 20}, observed[] = {0, 2, 2, 3, 10, 20};
  for (int i = 0; i < 6; ++i) {
    t.expected()[size_t(i)] = expected[i];
    t.observed()[size_t(i)] = observed[i];
  }
  ChiSquareResult r = t.run();
  EXPECT_TRUE(r.passed) << r.message;
  EXPECT_EQ(r.dof, 2);
  EXPECT_DOUBLE_EQ(r.statistic, 0.0);
  // A rest below 5 joins the last pooled cell: 1 + 1 + 1 + 1 + 2 = 6, then the 3 joins it.
  ChiSquareTest rest(6);
  const double e2[] = {1, 1, 2, 1, 3, 1};
  for (int i = 0; i < 6; ++i) rest.expected()[size_t(i)] = rest.observed()[size_t(i)] = e2[i];
  r = rest.run();
  EXPECT_EQ(r.dof, 0);
  EXPECT_FALSE(r.passed);  // one cell left: nothing to test
  // One sample in a cell of pdf 0 fails however well the rest fits.
  t.expected()[5] = 0.0;
  t.observed()[5] = 1.0;
  r = t.run();
  EXPECT_FALSE(r.passed);
  EXPECT_EQ(r.zero_pdf_samples, 1.0);
  EXPECT_NE(r.message.find("pdf is 0"), std::string::npos);
}

}  // namespace
}  // namespace testing
}  // namespace rf
