// Path guiding (render/guiding.h): the learned field's sampling against its own density (a
// chi-square test on the equal-area square), the density's integral over the sphere, what it
// learns from records with a known direction of light, and the guided tracer against the
// unguided one on scenes with closed-form or independently rendered answers.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <random>
#include <vector>

#include "render/guiding.h"
#include "sampling/sampling.h"
#include "render/integrators.h"
#include "render/render.h"
#include "scene/environment.h"
#include "testing/chi_square.h"
#include "testing/references.h"
#include "testing/test_scenes.h"

namespace rf {
namespace {

// Records at points spread over the unit cube: light from `towards` (within a cone of
// half-angle `spread` radians) carries value `bright`, every other direction `dim`.
std::vector<GuideRecord> records_towards(Vec3 towards, float spread, float bright, float dim,
                                         int count, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> u(0.f, 1.f);
  std::vector<GuideRecord> out;
  for (int i = 0; i < count; ++i) {
    const Vec3 p(u(rng), u(rng), u(rng));
    const Vec3 d = sample_uniform_sphere({u(rng), u(rng)});
    const bool lit = std::acos(std::clamp(dot(d, towards), -1.f, 1.f)) < spread;
    // Sampled uniformly over the sphere, as a BSDF would (the leaves' shares weigh by it).
    out.push_back({p, d, lit ? bright : dim, 0.25f / kPi, 0.25f / kPi});
  }
  return out;
}

TEST(GuideField, SquareMapRoundTrips) {
  for (float x : {0.01f, 0.3f, 0.5f, 0.77f, 0.99f})
    for (float y : {0.02f, 0.25f, 0.5f, 0.9f}) {
      const Vec3 d = sample_uniform_sphere({x, y});
      EXPECT_NEAR(length(d), 1.f, 1e-5f);
      const Point2 s = guide_square(d);
      EXPECT_NEAR(s.x, x, 1e-5f);
      EXPECT_NEAR(s.y, y, 1e-5f);
    }
}

TEST(GuideField, SamplesFollowTheirDensity) {
  const Vec3 towards = normalize(Vec3(0.3f, 0.8f, -0.5f));
  std::vector<GuideRecord> records = records_towards(towards, 0.3f, 50.f, 0.5f, 20000, 7);
  const GuideField field(Vec3(0.f, 0.f, 0.f), Vec3(1.f, 1.f, 1.f), &records);
  ASSERT_GT(field.distributions(), 0u);
  const uint32_t dist = field.distribution_at(Vec3(0.5f, 0.5f, 0.5f));
  ASSERT_NE(dist, GuideField::kNone);
  testing::ChiSquareTest chi(64, 64);
  std::mt19937 rng(3);
  std::uniform_real_distribution<float> u(0.f, 1.f);
  const int n = 400000;
  for (int i = 0; i < n; ++i) {
    float pdf = 0.f;
    const Vec3 d = field.sample(dist, {u(rng), u(rng)}, &pdf);
    ASSERT_GT(pdf, 0.f);
    // The density sample() reports is the one pdf() gives for its direction.
    if (i % 97 == 0) {
      EXPECT_NEAR(field.pdf(dist, d) / pdf, 1.f, 2e-3f);
    }
    const Point2 s = guide_square(d);
    chi.add_sample(s.x, s.y);
  }
  // On the square the density is 4 pi times the solid-angle density; 16 x 16 points per cell
  // are the centres of cells at least as fine as the quadtree's (64 x 16 = 2^10), where the
  // midpoint rule is exact.
  static_assert(GuideField::kMaxQuadDepth <= 10, "the cells' resolution");
  chi.integrate(
      [&](double x, double y) {
        return 4.0 * kPi * field.pdf(dist, sample_uniform_sphere({float(x), float(y)}));
      },
      16, n);
  const testing::ChiSquareResult r = chi.run();
  EXPECT_TRUE(r.passed) << r.message;
}

TEST(GuideField, DensityIntegratesToOneAndFindsTheLight) {
  const Vec3 towards = normalize(Vec3(-0.2f, 0.1f, 0.97f));
  std::vector<GuideRecord> records = records_towards(towards, 0.4f, 100.f, 0.1f, 30000, 11);
  const GuideField field(Vec3(0.f, 0.f, 0.f), Vec3(1.f, 1.f, 1.f), &records);
  const uint32_t dist = field.distribution_at(Vec3(0.2f, 0.7f, 0.4f));
  ASSERT_NE(dist, GuideField::kNone);
  // The integral over the sphere, by the midpoint rule on the square (4 pi du dv).
  const int k = 512;
  double integral = 0.0, in_cone = 0.0;
  for (int i = 0; i < k; ++i)
    for (int j = 0; j < k; ++j) {
      const Vec3 d = sample_uniform_sphere({(i + 0.5f) / k, (j + 0.5f) / k});
      const double p = field.pdf(dist, d) * 4.0 * kPi / (double(k) * k);
      integral += p;
      if (std::acos(std::clamp(dot(d, towards), -1.f, 1.f)) < 0.4f) in_cone += p;
    }
  EXPECT_NEAR(integral, 1.0, 1e-3);
  // The cone is 4% of the sphere and carries (100 x 4%) / (100 x 4% + 0.1 x 96%) = 98% of the
  // records' value: the density there is most of it (less the uniform share and the cells
  // the cone's edge cuts and the cells too few records split), where a uniform density would
  // give it 4%.
  EXPECT_GT(in_cone, 0.5);
}

TEST(GuideField, BuildsTheSameFieldFromTheSameRecords) {
  const Vec3 towards(0.f, 0.f, 1.f);
  std::vector<GuideRecord> a = records_towards(towards, 0.4f, 10.f, 1.f, 50000, 5);
  std::vector<GuideRecord> b = a;
  const GuideField fa(Vec3(0.f, 0.f, 0.f), Vec3(1.f, 1.f, 1.f), &a);
  const GuideField fb(Vec3(0.f, 0.f, 0.f), Vec3(1.f, 1.f, 1.f), &b);
  ASSERT_GT(fa.spatial_leaves(), 1u);  // more records than one leaf holds
  EXPECT_EQ(fa.spatial_leaves(), fb.spatial_leaves());
  EXPECT_EQ(fa.quad_nodes(), fb.quad_nodes());
  std::mt19937 rng(1);
  std::uniform_real_distribution<float> u(0.f, 1.f);
  for (int i = 0; i < 1000; ++i) {
    const Vec3 p(u(rng), u(rng), u(rng));
    const uint32_t da = fa.distribution_at(p), db = fb.distribution_at(p);
    ASSERT_EQ(da, db);
    if (da == GuideField::kNone) continue;
    const Vec3 d = sample_uniform_sphere({u(rng), u(rng)});
    EXPECT_EQ(fa.pdf(da, d), fb.pdf(db, d));
  }
}


// A Lambert diffuser of grey albedo, emitting `emission` in grey.
Material lambert(const char* name, float albedo, float emission = 0.f) {
  return testing::plain_material(name, albedo, 0.f, 1.f, 0.f, 0.f, emission);
}

using testing::PixelStats;

// A Lambert plane under an emissive square, direct light only: light sampling finds the square
// far better than any guide would (the training's BSDF samples that found it carry small MIS
// weights), and the render with the field is rho L F, F the closed-form form factor, within its
// error, as the unguided one is.
TEST(GuidedRendering, PlaneUnderAnEmitterIsTheClosedForm) {
  const float rho = 0.7f, L = 2.f, c = 1.f, h = 0.1f;
  SceneDescription desc;
  desc.source = "plane-under-emitter";
  desc.materials.push_back(lambert("plane", rho));
  desc.materials.push_back(lambert("emitter", 0.f, L));
  testing::add_quad(&desc, {-20, -20, 0}, {20, -20, 0}, {20, 20, 0}, {-20, 20, 0}, 0);
  testing::add_quad(&desc, {-h, -h, c}, {-h, h, c}, {h, h, c}, {h, -h, c}, 1);
  // Looking straight down at the origin through a narrow field: every pixel sees points within
  // 0.5 mm of it, where the irradiance differs from the centre's by far less than the error.
  desc.camera = testing::look_at({0.f, 0.f, 0.5f}, {0.f, 0.f, 0.f}, 0.002f);
  Scene scene(std::move(desc));
  RenderSettings settings;
  // 32 x 32 pixels: the training's paths are the image's pixels at 8 samples.
  settings.width = settings.height = 32;
  settings.sampler = SamplerType::Independent;
  settings.max_depth = 1;
  settings.seed = 3;
  const double expected = rho * L * testing::form_factor(0, 0, -h, h, -h, h, c);
  const std::vector<PixelStats> plain = testing::pixel_stats(scene, settings, 256);
  settings.guide = train_guide(scene, settings, 1);
  ASSERT_TRUE(settings.guide);
  const std::vector<PixelStats> guided = testing::pixel_stats(scene, settings, 256);
  for (size_t i = 0; i < guided.size(); ++i) {
    EXPECT_NEAR(guided[i].mean, expected, 4.0 * guided[i].standard_error);
    EXPECT_NEAR(plain[i].mean, expected, 4.0 * plain[i].standard_error);
  }
}

// Light found mostly indirectly: a small emitter facing up lights a white square above it,
// and the floor below sees that square's underside (the emitter's back is dark), plus a second
// small emitter facing down beside them that lights the floor directly. The floor's BSDF
// finds the square with the probability of its form factor; the guide learns its direction.
SceneDescription indirect_patch_scene() {
  SceneDescription desc;
  desc.source = "indirect-patch";
  desc.materials.push_back(lambert("floor", 0.8f));
  desc.materials.push_back(lambert("patch", 0.9f));
  desc.materials.push_back(lambert("emitter", 0.f, 50.f));
  testing::add_quad(&desc, {-20, -20, 0}, {20, -20, 0}, {20, 20, 0}, {-20, 20, 0}, 0);
  // The patch at z = 1 faces down, the emitter at z = 0.6 faces up.
  testing::add_quad(&desc, {-0.3f, -0.3f, 1.f}, {-0.3f, 0.3f, 1.f}, {0.3f, 0.3f, 1.f},
                    {0.3f, -0.3f, 1.f}, 1);
  testing::add_quad(&desc, {-0.05f, -0.05f, 0.6f}, {0.05f, -0.05f, 0.6f},
                    {0.05f, 0.05f, 0.6f}, {-0.05f, 0.05f, 0.6f}, 2);
  // The direct one at z = 2, off to the side, faces down.
  testing::add_quad(&desc, {1.5f, -0.02f, 2.f}, {1.5f, 0.02f, 2.f}, {1.54f, 0.02f, 2.f},
                    {1.54f, -0.02f, 2.f}, 2);
  desc.camera = testing::look_at({0.f, 0.f, 0.4f}, {0.f, 0.f, 0.f}, 1.0f);
  return desc;
}

// The guided floor is far less noisy at the same samples, and both are unbiased: their means
// agree within their errors (the direct emitter's light samples at guided vertices are
// MIS-weighted with the mixed density the BSDF side samples with; a mismatch would shift the
// guided mean).
TEST(GuidedRendering, IndirectLightFromASmallPatchIsFoundMoreOften) {
  Scene scene(indirect_patch_scene());
  RenderSettings settings;
  settings.width = settings.height = 32;
  settings.sampler = SamplerType::Independent;
  settings.max_depth = 2;
  settings.seed = 5;
  const std::vector<PixelStats> plain = testing::pixel_stats(scene, settings, 256);
  GuideStats stats;
  settings.guide = train_guide(scene, settings, 2, &stats);
  ASSERT_TRUE(settings.guide);
  ASSERT_GT(stats.distributions, 0u);
  const std::vector<PixelStats> guided = testing::pixel_stats(scene, settings, 256);
  double plain_sum = 0.0, guided_sum = 0.0, plain_var = 0.0, guided_var = 0.0;
  for (size_t i = 0; i < guided.size(); ++i) {
    plain_sum += plain[i].mean;
    guided_sum += guided[i].mean;
    plain_var += plain[i].standard_error * plain[i].standard_error;
    guided_var += guided[i].standard_error * guided[i].standard_error;
  }
  ASSERT_GT(plain_sum, 0.0);
  EXPECT_NEAR(guided_sum, plain_sum, 4.0 * std::sqrt(plain_var + guided_var));
  std::printf("indirect patch: variance guided / unguided %.3f\n", guided_var / plain_var);
  EXPECT_LT(guided_var, 0.7 * plain_var);
}

// The field and the image are the same bits whatever the training's thread count.
TEST(GuidedRendering, TheSameImageFromOneThreadOrThree) {
  Scene scene(indirect_patch_scene());
  RenderSettings settings;
  settings.width = 24;
  settings.height = 16;
  settings.max_depth = 4;
  settings.seed = 11;
  TileBuffer a, b;
  settings.guide = train_guide(scene, settings, 1);
  ASSERT_TRUE(settings.guide);
  ASSERT_TRUE(render_rect(scene, settings, {0, 0, 24, 16}, 0, 16, &a));
  settings.guide = train_guide(scene, settings, 3);
  ASSERT_TRUE(render_rect(scene, settings, {0, 0, 24, 16}, 0, 16, &b));
  ASSERT_EQ(a.rgb_sum.size(), b.rgb_sum.size());
  EXPECT_EQ(std::memcmp(a.rgb_sum.data(), b.rgb_sum.data(),
                        a.rgb_sum.size() * sizeof(a.rgb_sum[0])),
            0);
  // And guiding changed the image (the guide is used).
  settings.guide = nullptr;
  TileBuffer c;
  ASSERT_TRUE(render_rect(scene, settings, {0, 0, 24, 16}, 0, 16, &c));
  EXPECT_NE(std::memcmp(a.rgb_sum.data(), c.rgb_sum.data(),
                        a.rgb_sum.size() * sizeof(a.rgb_sum[0])),
            0);
}

// Under a uniform sky an open plane's light is the cosine the BSDF already samples: every
// leaf finds the BSDF alone best (GuideField::kShares) and none guides, so the image is the
// unguided one bit for bit.
TEST(GuidedRendering, AUniformSkyIsNotGuided) {
  SceneDescription desc;
  desc.source = "sky-plane";
  desc.materials.push_back(lambert("floor", 0.8f));
  testing::add_quad(&desc, {-20, -20, 0}, {20, -20, 0}, {20, 20, 0}, {-20, 20, 0}, 0);
  desc.camera = testing::look_at({0.f, -1.f, 1.f}, {0.f, 0.f, 0.f}, 0.8f);
  Scene scene(std::move(desc));
  RenderSettings settings;
  settings.width = settings.height = 32;
  settings.max_depth = 3;
  settings.environment = Environment::constant({1.f, 1.f, 1.f});
  TileBuffer plain, guided;
  ASSERT_TRUE(render_rect(scene, settings, {0, 0, 32, 32}, 0, 16, &plain));
  GuideStats stats;
  settings.guide = train_guide(scene, settings, 2, &stats);
  ASSERT_TRUE(settings.guide);
  EXPECT_GT(stats.records, 0u);
  EXPECT_EQ(stats.distributions, 0u);
  ASSERT_TRUE(render_rect(scene, settings, {0, 0, 32, 32}, 0, 16, &guided));
  EXPECT_EQ(std::memcmp(plain.rgb_sum.data(), guided.rgb_sum.data(),
                        plain.rgb_sum.size() * sizeof(plain.rgb_sum[0])),
            0);
}

}  // namespace
}  // namespace rf
