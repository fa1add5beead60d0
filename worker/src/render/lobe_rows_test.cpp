// The lobe rows of the channel table (aovs `lobes`, #40): the radiance split by the lobes of
// the path's first scattering vertex into diffuse, glossy and transmission, each direct and
// indirect, plus emission and background. Per sample the eight rows sum to the radiance; each
// is an unbiased estimate of its own integral, which the expected values below come from:
// closed forms (a Lambert or white metal plane under a uniform environment, Fresnel's
// equations for smooth glass, an emitter seen directly) and a quadrature of the glTF spec's
// BRDF (Appendix B with KHR_materials_specular) written out here, never the worker's code.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <memory>
#include <random>
#include <string>
#include <vector>

#include "render/channels.h"
#include "render/integrators.h"
#include "scene/environment.h"
#include "scene/materials.h"
#include "testing/test_scenes.h"

namespace rf {
namespace {

using channels::Id;

constexpr Id kLobeIds[kLobeRows] = {Id::DiffuseDirect,      Id::DiffuseIndirect,
                                    Id::GlossyDirect,       Id::GlossyIndirect,
                                    Id::TransmissionDirect, Id::TransmissionIndirect,
                                    Id::Emission,           Id::Background};
constexpr channels::Set kRadianceRows = channels::bit(Id::Rgb) |
                                        channels::bit(Id::Luminance) |
                                        channels::bit(Id::Coverage);
constexpr channels::Set kWithLobes = kRadianceRows | channels::kLobes;
constexpr channels::Set kIndirect = channels::bit(Id::DiffuseIndirect) |
                                    channels::bit(Id::GlossyIndirect) |
                                    channels::bit(Id::TransmissionIndirect);

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

// A varied environment (importance sampling has something to do), or null.
std::shared_ptr<const Environment> sky() {
  const uint32_t w = 16, h = 8;
  std::vector<float> rgb(size_t(w) * h * 3);
  for (uint32_t i = 0; i < w * h; ++i) {
    rgb[3 * i] = 0.2f + 0.1f * float(i % 5);
    rgb[3 * i + 1] = 0.3f + 0.05f * float(i % 7);
    rgb[3 * i + 2] = 0.4f + (i / w < 2 ? 1.5f : 0.f);  // a brighter band near the zenith
  }
  return std::make_shared<Environment>(std::move(rgb), w, h, 1.f, 20.f);
}

// The scenes of the sum test: each a floor (z = 0, facing +z) seen by a camera above it, with
// the objects and lights of its case; `lit`: rows some pixel must have nonzero (so that the
// scene exercises what it is for).
struct LobeScene {
  std::string name;
  SceneDescription desc;
  std::shared_ptr<const Environment> env;
  channels::Set lit;
};

uint32_t add_material(SceneDescription* desc, const Material& m) {
  desc->materials.push_back(m);
  return uint32_t(desc->materials.size() - 1);
}

// wall: a wall of the floor's material behind the objects (facing the camera), which light
// bounces off on its way to the floor (the diffuse_indirect row).
SceneDescription floor_scene(const char* name, const Material& floor, bool wall = true) {
  SceneDescription desc;
  desc.source = name;
  desc.materials.push_back(floor);
  testing::add_quad(&desc, {-6, -6, 0}, {6, -6, 0}, {6, 6, 0}, {-6, 6, 0}, 0);
  if (wall) testing::add_quad(&desc, {-6, 3, 0}, {6, 3, 0}, {6, 3, 3}, {-6, 3, 3}, 0);
  desc.camera = testing::look_at({0.f, -5.f, 3.5f}, {0.f, 0.f, 0.5f}, 0.9f);
  return desc;
}

// A 1 x 1 area light at height 2.5 facing down, and a point light.
void add_lights(SceneDescription* desc, float L = 4.f) {
  const uint32_t light = add_material(desc, emitter("light", {L, L, L}));
  testing::add_quad(desc, {-0.5f, -0.5f, 2.5f}, {-0.5f, 0.5f, 2.5f}, {0.5f, 0.5f, 2.5f},
                    {0.5f, -0.5f, 2.5f}, light);
  PunctualLight point;
  point.position = {1.5f, -1.f, 2.f};
  point.intensity = {4.f, 3.f, 2.f};
  desc->punctual_lights.push_back(point);
}

std::vector<LobeScene> lobe_scenes() {
  std::vector<LobeScene> out;
  const Material grey = lambert("grey", {0.6f, 0.6f, 0.6f});
  {  // A diffuse floor (no specular layer) under an area and a point light.
    SceneDescription d = floor_scene("diffuse", grey);
    add_lights(&d);
    out.push_back({"diffuse", std::move(d), nullptr,
                   channels::bit(Id::DiffuseDirect) | channels::bit(Id::DiffuseIndirect)});
  }
  {  // A rough coloured metal floor, an anisotropic iridescent metal sphere, the sky.
    Material metal = lambert("metal", {0.9f, 0.6f, 0.3f});
    metal.metallic = 1.f;
    metal.roughness = 0.5f;
    SceneDescription d = floor_scene("metal", metal, false);
    Material aniso = metal;
    aniso.name = "aniso";
    aniso.roughness = 0.3f;
    aniso.anisotropy = 0.7f;
    aniso.iridescence = 1.f;
    aniso.iridescence_thickness_max = 500.f;
    aniso.specular = 1.f;
    testing::add_sphere(&d, {0.f, 0.5f, 0.8f}, 0.8f, add_material(&d, aniso), 16, 32);
    add_lights(&d);
    out.push_back({"metal", std::move(d), sky(),
                   channels::bit(Id::GlossyDirect) | channels::bit(Id::GlossyIndirect) |
                       channels::bit(Id::Background)});
  }
  {  // Layered spheres: clear coat and sheen over a red dielectric; a coat over a metal.
    Material dielectric = grey;
    dielectric.specular = 1.f;
    dielectric.roughness = 0.6f;
    SceneDescription d = floor_scene("layered", dielectric);
    Material velvet = lambert("coat-sheen", {0.7f, 0.1f, 0.1f});
    velvet.specular = 0.5f;
    velvet.roughness = 0.4f;
    velvet.clearcoat = 1.f;
    velvet.clearcoat_roughness = 0.1f;
    velvet.sheen_color = {0.5f, 0.5f, 0.8f};
    velvet.sheen_roughness = 0.5f;
    Material coated = lambert("coated-metal", {0.3f, 0.8f, 0.4f});
    coated.metallic = 1.f;
    coated.roughness = 0.4f;
    coated.clearcoat = 0.8f;
    coated.clearcoat_roughness = 0.2f;
    testing::add_sphere(&d, {-0.9f, 0.f, 0.8f}, 0.8f, add_material(&d, velvet), 16, 32);
    testing::add_sphere(&d, {0.9f, 0.f, 0.8f}, 0.8f, add_material(&d, coated), 16, 32);
    add_lights(&d);
    out.push_back({"layered", std::move(d), sky(),
                   channels::bit(Id::DiffuseDirect) | channels::bit(Id::GlossyDirect) |
                       channels::bit(Id::DiffuseIndirect) | channels::bit(Id::GlossyIndirect)});
  }
  {  // Smooth, rough and dispersive absorbing glass spheres over a lit floor, and a sheet of
     // glass in front of an emitter (seen through it: transmission_direct).
    SceneDescription d = floor_scene("glass", grey);
    Material glass = lambert("glass", {1.f, 1.f, 1.f});
    glass.transmission = 1.f;
    glass.roughness = 0.f;
    glass.specular = 1.f;
    Material rough = glass;
    rough.name = "rough-glass";
    rough.roughness = 0.4f;
    Material dispersive = glass;
    dispersive.name = "dispersive-glass";
    dispersive.dispersion = 1.f;
    dispersive.absorption = {0.5f, 0.2f, 0.1f};
    testing::add_sphere(&d, {-1.4f, 0.f, 0.7f}, 0.7f, add_material(&d, glass), 16, 32);
    testing::add_sphere(&d, {0.f, 0.3f, 0.7f}, 0.7f, add_material(&d, rough), 16, 32);
    testing::add_sphere(&d, {1.4f, 0.f, 0.7f}, 0.7f, add_material(&d, dispersive), 16, 32);
    const uint32_t sheet = add_material(&d, glass);
    testing::add_quad(&d, {-3.f, 1.2f, 0.f}, {3.f, 1.2f, 0.f}, {3.f, 1.2f, 2.5f},
                      {-3.f, 1.2f, 2.5f}, sheet);
    const uint32_t panel = add_material(&d, emitter("panel", {1.f, 2.f, 3.f}));
    testing::add_quad(&d, {-2.f, 2.5f, 0.5f}, {2.f, 2.5f, 0.5f}, {2.f, 2.5f, 2.f},
                      {-2.f, 2.5f, 2.f}, panel);
    add_lights(&d);
    out.push_back({"glass", std::move(d), sky(),
                   channels::bit(Id::TransmissionDirect) |
                       channels::bit(Id::TransmissionIndirect) |
                       channels::bit(Id::GlossyDirect) | channels::bit(Id::GlossyIndirect)});
  }
  {  // A translucent sheet (diffuse transmission) with a point light under it, where only its
     // BTDF reaches it (through_eval_cos), and an area light above.
    SceneDescription d = floor_scene("diffuse-transmission", grey);
    Material sheet = lambert("sheet", {0.7f, 0.7f, 0.7f});
    sheet.diffuse_transmission = 0.7f;
    sheet.diffuse_transmission_color = {0.8f, 0.9f, 0.5f};
    sheet.specular = 0.5f;
    sheet.roughness = 0.5f;
    sheet.double_sided = true;
    testing::add_quad(&d, {-2, -2, 1}, {2, -2, 1}, {2, 2, 1}, {-2, 2, 1}, add_material(&d, sheet));
    add_lights(&d);
    PunctualLight below;
    below.position = {0.f, 0.f, 0.5f};
    below.intensity = {3.f, 3.f, 3.f};
    d.punctual_lights.push_back(below);
    out.push_back({"diffuse-transmission", std::move(d), sky(),
                   channels::bit(Id::DiffuseDirect) | channels::bit(Id::DiffuseIndirect) |
                       channels::bit(Id::GlossyDirect)});
  }
  {  // The environment alone: seen directly above the floor's far edge, and lighting it.
    SceneDescription d = floor_scene("environment", grey, false);
    out.push_back({"environment", std::move(d), sky(),
                   channels::bit(Id::Background) | channels::bit(Id::DiffuseDirect)});
  }
  {  // An emitter seen directly (facing the camera), lighting the floor.
    SceneDescription d = floor_scene("emissive", grey);
    const uint32_t light = add_material(&d, emitter("panel", {3.f, 2.f, 1.f}));
    testing::add_quad(&d, {-1.f, 1.f, 0.2f}, {1.f, 1.f, 0.2f}, {1.f, 1.f, 1.7f},
                      {-1.f, 1.f, 1.7f}, light);
    out.push_back({"emissive", std::move(d), nullptr,
                   channels::bit(Id::Emission) | channels::bit(Id::DiffuseDirect) |
                       channels::bit(Id::DiffuseIndirect)});
  }
  {  // Unlit quads (one adding its emission, as points and lines do) beside a lit floor.
    SceneDescription d = floor_scene("unlit", grey);
    Material unlit = lambert("unlit", {0.2f, 0.7f, 0.4f});
    unlit.unlit = true;
    Material adds = lambert("unlit-emission", {0.3f, 0.3f, 0.1f});
    adds.unlit = true;
    adds.unlit_adds_emission = true;
    adds.emission = {0.5f, 0.2f, 0.9f};
    testing::add_quad(&d, {-2.f, 1.f, 0.1f}, {0.f, 1.f, 0.1f}, {0.f, 1.f, 1.5f},
                      {-2.f, 1.f, 1.5f}, add_material(&d, unlit));
    testing::add_quad(&d, {0.2f, 1.f, 0.1f}, {2.f, 1.f, 0.1f}, {2.f, 1.f, 1.5f},
                      {0.2f, 1.f, 1.5f}, add_material(&d, adds));
    add_lights(&d);
    out.push_back({"unlit", std::move(d), nullptr,
                   channels::bit(Id::Emission) | channels::bit(Id::DiffuseDirect)});
  }
  {  // Alpha: a BLEND quad of alpha 0.5 and a MASK one over the floor.
    SceneDescription d = floor_scene("alpha", grey);
    Material blend = lambert("blend", {0.9f, 0.2f, 0.2f});
    blend.alpha_mode = AlphaMode::Blend;
    blend.alpha = 0.5f;
    blend.specular = 0.5f;
    blend.roughness = 0.3f;
    Material mask = blend;
    mask.name = "mask";
    mask.alpha_mode = AlphaMode::Mask;
    mask.alpha = 0.8f;
    testing::add_quad(&d, {-2, -2, 0.6f}, {0, -2, 0.6f}, {0, 2, 0.6f}, {-2, 2, 0.6f},
                      add_material(&d, blend));
    testing::add_quad(&d, {0.5f, -2, 0.6f}, {2, -2, 0.6f}, {2, 2, 0.6f}, {0.5f, 2, 0.6f},
                      add_material(&d, mask));
    add_lights(&d);
    out.push_back({"alpha", std::move(d), sky(),
                   channels::bit(Id::DiffuseDirect) | channels::bit(Id::GlossyDirect)});
  }
  return out;
}

RenderSettings settings_for(IntegratorType integrator, uint32_t max_depth,
                            std::shared_ptr<const Environment> env) {
  RenderSettings settings;
  settings.width = kWidth;
  settings.height = kHeight;
  settings.seed = 13;
  settings.integrator = integrator;
  settings.max_depth = max_depth;
  settings.environment = std::move(env);
  return settings;
}

TileBuffer render(const Scene& scene, const RenderSettings& settings, uint64_t start,
                  uint32_t count, channels::Set rows = kWithLobes) {
  TileBuffer tile;
  EXPECT_TRUE(render_rect(scene, settings, {0, 0, settings.width, settings.height}, start, count,
                          &tile, nullptr, rows));
  return tile;
}

double lobe(const TileBuffer& t, Id id, size_t i, int c) {
  return double(t.sum(id)[3 * i + size_t(c)]);
}

// Every sample of every scene (one-sample batches: a batch's sums are its sample's values):
// the eight rows sum to the radiance (each >= 0 but where a dispersive path's wavelength
// weights, which may be negative in a channel, are in its throughput); the direct
// integrator's indirect rows are 0; the ao integrator's lobe rows are all 0 (the server
// refuses `lobes` with ao).
TEST(LobeRows, EverySampleOfEverySceneSumsToTheRadiance) {
  constexpr uint32_t kSamples = 16;
  for (LobeScene& s : lobe_scenes()) {
    const Scene scene(std::move(s.desc));
    struct Run {
      IntegratorType integrator;
      uint32_t max_depth;
    };
    for (const Run run : {Run{IntegratorType::Path, 8}, Run{IntegratorType::Direct, 8},
                          Run{IntegratorType::AmbientOcclusion, 8}}) {
      SCOPED_TRACE(s.name + " " + integrator_type_name(run.integrator));
      const RenderSettings settings = settings_for(run.integrator, run.max_depth, s.env);
      channels::Set nonzero = 0;
      double total = 0.0;
      for (uint32_t k = 0; k < kSamples; ++k) {
        const TileBuffer t = render(scene, settings, k, 1);
        ASSERT_EQ(t.nonfinite_samples, 0u);
        for (size_t i = 0; i < t.rect.pixel_count(); ++i)
          for (int c = 0; c < 3; ++c) {
            const double rgb = t.rgb_sum[3 * i + size_t(c)];
            total += rgb;
            double sum = 0.0, magnitude = std::abs(rgb);
            for (Id id : kLobeIds) {
              const double v = lobe(t, id, i, c);
              if (s.name != "glass") {
                ASSERT_GE(v, 0.0) << channels::spec(id).name << " pixel " << i;
              }
              if (v != 0.0) nonzero |= channels::bit(id);
              sum += v;
              magnitude += std::abs(v);
            }
            if (run.integrator == IntegratorType::AmbientOcclusion) continue;
            ASSERT_NEAR(sum, rgb, 1e-5 * magnitude + 1e-6)
                << "sample " << k << " pixel " << i << " channel " << c;
          }
      }
      EXPECT_GT(total, 0.0);
      if (run.integrator == IntegratorType::AmbientOcclusion) {
        EXPECT_EQ(nonzero, 0u);
        continue;
      }
      if (run.integrator == IntegratorType::Direct) {
        EXPECT_EQ(nonzero & kIndirect, 0u);
      }
      const channels::Set want =
          run.integrator == IntegratorType::Direct ? s.lit & ~kIndirect : s.lit;
      EXPECT_EQ(nonzero & want, want) << "rows the scene should light are 0";
    }
  }
}

// The lobe rows change nothing else: the radiance, its luminance M2, the other rows and the
// ray count are bit for bit those of a render without them (same paths, same random
// numbers); and the same request twice gives the same bytes.
TEST(LobeRows, TurningThemOnChangesNothingElseAndIsDeterministic) {
  for (LobeScene& s : lobe_scenes()) {
    SCOPED_TRACE(s.name);
    const Scene scene(std::move(s.desc));
    for (IntegratorType integrator : {IntegratorType::Path, IntegratorType::Direct}) {
      const RenderSettings settings = settings_for(integrator, 8, s.env);
      // 40 samples from 3: full packets and a partial one.
      const channels::Set others = channels::kAll & ~channels::kLobes;
      const TileBuffer off = render(scene, settings, 3, 40, others);
      const TileBuffer on = render(scene, settings, 3, 40, channels::kAll);
      const TileBuffer again = render(scene, settings, 3, 40, channels::kAll);
      EXPECT_EQ(on.rgb_sum, off.rgb_sum);
      EXPECT_EQ(on.luminance_m2, off.luminance_m2);
      EXPECT_EQ(on.rays, off.rays);
      EXPECT_EQ(on.depth_sum, off.depth_sum);
      for (const channels::Spec& row : channels::kSpecs) {
        if (row.id == Id::Rgb || row.id == Id::Luminance) continue;
        if (row.ranked) {
          EXPECT_EQ(on.ranked(row.id), off.ranked(row.id)) << row.name;
          continue;
        }
        if (channels::kLobes & channels::bit(row.id)) {
          EXPECT_TRUE(off.sum(row.id).empty()) << row.name;
          ASSERT_EQ(on.sum(row.id).size(), 3 * on.rect.pixel_count()) << row.name;
          const std::vector<float>& a = on.sum(row.id);
          const std::vector<float>& b = again.sum(row.id);
          ASSERT_EQ(a.size(), b.size());
          EXPECT_EQ(std::memcmp(a.data(), b.data(), a.size() * sizeof(float)), 0) << row.name;
          continue;
        }
        EXPECT_EQ(on.sum(row.id), off.sum(row.id)) << row.name;
      }
      EXPECT_EQ(on.rgb_sum, again.rgb_sum);
      // The radiance alone, too.
      const TileBuffer rgb_only = render(scene, settings, 3, 40, channels::bit(Id::Rgb));
      EXPECT_EQ(rgb_only.rgb_sum, on.rgb_sum);
    }
  }
}

// A sample whose radiance is not finite is recorded as 0 in the radiance and in every lobe
// row: here an unlit quad of infinite colour beside a lit floor.
TEST(LobeRows, NonFiniteSamplesAreZeroInEveryRow) {
  SceneDescription d = floor_scene("inf", lambert("grey", {0.6f, 0.6f, 0.6f}), false);
  Material bad = lambert("inf", {std::numeric_limits<float>::infinity(), 1.f, 1.f});
  bad.unlit = true;
  testing::add_quad(&d, {-1.f, 1.f, 0.1f}, {1.f, 1.f, 0.1f}, {1.f, 1.f, 1.5f}, {-1.f, 1.f, 1.5f},
                    add_material(&d, bad));
  add_lights(&d);
  const Scene scene(std::move(d));
  const RenderSettings settings = settings_for(IntegratorType::Path, 4, nullptr);
  const TileBuffer t = render(scene, settings, 0, 8);
  EXPECT_GT(t.nonfinite_samples, 0u);
  for (size_t i = 0; i < t.rect.pixel_count(); ++i)
    for (int c = 0; c < 3; ++c) {
      double sum = 0.0;
      for (Id id : kLobeIds) {
        EXPECT_TRUE(std::isfinite(lobe(t, id, i, c)));
        sum += lobe(t, id, i, c);
      }
      const double rgb = t.rgb_sum[3 * i + size_t(c)];
      EXPECT_NEAR(sum, rgb, 1e-5 * std::abs(rgb) + 1e-5) << "pixel " << i;
    }
}

// ---- Expected values from closed forms.

// A camera above a large plane (z = 0) looking at the horizon: the lower rows see the plane,
// the upper ones the sky (beyond the plane's far edge).
SceneDescription plane_to_horizon(const Material& m) {
  SceneDescription desc;
  desc.source = "plane";
  desc.materials.push_back(m);
  testing::add_quad(&desc, {-40, -10, 0}, {40, -10, 0}, {40, 30, 0}, {-40, 30, 0}, 0);
  desc.camera = testing::look_at({0.f, -5.f, 1.f}, {0.f, 0.f, 0.6f}, 0.8f);
  return desc;
}

// Mean and standard error of the pixels' means (each pixel an independent estimate of the
// same value).
struct Estimate {
  double mean = 0.0, standard_error = 0.0;
  size_t n = 0;
};
Estimate over_pixels(const std::vector<double>& means) {
  Estimate e;
  e.n = means.size();
  double sum = 0.0, sum2 = 0.0;
  for (double v : means) {
    sum += v;
    sum2 += v * v;
  }
  e.mean = sum / double(e.n);
  e.standard_error = std::sqrt(std::max(0.0, sum2 / double(e.n) - e.mean * e.mean) /
                               double(e.n - 1));
  return e;
}

// A white-ish Lambert plane (no specular layer) under a uniform environment of radiance E,
// one bounce: a point of the plane sees the environment over its whole upper hemisphere, so
// its radiance is rho E, all of it diffuse_direct; the glossy, transmission, indirect,
// emission and background rows are exactly 0 there; where the camera sees the sky, the
// background row is E exactly and every other lobe row 0.
TEST(LobeRows, LambertPlaneUnderAUniformSkyIsDiffuseDirectAlbedoTimesE) {
  const float rho = 0.6f, E = 0.75f;
  const Scene scene(plane_to_horizon(lambert("white", {rho, rho, rho})));
  const RenderSettings settings =
      settings_for(IntegratorType::Path, 1, Environment::constant({E, E, E}));
  const uint32_t spp = 256;
  const TileBuffer t = render(scene, settings, 0, spp);
  std::vector<double> plane;
  size_t sky_pixels = 0;
  for (size_t i = 0; i < t.rect.pixel_count(); ++i) {
    const float coverage = t.sum(Id::Coverage)[i];
    for (Id id : {Id::GlossyDirect, Id::GlossyIndirect, Id::TransmissionDirect,
                  Id::TransmissionIndirect, Id::DiffuseIndirect, Id::Emission})
      for (int c = 0; c < 3; ++c) EXPECT_EQ(lobe(t, id, i, c), 0.0) << channels::spec(id).name;
    if (coverage == 0.f) {
      ++sky_pixels;
      for (int c = 0; c < 3; ++c) {
        EXPECT_EQ(lobe(t, Id::Background, i, c), double(E) * spp) << "pixel " << i;
        EXPECT_EQ(lobe(t, Id::DiffuseDirect, i, c), 0.0) << "pixel " << i;
      }
    } else if (coverage == float(spp)) {
      for (int c = 0; c < 3; ++c) EXPECT_EQ(lobe(t, Id::Background, i, c), 0.0);
      plane.push_back(lobe(t, Id::DiffuseDirect, i, 0) / spp);
    }
  }
  EXPECT_GT(sky_pixels, 10u);
  ASSERT_GT(plane.size(), 50u);
  const Estimate e = over_pixels(plane);
  EXPECT_LT(e.standard_error, 0.01 * rho * E) << "test would have no power";
  EXPECT_NEAR(e.mean, double(rho) * E, 4.0 * e.standard_error + 1e-5);
}

// A white rough metal plane (metallic 1, roughness 0.5) under the same sky, seen from 45
// degrees above: the diffuse and transmission rows are exactly 0, and what it reflects, all
// glossy_direct, is E times the metal's directional albedo, 1 with the multiple-scattering
// compensation (to its table's accuracy, as the white furnace test allows).
TEST(LobeRows, WhiteMetalPlaneIsGlossyOnly) {
  const float E = 0.75f;
  Material metal = lambert("metal", {1.f, 1.f, 1.f});
  metal.metallic = 1.f;
  metal.roughness = 0.5f;
  SceneDescription desc = plane_to_horizon(metal);
  desc.camera = testing::look_at({0.f, -3.f, 3.f}, {0.f, 0.f, 0.f}, 0.6f);
  const Scene scene(std::move(desc));
  const RenderSettings settings =
      settings_for(IntegratorType::Path, 1, Environment::constant({E, E, E}));
  const uint32_t spp = 256;
  const TileBuffer t = render(scene, settings, 0, spp);
  std::vector<double> plane;
  for (size_t i = 0; i < t.rect.pixel_count(); ++i) {
    for (Id id : {Id::DiffuseDirect, Id::DiffuseIndirect, Id::TransmissionDirect,
                  Id::TransmissionIndirect, Id::GlossyIndirect, Id::Emission})
      for (int c = 0; c < 3; ++c) EXPECT_EQ(lobe(t, id, i, c), 0.0) << channels::spec(id).name;
    ASSERT_EQ(t.sum(Id::Coverage)[i], float(spp));
    plane.push_back(lobe(t, Id::GlossyDirect, i, 0) / spp);
  }
  const Estimate e = over_pixels(plane);
  EXPECT_NEAR(e.mean, double(E), 4.0 * e.standard_error + 5e-3 * E);
}

// Fresnel's equations for unpolarized light from air into a dielectric of index n.
double fresnel(double cos_i, double n) {
  const double sin_t2 = (1.0 - cos_i * cos_i) / (n * n);
  const double cos_t = std::sqrt(1.0 - sin_t2);
  const double rs = (cos_i - n * cos_t) / (cos_i + n * cos_t);
  const double rp = (n * cos_i - cos_t) / (n * cos_i + cos_t);
  return 0.5 * (rs * rs + rp * rp);
}

// A sheet of smooth glass (transmission 1, roughness 0) under a uniform sky, seen at 50
// degrees from its normal through a tiny field of view: a path reflects (glossy) with
// probability F and finds the sky, E; or refracts (transmission) and finds the sky below,
// radiance scaled by 1 / eta^2 (the sheet has no back face to undo it). So glossy_direct is
// F E, transmission_direct (1 - F) E / eta^2, and the diffuse, indirect, emission and
// background rows are exactly 0.
TEST(LobeRows, SmoothGlassSplitsIntoGlossyAndTransmission) {
  const float E = 0.75f, ior = 1.5f;
  const double theta = 50.0 * M_PI / 180.0;
  Material glass = lambert("glass", {1.f, 1.f, 1.f});
  glass.transmission = 1.f;
  glass.roughness = 0.f;
  glass.ior = ior;
  SceneDescription desc;
  desc.source = "glass-sheet";
  desc.materials.push_back(glass);
  testing::add_quad(&desc, {-4, -4, 0}, {4, -4, 0}, {4, 4, 0}, {-4, 4, 0}, 0);
  desc.camera = testing::look_at(
      {0.f, float(-3.0 * std::sin(theta)), float(3.0 * std::cos(theta))}, {0, 0, 0}, 1e-3f);
  const Scene scene(std::move(desc));
  RenderSettings settings = settings_for(IntegratorType::Path, 8, Environment::constant({E, E, E}));
  settings.width = settings.height = 8;
  const uint32_t spp = 256;
  const TileBuffer t = render(scene, settings, 0, spp);
  std::vector<double> glossy, transmission;
  for (size_t i = 0; i < t.rect.pixel_count(); ++i) {
    for (Id id : {Id::DiffuseDirect, Id::DiffuseIndirect, Id::GlossyIndirect,
                  Id::TransmissionIndirect, Id::Emission, Id::Background})
      for (int c = 0; c < 3; ++c) EXPECT_EQ(lobe(t, id, i, c), 0.0) << channels::spec(id).name;
    glossy.push_back(lobe(t, Id::GlossyDirect, i, 1) / spp);
    transmission.push_back(lobe(t, Id::TransmissionDirect, i, 1) / spp);
  }
  const double F = fresnel(std::cos(theta), ior);
  const Estimate g = over_pixels(glossy), tr = over_pixels(transmission);
  EXPECT_NEAR(g.mean, F * E, 4.0 * g.standard_error + 1e-4);
  EXPECT_NEAR(tr.mean, (1.0 - F) * E / (ior * ior), 4.0 * tr.standard_error + 1e-4);
}

// An emitter filling the view, one bounce, no environment: its emission row is its radiance
// (every sample's, exactly), and nothing else is lit (its light cannot reach its own plane).
// An unlit quad likewise shows its base colour in the emission row.
TEST(LobeRows, EmitterAndUnlitSurfaceSeenDirectlyAreEmissionOnly) {
  const Vec3 Le(3.f, 2.f, 0.5f), base(0.25f, 0.5f, 0.75f);
  Material lit = lambert("emitter", {0.8f, 0.8f, 0.8f});
  lit.emission = Le;
  Material unlit = lambert("unlit", base);
  unlit.unlit = true;
  for (const Material& m : {lit, unlit}) {
    SCOPED_TRACE(m.name);
    SceneDescription desc;
    desc.source = m.name;
    desc.materials.push_back(m);
    testing::add_quad(&desc, {-10, -10, 0}, {10, -10, 0}, {10, 10, 0}, {-10, 10, 0}, 0);
    desc.camera = testing::look_at({0.f, -1.f, 2.f}, {0, 0, 0}, 0.8f);
    const Scene scene(std::move(desc));
    const RenderSettings settings = settings_for(IntegratorType::Path, 1, nullptr);
    const uint32_t spp = 32;
    const TileBuffer t = render(scene, settings, 0, spp);
    const Vec3 want = m.unlit ? base : Le;
    for (size_t i = 0; i < t.rect.pixel_count(); ++i) {
      ASSERT_EQ(t.sum(Id::Coverage)[i], float(spp));
      for (int c = 0; c < 3; ++c) {
        EXPECT_EQ(lobe(t, Id::Emission, i, c), double(want[c]) * spp) << "pixel " << i;
        EXPECT_EQ(t.rgb_sum[3 * i + size_t(c)], double(want[c]) * spp) << "pixel " << i;
        for (Id id : kLobeIds) {
          if (id != Id::Emission) {
            EXPECT_EQ(lobe(t, id, i, c), 0.0) << channels::spec(id).name << " pixel " << i;
          }
        }
      }
    }
  }
}

// ---- The split is unbiased: a quadrature of the glTF spec's dielectric BRDF.

// The spec's BRDF (Appendix B, with KHR_materials_specular at specular 1, colour 1): the
// dielectric Fresnel F = f0 + (1 - f0) (1 - |V.H|)^5, f0 = ((ior - 1) / (ior + 1))^2; the
// diffuse part (1 - F) rho / pi and the specular part F D G2 / (4 |N.L| |N.V|), GGX D with
// alpha = roughness^2 and the height-correlated Smith G2. Integrated against a uniform sky of
// radiance 1 over the hemisphere by the midpoint rule in (theta, phi): the diffuse and glossy
// parts of what the surface reflects towards wo = (sin theta_o, 0, cos theta_o).
struct Reflected {
  double diffuse = 0.0, glossy = 0.0;
};
Reflected spec_quadrature(double theta_o, double rho, double roughness, double ior) {
  const double alpha = roughness * roughness, a2 = alpha * alpha;
  const double f0 = std::pow((ior - 1.0) / (ior + 1.0), 2.0);
  const double wo[3] = {std::sin(theta_o), 0.0, std::cos(theta_o)};
  auto lambda = [&](double cos_t) {
    const double tan2 = (1.0 - cos_t * cos_t) / (cos_t * cos_t);
    return 0.5 * (-1.0 + std::sqrt(1.0 + a2 * tan2));
  };
  const int nt = 1024, np = 2048;
  Reflected r;
  for (int i = 0; i < nt; ++i) {
    const double t = (i + 0.5) * (M_PI / 2) / nt;
    const double ct = std::cos(t), st = std::sin(t);
    for (int j = 0; j < np; ++j) {
      const double p = (j + 0.5) * 2.0 * M_PI / np;
      const double wi[3] = {st * std::cos(p), st * std::sin(p), ct};
      double h[3] = {wo[0] + wi[0], wo[1] + wi[1], wo[2] + wi[2]};
      const double hl = std::sqrt(h[0] * h[0] + h[1] * h[1] + h[2] * h[2]);
      for (double& x : h) x /= hl;
      const double vh = wo[0] * h[0] + wo[1] * h[1] + wo[2] * h[2];
      const double F = f0 + (1.0 - f0) * std::pow(1.0 - vh, 5.0);
      const double nh2 = h[2] * h[2];
      const double D = a2 / (M_PI * std::pow(nh2 * (a2 - 1.0) + 1.0, 2.0));
      const double G2 = 1.0 / (1.0 + lambda(wo[2]) + lambda(ct));
      const double d_omega = st * ((M_PI / 2) / nt) * (2.0 * M_PI / np);
      r.diffuse += (1.0 - F) * rho / M_PI * ct * d_omega;
      r.glossy += F * D * G2 / (4.0 * wo[2] * ct) * ct * d_omega;
    }
  }
  return r;
}

// A dielectric plane (metallic 0, roughness 0.5, specular 1, ior 1.5) under a uniform white
// sky, one bounce, seen at 55 degrees from its normal through a tiny field of view: the
// diffuse_direct and glossy_direct means are the quadrature's diffuse and glossy parts (each
// within 4 standard errors; their sum, the radiance, would hold however the split was made).
TEST(LobeRows, DielectricSplitMatchesAQuadratureOfTheSpecBrdf) {
  const double theta = 55.0 * M_PI / 180.0;
  const float rho = 0.5f;
  Material m = lambert("dielectric", {rho, rho, rho});
  m.metallic = 0.f;
  m.roughness = 0.5f;
  m.specular = 1.f;
  m.ior = 1.5f;
  SceneDescription desc;
  desc.source = "dielectric";
  desc.materials.push_back(m);
  testing::add_quad(&desc, {-4, -4, 0}, {4, -4, 0}, {4, 4, 0}, {-4, 4, 0}, 0);
  desc.camera = testing::look_at(
      {0.f, float(-3.0 * std::sin(theta)), float(3.0 * std::cos(theta))}, {0, 0, 0}, 1e-3f);
  const Scene scene(std::move(desc));
  RenderSettings settings =
      settings_for(IntegratorType::Path, 1, Environment::constant({1.f, 1.f, 1.f}));
  settings.width = settings.height = 8;
  const uint32_t spp = 1024;
  const TileBuffer t = render(scene, settings, 0, spp);
  std::vector<double> diffuse, glossy;
  for (size_t i = 0; i < t.rect.pixel_count(); ++i) {
    diffuse.push_back(lobe(t, Id::DiffuseDirect, i, 0) / spp);
    glossy.push_back(lobe(t, Id::GlossyDirect, i, 0) / spp);
    for (Id id : {Id::DiffuseIndirect, Id::GlossyIndirect, Id::TransmissionDirect,
                  Id::TransmissionIndirect, Id::Emission, Id::Background})
      EXPECT_EQ(lobe(t, id, i, 0), 0.0) << channels::spec(id).name;
  }
  const Reflected want = spec_quadrature(theta, rho, 0.5, 1.5);
  const Estimate d = over_pixels(diffuse), g = over_pixels(glossy);
  EXPECT_LT(d.standard_error, 0.01 * want.diffuse) << "test would have no power";
  EXPECT_LT(g.standard_error, 0.02 * want.glossy) << "test would have no power";
  EXPECT_NEAR(d.mean, want.diffuse, 4.0 * d.standard_error + 1e-4 * want.diffuse);
  EXPECT_NEAR(g.mean, want.glossy, 4.0 * g.standard_error + 1e-4 * want.glossy);
}

// ---- The per-category evaluation the split uses.

// bsdf_eval_lobes' categories sum to bsdf_eval_pdf's f (and through_eval_lobes' to
// through_eval_cos) for random materials and directions, layered, anisotropic, iridescent
// and translucent ones among them; a metal has no diffuse part and a material without a
// specular layer, coat or metal no glossy part.
TEST(LobeRows, CategoryEvaluationSumsToTheBsdf) {
  std::mt19937 rng(7);
  std::uniform_real_distribution<float> u(0.f, 1.f);
  auto direction = [&](bool upper) {
    const float z = u(rng) * 0.98f + 0.01f, phi = 2.f * kPi * u(rng);
    const float r = std::sqrt(1.f - z * z);
    return Vec3(r * std::cos(phi), r * std::sin(phi), upper ? z : -z);
  };
  int transmitted = 0;
  for (int n = 0; n < 4000; ++n) {
    BsdfParams p;
    p.base = Vec3(u(rng), u(rng), u(rng));
    const int kind = n % 8;
    p.metallic = kind == 1 ? 1.f : (kind == 2 ? u(rng) : 0.f);
    p.alpha = std::max(kMinAlpha, std::pow(u(rng), 2.f));
    p.specular = kind == 0 ? 0.f : u(rng);
    p.specular_color = Vec3(1.f, 1.f - 0.5f * u(rng), 1.f);
    p.ior = 1.2f + u(rng);
    if (kind == 3) p.alpha_t = p.alpha + (1.f - p.alpha) * u(rng);
    if (kind == 4) p.iridescence = u(rng);
    if (kind == 5) {
      p.diffuse_transmission = u(rng);
      p.diffuse_transmission_color = Vec3(u(rng), u(rng), u(rng));
    }
    if (kind == 6) {
      p.clearcoat = u(rng);
      p.clearcoat_alpha = std::max(kMinAlpha, u(rng) * u(rng));
      p.sheen = Vec3(u(rng), u(rng), u(rng));
      p.sheen_alpha = std::max(kMinSheenAlpha, u(rng) * u(rng));
    }
    if (kind == 7) {
      p.transmission = u(rng);
      p.alpha = std::max(0.01f, p.alpha);
    }
    const Vec3 wo = direction(true), wi = direction(true);
    const BsdfLobes l = bsdf_lobes(p, wo);
    float pdf = 0.f;
    const Vec3 f = bsdf_eval_pdf(p, l, wo, wi, &pdf);
    Vec3 parts[kLobeCategories];
    bsdf_eval_lobes(p, l, wo, wi, parts);
    for (int c = 0; c < 3; ++c) {
      const float sum = parts[0][c] + parts[1][c] + parts[2][c];
      ASSERT_NEAR(sum, f[c], 2e-4f * f[c] + 1e-6f) << "kind " << kind << " channel " << c;
      EXPECT_EQ(parts[kTransmissionLobes][c], 0.f);
      if (kind == 1) {
        EXPECT_EQ(parts[kDiffuseLobes][c], 0.f);
      }
      if (kind == 0) {
        EXPECT_EQ(parts[kGlossyLobes][c], 0.f);
      }
    }
    // The sampled-only lobes a punctual light reaches, on either side.
    for (const Vec3 w : {wi, direction(false)}) {
      const Vec3 through = through_eval_cos(p, wo, w);
      Vec3 split[kLobeCategories];
      through_eval_lobes(p, wo, w, split);
      for (int c = 0; c < 3; ++c)
        ASSERT_NEAR(split[0][c] + split[1][c] + split[2][c], through[c],
                    1e-5f * through[c] + 1e-7f);
      if (w.z < 0.f && split[kTransmissionLobes].x > 0.f) ++transmitted;
      if (w.z > 0.f) {
        EXPECT_EQ(split[kTransmissionLobes].x, 0.f);
      }
    }
  }
  EXPECT_GT(transmitted, 100);  // the rough glass's transmission was reached
}

}  // namespace
}  // namespace rf
