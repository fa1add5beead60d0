#include "sampling/sampling.h"

#include <gtest/gtest.h>

#include "testing/chi_square.h"
#include "math/simd.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <functional>
#include <random>
#include <vector>

namespace rf {
namespace {

using testing::ChiSquareResult;
using testing::ChiSquareTest;

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

// Chi-square test of samples against pdf over a (z, phi) grid on the sphere: the test's unit
// square is x = (z + 1) / 2, y = phi / (2 pi), where d(omega) = dz dphi = 4 pi dx dy.
ChiSquareResult sphere_chi2(const DirSampler& sample, const DirPdf& pdf) {
  const int nz = 10, nphi = 20, sub = 16, n = 200000;
  ChiSquareTest chi2(nz, nphi);
  std::mt19937_64 rng(12345);
  std::uniform_real_distribution<float> uni(0.f, 1.f);
  for (int s = 0; s < n; ++s) {
    const Vec3 w = sample({uni(rng), uni(rng)});
    double phi = std::atan2(w.y, w.x);
    if (phi < 0) phi += 2 * M_PI;
    chi2.add_sample((w.z + 1.0) * 0.5, phi / (2 * M_PI));
  }
  chi2.integrate(
      [&](double x, double y) {
        const double z = 2.0 * x - 1.0, phi = 2 * M_PI * y;
        const double r = std::sqrt(std::max(0.0, 1.0 - z * z));
        return pdf(Vec3(float(r * std::cos(phi)), float(r * std::sin(phi)), float(z))) * 4 *
               M_PI;
      },
      sub, n);
  return chi2.run();
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
  const ChiSquareResult chi2 = sphere_chi2(sample_cosine_hemisphere, cosine_hemisphere_pdf);
  EXPECT_TRUE(chi2.passed) << chi2.message;
}

TEST(Warps, UniformSphere) {
  EXPECT_NEAR(integrate_sphere(uniform_sphere_pdf), 1.0, 2e-3);
  expect_round_trip(sample_uniform_sphere, invert_uniform_sphere);
  const ChiSquareResult chi2 = sphere_chi2(sample_uniform_sphere, uniform_sphere_pdf);
  EXPECT_TRUE(chi2.passed) << chi2.message;
}

TEST(Warps, UniformHemisphere) {
  EXPECT_NEAR(integrate_sphere(uniform_hemisphere_pdf), 1.0, 2e-3);
  expect_round_trip(sample_uniform_hemisphere, invert_uniform_hemisphere);
  const ChiSquareResult chi2 = sphere_chi2(sample_uniform_hemisphere, uniform_hemisphere_pdf);
  EXPECT_TRUE(chi2.passed) << chi2.message;
}

TEST(Warps, ChiSquareRejectsAMismatchedPdf) {
  // The test must be able to fail: cosine-distributed samples are not uniform.
  EXPECT_FALSE(sphere_chi2(sample_cosine_hemisphere, uniform_hemisphere_pdf).passed);
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
  // Chi-square over a grid of cells of the (b0, b1) square (twice the covered area's mass).
  const int cells = 16, sub = 32, samples = 200000;
  ChiSquareTest chi2(cells, cells);
  std::mt19937_64 rng(7);
  std::uniform_real_distribution<float> uni(0.f, 1.f);
  for (int s = 0; s < samples; ++s) {
    const Point2 b = sample_triangle({uni(rng), uni(rng)});
    chi2.add_sample(b.x, b.y);
  }
  chi2.integrate([](double x, double y) { return triangle_pdf({float(x), float(y)}); }, sub,
                 samples);
  const ChiSquareResult result = chi2.run();
  EXPECT_TRUE(result.passed) << result.message;
}

// The warps' sine and cosine against double precision, to within 4 float ulps of 1 (2^-22):
// a wrong coefficient or quarter-turn swap is off by far more.
TEST(Trig, QuarterKernelAndTurnsMatchDoublePrecision) {
  const double tol = std::ldexp(1.0, -22);
  double worst = 0.0;
  for (int i = 0; i <= 200000; ++i) {
    const float x = float(-0.8 + 1.6 * i / 200000.0);  // a little beyond +-pi/4
    float s, c;
    sincos_quarter(x, &s, &c);
    worst = std::max({worst, std::fabs(s - std::sin(double(x))),
                      std::fabs(c - std::cos(double(x)))});
  }
  EXPECT_LT(worst, tol);
  worst = 0.0;
  // Every quarter turn, its boundaries (where the nearest quarter changes) and both ends.
  for (int i = 0; i <= 400000; ++i) {
    const float u = float(i / 400000.0);
    float s, c;
    sincos_turn(u, &s, &c);
    const double phi = 2.0 * M_PI * double(u);
    worst = std::max({worst, std::fabs(s - std::sin(phi)), std::fabs(c - std::cos(phi))});
  }
  for (float u : {0.f, 0.125f, 0.375f, 0.625f, 0.875f, 1.f, std::nextafter(0.125f, 0.f),
                  std::nextafter(0.875f, 1.f), std::nextafter(1.f, 0.f)}) {
    float s, c;
    sincos_turn(u, &s, &c);
    const double phi = 2.0 * M_PI * double(u);
    worst = std::max({worst, std::fabs(s - std::sin(phi)), std::fabs(c - std::cos(phi))});
  }
  EXPECT_LT(worst, tol);
}

// The packet tracer's four-lane disk warps give the scalar warps' bits, including at the
// disk's centre (0/0 in the concentric map) and at the quarter-turn boundaries.
TEST(Warps, FourLaneDiskWarpsEqualTheScalarOnesBitForBit) {
  std::mt19937 rng(7);
  std::uniform_real_distribution<float> uni(0.f, 1.f);
  std::vector<Point2> us = {{0.5f, 0.5f}, {0.f, 0.f}, {0.5f, 0.125f}, {0.25f, 0.375f},
                            {0.75f, 0.625f}, {1.f, 0.875f}, {0.5f, 0.9f}, {0.1f, 0.5f}};
  for (int i = 0; i < 4000; ++i) us.push_back({uni(rng), uni(rng)});
  const auto bits = [](float f) {
    uint32_t b;
    std::memcpy(&b, &f, sizeof b);
    return b;
  };
  for (size_t i = 0; i + 4 <= us.size(); i += 4) {
    F32x4 ux, uy;
    for (int k = 0; k < 4; ++k) {
      ux[k] = us[i + size_t(k)].x;
      uy[k] = us[i + size_t(k)].y;
    }
    F32x4 cx, cy, cz, px, py;
    sample_cosine_hemisphere4(ux, uy, &cx, &cy, &cz);
    sample_polar_disk4(ux, uy, &px, &py);
    for (int k = 0; k < 4; ++k) {
      const BsdfDisks d = bsdf_disks(us[i + size_t(k)]);
      ASSERT_EQ(bits(cx[k]), bits(d.cosine.x)) << ux[k] << " " << uy[k];
      ASSERT_EQ(bits(cy[k]), bits(d.cosine.y)) << ux[k] << " " << uy[k];
      ASSERT_EQ(bits(cz[k]), bits(d.cosine.z)) << ux[k] << " " << uy[k];
      ASSERT_EQ(bits(px[k]), bits(d.polar.x)) << ux[k] << " " << uy[k];
      ASSERT_EQ(bits(py[k]), bits(d.polar.y)) << ux[k] << " " << uy[k];
    }
  }
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

TEST(Warps, ConcentricDiskPdfAndChiSquare) {
  // The pdf integrates to 1 over the bounding square (it is 1/pi on the disk, 0 outside).
  const int g = 1000;
  double integral = 0.0;
  for (int i = 0; i < g; ++i)
    for (int j = 0; j < g; ++j)
      integral += concentric_disk_pdf({-1.f + (i + 0.5f) * 2.f / g, -1.f + (j + 0.5f) * 2.f / g}) *
                  (4.0 / (double(g) * g));
  EXPECT_NEAR(integral, 1.0, 2e-3);
  // Chi-square over the bounding square: x = (p.x + 1) / 2, y = (p.y + 1) / 2, dp = 4 dx dy.
  const int cells = 16, sub = 16, samples = 200000;
  ChiSquareTest chi2(cells, cells);
  std::mt19937_64 rng(8);
  std::uniform_real_distribution<float> uni(0.f, 1.f);
  for (int s = 0; s < samples; ++s) {
    const Point2 p = sample_concentric_disk({uni(rng), uni(rng)});
    chi2.add_sample((p.x + 1.f) * 0.5f, (p.y + 1.f) * 0.5f);
  }
  chi2.integrate(
      [](double x, double y) {
        return concentric_disk_pdf({float(2.0 * x - 1.0), float(2.0 * y - 1.0)}) * 4.0;
      },
      sub, samples);
  const ChiSquareResult result = chi2.run();
  EXPECT_TRUE(result.passed) << result.message;
}

TEST(Warps, PowerHeuristic) {
  EXPECT_FLOAT_EQ(power_heuristic(1.f, 1.f), 0.5f);
  EXPECT_FLOAT_EQ(power_heuristic(3.f, 1.f), 0.9f);
  EXPECT_FLOAT_EQ(power_heuristic(0.f, 1.f), 0.f);
  EXPECT_FLOAT_EQ(power_heuristic(2.f, 1.f) + power_heuristic(1.f, 2.f), 1.f);
}

TEST(Warps, GgxVisibleNormals) {
  for (float alpha : {0.35f, 0.8f})
    for (Vec3 wo : {normalize(Vec3(0.f, 0.f, 1.f)), normalize(Vec3(0.4f, -0.2f, 0.7f)),
                    normalize(Vec3(-0.9f, 0.1f, 0.25f))}) {
      auto pdf = [&](Vec3 m) { return ggx_vndf_pdf(wo, m, alpha); };
      EXPECT_NEAR(integrate_sphere(pdf, 800, 400), 1.0, 5e-3) << alpha << " " << wo.z;
      // D itself is normalized over projected area: integral of D(m) m.z = 1.
      EXPECT_NEAR(integrate_sphere([&](Vec3 m) { return ggx_d(m, alpha) * std::max(0.f, m.z); },
                                   800, 400),
                  1.0, 5e-3);
      auto sample = [&](Point2 u) { return sample_ggx_vndf(wo, alpha, u); };
      const ChiSquareResult chi2 = sphere_chi2(sample, pdf);
      EXPECT_TRUE(chi2.passed) << chi2.message << ", alpha " << alpha << " wo.z " << wo.z;
      for (int i = 1; i < 20; ++i)
        for (int j = 1; j < 20; ++j) {
          const Point2 u{i / 20.f, j / 20.f};
          const Point2 back = invert_ggx_vndf(wo, alpha, sample(u));
          EXPECT_NEAR(back.x, u.x, 1e-3f);
          EXPECT_NEAR(back.y, u.y, 1e-3f);
        }
    }
}

TEST(Warps, PiecewiseConstant1D) {
  const Distribution1D d({1.f, 0.f, 3.f, 0.5f, 2.f});
  double integral = 0.0;
  for (int i = 0; i < 10000; ++i) integral += d.pdf((i + 0.5f) / 10000.f) / 10000.0;
  EXPECT_NEAR(integral, 1.0, 1e-4);
  for (int i = 1; i < 200; ++i) {
    const float u = i / 200.f;
    float pdf = 0.f;
    const float x = d.sample(u, &pdf, nullptr);
    EXPECT_GT(pdf, 0.f);  // never in the empty cell
    EXPECT_FLOAT_EQ(pdf, d.pdf(x));
    EXPECT_NEAR(d.invert(x), u, 1e-5f);
  }
  // Chi-square over the 5 cells.
  std::mt19937_64 rng(4);
  std::uniform_real_distribution<float> uni(0.f, 1.f);
  const int n = 100000;
  ChiSquareTest chi2(5);
  for (int s = 0; s < n; ++s) chi2.add_sample(d.sample(uni(rng), nullptr, nullptr));
  chi2.integrate([&](double x, double) { return d.pdf(float(x)); }, 1, n);
  const ChiSquareResult result = chi2.run();
  EXPECT_TRUE(result.passed) << result.message;
}

// The cell search narrowed by the guide table finds what a search of the whole cdf finds (the
// cdf built here as pbrt's PiecewiseConstant1D builds it), bit for bit, on distributions with
// empty runs, one bright cell among faint ones, all cells empty, and one cell; at random u and
// at the guide's bucket bounds and the floats next to them.
TEST(Warps, PiecewiseConstant1DFindsTheCellTheWholeCdfGives) {
  std::mt19937 rng(5);
  std::uniform_real_distribution<float> uni(0.f, 1.f);
  std::vector<std::vector<float>> cases;
  {
    std::vector<float> w(37);
    for (float& x : w) x = uni(rng) < 0.3f ? 0.f : uni(rng);
    cases.push_back(w);
    std::vector<float> sun(2048, 1e-3f);
    sun[1500] = 1e6f;
    for (size_t i = 100; i < 400; ++i) sun[i] = 0.f;
    cases.push_back(sun);
    cases.push_back(std::vector<float>(16, 0.f));
    cases.push_back({2.f});
    std::vector<float> ramp(1000);
    for (size_t i = 0; i < ramp.size(); ++i) ramp[i] = float(i * i % 97);
    cases.push_back(ramp);
  }
  for (const std::vector<float>& w : cases) {
    const size_t n = w.size();
    std::vector<double> cdf(n + 1, 0.0);
    std::vector<float> f(w);
    for (size_t i = 0; i < n; ++i) cdf[i + 1] = cdf[i] + double(f[i]) / double(n);
    double integral = cdf[n];
    if (!(integral > 0.0)) {
      for (size_t i = 0; i < n; ++i) {
        f[i] = 1.f;
        cdf[i + 1] = double(i + 1) / double(n);
      }
      integral = 1.0;
    } else {
      for (size_t i = 1; i <= n; ++i) cdf[i] /= integral;
    }
    std::vector<float> us;
    for (int k = 0; k < 20000; ++k) us.push_back(uni(rng));
    for (size_t j = 0; j <= n; ++j) {
      const float b = float(double(j) / double(n));
      for (const float u : {std::nextafter(b, 0.f), b, std::nextafter(b, 1.f)})
        if (u >= 0.f && u < 1.f) us.push_back(u);
    }
    const Distribution1D d(w);
    for (const float u : us) {
      size_t want = size_t(std::upper_bound(cdf.begin(), cdf.end(), double(u)) - cdf.begin());
      want = std::min(n - 1, want > 0 ? want - 1 : 0);
      while (want + 1 < n && f[want] == 0.f) ++want;
      size_t cell = n;
      float pdf = 0.f;
      const float x = d.sample(u, &pdf, &cell);
      ASSERT_EQ(cell, want) << "u = " << u << " of " << n << " cells";
      const double width = cdf[want + 1] - cdf[want];
      const double du = std::clamp(width > 0.0 ? (double(u) - cdf[want]) / width : 0.5, 0.0, 1.0);
      ASSERT_EQ(x, std::min(float((double(want) + du) / double(n)), 0.99999994f)) << "u = " << u;
      ASSERT_EQ(pdf, float(double(f[want]) / integral));
    }
  }
}

TEST(Warps, PiecewiseConstant2D) {
  const size_t nu = 8, nv = 6;
  std::vector<float> w(nu * nv);
  for (size_t i = 0; i < w.size(); ++i) w[i] = float((i * 7) % 5) + (i % 11 == 0 ? 0.f : 0.25f);
  const Distribution2D d(w, nu, nv);
  double integral = 0.0;
  const int g = 400;
  for (int i = 0; i < g; ++i)
    for (int j = 0; j < g; ++j) integral += d.pdf({(i + 0.5f) / g, (j + 0.5f) / g}) / (g * g);
  EXPECT_NEAR(integral, 1.0, 1e-3);
  for (int i = 1; i < 30; ++i)
    for (int j = 1; j < 30; ++j) {
      const Point2 u{i / 30.f, j / 30.f};
      float pdf = 0.f;
      const Point2 p = d.sample(u, &pdf);
      EXPECT_NEAR(pdf, d.pdf(p), 1e-4f * pdf);
      const Point2 back = d.invert(p);
      EXPECT_NEAR(back.x, u.x, 1e-4f);
      EXPECT_NEAR(back.y, u.y, 1e-4f);
    }
  std::mt19937_64 rng(5);
  std::uniform_real_distribution<float> uni(0.f, 1.f);
  const int n = 200000;
  ChiSquareTest chi2(static_cast<int>(nu), static_cast<int>(nv));
  for (int s = 0; s < n; ++s) {
    const Point2 p = d.sample({uni(rng), uni(rng)}, nullptr);
    chi2.add_sample(p.x, p.y);
  }
  chi2.integrate([&](double x, double y) { return d.pdf({float(x), float(y)}); }, 1, n);
  const ChiSquareResult result = chi2.run();
  EXPECT_TRUE(result.passed) << result.message;
}

}  // namespace
}  // namespace rf
