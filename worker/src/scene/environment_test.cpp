// Environment map: importance sampling matches the pdf (chi-square), the pdf integrates to 1,
// sample/invert round-trip, the mapping and rotation conventions, and file loading.
#include "scene/environment.h"

#include <OpenImageIO/imageio.h>
#include <gtest/gtest.h>

#include "testing/chi_square.h"
#include "testing/test_scenes.h"

#include <cstdio>
#include <random>

namespace rf {
namespace {

using testing::ChiSquareResult;
using testing::ChiSquareTest;

// A 32 x 16 map: a smooth gradient, a hot spot and a black band.
std::shared_ptr<Environment> test_map(float rotation_deg) {
  const uint32_t w = 32, h = 16;
  std::vector<float> rgb(size_t(w) * h * 3);
  for (uint32_t y = 0; y < h; ++y)
    for (uint32_t x = 0; x < w; ++x) {
      const size_t i = 3 * (size_t(y) * w + x);
      float v = 0.2f + 0.05f * float(x) + 0.1f * float(y);
      if (x == 20 && y == 5) v = 40.f;
      if (y == 12) v = 0.f;
      rgb[i] = v;
      rgb[i + 1] = 0.5f * v;
      rgb[i + 2] = 0.25f * v;
    }
  return std::make_shared<Environment>(std::move(rgb), w, h, 2.f, rotation_deg);
}

Vec3 spherical(double z, double phi) {
  const double r = std::sqrt(std::max(0.0, 1.0 - z * z));
  return Vec3(float(r * std::cos(phi)), float(r * std::sin(phi)), float(z));
}

TEST(Environment, PdfIntegratesToOneAndSamplesFollowIt) {
  for (float rot : {0.f, 37.f}) {
    const auto env = test_map(rot);
    // Integral over the sphere with dω = dz dφ (z, φ about world +Z: any axis will do).
    const int nz = 600, nphi = 600;
    double integral = 0.0;
    for (int i = 0; i < nz; ++i)
      for (int j = 0; j < nphi; ++j)
        integral += env->pdf(spherical(-1.0 + (i + 0.5) * 2.0 / nz, (j + 0.5) * 2 * M_PI / nphi)) *
                    (2.0 / nz) * (2 * M_PI / nphi);
    EXPECT_NEAR(integral, 1.0, 5e-3);
    // Chi-square in map space: cells are texels, expected mass = pdf x solid angle, where
    // d(omega) = sin(theta) dtheta dphi = 2 pi^2 sin(pi v) du dv. The black band has pdf 0:
    // a sample there fails the test.
    std::mt19937_64 rng(21);
    std::uniform_real_distribution<float> uni(0.f, 1.f);
    const uint32_t w = env->width(), h = env->height();
    const int n = 200000;
    ChiSquareTest chi2(static_cast<int>(w), static_cast<int>(h));
    int pdf_mismatch = 0;  // only possible on texel edges (float round trip of the direction)
    for (int s = 0; s < n; ++s) {
      float pdf = 0.f;
      const Vec3 d = env->sample({uni(rng), uni(rng)}, &pdf);
      ASSERT_GT(pdf, 0.f);
      pdf_mismatch += std::fabs(pdf - env->pdf(d)) > 1e-3f * pdf;
      const Point2 uv = env->direction_to_uv(d);
      chi2.add_sample(uv.x, uv.y);
    }
    chi2.integrate(
        [&](double x, double y) {
          return env->pdf(env->uv_to_direction({float(x), float(y)})) * std::sin(M_PI * y) * 2 *
                 M_PI * M_PI;
        },
        8, n);
    const ChiSquareResult result = chi2.run();
    EXPECT_TRUE(result.passed) << result.message << ", rotation " << rot;
    EXPECT_LT(pdf_mismatch, n / 1000);
  }
}

TEST(Environment, SampleInvertRoundTripAndMapping) {
  const auto env = test_map(25.f);
  for (int i = 1; i < 30; ++i)
    for (int j = 1; j < 30; ++j) {
      const Point2 u{i / 30.f, j / 30.f};
      float pdf = 0.f;
      const Vec3 d = env->sample(u, &pdf);
      const Point2 back = env->invert(d);
      EXPECT_NEAR(back.x, u.x, 2e-3f);
      EXPECT_NEAR(back.y, u.y, 2e-3f);
      const Point2 uv{(i - 0.5f) / 29.f, (j - 0.5f) / 29.f};
      const Point2 uv2 = env->direction_to_uv(env->uv_to_direction(uv));
      EXPECT_NEAR(uv2.x, uv.x, 1e-4f);
      EXPECT_NEAR(uv2.y, uv.y, 1e-4f);
    }
}

TEST(Environment, ConventionsCenterIsMinusZTopIsPlusYRotationAboutY) {
  const auto env = test_map(0.f);
  const Point2 c = env->direction_to_uv({0.f, 0.f, -1.f});
  EXPECT_NEAR(c.x, 0.5f, 1e-6f);
  EXPECT_NEAR(c.y, 0.5f, 1e-6f);
  EXPECT_NEAR(env->direction_to_uv({0.f, 1.f, 0.f}).y, 0.f, 1e-6f);
  EXPECT_NEAR(env->direction_to_uv({1.f, 0.f, 0.f}).x, 0.75f, 1e-6f);  // u grows towards +X
  // +90 degrees: what was at -Z is now at -X.
  const auto rotated = test_map(90.f);
  const Vec3 a = env->eval({0.3f, 0.2f, -0.93f});
  const Vec3 b = rotated->eval(normalize(Vec3(-0.93f, 0.2f, -0.3f)));
  EXPECT_NEAR(a.x, b.x, 1e-5f);
  // Intensity scales radiance (test_map uses 2).
  EXPECT_NEAR(env->eval({0.f, 0.f, -1.f}).x, 2.f * (0.2f + 0.05f * 16 + 0.1f * 8), 1e-5f);
}

TEST(Environment, LoadsAnHdrFile) {
  const std::string path = testing::test_path("env_test.hdr");
  {
    auto out = OIIO::ImageOutput::create(path);
    ASSERT_TRUE(out);
    OIIO::ImageSpec spec(4, 2, 3, OIIO::TypeDesc::FLOAT);
    std::vector<float> px(4 * 2 * 3, 0.5f);
    px[0] = 8.f;  // top-left texel red channel
    ASSERT_TRUE(out->open(path, spec));
    ASSERT_TRUE(out->write_image(OIIO::TypeDesc::FLOAT, px.data()));
    ASSERT_TRUE(out->close());
  }
  const auto env = Environment::load(path, 3.f, 0.f);
  EXPECT_EQ(env->width(), 4u);
  EXPECT_EQ(env->height(), 2u);
  EXPECT_NEAR(env->eval(env->uv_to_direction({0.9f, 0.9f})).y, 1.5f, 0.02f);  // RGBE rounding
  EXPECT_NEAR(env->eval(env->uv_to_direction({0.1f, 0.1f})).x, 24.f, 0.3f);
  EXPECT_THROW(Environment::load(path + ".missing", 1.f, 0.f), std::runtime_error);
  std::remove(path.c_str());
}

}  // namespace
}  // namespace rf
