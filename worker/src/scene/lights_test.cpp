#include "scene/lights.h"

#include <gtest/gtest.h>

#include "testing/chi_square.h"

#include <random>

#include "scene/scene.h"
#include "testing/test_scenes.h"

namespace rf {
namespace {

using testing::ChiSquareResult;
using testing::ChiSquareTest;

TEST(AliasTable, ReproducesItsProbabilities) {
  const std::vector<double> weights = {1, 2, 3, 0, 4, 10, 0.5, 7};
  double total = 0;
  for (double w : weights) total += w;
  AliasTable table(weights);
  ASSERT_EQ(table.size(), weights.size());
  const int n = 200000;
  // One cell per entry; zero weight is never chosen.
  ChiSquareTest chi2(int(weights.size()));
  std::mt19937_64 rng(99);
  std::uniform_real_distribution<float> uni(0.f, 1.f);
  for (int i = 0; i < n; ++i) {
    double pmf = 0;
    const uint32_t k = table.sample(uni(rng), &pmf);
    ASSERT_LT(k, weights.size());
    ASSERT_DOUBLE_EQ(pmf, weights[k] / total);
    chi2.observed()[k] += 1.0;
  }
  for (size_t k = 0; k < weights.size(); ++k) chi2.expected()[k] = n * weights[k] / total;
  const ChiSquareResult result = chi2.run();
  EXPECT_TRUE(result.passed) << result.message;
}

TEST(AliasTable, AllZeroWeightsGiveAnEmptyTable) {
  EXPECT_EQ(AliasTable({0.0, 0.0}).size(), 0u);
}

TEST(LightSet, SelectionProportionalToPowerAndPointsOnTheLight) {
  SceneDescription desc;
  desc.source = "two-lights";
  desc.materials.push_back(Material{"dim", {0, 0, 0}, {1, 1, 1}});
  desc.materials.push_back(Material{"bright", {0, 0, 0}, {3, 3, 3}});
  desc.materials.push_back(Material{"diffuse", {0.5f, 0.5f, 0.5f}, {0, 0, 0}});
  testing::add_quad(&desc, {0, 0, 0}, {1, 0, 0}, {1, 1, 0}, {0, 1, 0}, 0);    // area 1, L 1
  testing::add_quad(&desc, {0, 0, 5}, {2, 0, 5}, {2, 2, 5}, {0, 2, 5}, 1);    // area 4, L 3
  testing::add_quad(&desc, {0, 0, -1}, {9, 0, -1}, {9, 9, -1}, {0, 9, -1}, 2);  // not a light
  Scene scene(std::move(desc));
  const LightSet& lights = scene.lights();
  ASSERT_EQ(lights.size(), 4u);
  // Power ratio 1 : 12 between the quads; the area pdf of a point is P(quad) / area(quad).
  EXPECT_NEAR(lights.pdf_area(0), (1.0 / 13.0) / 1.0, 1e-6);
  EXPECT_NEAR(lights.pdf_area(2), (12.0 / 13.0) / 4.0, 1e-6);
  EXPECT_EQ(lights.pdf_area(4), 0.f);
  std::mt19937_64 rng(1);
  std::uniform_real_distribution<float> uni(0.f, 1.f);
  int bright = 0;
  const int n = 100000;
  for (int i = 0; i < n; ++i) {
    const LightSample s = lights.sample(uni(rng), uni(rng), uni(rng));
    const Triangle t = scene.world().triangle(s.prim);
    // The point lies in the triangle's plane and inside it.
    EXPECT_NEAR(dot(s.p - t.p[0], t.ng), 0.f, 1e-5f);
    EXPECT_NEAR(s.pdf_area, lights.pdf_area(s.prim), 1e-7f);
    bright += s.emission.x > 2.f;
  }
  const double p = 12.0 / 13.0;
  EXPECT_NEAR(double(bright) / n, p, 4.0 * std::sqrt(p * (1 - p) / n));
}

}  // namespace
}  // namespace rf

namespace rf {
namespace {

// One alias table over every light: emitters and punctual lights are chosen in proportion
// to their power (triangle: pi A L; point: 4 pi I; spot: 2 pi (1 - mean cone cos) I;
// directional: pi R^2 E).
TEST(LightSet, PunctualAndAreaLightsShareOneTableByPower) {
  SceneDescription desc;
  desc.source = "mixed-lights";
  desc.materials.push_back(Material{"lamp", {0, 0, 0}, {2, 2, 2}});
  testing::add_quad(&desc, {0, 0, 0}, {1, 0, 0}, {1, 1, 0}, {0, 1, 0}, 0);  // area 1, L 2
  PunctualLight point;
  point.type = PunctualType::Point;
  point.intensity = Vec3(3, 3, 3);
  PunctualLight spot;
  spot.type = PunctualType::Spot;
  spot.intensity = Vec3(5, 5, 5);
  spot.cos_inner = 0.9f;
  spot.cos_outer = 0.7f;
  PunctualLight sun;
  sun.type = PunctualType::Directional;
  sun.intensity = Vec3(1, 1, 1);
  desc.punctual_lights = {point, spot, sun};
  Scene scene(std::move(desc));
  const LightSet& lights = scene.lights();
  ASSERT_EQ(lights.size(), 5u);
  const double r = 0.5 * scene.diagonal();
  const double powers[] = {M_PI * 0.5 * 2, M_PI * 0.5 * 2, 4 * M_PI * 3,
                           2 * M_PI * (1 - 0.8) * 5, M_PI * r * r * 1};
  double total = 0;
  for (double p : powers) total += p;
  EXPECT_NEAR(lights.total_power(), total, 1e-4 * total);
  std::mt19937_64 rng(2);
  std::uniform_real_distribution<float> uni(0.f, 1.f);
  std::vector<double> count(5, 0.0);
  const int n = 200000;
  for (int i = 0; i < n; ++i) {
    const LightSample s = lights.sample(uni(rng), uni(rng), uni(rng));
    count[s.punctual >= 0 ? 2 + size_t(s.punctual) : s.prim] += 1;
    const double expected_pmf = powers[s.punctual >= 0 ? 2 + s.punctual : int(s.prim)] / total;
    if (s.punctual >= 0) {
      ASSERT_NEAR(s.pdf_area, expected_pmf, 1e-5);
    }
  }
  for (size_t k = 0; k < 5; ++k) {
    const double p = powers[k] / total;
    EXPECT_NEAR(count[k] / n, p, 4 * std::sqrt(p * (1 - p) / n)) << k;
  }
}

}  // namespace
}  // namespace rf
