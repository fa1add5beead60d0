#include "sampling.h"

#include <gtest/gtest.h>

#include <functional>
#include <random>
#include <vector>

namespace rf {
namespace {

// Upper critical value of the chi-square distribution with `dof` degrees of freedom at
// significance 1e-3 (Wilson-Hilferty approximation, z = 3.09).
double chi2_critical(int dof) {
  const double k = dof, z = 3.09;
  const double t = 1.0 - 2.0 / (9.0 * k) + z * std::sqrt(2.0 / (9.0 * k));
  return k * t * t * t;
}

// Pearson statistic of observed vs expected counts; cells with expected < 5 are pooled.
double chi2_statistic(const std::vector<double>& observed, const std::vector<double>& expected,
                      int* dof) {
  double stat = 0.0, pooled_obs = 0.0, pooled_exp = 0.0;
  int cells = 0;
  for (size_t i = 0; i < observed.size(); ++i) {
    if (expected[i] < 5.0) {
      pooled_obs += observed[i];
      pooled_exp += expected[i];
      continue;
    }
    stat += (observed[i] - expected[i]) * (observed[i] - expected[i]) / expected[i];
    ++cells;
  }
  if (pooled_exp >= 5.0) {
    stat += (pooled_obs - pooled_exp) * (pooled_obs - pooled_exp) / pooled_exp;
    ++cells;
  } else if (pooled_obs > 0.0 && pooled_exp == 0.0) {
    stat = 1e30;  // samples where the pdf is zero
  }
  *dof = cells - 1;
  return stat;
}

using DirSampler = std::function<Vec3(Point2)>;
using DirPdf = std::function<float(Vec3)>;

// Integral of pdf over the sphere by the midpoint rule in (z, phi), where d(omega) = dz dphi.
double integrate_sphere(const DirPdf& pdf, int nz = 400, int nphi = 400) {
  double sum = 0.0;
  const double dz = 2.0 / nz, dphi = 2.0 * M_PI / nphi;
  for (int i = 0; i < nz; ++i)
    for (int j = 0; j < nphi; ++j) {
      const double z = -1.0 + (i + 0.5) * dz, phi = (j + 0.5) * dphi;
      const double r = std::sqrt(std::max(0.0, 1.0 - z * z));
      sum += pdf(Vec3(float(r * std::cos(phi)), float(r * std::sin(phi)), float(z))) * dz * dphi;
    }
  return sum;
}

// Chi-square test of samples against pdf over a (z, phi) grid on the sphere.
bool sphere_chi2_passes(const DirSampler& sample, const DirPdf& pdf) {
  const int nz = 10, nphi = 20, sub = 16, n = 200000;
  std::vector<double> observed(nz * nphi, 0.0), expected(nz * nphi, 0.0);
  std::mt19937_64 rng(12345);
  std::uniform_real_distribution<float> uni(0.f, 1.f);
  for (int s = 0; s < n; ++s) {
    const Vec3 w = sample({uni(rng), uni(rng)});
    double phi = std::atan2(w.y, w.x);
    if (phi < 0) phi += 2 * M_PI;
    const int iz = std::min(nz - 1, int((w.z + 1.0) * 0.5 * nz));
    const int ip = std::min(nphi - 1, int(phi / (2 * M_PI) * nphi));
    observed[size_t(iz * nphi + ip)] += 1.0;
  }
  for (int iz = 0; iz < nz; ++iz)
    for (int ip = 0; ip < nphi; ++ip) {
      double integral = 0.0;
      const double dz = 2.0 / nz / sub, dphi = 2 * M_PI / nphi / sub;
      for (int a = 0; a < sub; ++a)
        for (int b = 0; b < sub; ++b) {
          const double z = -1.0 + iz * 2.0 / nz + (a + 0.5) * dz;
          const double phi = ip * 2 * M_PI / nphi + (b + 0.5) * dphi;
          const double r = std::sqrt(std::max(0.0, 1.0 - z * z));
          integral += pdf(Vec3(float(r * std::cos(phi)), float(r * std::sin(phi)), float(z))) *
                      dz * dphi;
        }
      expected[size_t(iz * nphi + ip)] = integral * n;
    }
  int dof = 0;
  const double stat = chi2_statistic(observed, expected, &dof);
  return dof > 0 && stat < chi2_critical(dof);
}

void expect_round_trip(const DirSampler& sample, const std::function<Point2(Vec3)>& invert) {
  for (int i = 1; i < 40; ++i)
    for (int j = 1; j < 40; ++j) {
      const Point2 u{i / 40.f, j / 40.f};
      const Point2 back = invert(sample(u));
      EXPECT_NEAR(back.x, u.x, 2e-4f) << u.x << "," << u.y;
      EXPECT_NEAR(back.y, u.y, 2e-4f) << u.x << "," << u.y;
    }
}

TEST(Warps, CosineHemisphere) {
  EXPECT_NEAR(integrate_sphere(cosine_hemisphere_pdf), 1.0, 2e-3);
  expect_round_trip(sample_cosine_hemisphere, invert_cosine_hemisphere);
  EXPECT_TRUE(sphere_chi2_passes(sample_cosine_hemisphere, cosine_hemisphere_pdf));
}

TEST(Warps, UniformSphere) {
  EXPECT_NEAR(integrate_sphere(uniform_sphere_pdf), 1.0, 2e-3);
  expect_round_trip(sample_uniform_sphere, invert_uniform_sphere);
  EXPECT_TRUE(sphere_chi2_passes(sample_uniform_sphere, uniform_sphere_pdf));
}

TEST(Warps, UniformHemisphere) {
  EXPECT_NEAR(integrate_sphere(uniform_hemisphere_pdf), 1.0, 2e-3);
  expect_round_trip(sample_uniform_hemisphere, invert_uniform_hemisphere);
  EXPECT_TRUE(sphere_chi2_passes(sample_uniform_hemisphere, uniform_hemisphere_pdf));
}

TEST(Warps, ChiSquareRejectsAMismatchedPdf) {
  // The test must be able to fail: cosine-distributed samples are not uniform.
  EXPECT_FALSE(sphere_chi2_passes(sample_cosine_hemisphere, uniform_hemisphere_pdf));
}

TEST(Warps, Triangle) {
  // pdf integrates to 1 over the unit square (it is 0 outside the reference triangle).
  const int n = 1000;
  double integral = 0.0;
  for (int i = 0; i < n; ++i)
    for (int j = 0; j < n; ++j)
      integral += triangle_pdf({(i + 0.5f) / n, (j + 0.5f) / n}) / (double(n) * n);
  EXPECT_NEAR(integral, 1.0, 5e-3);
  for (int i = 1; i < 40; ++i)
    for (int j = 1; j < 40; ++j) {
      const Point2 u{i / 40.f, j / 40.f};
      const Point2 b = sample_triangle(u);
      EXPECT_GT(triangle_pdf(b), 0.f);
      const Point2 back = invert_triangle(b);
      EXPECT_NEAR(back.x, u.x, 1e-5f);
      EXPECT_NEAR(back.y, u.y, 1e-5f);
    }
  // Chi-square over a grid of cells of the (b0, b1) square; expected mass = 2 x covered area.
  const int cells = 16, sub = 32, samples = 200000;
  std::vector<double> observed(cells * cells, 0.0), expected(cells * cells, 0.0);
  std::mt19937_64 rng(7);
  std::uniform_real_distribution<float> uni(0.f, 1.f);
  for (int s = 0; s < samples; ++s) {
    const Point2 b = sample_triangle({uni(rng), uni(rng)});
    const int ix = std::min(cells - 1, int(b.x * cells)), iy = std::min(cells - 1, int(b.y * cells));
    observed[size_t(iy * cells + ix)] += 1.0;
  }
  for (int iy = 0; iy < cells; ++iy)
    for (int ix = 0; ix < cells; ++ix) {
      double mass = 0.0;
      for (int a = 0; a < sub; ++a)
        for (int c = 0; c < sub; ++c) {
          const float x = (ix + (a + 0.5f) / sub) / cells, y = (iy + (c + 0.5f) / sub) / cells;
          mass += triangle_pdf({x, y}) / (double(cells) * cells * sub * sub);
        }
      expected[size_t(iy * cells + ix)] = mass * samples;
    }
  int dof = 0;
  const double stat = chi2_statistic(observed, expected, &dof);
  EXPECT_LT(stat, chi2_critical(dof));
}

TEST(Warps, ConcentricDiskRoundTrip) {
  for (int i = 1; i < 40; ++i)
    for (int j = 1; j < 40; ++j) {
      const Point2 u{i / 40.f, j / 40.f};
      const Point2 back = invert_concentric_disk(sample_concentric_disk(u));
      EXPECT_NEAR(back.x, u.x, 1e-4f);
      EXPECT_NEAR(back.y, u.y, 1e-4f);
    }
}

TEST(Warps, PowerHeuristic) {
  EXPECT_FLOAT_EQ(power_heuristic(1.f, 1.f), 0.5f);
  EXPECT_FLOAT_EQ(power_heuristic(3.f, 1.f), 0.9f);
  EXPECT_FLOAT_EQ(power_heuristic(0.f, 1.f), 0.f);
  EXPECT_FLOAT_EQ(power_heuristic(2.f, 1.f) + power_heuristic(1.f, 2.f), 1.f);
}

}  // namespace
}  // namespace rf
