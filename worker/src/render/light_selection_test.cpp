// Per-shading-point light selection (scene/lights.h, render/light_sampling.h): the
// probabilities sum to 1, the choice follows them, and a light gets probability 0 only where
// it cannot contribute to light sampling.
#include <gtest/gtest.h>

#include <cmath>
#include <map>
#include <memory>
#include <random>
#include <vector>

#include "render/light_sampling.h"
#include "scene/environment.h"
#include "scene/scene.h"
#include "testing/chi_square.h"
#include "testing/test_scenes.h"

namespace rf {
namespace {

// Many lights of every kind: one-sided quads facing down and up, a double-sided quad, an
// emissive sphere of many triangles (split into several clusters), 20 point lights (more than
// get a cluster each), a spot and two directional lights; under an environment.
std::unique_ptr<Scene> many_lights_scene() {
  SceneDescription desc;
  desc.source = "many-lights";
  desc.materials.push_back(Material{"floor", {0.5f, 0.5f, 0.5f}, {0, 0, 0}});
  desc.materials.push_back(Material{"down", {0, 0, 0}, {4, 4, 4}});
  desc.materials.push_back(Material{"up", {0, 0, 0}, {1, 2, 3}});
  Material two{"two", {0, 0, 0}, {2, 2, 2}};
  two.double_sided = true;
  desc.materials.push_back(two);
  desc.materials.push_back(Material{"ball", {0, 0, 0}, {0.5f, 1, 0.5f}});
  testing::add_quad(&desc, {-5, -5, 0}, {5, -5, 0}, {5, 5, 0}, {-5, 5, 0}, 0);
  testing::add_quad(&desc, {-1, -1, 3}, {-1, 1, 3}, {1, 1, 3}, {1, -1, 3}, 1);      // faces -z
  testing::add_quad(&desc, {2, 2, 1}, {3, 2, 1}, {3, 3, 1}, {2, 3, 1}, 2);          // faces +z
  testing::add_quad(&desc, {-3, 0, 0.5f}, {-3, 1, 0.5f}, {-3, 1, 1.5f}, {-3, 0, 1.5f}, 3);
  testing::add_sphere(&desc, {1.5f, -2.f, 1.f}, 0.4f, 4, 8, 16);
  std::mt19937_64 rng(5);
  std::uniform_real_distribution<float> pos(-4.f, 4.f), height(-1.f, 5.f), power(0.5f, 20.f);
  for (int i = 0; i < 20; ++i) {
    PunctualLight l;
    l.position = Vec3(pos(rng), pos(rng), height(rng));
    const float I = power(rng);
    l.intensity = Vec3(I, 0.5f * I, I);
    desc.punctual_lights.push_back(l);
  }
  PunctualLight spot;
  spot.type = PunctualType::Spot;
  spot.position = Vec3(0, 0, 4);
  spot.intensity = Vec3(30, 30, 30);
  spot.cos_inner = 0.95f;
  spot.cos_outer = 0.9f;
  desc.punctual_lights.push_back(spot);
  PunctualLight sun;
  sun.type = PunctualType::Directional;
  sun.direction = normalize(Vec3(0.3f, 0.2f, -1.f));
  sun.intensity = Vec3(2, 2, 2);
  desc.punctual_lights.push_back(sun);
  sun.direction = normalize(Vec3(-0.5f, 0.f, 0.8f));  // from below
  desc.punctual_lights.push_back(sun);
  desc.camera = testing::look_at({0, -8, 4}, {0, 0, 0}, 0.6f);
  return std::make_unique<Scene>(std::move(desc));
}

std::shared_ptr<Environment> sky() {
  const uint32_t w = 16, h = 8;
  std::vector<float> rgb(3 * w * h);
  for (uint32_t i = 0; i < w * h; ++i)
    for (int c = 0; c < 3; ++c) rgb[3 * i + c] = 0.2f + 0.1f * float(c) + float(i % 5 == 0);
  return std::make_shared<Environment>(rgb, w, h, 1.f, 0.f);
}

Vec3 random_unit(std::mt19937_64& rng) {
  std::normal_distribution<float> g;
  return normalize(Vec3(g(rng), g(rng), g(rng)));
}

// The power the selection uses inside a cluster, computed here from the lights themselves.
double light_power(const Scene& scene, uint32_t li) {
  const LightSet& lights = scene.lights();
  if (li < lights.emitter_count()) {
    const Emitter& e = lights.emitters()[li];
    return double(e.area) * double(luminance(scene.materials()[e.material].emission));
  }
  const PunctualLight& l = lights.punctual()[li - lights.emitter_count()];
  const double I = luminance(l.intensity);
  if (l.type == PunctualType::Spot)
    return 2.0 * M_PI * (1.0 - 0.5 * (double(l.cos_inner) + double(l.cos_outer))) * I;
  return 4.0 * M_PI * I;  // points (directional lights are each alone in their cluster)
}

TEST(LightSelection, ClustersCoverEveryLightOnceAndTheSphereIsSplit) {
  const auto scene = many_lights_scene();
  const LightSet& lights = scene->lights();
  std::vector<int> seen(lights.size(), 0);
  for (uint32_t c = 0; c < lights.cluster_count(); ++c)
    for (uint32_t i = 0; i < lights.cluster(c).count; ++i)
      ++seen[lights.member(lights.cluster(c).first + i)];
  for (size_t li = 0; li < seen.size(); ++li) EXPECT_EQ(seen[li], 1) << li;
  EXPECT_LE(lights.cluster_count(), LightSet::kMaxClusters);
  // 4 quads' triangles + 256 of the sphere in more than the 4 meshes' clusters; 20 points in
  // more than one but fewer than 20; the spot with them; 2 directional alone.
  EXPECT_GT(lights.cluster_count(), 4u + 1u + 2u);
}

TEST(LightSelection, ProbabilitiesSumToOneAtAnyPoint) {
  const auto scene = many_lights_scene();
  RenderSettings settings;
  settings.environment = sky();
  const LightContext lc = light_context(*scene, settings);
  ASSERT_FALSE(lc.single);
  ASSERT_EQ(lc.entries(), scene->lights().cluster_count() + 1);
  std::mt19937_64 rng(7);
  std::uniform_real_distribution<float> pos(-6.f, 6.f);
  for (int k = 0; k < 2000; ++k) {
    const Vec3 o(pos(rng), pos(rng), 0.5f * pos(rng) + 2.f), ng = random_unit(rng);
    float w[kMaxLightEntries];
    const float total = light_weights(lc, o, ng, w);
    ASSERT_GT(total, 0.f);  // the environment is always there
    double sum = 0.0;
    for (uint32_t e = 0; e < lc.entries(); ++e) {
      const float p = light_entry_pmf(lc, e, o, ng, total);
      ASSERT_GE(p, 0.f);
      ASSERT_EQ(p, w[e] / total);  // what MIS recomputes is what the choice used
      sum += p;
    }
    ASSERT_NEAR(sum, 1.0, 1e-5) << k;
  }
}

TEST(LightSelection, ChoosesEveryLightWithItsProbability) {
  const auto scene = many_lights_scene();
  const LightSet& lights = scene->lights();
  RenderSettings settings;
  settings.environment = sky();
  const LightContext lc = light_context(*scene, settings);
  // Per cluster, the sum of its lights' powers.
  std::vector<double> cluster_power(lights.cluster_count(), 0.0);
  std::vector<uint32_t> cluster_of(lights.size());
  for (uint32_t c = 0; c < lights.cluster_count(); ++c)
    for (uint32_t i = 0; i < lights.cluster(c).count; ++i) {
      const uint32_t li = lights.member(lights.cluster(c).first + i);
      cluster_power[c] += light_power(*scene, li);
      cluster_of[li] = c;
    }
  // A light's cell: emitters by (slot, prim), punctual lights by index; the environment last.
  std::map<std::pair<uint32_t, uint32_t>, uint32_t> emitter_index;
  for (uint32_t li = 0; li < lights.emitter_count(); ++li)
    emitter_index[{lights.emitters()[li].slot, lights.emitters()[li].prim}] = li;
  const uint32_t cells = uint32_t(lights.size()) + 1;
  std::mt19937_64 rng(3);
  std::uniform_real_distribution<float> uni(0.f, 1.f);
  const Vec3 points[][2] = {{{0, 0, 0.01f}, {0, 0, 1}},
                            {{2.5f, 2.5f, 2.f}, {0, 0, -1}},
                            {{-2.f, 0.5f, 1.f}, normalize(Vec3(-1, 0.2f, 0.3f))},
                            {{1.5f, -2.f, 2.f}, {0, 0, -1}}};
  for (const auto& pt : points) {
    const Vec3 o = pt[0], ng = pt[1];
    float w[kMaxLightEntries];
    const float total = light_weights(lc, o, ng, w);
    testing::ChiSquareTest chi2{int(cells)};
    const int n = 300000;
    for (int s = 0; s < n; ++s) {
      uint32_t entry = 0;
      float pmf = 0.f, u_rest = 0.f;
      ASSERT_TRUE(choose_light(lc, w, total, uni(rng), &entry, &pmf, &u_rest));
      ASSERT_EQ(pmf, w[entry] / total);
      ASSERT_GE(u_rest, 0.f);
      ASSERT_LT(u_rest, 1.f);
      if (entry == lc.clusters) {
        chi2.observed()[cells - 1] += 1;
        continue;
      }
      const LightSample ls = lights.sample_in(entry, u_rest, uni(rng));
      const uint32_t li = ls.punctual >= 0 ? uint32_t(lights.emitter_count()) + uint32_t(ls.punctual)
                                           : emitter_index.at({ls.slot, ls.prim});
      ASSERT_EQ(cluster_of[li], entry);
      chi2.observed()[li] += 1;
    }
    for (uint32_t li = 0; li < lights.size(); ++li) {
      const uint32_t c = cluster_of[li];
      chi2.expected()[li] =
          n * double(w[c] / total) * light_power(*scene, li) / cluster_power[c];
    }
    chi2.expected()[cells - 1] = n * double(w[lc.clusters] / total);
    const testing::ChiSquareResult result = chi2.run();
    EXPECT_TRUE(result.passed) << result.message;
  }
}

// Whether light sampling at (o, ng) keeps a sample of light li at point p (area lights) or
// the punctual light: the tests of render/light_sampling.cpp, before the BSDF and visibility.
bool can_contribute(const Scene& scene, uint32_t li, Vec3 o, Vec3 ng, Vec3 p) {
  const LightSet& lights = scene.lights();
  if (li < lights.emitter_count()) {
    const Emitter& e = lights.emitters()[li];
    if (dot(ng, p - o) <= 0.f) return false;
    return scene.materials()[e.material].double_sided || dot(e.ng, o - p) > 0.f;
  }
  const PunctualLight& l = lights.punctual()[li - lights.emitter_count()];
  if (l.type == PunctualType::Directional) return dot(-l.direction, ng) > 0.f;
  return dot(l.position - o, ng) > 0.f;
}

TEST(LightSelection, ZeroProbabilityOnlyWhereNoLightOfTheClusterCanContribute) {
  const auto scene = many_lights_scene();
  const LightSet& lights = scene->lights();
  std::mt19937_64 rng(11);
  std::uniform_real_distribution<float> pos(-6.f, 6.f), uni(0.f, 1.f);
  int zeros = 0, positive = 0;
  for (int k = 0; k < 3000; ++k) {
    // Points anywhere, also right next to a light (on the quads' planes, by the sphere).
    Vec3 o(pos(rng), pos(rng), 0.5f * pos(rng) + 2.f);
    if (k % 3 == 1) o.z = 3.f - 1e-3f;
    if (k % 3 == 2) o = Vec3(1.5f, -2.f, 1.f) + random_unit(rng) * 0.45f;
    const Vec3 ng = random_unit(rng);
    for (uint32_t c = 0; c < lights.cluster_count(); ++c) {
      const LightCluster& cl = lights.cluster(c);
      if (lights.importance(c, o, ng) > 0.f) {
        ++positive;
        continue;
      }
      ++zeros;
      for (uint32_t i = 0; i < cl.count; ++i) {
        const uint32_t li = lights.member(cl.first + i);
        if (li >= lights.emitter_count()) {
          ASSERT_FALSE(can_contribute(*scene, li, o, ng, Vec3())) << "light " << li;
          continue;
        }
        // The vertices and points spread over the triangle.
        const Emitter& e = lights.emitters()[li];
        for (int s = 0; s < 64; ++s) {
          float b1 = uni(rng), b2 = uni(rng);
          if (b1 + b2 > 1.f) b1 = 1.f - b1, b2 = 1.f - b2;
          if (s < 3) b1 = float(s == 1), b2 = float(s == 2);
          const Vec3 p = e.p[0] * (1.f - b1 - b2) + e.p[1] * b1 + e.p[2] * b2;
          ASSERT_FALSE(can_contribute(*scene, li, o, ng, p))
              << "emitter " << li << " at point " << k << " cluster " << c;
        }
      }
    }
  }
  // The test has power: many clusters were ruled out, many were not.
  EXPECT_GT(zeros, 3000);
  EXPECT_GT(positive, 3000);
}

}  // namespace
}  // namespace rf
