// The light groups (aovs `light_groups`, #40): the radiance split by the light it came from,
// one RGB block per group of settings.light_groups. Per sample the groups sum to the radiance,
// and each is an unbiased estimate of its own light; the expected values below come from
// renders of other scenes (a scene with one light alone), from closed forms (a Lambert plane
// under a uniform sky) and from emitters seen directly, never from the code under test.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "render/channels.h"
#include "render/integrators.h"
#include "render/light_groups.h"
#include "scene/environment.h"
#include "scene/materials.h"
#include "testing/test_scenes.h"

namespace rf {
namespace {

using channels::Id;

constexpr channels::Set kRadianceRows = channels::bit(Id::Rgb) |
                                        channels::bit(Id::Luminance) |
                                        channels::bit(Id::Coverage);
constexpr channels::Set kWithGroups = kRadianceRows | channels::bit(Id::LightGroups);

constexpr uint32_t kWidth = 16, kHeight = 12;

Material lambert(const char* name, Vec3 albedo) {
  Material m;
  m.name = name;
  m.albedo = albedo;
  return m;
}

Material emitter(const char* name, Vec3 radiance) {
  Material m = lambert(name, {0.f, 0.f, 0.f});
  m.emission = radiance;
  return m;
}

uint32_t add_material(SceneDescription* desc, const Material& m) {
  desc->materials.push_back(m);
  return uint32_t(desc->materials.size() - 1);
}

// The world triangles from `first` on belong to glTF node `node`.
void set_node(SceneDescription* desc, size_t first, uint32_t node) {
  desc->world.node.resize(desc->world.size(), kNoNode);
  for (size_t i = first; i < desc->world.size(); ++i) desc->world.node[i] = node;
}

// testing::add_quad, the quad of glTF node `node`.
void add_quad(SceneDescription* desc, Vec3 p0, Vec3 p1, Vec3 p2, Vec3 p3, uint32_t material,
              uint32_t node) {
  const size_t first = desc->world.size();
  testing::add_quad(desc, p0, p1, p2, p3, material);
  set_node(desc, first, node);
}

PunctualLight point(Vec3 position, Vec3 intensity, uint32_t node) {
  PunctualLight l;
  l.position = position;
  l.intensity = intensity;
  l.node = node;
  return l;
}

using GroupList = std::vector<std::pair<std::string, std::vector<uint32_t>>>;
std::shared_ptr<const LightGroups> make_groups(const GroupList& list) {
  auto g = std::make_shared<LightGroups>();
  for (const auto& [name, nodes] : list) {
    g->names.push_back(name);
    g->nodes.push_back(nodes);
  }
  return g;
}

// A varied environment (importance sampling has something to do).
std::shared_ptr<const Environment> sky() {
  const uint32_t w = 16, h = 8;
  std::vector<float> rgb(size_t(w) * h * 3);
  for (uint32_t i = 0; i < w * h; ++i) {
    rgb[3 * i] = 0.2f + 0.1f * float(i % 5);
    rgb[3 * i + 1] = 0.3f + 0.05f * float(i % 7);
    rgb[3 * i + 2] = 0.4f + (i / w < 2 ? 1.5f : 0.f);
  }
  return std::make_shared<Environment>(std::move(rgb), w, h, 1.f, 20.f);
}

// A floor (z = 0, facing +z; node 0, which emits nothing) and a wall behind it, seen by a
// camera above it.
SceneDescription floor_scene(const char* name, const Material& floor) {
  SceneDescription desc;
  desc.source = name;
  desc.materials.push_back(floor);
  add_quad(&desc, {-6, -6, 0}, {6, -6, 0}, {6, 6, 0}, {-6, 6, 0}, 0, 0);
  add_quad(&desc, {-6, 3, 0}, {6, 3, 0}, {6, 3, 3}, {-6, 3, 3}, 0, 0);
  desc.camera = testing::look_at({0.f, -5.f, 3.5f}, {0.f, 0.f, 0.5f}, 0.9f);
  return desc;
}

// The scenes of the sum test, each with its groups (the environment's last) and the groups
// some pixel must have nonzero, so that the scene exercises what it is for.
struct GroupScene {
  std::string name;
  SceneDescription desc;
  std::shared_ptr<const Environment> env;
  std::shared_ptr<const LightGroups> groups;
  std::vector<std::string> lit;
};

std::vector<GroupScene> group_scenes() {
  std::vector<GroupScene> out;
  const Material grey = lambert("grey", {0.6f, 0.6f, 0.6f});
  {  // Two point lights in two groups and an emissive quad in a third, under the sky.
    SceneDescription d = floor_scene("points-and-panel", grey);
    d.punctual_lights.push_back(point({1.5f, -1.f, 2.f}, {4.f, 3.f, 2.f}, 1));
    d.punctual_lights.push_back(point({-1.5f, -0.5f, 1.5f}, {1.f, 2.f, 3.f}, 2));
    add_quad(&d, {-1.f, 1.f, 0.2f}, {1.f, 1.f, 0.2f}, {1.f, 1.f, 1.7f}, {-1.f, 1.f, 1.7f},
             add_material(&d, emitter("panel", {3.f, 2.f, 1.f})), 3);
    out.push_back({"points-and-panel", std::move(d), sky(),
                   make_groups({{"a", {1}}, {"b", {2}}, {"panel", {3}}, {"environment", {}}}),
                   {"a", "b", "panel", "environment"}});
  }
  {  // Two point lights in one group; an emissive mesh placed twice (instances), each
     // instance's node in a group of its own; a node in the groups that emits nothing.
    SceneDescription d = floor_scene("instances", grey);
    d.punctual_lights.push_back(point({1.5f, -1.f, 2.f}, {2.f, 2.f, 2.f}, 1));
    d.punctual_lights.push_back(point({-1.5f, -1.f, 2.f}, {1.f, 1.f, 3.f}, 2));
    SceneDescription tile;
    testing::add_quad(&tile, {-0.5f, 0.f, 0.f}, {0.5f, 0.f, 0.f}, {0.5f, 0.f, 1.f},
                      {-0.5f, 0.f, 1.f}, add_material(&d, emitter("tile", {2.f, 1.f, 3.f})));
    Mesh mesh;
    mesh.name = "tile";
    mesh.geometry = std::move(tile.world);
    d.meshes.push_back(std::move(mesh));
    for (const auto& [x, node] : {std::pair<float, uint32_t>{-1.2f, 3u}, {1.2f, 4u}}) {
      Mat4 at = Mat4::identity();
      at.m[3][0] = x;
      at.m[3][1] = 1.f;
      at.m[3][2] = 0.3f;
      d.instances.push_back({0, node, at});
    }
    out.push_back({"instances", std::move(d), nullptr,
                   make_groups({{"fill", {1, 2}},
                                {"left", {3}},
                                {"right", {4}},
                                {"floor", {0}},
                                {"environment", {}}}),
                   {"fill", "left", "right"}});
  }
  {  // Unlit quads (one adding its emission, as points and lines do) beside a lit floor.
    SceneDescription d = floor_scene("unlit", grey);
    Material unlit = lambert("unlit", {0.2f, 0.7f, 0.4f});
    unlit.unlit = true;
    Material adds = lambert("unlit-emission", {0.3f, 0.3f, 0.1f});
    adds.unlit = true;
    adds.unlit_adds_emission = true;
    adds.emission = {0.5f, 0.2f, 0.9f};
    add_quad(&d, {-2.f, 1.f, 0.1f}, {0.f, 1.f, 0.1f}, {0.f, 1.f, 1.5f}, {-2.f, 1.f, 1.5f},
             add_material(&d, unlit), 5);
    add_quad(&d, {0.2f, 1.f, 0.1f}, {2.f, 1.f, 0.1f}, {2.f, 1.f, 1.5f}, {0.2f, 1.f, 1.5f},
             add_material(&d, adds), 6);
    d.punctual_lights.push_back(point({0.f, -1.f, 2.f}, {3.f, 3.f, 3.f}, 1));
    out.push_back({"unlit", std::move(d), nullptr,
                   make_groups({{"unlit", {5}},
                                {"key", {1}},
                                {"adds", {6}},
                                {"environment", {}}}),
                   {"unlit", "key", "adds"}});
  }
  {  // A spot light and a directional light on a glossy floor, a translucent sheet (diffuse
     // transmission) with a point light under it, reached only through its BTDF.
    Material glossy = grey;
    glossy.specular = 1.f;
    glossy.roughness = 0.4f;
    SceneDescription d = floor_scene("spot", glossy);
    PunctualLight spot = point({0.f, -1.f, 3.f}, {20.f, 15.f, 10.f}, 1);
    spot.type = PunctualType::Spot;
    spot.direction = normalize(Vec3(0.f, 0.3f, -1.f));
    spot.cos_inner = std::cos(0.3f);
    spot.cos_outer = std::cos(0.6f);
    d.punctual_lights.push_back(spot);
    PunctualLight sun = point({}, {0.5f, 0.5f, 0.4f}, 2);
    sun.type = PunctualType::Directional;
    sun.direction = normalize(Vec3(0.3f, 0.5f, -1.f));
    d.punctual_lights.push_back(sun);
    Material sheet = lambert("sheet", {0.7f, 0.7f, 0.7f});
    sheet.diffuse_transmission = 0.7f;
    sheet.diffuse_transmission_color = {0.8f, 0.9f, 0.5f};
    sheet.double_sided = true;
    add_quad(&d, {1.f, -2.f, 1.f}, {3.f, -2.f, 1.f}, {3.f, 0.f, 1.f}, {1.f, 0.f, 1.f},
             add_material(&d, sheet), 0);
    d.punctual_lights.push_back(point({2.f, -1.f, 0.5f}, {2.f, 2.f, 2.f}, 3));
    out.push_back({"spot", std::move(d), nullptr,
                   make_groups({{"spot", {1}},
                                {"sun", {2}},
                                {"under", {3}},
                                {"environment", {}}}),
                   {"spot", "sun", "under"}});
  }
  {  // An area light seen directly, in a mirror floor and through smooth and rough glass; a
     // point light; the sky.
    Material mirror = lambert("mirror", {1.f, 1.f, 1.f});
    mirror.metallic = 1.f;
    mirror.roughness = 0.f;
    SceneDescription d = floor_scene("mirror-glass", mirror);
    Material glass = lambert("glass", {1.f, 1.f, 1.f});
    glass.transmission = 1.f;
    glass.roughness = 0.f;
    glass.specular = 1.f;
    Material rough = glass;
    rough.name = "rough-glass";
    rough.roughness = 0.3f;
    size_t first = d.world.size();
    testing::add_sphere(&d, {-1.2f, 0.f, 0.7f}, 0.6f, add_material(&d, glass), 12, 24);
    testing::add_sphere(&d, {1.2f, 0.f, 0.7f}, 0.6f, add_material(&d, rough), 12, 24);
    set_node(&d, first, 8);
    Material panel = emitter("panel", {4.f, 3.f, 2.f});
    panel.double_sided = true;
    add_quad(&d, {-1.5f, 1.5f, 0.3f}, {1.5f, 1.5f, 0.3f}, {1.5f, 1.5f, 2.f}, {-1.5f, 1.5f, 2.f},
             add_material(&d, panel), 3);
    d.punctual_lights.push_back(point({0.f, -2.f, 2.5f}, {3.f, 3.f, 3.f}, 1));
    out.push_back({"mirror-glass", std::move(d), sky(),
                   make_groups({{"panel", {3}}, {"key", {1}}, {"environment", {}}}),
                   {"panel", "key", "environment"}});
  }
  return out;
}

RenderSettings settings_for(IntegratorType integrator, uint32_t max_depth,
                            std::shared_ptr<const Environment> env,
                            std::shared_ptr<const LightGroups> groups) {
  RenderSettings settings;
  settings.width = kWidth;
  settings.height = kHeight;
  settings.seed = 13;
  settings.integrator = integrator;
  settings.max_depth = max_depth;
  settings.environment = std::move(env);
  settings.light_groups = std::move(groups);
  return settings;
}

TileBuffer render(const Scene& scene, const RenderSettings& settings, uint64_t start,
                  uint32_t count, channels::Set rows = kWithGroups) {
  TileBuffer tile;
  EXPECT_TRUE(render_rect(scene, settings, {0, 0, settings.width, settings.height}, start, count,
                          &tile, nullptr, rows));
  return tile;
}

// Group g's sum at pixel i, channel c.
double group(const TileBuffer& t, uint32_t g, size_t i, int c) {
  return double(t.sum(Id::LightGroups)[3 * (t.groups * i + g) + size_t(c)]);
}

// Every sample of every scene (one-sample batches: a batch's sums are its sample's values),
// path and direct: the groups sum to the radiance; ao: every group is 0 (its value is not
// light).
TEST(LightGroups, EverySampleOfEverySceneSumsToTheRadiance) {
  constexpr uint32_t kSamples = 16;
  for (GroupScene& s : group_scenes()) {
    ASSERT_EQ(check_light_groups(Scene(SceneDescription(s.desc)), *s.groups), "") << s.name;
    const Scene scene(std::move(s.desc));
    const uint32_t n = s.groups->count();
    for (IntegratorType integrator : {IntegratorType::Path, IntegratorType::Direct,
                                      IntegratorType::AmbientOcclusion}) {
      SCOPED_TRACE(s.name + " " + integrator_type_name(integrator));
      const RenderSettings settings = settings_for(integrator, 8, s.env, s.groups);
      std::vector<double> total(n, 0.0);
      double rgb_total = 0.0;
      for (uint32_t k = 0; k < kSamples; ++k) {
        const TileBuffer t = render(scene, settings, k, 1);
        ASSERT_EQ(t.nonfinite_samples, 0u);
        ASSERT_EQ(t.groups, n);
        ASSERT_EQ(t.sum(Id::LightGroups).size(), 3 * n * t.rect.pixel_count());
        for (size_t i = 0; i < t.rect.pixel_count(); ++i)
          for (int c = 0; c < 3; ++c) {
            const double rgb = t.rgb_sum[3 * i + size_t(c)];
            rgb_total += rgb;
            double sum = 0.0, magnitude = std::abs(rgb);
            for (uint32_t g = 0; g < n; ++g) {
              const double v = group(t, g, i, c);
              if (integrator == IntegratorType::AmbientOcclusion) {
                ASSERT_EQ(v, 0.0) << s.groups->names[g];
              }
              total[g] += std::abs(v);
              sum += v;
              magnitude += std::abs(v);
            }
            if (integrator == IntegratorType::AmbientOcclusion) continue;
            ASSERT_NEAR(sum, rgb, 1e-5 * magnitude + 1e-6)
                << "sample " << k << " pixel " << i << " channel " << c;
          }
      }
      EXPECT_GT(rgb_total, 0.0);
      if (integrator == IntegratorType::AmbientOcclusion) continue;
      for (uint32_t g = 0; g < n; ++g) {
        const bool lit = std::count(s.lit.begin(), s.lit.end(), s.groups->names[g]) > 0;
        if (lit) {
          EXPECT_GT(total[g], 0.0) << "group " << s.groups->names[g] << " is 0";
        }
      }
    }
  }
}

// The light groups change nothing else: the radiance, its luminance M2, every other row
// (the lobe rows among them) and the ray count are bit for bit those of a render without
// them; the same request twice gives the same bytes; the row asked for without groups in the
// settings is not rendered.
TEST(LightGroups, TurningThemOnChangesNothingElseAndIsDeterministic) {
  for (GroupScene& s : group_scenes()) {
    SCOPED_TRACE(s.name);
    const Scene scene(std::move(s.desc));
    for (IntegratorType integrator : {IntegratorType::Path, IntegratorType::Direct}) {
      const RenderSettings settings = settings_for(integrator, 8, s.env, s.groups);
      RenderSettings without = settings;
      without.light_groups = nullptr;
      // 40 samples from 3: full packets and a partial one.
      const channels::Set others = channels::kAll & ~channels::bit(Id::LightGroups);
      const TileBuffer off = render(scene, settings, 3, 40, others);
      const TileBuffer on = render(scene, settings, 3, 40, channels::kAll);
      const TileBuffer again = render(scene, settings, 3, 40, channels::kAll);
      const TileBuffer no_groups = render(scene, without, 3, 40, channels::kAll);
      for (const TileBuffer* t : {&on, &no_groups}) {
        EXPECT_EQ(t->rgb_sum, off.rgb_sum);
        EXPECT_EQ(t->luminance_m2, off.luminance_m2);
        EXPECT_EQ(t->rays, off.rays);
        EXPECT_EQ(t->depth_sum, off.depth_sum);
        for (const channels::Spec& row : channels::kSpecs) {
          if (row.id == Id::Rgb || row.id == Id::Luminance || row.id == Id::LightGroups) continue;
          if (row.ranked) {
            EXPECT_EQ(t->ranked(row.id), off.ranked(row.id)) << row.name;
          } else {
            EXPECT_EQ(t->sum(row.id), off.sum(row.id)) << row.name;
          }
        }
      }
      EXPECT_TRUE(off.sum(Id::LightGroups).empty());
      EXPECT_TRUE(no_groups.sum(Id::LightGroups).empty());
      EXPECT_EQ(no_groups.groups, 0u);
      const std::vector<float>& a = on.sum(Id::LightGroups);
      const std::vector<float>& b = again.sum(Id::LightGroups);
      ASSERT_EQ(a.size(), 3 * s.groups->count() * on.rect.pixel_count());
      ASSERT_EQ(a.size(), b.size());
      EXPECT_EQ(std::memcmp(a.data(), b.data(), a.size() * sizeof(float)), 0);
      EXPECT_EQ(on.rgb_sum, again.rgb_sum);
      const TileBuffer rgb_only = render(scene, settings, 3, 40, channels::bit(Id::Rgb));
      EXPECT_EQ(rgb_only.rgb_sum, on.rgb_sum);
    }
  }
}

// A sample whose radiance is not finite is recorded as 0 in the radiance and in every group:
// here an unlit quad of infinite colour beside a lit floor.
TEST(LightGroups, NonFiniteSamplesAreZeroInEveryGroup) {
  SceneDescription d = floor_scene("inf", lambert("grey", {0.6f, 0.6f, 0.6f}));
  Material bad = lambert("inf", {std::numeric_limits<float>::infinity(), 1.f, 1.f});
  bad.unlit = true;
  add_quad(&d, {-1.f, 1.f, 0.1f}, {1.f, 1.f, 0.1f}, {1.f, 1.f, 1.5f}, {-1.f, 1.f, 1.5f},
           add_material(&d, bad), 5);
  d.punctual_lights.push_back(point({0.f, -1.f, 2.f}, {3.f, 3.f, 3.f}, 1));
  const Scene scene(std::move(d));
  const auto groups = make_groups({{"bad", {5}}, {"key", {1}}, {"environment", {}}});
  const TileBuffer t =
      render(scene, settings_for(IntegratorType::Path, 4, sky(), groups), 0, 8);
  EXPECT_GT(t.nonfinite_samples, 0u);
  double key = 0.0;
  for (size_t i = 0; i < t.rect.pixel_count(); ++i)
    for (int c = 0; c < 3; ++c) {
      double sum = 0.0;
      for (uint32_t g = 0; g < 3; ++g) {
        ASSERT_TRUE(std::isfinite(group(t, g, i, c))) << "pixel " << i;
        sum += group(t, g, i, c);
      }
      key += group(t, 1, i, c);
      const double rgb = t.rgb_sum[3 * i + size_t(c)];
      EXPECT_NEAR(sum, rgb, 1e-5 * std::abs(rgb) + 1e-5) << "pixel " << i;
    }
  EXPECT_GT(key, 0.0);
}

// ---- Each group is its own light.

// Mean and standard error of the pixels' values (each pixel an independent estimate).
struct Estimate {
  double mean = 0.0, standard_error = 0.0;
};
Estimate over_pixels(const std::vector<double>& values) {
  double sum = 0.0, sum2 = 0.0;
  for (double v : values) {
    sum += v;
    sum2 += v * v;
  }
  const double n = double(values.size());
  Estimate e;
  e.mean = sum / n;
  e.standard_error = std::sqrt(std::max(0.0, sum2 / n - e.mean * e.mean) / (n - 1.0));
  return e;
}

// Two point lights A and B and an area light C (out of view), of different colours, over a
// Lambert plane, one bounce: group A's image is an unbiased estimate of A's light alone, which
// a render of the plane lit by A alone (another scene, where light selection always picks A)
// estimates too. Per pixel and channel the two renders' means differ by noise alone: the mean
// difference over the pixels is within four standard errors of 0, while A's light is far
// larger than that error. Likewise for B, and for C (its light samples, and the rays that
// find it, weighted by MIS).
TEST(LightGroups, EachLightsGroupIsThatLightAlone) {
  const PunctualLight a = point({1.2f, 0.5f, 1.f}, {3.f, 2.f, 1.f}, 1);
  const PunctualLight b = point({-1.f, -0.5f, 1.5f}, {1.f, 2.f, 4.f}, 2);
  // lights: which of A, B and C the scene has (bits 0, 1, 2).
  const auto plane = [&](uint32_t lights) {
    SceneDescription d;
    d.source = "plane";
    d.materials.push_back(lambert("white", {0.7f, 0.7f, 0.7f}));
    add_quad(&d, {-8, -8, 0}, {8, -8, 0}, {8, 8, 0}, {-8, 8, 0}, 0, 0);
    d.camera = testing::look_at({0.f, -1.f, 4.f}, {0.f, 0.f, 0.f}, 0.8f);
    if (lights & 1) d.punctual_lights.push_back(a);
    if (lights & 2) d.punctual_lights.push_back(b);
    if (lights & 4)  // 1 x 1 at height 1.5 beside the view, facing down
      add_quad(&d, {3.f, -0.5f, 1.5f}, {3.f, 0.5f, 1.5f}, {4.f, 0.5f, 1.5f}, {4.f, -0.5f, 1.5f},
               add_material(&d, emitter("c", {2.f, 4.f, 3.f})), 3);
    return d;
  };
  const Scene all(plane(7));
  const auto groups = make_groups({{"a", {1}}, {"b", {2}}, {"c", {3}}, {"environment", {}}});
  const uint32_t spp = 256;
  const TileBuffer t =
      render(all, settings_for(IntegratorType::Path, 1, nullptr, groups), 0, spp);
  for (uint32_t g = 0; g < 3; ++g) {
    const Scene alone(plane(1u << g));
    const TileBuffer ref = render(alone, settings_for(IntegratorType::Path, 1, nullptr, nullptr),
                                  0, spp, kRadianceRows);
    for (int c = 0; c < 3; ++c) {
      SCOPED_TRACE(groups->names[g] + " channel " + std::to_string(c));
      std::vector<double> diff, light;
      for (size_t i = 0; i < t.rect.pixel_count(); ++i) {
        ASSERT_EQ(t.sum(Id::Coverage)[i], float(spp));
        diff.push_back((group(t, g, i, c) - ref.rgb_sum[3 * i + size_t(c)]) / spp);
        light.push_back(ref.rgb_sum[3 * i + size_t(c)] / spp);
        EXPECT_EQ(group(t, 3, i, c), 0.0);  // no environment
      }
      const Estimate d = over_pixels(diff), l = over_pixels(light);
      EXPECT_LT(d.standard_error, 0.02 * l.mean) << "test would have no power";
      EXPECT_NEAR(d.mean, 0.0, 4.0 * d.standard_error);
    }
  }
}

// A Lambert plane lit by a point light under a uniform sky of radiance E, one bounce, the
// camera seeing the sky beyond the plane: where it sees the sky, the environment's group is E
// exactly and the light's 0; on the plane, the environment's group is albedo x E (the sky over
// the whole upper hemisphere, whatever the point light adds to the image).
TEST(LightGroups, TheEnvironmentsGroupIsTheSkyAndWhatItLights) {
  const float rho = 0.6f, E = 0.75f;
  SceneDescription d;
  d.source = "horizon";
  d.materials.push_back(lambert("white", {rho, rho, rho}));
  add_quad(&d, {-40, -10, 0}, {40, -10, 0}, {40, 30, 0}, {-40, 30, 0}, 0, 0);
  d.camera = testing::look_at({0.f, -5.f, 1.f}, {0.f, 0.f, 0.6f}, 0.8f);
  d.punctual_lights.push_back(point({0.f, 2.f, 1.f}, {5.f, 5.f, 5.f}, 1));
  const Scene scene(std::move(d));
  const auto groups = make_groups({{"key", {1}}, {"environment", {}}});
  const uint32_t spp = 256;
  const TileBuffer t = render(
      scene, settings_for(IntegratorType::Path, 1, Environment::constant({E, E, E}), groups), 0,
      spp);
  std::vector<double> plane;
  size_t sky_pixels = 0;
  double key = 0.0;
  for (size_t i = 0; i < t.rect.pixel_count(); ++i) {
    const float coverage = t.sum(Id::Coverage)[i];
    if (coverage == 0.f) {
      ++sky_pixels;
      for (int c = 0; c < 3; ++c) {
        EXPECT_EQ(group(t, 1, i, c), double(E) * spp) << "pixel " << i;
        EXPECT_EQ(group(t, 0, i, c), 0.0) << "pixel " << i;
      }
    } else if (coverage == float(spp)) {
      plane.push_back(group(t, 1, i, 1) / spp);
      key += group(t, 0, i, 1);
    }
  }
  EXPECT_GT(sky_pixels, 10u);
  ASSERT_GT(plane.size(), 50u);
  EXPECT_GT(key, 0.0);
  const Estimate e = over_pixels(plane);
  EXPECT_LT(e.standard_error, 0.01 * rho * E) << "test would have no power";
  EXPECT_NEAR(e.mean, double(rho) * E, 4.0 * e.standard_error + 1e-5);
}

// An emitter filling the view, and an unlit quad, each with a point light and the sky in
// groups of their own: the surface's group is its emission (or colour) exactly, every sample,
// and every other group exactly 0 (a black, non-specular emitter reflects nothing; an unlit
// surface ends the path).
TEST(LightGroups, EmittersSeenDirectlyGiveTheirOwnGroupTheirLight) {
  const Vec3 Le(3.f, 2.f, 0.5f), base(0.25f, 0.5f, 0.75f);
  Material unlit = lambert("unlit", base);
  unlit.unlit = true;
  const auto groups = make_groups({{"key", {1}}, {"surface", {4}}, {"environment", {}}});
  for (const Material& m : {emitter("emitter", Le), unlit}) {
    SCOPED_TRACE(m.name);
    SceneDescription d;
    d.source = m.name;
    add_quad(&d, {-10, -10, 0}, {10, -10, 0}, {10, 10, 0}, {-10, 10, 0}, add_material(&d, m), 4);
    d.camera = testing::look_at({0.f, -1.f, 2.f}, {0, 0, 0}, 0.8f);
    d.punctual_lights.push_back(point({0.f, 0.f, 1.f}, {5.f, 5.f, 5.f}, 1));
    const Scene scene(std::move(d));
    const uint32_t spp = 32;
    const TileBuffer t = render(
        scene, settings_for(IntegratorType::Path, 8, Environment::constant({1, 1, 1}), groups), 0,
        spp);
    const Vec3 want = m.unlit ? base : Le;
    for (size_t i = 0; i < t.rect.pixel_count(); ++i) {
      ASSERT_EQ(t.sum(Id::Coverage)[i], float(spp));
      for (int c = 0; c < 3; ++c) {
        EXPECT_EQ(group(t, 1, i, c), double(want[c]) * spp) << "pixel " << i;
        EXPECT_EQ(t.rgb_sum[3 * i + size_t(c)], double(want[c]) * spp) << "pixel " << i;
        EXPECT_EQ(group(t, 0, i, c), 0.0) << "pixel " << i;
        EXPECT_EQ(group(t, 2, i, c), 0.0) << "pixel " << i;
      }
    }
  }
}

// The same surfaces facing down over a mirror (metal, roughness 0), seen only in it, with a
// point light and the sky: the surface's group is what a render of the surface and the mirror
// alone (no other light) estimates, within four standard errors over the pixels; for the
// emitter, an area light the mirror's vertex samples (its light samples and the rays that
// find it weighted by MIS against each other), through the mirror's glossy lobe.
TEST(LightGroups, AnEmitterSeenInAMirrorIsItsGroupAlone) {
  const Vec3 Le(3.f, 2.f, 0.5f), base(0.25f, 0.5f, 0.75f);
  Material unlit = lambert("unlit", base);
  unlit.unlit = true;
  const auto groups = make_groups({{"key", {1}}, {"surface", {4}}, {"environment", {}}});
  for (const Material& m : {emitter("emitter", Le), unlit}) {
    SCOPED_TRACE(m.name);
    const auto mirrored = [&m](bool others) {
      SceneDescription d;
      d.source = m.name;
      Material mirror = lambert("mirror", {0.9f, 0.9f, 0.9f});
      mirror.metallic = 1.f;
      mirror.roughness = 0.f;
      add_quad(&d, {-10, -10, 0}, {10, -10, 0}, {10, 10, 0}, {-10, 10, 0},
               add_material(&d, mirror), 0);
      // The surface at height 2, facing down; the camera under it looks down at the mirror.
      add_quad(&d, {-3, -3, 2}, {-3, 3, 2}, {3, 3, 2}, {3, -3, 2}, add_material(&d, m), 4);
      d.camera = testing::look_at({0.f, -0.2f, 1.f}, {0, 0, 0}, 0.5f);
      if (others) d.punctual_lights.push_back(point({0.f, 0.f, 1.5f}, {5.f, 5.f, 5.f}, 1));
      return d;
    };
    const Scene scene(mirrored(true)), alone(mirrored(false));
    const uint32_t spp = 256;
    const TileBuffer t = render(
        scene, settings_for(IntegratorType::Path, 8, Environment::constant({1, 1, 1}), groups), 0,
        spp);
    const TileBuffer ref = render(alone, settings_for(IntegratorType::Path, 8, nullptr, nullptr),
                                  0, spp, kRadianceRows);
    for (int c = 0; c < 3; ++c) {
      std::vector<double> diff, light;
      double key = 0.0;
      for (size_t i = 0; i < t.rect.pixel_count(); ++i) {
        diff.push_back((group(t, 1, i, c) - ref.rgb_sum[3 * i + size_t(c)]) / spp);
        light.push_back(ref.rgb_sum[3 * i + size_t(c)] / spp);
        key += group(t, 0, i, c);
      }
      EXPECT_GT(key, 0.0);  // the point light shines in the mirror too
      const Estimate dm = over_pixels(diff), l = over_pixels(light);
      EXPECT_GT(l.mean, 0.5 * (m.unlit ? base : Le)[c]);  // it is seen
      EXPECT_LT(dm.standard_error, 0.01 * l.mean) << "test would have no power";
      // (The unlit surface is no light: its paths are the same in both scenes, and the two
      // differ by the rounding of the group's float32 sums alone.)
      EXPECT_NEAR(dm.mean, 0.0, 4.0 * dm.standard_error + 1e-5 * l.mean) << "channel " << c;
    }
  }
}

// ---- The settings and the scene's emitting nodes.

TEST(LightGroups, ParsesTheSettingInItsOrder) {
  LightGroups g;
  ASSERT_EQ(parse_light_groups(R"({"z":[3],"key":[1,2,1],"environment":[]})", &g), "");
  ASSERT_EQ(g.count(), 3u);
  EXPECT_EQ(g.names, (std::vector<std::string>{"z", "key", "environment"}));
  EXPECT_EQ(g.nodes[0], std::vector<uint32_t>{3});
  EXPECT_EQ(g.nodes[1], (std::vector<uint32_t>{1, 2}));  // listed twice in one group: once
  EXPECT_TRUE(g.nodes[2].empty());
  ASSERT_EQ(parse_light_groups(R"( {"environment": [0, 4294967294]} )", &g), "");
  EXPECT_EQ(g.nodes[0], (std::vector<uint32_t>{0, 4294967294u}));
}

TEST(LightGroups, RefusesMalformedSettings) {
  std::string many = "{";
  for (int i = 0; i < 33; ++i) many += (i ? ",\"g" : "\"g") + std::to_string(i) + "\":[]";
  many += "}";
  const std::pair<std::string, std::string> cases[] = {
      {"", "settings.light_groups: empty, while the task asks for the light_groups row"},
      {"{}", "settings.light_groups: no light group"},
      {"{\"a\":[1]", "settings.light_groups: not JSON"},
      {"[[1]]", "settings.light_groups: not a JSON object"},
      {"\"a\"", "settings.light_groups: not a JSON object"},
      {R"({"a":3})", "settings.light_groups: group \"a\" is not a list of node indices"},
      {R"({"a":{"n":1}})", "settings.light_groups: group \"a\" is not a list of node indices"},
      {R"({"a":[-1]})", "settings.light_groups: group \"a\" holds -1, not a glTF node index"},
      {R"({"a":[1.5]})", "settings.light_groups: group \"a\" holds 1.5, not a glTF node index"},
      {R"({"a":["1"]})", "settings.light_groups: group \"a\" holds \"1\", not a glTF node index"},
      {R"({"a":[true]})", "settings.light_groups: group \"a\" holds true, not a glTF node index"},
      {R"({"a":[4294967295]})", "settings.light_groups: group \"a\" holds 4294967295"},
      {R"({"a":[1],"b":[2,1]})",
       "settings.light_groups: node 1 is in two light groups, \"a\" and \"b\""},
      {many, "settings.light_groups: 33 light groups, more than 32"},
  };
  for (const auto& [json, message] : cases) {
    LightGroups g;
    const std::string err = parse_light_groups(json, &g);
    EXPECT_EQ(err.substr(0, message.size()), message) << json << "\n" << err;
  }
  LightGroups g;
  std::string exactly = many.substr(0, many.rfind(",\"g32\"")) + "}";
  EXPECT_EQ(parse_light_groups(exactly, &g), "");
  EXPECT_EQ(g.count(), 32u);
}

// A scene built here: a floor (node 0, emitting nothing), an emissive quad (node 7, named
// "lamp"), a point light (node 4, no name), an unlit quad (node 9) and an emissive mesh placed
// by an instance (node 11).
SceneDescription emitting_scene() {
  SceneDescription d = floor_scene("emitting", lambert("grey", {0.5f, 0.5f, 0.5f}));
  add_quad(&d, {-1.f, 1.f, 0.2f}, {1.f, 1.f, 0.2f}, {1.f, 1.f, 1.7f}, {-1.f, 1.f, 1.7f},
           add_material(&d, emitter("lamp", {2.f, 2.f, 2.f})), 7);
  d.node_names[7] = "lamp";
  d.punctual_lights.push_back(point({0.f, -1.f, 2.f}, {3.f, 3.f, 3.f}, 4));
  Material unlit = lambert("unlit", {0.5f, 0.5f, 0.5f});
  unlit.unlit = true;
  add_quad(&d, {2.f, 1.f, 0.2f}, {3.f, 1.f, 0.2f}, {3.f, 1.f, 1.f}, {2.f, 1.f, 1.f},
           add_material(&d, unlit), 9);
  SceneDescription tile;
  testing::add_quad(&tile, {-0.5f, 0.f, 0.f}, {0.5f, 0.f, 0.f}, {0.5f, 0.f, 1.f},
                    {-0.5f, 0.f, 1.f}, add_material(&d, emitter("tile", {1.f, 2.f, 1.f})));
  Mesh mesh;
  mesh.geometry = std::move(tile.world);
  d.meshes.push_back(std::move(mesh));
  Mat4 at = Mat4::identity();
  at.m[3][0] = -2.5f;
  at.m[3][1] = 1.f;
  d.instances.push_back({0, 11, at});
  return d;
}

TEST(LightGroups, RefusesAScenesEmittingNodeInNoGroup) {
  const Scene scene(emitting_scene());
  EXPECT_EQ(scene.emitting_nodes(), (std::vector<uint32_t>{4, 7, 9, 11}));
  const GroupList all = {{"lamp", {7}}, {"key", {4}}, {"unlit", {9}}, {"tile", {11}},
                         {"environment", {}}};
  // Every emitting node in a group, and nodes that emit nothing (the floor, a node the scene
  // does not have) in groups too: fine, their groups are black.
  GroupList extra = all;
  extra.insert(extra.begin(), std::make_pair(std::string("floor"), std::vector<uint32_t>{0, 100}));
  EXPECT_EQ(check_light_groups(scene, *make_groups(all)), "");
  EXPECT_EQ(check_light_groups(scene, *make_groups(extra)), "");
  const TileBuffer t =
      render(scene, settings_for(IntegratorType::Path, 4, sky(), make_groups(extra)), 0, 8);
  for (size_t i = 0; i < t.rect.pixel_count(); ++i)
    for (int c = 0; c < 3; ++c) EXPECT_EQ(group(t, 0, i, c), 0.0);
  // Each emitting node left out in turn.
  const std::pair<size_t, std::string> missing[] = {
      {0, "settings.light_groups: node 7 (\"lamp\") emits light but is in no light group"},
      {1, "settings.light_groups: node 4 emits light but is in no light group"},
      {2, "settings.light_groups: node 9 emits light but is in no light group"},
      {3, "settings.light_groups: node 11 emits light but is in no light group"},
  };
  for (const auto& [left_out, message] : missing) {
    GroupList some = all;
    some[left_out].second.clear();
    EXPECT_EQ(check_light_groups(scene, *make_groups(some)), message);
  }
  // An emitter without a glTF node (a scene built by hand) cannot be in any group.
  SceneDescription d = emitting_scene();
  d.world.node.back() = kNoNode;
  const Scene unnamed(std::move(d));
  EXPECT_EQ(check_light_groups(unnamed, *make_groups(all)),
            "settings.light_groups: the scene has light that comes from no glTF node, which "
            "no light group can hold");
}

// A glTF scene: a floor, a point light (node 1, "lamp"), a hidden one (node 2), an emissive
// mesh shared by two nodes (3 "tile-a" and 4 "tile-b", instances), an unnamed emissive node
// (5) and an unlit one (6, "sign"); the loader gives the lights their nodes and the scene
// knows which nodes emit and their names.
std::string emitting_gltf() {
  return R"({
  "asset": {"version": "2.0"},
  "extensionsUsed": ["KHR_lights_punctual", "KHR_node_visibility", "KHR_materials_unlit"],
  "extensions": {"KHR_lights_punctual": {"lights": [
    {"type": "point", "intensity": 5, "color": [1, 0.5, 0.25]}]}},
  "scene": 0,
  "scenes": [{"nodes": [0, 1, 2, 3, 4, 5, 6, 7]}],
  "nodes": [
    {"name": "floor", "mesh": 0, "scale": [4, 4, 1]},
    {"name": "lamp", "translation": [0, 0, 2],
     "extensions": {"KHR_lights_punctual": {"light": 0}}},
    {"name": "off", "translation": [1, 0, 2],
     "extensions": {"KHR_lights_punctual": {"light": 0},
                    "KHR_node_visibility": {"visible": false}}},
    {"name": "tile-a", "mesh": 1, "translation": [-1.5, 0, 0.5], "scale": [0.3, 0.3, 1]},
    {"name": "tile-b", "mesh": 1, "translation": [1.5, 0, 0.5], "scale": [0.3, 0.3, 1]},
    {"mesh": 2, "translation": [0, 1.5, 0.5], "scale": [0.3, 0.3, 1]},
    {"name": "sign", "mesh": 3, "translation": [0, -1.5, 0.5], "scale": [0.3, 0.3, 1]},
    {"name": "camera", "camera": 0, "translation": [0, 0, 6]}
  ],
  "cameras": [{"type": "perspective", "perspective": {"yfov": 0.9, "znear": 0.01}}],
  "materials": [
    {"name": "grey", "pbrMetallicRoughness": {"baseColorFactor": [0.6, 0.6, 0.6, 1],
                                              "metallicFactor": 0}},
    {"name": "glow", "emissiveFactor": [1, 0.5, 0.25]},
    {"name": "flat", "pbrMetallicRoughness": {"baseColorFactor": [0.2, 0.4, 0.6, 1]},
     "extensions": {"KHR_materials_unlit": {}}}
  ],
  "meshes": [
    {"primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1}, "indices": 3, "material": 0}]},
    {"primitives": [{"attributes": {"POSITION": 0}, "indices": 3, "material": 1}]},
    {"primitives": [{"attributes": {"POSITION": 0}, "indices": 3, "material": 1}]},
    {"primitives": [{"attributes": {"POSITION": 0}, "indices": 3, "material": 2}]}
  ],
  )" + testing::quad_gltf_buffers_json() + "\n}";
}

TEST(LightGroups, GltfScenesKnowTheirEmittingNodes) {
  std::vector<std::string> warnings;
  const Scene scene(load_gltf_from_string(emitting_gltf(), ".", "lights.gltf", &warnings));
  EXPECT_EQ(scene.emitting_nodes(), (std::vector<uint32_t>{1, 3, 4, 5, 6}));
  ASSERT_EQ(scene.lights().punctual().size(), 1u);
  EXPECT_EQ(scene.lights().punctual()[0].node, 1u);
  EXPECT_EQ(scene.node_name(1), "lamp");
  EXPECT_EQ(scene.node_name(4), "tile-b");
  EXPECT_EQ(scene.node_name(5), "");
  EXPECT_EQ(scene.node_name(6), "sign");
  const GroupList all = {{"tile-a", {3}}, {"lamp", {1, 2}}, {"tile-b", {4}},
                         {"nodes_5_", {5}}, {"sign", {6}}, {"environment", {}}};
  EXPECT_EQ(check_light_groups(scene, *make_groups(all)), "");
  GroupList some = all;
  some[1].second = {2};
  EXPECT_EQ(check_light_groups(scene, *make_groups(some)),
            "settings.light_groups: node 1 (\"lamp\") emits light but is in no light group");
  some = all;
  some[2].second.clear();
  EXPECT_EQ(check_light_groups(scene, *make_groups(some)),
            "settings.light_groups: node 4 (\"tile-b\") emits light but is in no light group");
  // Rendered: every group lit (the camera sees the tiles and the sign; the lamp lights the
  // floor), summing to the image.
  RenderSettings settings = settings_for(IntegratorType::Path, 4, nullptr, make_groups(all));
  const uint32_t spp = 16;
  const TileBuffer t = render(scene, settings, 0, spp);
  std::vector<double> total(6, 0.0);
  for (size_t i = 0; i < t.rect.pixel_count(); ++i)
    for (int c = 0; c < 3; ++c) {
      double sum = 0.0, magnitude = std::abs(t.rgb_sum[3 * i + size_t(c)]);
      for (uint32_t g = 0; g < 6; ++g) {
        sum += group(t, g, i, c);
        magnitude += std::abs(group(t, g, i, c));
        total[g] += group(t, g, i, c);
      }
      EXPECT_NEAR(sum, t.rgb_sum[3 * i + size_t(c)], 1e-5 * magnitude + 1e-5);
    }
  for (uint32_t g = 0; g < 5; ++g) EXPECT_GT(total[g], 0.0) << all[g].first;
  EXPECT_EQ(total[5], 0.0);  // no environment
}

}  // namespace
}  // namespace rf
