#include "integrators.h"

#include <gtest/gtest.h>

#include <cmath>

#include "test_scenes.h"

namespace rf {
namespace {

// Form factor from a point to a parallel a x b rectangle at height c with the point under a
// corner (Howell's catalogue, configuration B-3 / the "corner formula").
double form_factor_corner(double a, double b, double c) {
  const double X = a / c, Y = b / c;
  const double sx = std::sqrt(1 + X * X), sy = std::sqrt(1 + Y * Y);
  return (X / sx * std::atan(Y / sx) + Y / sy * std::atan(X / sy)) / (2 * M_PI);
}

struct Estimate {
  double mean, standard_error;
};

Estimate render_pixel(const Scene& scene, const RenderSettings& settings, uint32_t spp) {
  TileBuffer tile;
  EXPECT_TRUE(render_rect(scene, settings, {0, 0, 1, 1}, 0, spp, &tile));
  EXPECT_EQ(tile.nonfinite_samples, 0u);
  const double mean = tile.rgb_sum[0] / spp;
  // Gray emitter and albedo: R equals the luminance, whose M2 is reported.
  const double variance = tile.luminance_m2[0] / (spp - 1);
  return {mean, std::sqrt(variance / spp)};
}

TEST(PathIntegrator, PlaneUnderEmitterMatchesClosedForm) {
  const float rho = 0.5f, L = 3.f, a = 1.f, b = 1.f, c = 1.f;
  // Camera looks obliquely at the origin with a tiny field of view, so the single pixel sees
  // the plane point under the emitter's center.
  Scene scene(testing::plane_under_emitter(rho, L, a, b, c, {0.f, -2.f, 0.4f}, 1e-3f));
  // Point under the center: four quarter rectangles of a/2 x b/2 with the point at a corner.
  const double F = 4.0 * form_factor_corner(a / 2, b / 2, c);
  const double expected = rho * L * F;
  for (SamplerType sampler : {SamplerType::Sobol, SamplerType::Independent}) {
    for (uint32_t depth : {1u, 8u}) {
      RenderSettings settings;
      settings.width = settings.height = 1;
      settings.sampler = sampler;
      settings.max_depth = depth;
      settings.seed = 11;
      const Estimate e = render_pixel(scene, settings, 8192);
      EXPECT_LT(e.standard_error, 0.02 * expected) << "test would have no power";
      EXPECT_NEAR(e.mean, expected, 4.0 * e.standard_error + 1e-4 * expected)
          << sampler_type_name(sampler) << " depth " << depth;
    }
  }
}

TEST(PathIntegrator, EmitterSeenDirectlyHasFullWeightAndIsOneSided) {
  const float L = 2.5f;
  RenderSettings settings;
  settings.width = settings.height = 4;
  // From below, looking up at the emitter's front face: exactly L in every sample.
  SceneDescription below_desc =
      testing::plane_under_emitter(0.5f, L, 1.f, 1.f, 1.f, {0.f, 0.f, 0.5f}, 0.2f);
  below_desc.camera = testing::look_at({0.f, 0.f, 0.5f}, {0.f, 0.01f, 1.f}, 0.2f);
  Scene below(std::move(below_desc));
  TileBuffer tile;
  ASSERT_TRUE(render_rect(below, settings, {0, 0, 4, 4}, 0, 16, &tile));
  for (size_t i = 0; i < 16; ++i) {
    EXPECT_DOUBLE_EQ(tile.rgb_sum[3 * i], 16.0 * L);
    EXPECT_NEAR(tile.luminance_m2[i], 0.0, 1e-9);
    EXPECT_NEAR(tile.normal_sum[3 * i + 2], -16.f, 1e-3f);  // shading normal faces down
  }
  // From above, the back of the emitter is black (its albedo is 0 and it emits downwards).
  Scene above(testing::plane_under_emitter(0.5f, L, 1.f, 1.f, 1.f, {0.f, 0.01f, 3.f}, 0.2f));
  ASSERT_TRUE(render_rect(above, settings, {0, 0, 4, 4}, 0, 16, &tile));
  for (size_t i = 0; i < 16; ++i) EXPECT_EQ(tile.rgb_sum[3 * i], 0.0);
}

TEST(PathIntegrator, BatchesSumToTheWholeRange) {
  Scene scene(testing::plane_under_emitter(0.7f, 4.f, 1.f, 1.f, 1.f, {0.3f, -2.f, 1.f}, 1.2f));
  RenderSettings settings;
  settings.width = 24;
  settings.height = 16;
  settings.seed = 3;
  const PixelRect rect{8, 4, 8, 8};
  for (SamplerType sampler : {SamplerType::Sobol, SamplerType::Independent}) {
    settings.sampler = sampler;
    TileBuffer whole, part;
    ASSERT_TRUE(render_rect(scene, settings, rect, 0, 16, &whole));
    std::vector<double> sum(whole.rgb_sum.size(), 0.0);
    uint64_t rays = 0;
    for (auto [start, count] : {std::pair<uint32_t, uint32_t>{0, 4}, {4, 4}, {8, 8}}) {
      ASSERT_TRUE(render_rect(scene, settings, rect, start, count, &part));
      for (size_t i = 0; i < sum.size(); ++i) sum[i] += part.rgb_sum[i];
      rays += part.rays;
    }
    EXPECT_EQ(rays, whole.rays);
    double total_whole = 0.0;
    for (size_t i = 0; i < sum.size(); ++i) {
      EXPECT_NEAR(sum[i], whole.rgb_sum[i], 1e-12 * std::max(1.0, std::fabs(whole.rgb_sum[i])));
      total_whole += whole.rgb_sum[i];
    }
    EXPECT_GT(total_whole, 0.0);
  }
}

TEST(PathIntegrator, CancelStopsEarly) {
  Scene scene(testing::plane_under_emitter(0.5f, 1.f, 1.f, 1.f, 1.f, {0.f, -2.f, 1.f}, 1.f));
  RenderSettings settings;
  std::atomic<bool> cancel{true};
  TileBuffer tile;
  EXPECT_FALSE(render_rect(scene, settings, {0, 0, 32, 32}, 0, 4, &tile, &cancel));
}

TEST(AoIntegrator, OpenPlaneIsUnoccludedAndMissesAreBlack) {
  SceneDescription desc;
  desc.source = "plane";
  desc.materials.push_back(Material{});
  testing::add_quad(&desc, {-1, -1, 0}, {1, -1, 0}, {1, 1, 0}, {-1, 1, 0}, 0);
  desc.camera = testing::look_at({0.f, 0.f, 3.f}, {0.f, 0.f, 0.f}, 1.2f);
  Scene scene(std::move(desc));
  RenderSettings settings;
  settings.integrator = IntegratorType::AmbientOcclusion;
  settings.width = settings.height = 16;
  TileBuffer tile;
  ASSERT_TRUE(render_rect(scene, settings, {0, 0, 16, 16}, 0, 8, &tile));
  // Center pixels see the plane: nothing above it, AO = 1. Corner pixels see nothing: 0.
  const size_t center = 8 * 16 + 8, corner = 0;
  EXPECT_DOUBLE_EQ(tile.rgb_sum[3 * center], 8.0);
  EXPECT_DOUBLE_EQ(tile.rgb_sum[3 * corner], 0.0);
  EXPECT_EQ(tile.albedo_sum[3 * corner], 0.f);
}

TEST(AoIntegrator, BoxInteriorIsPartlyOccluded) {
  // Looking into a box through its open front: the floor near the back wall sees walls
  // within the AO radius, so its AO is strictly between 0 and 1.
  SceneDescription desc;
  desc.source = "box";
  desc.materials.push_back(Material{});
  testing::add_quad(&desc, {-1, -1, -1}, {1, -1, -1}, {1, 1, -1}, {-1, 1, -1}, 0);  // back
  testing::add_quad(&desc, {-1, -1, 1}, {1, -1, 1}, {1, -1, -1}, {-1, -1, -1}, 0);  // floor
  testing::add_quad(&desc, {-1, -1, 1}, {-1, -1, -1}, {-1, 1, -1}, {-1, 1, 1}, 0);  // left
  desc.camera = testing::look_at({0.f, 0.f, 4.f}, {-0.95f, -0.95f, -0.95f}, 0.01f);
  Scene scene(std::move(desc));
  RenderSettings settings;
  settings.integrator = IntegratorType::AmbientOcclusion;
  settings.width = settings.height = 1;
  TileBuffer tile;
  ASSERT_TRUE(render_rect(scene, settings, {0, 0, 1, 1}, 0, 256, &tile));
  EXPECT_GT(tile.rgb_sum[0], 0.0);
  EXPECT_LT(tile.rgb_sum[0], 256.0);
}

TEST(Integrators, ValidateRequest) {
  RenderSettings s;
  s.width = 64;
  s.height = 32;
  EXPECT_EQ(validate_render_request(s, {0, 0, 64, 32}, 0, 16), "");
  EXPECT_NE(validate_render_request(s, {40, 0, 32, 32}, 0, 16), "");
  EXPECT_NE(validate_render_request(s, {0, 0, 8, 8}, 0, 0), "");
  EXPECT_NE(validate_render_request(s, {0, 0, 8, 8}, (1ull << 31) - 4, 8), "");
  IntegratorType t;
  EXPECT_FALSE(parse_integrator_type("bdpt", &t));
}

}  // namespace
}  // namespace rf
