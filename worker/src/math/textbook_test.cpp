// Textbook Monte Carlo results (Shirley, "Monte Carlo Methods", section 3 and Table 1),
// reproduced with the project's own estimator code: RunningStats (the Welford statistics of
// every TileBuffer), importance_sampling_variance, and the samplers.
#include <gtest/gtest.h>

#include <cmath>
#include <functional>

#include "math/estimators.h"
#include "sampling/samplers.h"

namespace rf {
namespace {

struct Pdf {
  const char* name;
  std::function<double(double)> pdf;
  std::function<double(double)> inverse_cdf;  // maps u in [0, 1) to x ~ pdf
  double table_variance;                      // Shirley's Table 1
  double table_samples;                       // N for a standard error of 0.008
};

// I = integral of x over [0, 4] = 8.
std::vector<Pdf> table1() {
  return {
      {"(6-x)/16", [](double x) { return (6 - x) / 16; },
       [](double u) { return 6 - std::sqrt(36 - 32 * u); }, 56.8, 887500},
      {"1/4", [](double) { return 0.25; }, [](double u) { return 4 * u; }, 21.3, 332812},
      {"(x+2)/16", [](double x) { return (x + 2) / 16; },
       [](double u) { return -2 + std::sqrt(4 + 32 * u); }, 6.3, 98437},
      {"x/8", [](double x) { return x / 8; }, [](double u) { return 4 * std::sqrt(u); }, 0.0, 1},
  };
}

TEST(Textbook, ShirleyTable1VariancesAndSampleCounts) {
  const auto h = [](double x) { return x; };
  for (const Pdf& p : table1()) {
    const double var = importance_sampling_variance(h, p.pdf, 0.0, 4.0);
    // Table 1 gives one decimal.
    EXPECT_NEAR(var, p.table_variance, 0.05) << p.name;
    // Samples for a standard error of 0.008: N = variance / 0.008^2 (at least 1), with the
    // table's rounded variance as in the text.
    const double n = std::max(1.0, std::floor(std::round(var * 10) / 10 / (0.008 * 0.008)));
    EXPECT_NEAR(n, p.table_samples, 1.0) << p.name;
    // The same variance measured by sampling with the independent sampler.
    const Sampler sampler(SamplerType::Independent, 17);
    RunningStats stats;
    for (uint32_t i = 0; i < 200000; ++i) {
      const double x = p.inverse_cdf(sampler.value(0, i, 0));
      stats.add(h(x) / p.pdf(x));
    }
    EXPECT_NEAR(stats.mean, 8.0, 4 * std::sqrt(std::max(0.0, var) / 200000) + 1e-9) << p.name;
    EXPECT_NEAR(stats.sample_variance(), var, 0.05 * var + 1e-6) << p.name;
  }
}

// Stratified sampling of the same integral with N strata: variance 21.3 / N^3. The
// stratified sampler's batch of N = 2^k samples is exactly such a stratification in every
// dimension >= 2 (Latin hypercube); pixels give independent replicates.
TEST(Textbook, StratifiedUniformSamplingVarianceIsCubic) {
  const Sampler sampler(SamplerType::Stratified, 5);
  for (uint32_t batch : {3u, 5u, 7u}) {  // sizes 4, 16, 64
    const BatchRange r = batch_range(batch);
    const double n = r.size;
    RunningStats across_pixels;
    const uint32_t pixels = 20000;
    for (uint32_t px = 0; px < pixels; ++px) {
      double sum = 0.0;
      for (uint32_t j = 0; j < r.size; ++j)
        sum += 4.0 * (4.0 * sampler.value(px, uint32_t(r.start + j), 2));  // h / p, p = 1/4
      across_pixels.add(sum / n);
    }
    const double expected = 256.0 / 12.0 / (n * n * n);  // = 21.3 / N^3
    EXPECT_NEAR(across_pixels.mean, 8.0, 4 * std::sqrt(expected / pixels));
    // Relative standard error of a variance estimate from 20000 replicates is ~1%.
    EXPECT_NEAR(across_pixels.sample_variance(), expected, 0.06 * expected) << "N = " << n;
  }
}

// Integral of cos(pi x / 2) over [0, 1] = 2 / pi: uniform sampling has variance ~0.0947 and
// the pdf (3/2)(1 - x^2) ~0.000990.
TEST(Textbook, CosineIntegralImportanceSampling) {
  const auto h = [](double x) { return std::cos(M_PI * x / 2); };
  const double v_uniform = importance_sampling_variance(h, [](double) { return 1.0; }, 0, 1);
  const auto p = [](double x) { return 1.5 * (1 - x * x); };
  const double v_is = importance_sampling_variance(h, p, 0, 1);
  EXPECT_NEAR(v_uniform, 0.0947, 5e-5);
  EXPECT_NEAR(v_is, 0.000990, 5e-6);
  // Sampling p by inverting its CDF (3x - x^3)/2 = u: the trigonometric root of the cubic.
  const auto inv = [](double u) { return 2 * std::cos(std::acos(-u) / 3 - 2 * M_PI / 3); };
  const Sampler sampler(SamplerType::Independent, 23);
  RunningStats uniform, importance;
  for (uint32_t i = 0; i < 200000; ++i) {
    const double u = sampler.value(1, i, 0);
    uniform.add(h(u));
    const double x = inv(u);
    importance.add(h(x) / p(x));
  }
  EXPECT_NEAR(uniform.mean, 2 / M_PI, 4 * std::sqrt(v_uniform / 200000));
  EXPECT_NEAR(importance.mean, 2 / M_PI, 4 * std::sqrt(v_is / 200000));
  EXPECT_NEAR(uniform.sample_variance(), v_uniform, 0.03 * v_uniform);
  EXPECT_NEAR(importance.sample_variance(), v_is, 0.05 * v_is);
}

TEST(Textbook, RunningStatsMergeEqualsOnePass) {
  const Sampler sampler(SamplerType::Independent, 2);
  RunningStats all, a, b;
  for (uint32_t i = 0; i < 1000; ++i) {
    const double x = 10.0 + sampler.value(0, i, 0);
    all.add(x);
    (i < 300 ? a : b).add(x);
  }
  a.merge(b);
  EXPECT_EQ(a.n, all.n);
  EXPECT_NEAR(a.mean, all.mean, 1e-12);
  EXPECT_NEAR(a.m2, all.m2, 1e-9);
}

}  // namespace
}  // namespace rf
