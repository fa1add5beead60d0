#include "render/integrators.h"

#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <memory>
#include <string>
#include <vector>

#include "scene/environment.h"
#include "math/estimators.h"
#include "render/packet_tracer.h"
#include "render/reference.h"
#include "sampling/samplers.h"
#include "testing/references.h"
#include "testing/test_scenes.h"

namespace rf {
namespace {

using testing::form_factor_corner;

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
  for (SamplerType sampler : {SamplerType::Sobol, SamplerType::Independent,
                              SamplerType::Stratified, SamplerType::Halton}) {
    for (uint32_t depth : {1u, 8u}) {
      for (IntegratorType integrator : {IntegratorType::Path, IntegratorType::Direct}) {
        RenderSettings settings;
        settings.width = settings.height = 1;
        settings.sampler = sampler;
        settings.integrator = integrator;
        settings.max_depth = depth;
        settings.seed = 11;
        const Estimate e = render_pixel(scene, settings, 4096);
        EXPECT_LT(e.standard_error, 0.03 * expected) << "test would have no power";
        EXPECT_NEAR(e.mean, expected, 4.0 * e.standard_error + 1e-4 * expected)
            << sampler_type_name(sampler) << " depth " << depth << " "
            << integrator_type_name(integrator);
      }
    }
  }
}

// Lights at very different distances and orientations around one floor point (the origin):
// the per-point light selection weights them very unequally, and lights that cannot reach the
// point (behind the floor, facing away) get none; the mean is still the closed form.
TEST(PathIntegrator, ManyLightsAtDifferentDistancesMatchTheClosedForm) {
  const float rho = 0.5f;
  SceneDescription desc;
  desc.source = "many-lights";
  desc.materials.push_back(Material{"floor", {rho, rho, rho}, {0, 0, 0}});
  desc.materials.push_back(Material{"near", {0, 0, 0}, {2, 2, 2}});
  desc.materials.push_back(Material{"far", {0, 0, 0}, {20, 20, 20}});
  desc.materials.push_back(Material{"away", {0, 0, 0}, {50, 50, 50}});
  testing::add_quad(&desc, {-20, -20, 0}, {20, -20, 0}, {20, 20, 0}, {-20, 20, 0}, 0);
  // Facing -z (clockwise from above): 0.5 x 0.5 at height 0.5 with the origin under its
  // corner; 2 x 1 at height 3 the same, in the other quadrant.
  testing::add_quad(&desc, {0, 0, 0.5f}, {0, 0.5f, 0.5f}, {0.5f, 0.5f, 0.5f}, {0.5f, 0, 0.5f}, 1);
  testing::add_quad(&desc, {-2, -1, 3}, {-2, 0, 3}, {0, 0, 3}, {0, -1, 3}, 2);
  // Facing +z, above the floor: it lights nothing here.
  testing::add_quad(&desc, {3, 3, 2}, {4, 3, 2}, {4, 4, 2}, {3, 4, 2}, 3);
  struct Point {
    Vec3 p;
    float I;
  };
  // (None on a segment to the origin crosses the near quad.)
  const Point points[] = {{{1, 1.5f, 1}, 2.f}, {{-4, 3, 6}, 60.f}, {{0.2f, 0.1f, -1}, 100.f},
                          {{8, -5, 0.5f}, 30.f}};
  for (const Point& pt : points) {
    PunctualLight l;
    l.position = pt.p;
    l.intensity = Vec3(pt.I, pt.I, pt.I);
    desc.punctual_lights.push_back(l);
  }
  desc.camera = testing::look_at({0.f, -2.f, 0.4f}, {0, 0, 0}, 1e-3f);
  Scene scene(std::move(desc));
  double E = 2.0 * M_PI * form_factor_corner(0.5, 0.5, 0.5) +
             20.0 * M_PI * form_factor_corner(2.0, 1.0, 3.0);
  for (const Point& pt : points) {
    const double d2 = double(dot(pt.p, pt.p));
    if (pt.p.z > 0.f) E += pt.I * double(pt.p.z) / (d2 * std::sqrt(d2));
  }
  const double expected = rho / M_PI * E;
  for (SamplerType sampler : {SamplerType::Sobol, SamplerType::Independent}) {
    for (IntegratorType integrator : {IntegratorType::Path, IntegratorType::Direct}) {
      RenderSettings settings;
      settings.width = settings.height = 1;
      settings.sampler = sampler;
      settings.integrator = integrator;
      settings.seed = 5;
      const Estimate e = render_pixel(scene, settings, 16384);
      EXPECT_LT(e.standard_error, 0.02 * expected) << "test would have no power";
      EXPECT_NEAR(e.mean, expected, 4.0 * e.standard_error + 1e-4 * expected)
          << sampler_type_name(sampler) << " " << integrator_type_name(integrator);
    }
  }
}

// A quad light is two triangles, and a point light beside it is another entry of the light
// selection: with the sobol sampler the choice among them is made from the light position's
// own (0, m, 2)-net pair (rescaled at each choice), so each triangle's samples are still a
// well-spread set. Choosing with an unrelated dimension instead gave each triangle a random
// subset of the pair's points: at 64 spp the variance was 4 times below the independent
// sampler's (measured with that choice), and sharing the pair makes it about 30 times below.
// The mean stays the closed form.
TEST(PathIntegrator, LightChoiceKeepsTheLightSamplesStratified) {
  const float rho = 0.5f, L = 4.f, I = 3.f;
  SceneDescription desc;
  desc.source = "stratified-lights";
  desc.materials.push_back(Material{"floor", {rho, rho, rho}, {0, 0, 0}});
  desc.materials.push_back(Material{"light", {0, 0, 0}, {L, L, L}});
  testing::add_quad(&desc, {-20, -20, 0}, {20, -20, 0}, {20, 20, 0}, {-20, 20, 0}, 0);
  // Facing -z, 2 x 1 at height 1.5 with the origin under its corner.
  testing::add_quad(&desc, {0, 0, 1.5f}, {0, 1, 1.5f}, {2, 1, 1.5f}, {2, 0, 1.5f}, 1);
  PunctualLight point;
  point.position = Vec3(-1.f, -0.5f, 2.f);
  point.intensity = Vec3(I, I, I);
  desc.punctual_lights.push_back(point);
  desc.camera = testing::look_at({0.f, -2.f, 0.4f}, {0, 0, 0}, 1e-3f);
  Scene scene(std::move(desc));
  const Vec3 p = point.position;
  const double d2 = double(dot(p, p));
  const double expected = rho / M_PI *
                          (L * M_PI * form_factor_corner(2.0, 1.0, 1.5) +
                           I * double(p.z) / (d2 * std::sqrt(d2)));
  // The variance of one 64-sample pixel estimate, over independent seeds.
  const auto variance_of_64 = [&](SamplerType sampler, double* mean) {
    const int seeds = 400;
    double sum = 0.0, sum2 = 0.0;
    for (int seed = 1; seed <= seeds; ++seed) {
      RenderSettings settings;
      settings.width = settings.height = 1;
      settings.sampler = sampler;
      settings.integrator = IntegratorType::Direct;
      settings.seed = uint64_t(seed);
      const double m = render_pixel(scene, settings, 64).mean;
      sum += m;
      sum2 += m * m;
    }
    *mean = sum / seeds;
    return (sum2 - sum * sum / seeds) / (seeds - 1);
  };
  double mean_sobol = 0.0, mean_independent = 0.0;
  const double v_sobol = variance_of_64(SamplerType::Sobol, &mean_sobol);
  const double v_independent = variance_of_64(SamplerType::Independent, &mean_independent);
  EXPECT_NEAR(mean_independent, expected, 4.0 * std::sqrt(v_independent / 400));
  EXPECT_NEAR(mean_sobol, expected, 4.0 * std::sqrt(v_sobol / 400) + 1e-4 * expected);
  EXPECT_GT(v_independent, 15.0 * v_sobol)
      << "independent " << v_independent << ", sobol " << v_sobol;
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
    // The shading normal faces down.
    EXPECT_NEAR(tile.sum(channels::Id::Normal)[3 * i + 2], -16.f, 1e-3f);
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
  for (SamplerType sampler : {SamplerType::Sobol, SamplerType::Independent,
                              SamplerType::Stratified, SamplerType::Halton}) {
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

// Coverage (the alpha): a quad whose right edge lies a quarter of the way into column 8 of a
// 16 x 16 image. With the box pixel filter, a pixel's alpha is the share of its area the quad
// covers: 1 left of the edge's column, 1/4 in it, 0 right of it. The edge's x at the quad's
// depth follows from the pinhole: column c's left side is at (2 c / 16 - 1) tan(yfov / 2) d.
TEST(Coverage, IsTheShareOfThePixelTheGeometryCovers) {
  SceneDescription desc;
  desc.source = "edge";
  desc.materials.push_back(Material{});
  const float d = 3.f, yfov = 1.2f;
  const float edge = (2.f * 8.25f / 16.f - 1.f) * std::tan(yfov / 2) * d;
  testing::add_quad(&desc, {-10, -10, 0}, {edge, -10, 0}, {edge, 10, 0}, {-10, 10, 0}, 0);
  desc.camera = testing::look_at({0.f, 0.f, d}, {0.f, 0.f, 0.f}, yfov);
  Scene scene(std::move(desc));
  RenderSettings settings;
  settings.integrator = IntegratorType::AmbientOcclusion;
  settings.width = settings.height = 16;
  const uint32_t spp = 256;
  TileBuffer tile;
  ASSERT_TRUE(render_rect(scene, settings, {0, 0, 16, 16}, 0, spp, &tile));
  for (uint32_t y = 0; y < 16; ++y) {
    for (uint32_t x = 0; x < 16; ++x) {
      const float alpha = tile.sum(channels::Id::Coverage)[y * 16 + x] / float(spp);
      const float want = x < 8 ? 1.f : x == 8 ? 0.25f : 0.f;
      // Owen-scrambled Sobol' points stratify the pixel: far under 1/spp of error per axis.
      EXPECT_NEAR(alpha, want, 2.f / float(spp)) << x << ", " << y;
      const float hits = tile.sum(channels::Id::Coverage)[y * 16 + x];
      EXPECT_EQ(hits, std::floor(hits));
    }
  }
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
  EXPECT_EQ(tile.sum(channels::Id::Albedo)[3 * corner], 0.f);
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
  s.aperture_radius = 0.1f;
  EXPECT_NE(validate_render_request(s, {0, 0, 8, 8}, 0, 16), "");  // focus distance missing
  s.focus_distance = 2.f;
  EXPECT_EQ(validate_render_request(s, {0, 0, 8, 8}, 0, 16), "");
  s.aperture_radius = -1.f;
  EXPECT_NE(validate_render_request(s, {0, 0, 8, 8}, 0, 16), "");
  IntegratorType t;
  EXPECT_FALSE(parse_integrator_type("bdpt", &t));
  for (IntegratorType u :
       {IntegratorType::Path, IntegratorType::Direct, IntegratorType::AmbientOcclusion}) {
    ASSERT_TRUE(parse_integrator_type(integrator_type_name(u), &t));
    EXPECT_EQ(t, u);
  }
}

// Thin lens: an emitter in the plane of focus is sharp (every lens ray through the pixel
// reaches the same point on it), while focusing far behind it blurs it away; the depth AOV is
// the distance to the first hit.
TEST(Camera, ThinLensFocusesThePlaneOfFocus) {
  SceneDescription desc;
  desc.source = "lens";
  desc.materials.push_back(Material{"emitter", {0, 0, 0}, {2, 2, 2}});
  const float h = 0.01f;
  testing::add_quad(&desc, {-h, -h, 0}, {h, -h, 0}, {h, h, 0}, {-h, h, 0}, 0);  // faces +z
  desc.camera = testing::look_at({0.f, 0.f, 1.f}, {0.f, 0.f, 0.f}, 1e-3f);
  Scene scene(std::move(desc));
  RenderSettings settings;
  settings.width = settings.height = 1;
  settings.aperture_radius = 0.2f;
  settings.focus_distance = 1.f;
  TileBuffer tile;
  ASSERT_TRUE(render_rect(scene, settings, {0, 0, 1, 1}, 0, 64, &tile));
  EXPECT_NEAR(tile.rgb_sum[0] / 64.0, 2.0, 1e-6);
  EXPECT_GT(tile.depth_sum[0] / 64.0, 1.0);  // lens rays are longer than the axis
  EXPECT_LT(tile.depth_sum[0] / 64.0, 1.03);
  settings.focus_distance = 10.f;  // lens rays cross the emitter's plane 0.18 r off axis
  ASSERT_TRUE(render_rect(scene, settings, {0, 0, 1, 1}, 0, 64, &tile));
  EXPECT_LT(tile.rgb_sum[0] / 64.0, 0.1);
  settings.aperture_radius = 0.f;  // pinhole: sharp whatever the focus distance
  ASSERT_TRUE(render_rect(scene, settings, {0, 0, 1, 1}, 0, 16, &tile));
  EXPECT_NEAR(tile.rgb_sum[0] / 16.0, 2.0, 1e-6);
  EXPECT_NEAR(tile.depth_sum[0] / 16.0, 1.0, 1e-5);
}

}  // namespace
}  // namespace rf

namespace rf {
namespace {

// KHR_lights_punctual through the glTF loader: a Lambertian (specularFactor 0) quad lit by one
// light; a narrow camera at +z looks at (x, 0, 0). Delta lights make next-event estimation
// exact, so the pixel equals rho / pi * E with E the light's irradiance there.
double lit_quad_radiance(const std::string& light, const std::string& light_node, float x) {
  const std::string json = R"({"asset": {"version": "2.0"},
  "extensionsUsed": ["KHR_lights_punctual", "KHR_materials_specular"],
  "extensions": {"KHR_lights_punctual": {"lights": [)" + light + R"(]}},
  "scene": 0, "scenes": [{"nodes": [0, 1]}],
  "nodes": [{"mesh": 0}, )" + light_node + R"(],
  "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1}, "indices": 3,
                              "material": 0}]}],
  "materials": [{"pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.5, 0.5, 1],
                 "metallicFactor": 0},
                 "extensions": {"KHR_materials_specular": {"specularFactor": 0}}}],
  )" + testing::quad_gltf_buffers_json() + "}";
  std::vector<std::string> warnings;
  SceneDescription desc = load_gltf_from_string(json, "", "lights.gltf", &warnings);
  EXPECT_TRUE(warnings.empty()) << warnings.front();
  desc.camera = testing::look_at({x, 0.f, 3.f}, {x, 0.f, 0.f}, 1e-4f);
  Scene scene(std::move(desc));
  EXPECT_EQ(scene.lights().punctual().size(), 1u);
  RenderSettings settings;
  settings.width = settings.height = 1;
  TileBuffer tile;
  EXPECT_TRUE(render_rect(scene, settings, {0, 0, 1, 1}, 0, 8, &tile));
  return tile.rgb_sum[0] / 8.0;
}

TEST(PunctualLights, PointSpotAndDirectionalMatchClosedForms) {
  const double rho = 0.5;
  // Point light of intensity 8 at height 2: E = I / d^2.
  EXPECT_NEAR(lit_quad_radiance(R"({"type": "point", "intensity": 8})",
                                R"({"translation": [0, 0, 2], "extensions":
                                   {"KHR_lights_punctual": {"light": 0}}})",
                                0.f),
              rho / M_PI * 8.0 / 4.0, 1e-5);
  // Off axis: E = I cos(theta) / d^2.
  {
    const double x = 0.5, d2 = 4.0 + x * x, c = 2.0 / std::sqrt(d2);
    EXPECT_NEAR(lit_quad_radiance(R"({"type": "point", "intensity": 8, "color": [1, 1, 1]})",
                                  R"({"translation": [0, 0, 2], "extensions":
                                     {"KHR_lights_punctual": {"light": 0}}})",
                                  float(x)),
                rho / M_PI * 8.0 * c / d2, 1e-5);
  }
  // Spot pointing down (-Z): full inside the inner cone, glTF's quadratic ramp between the
  // cones, nothing outside.
  const std::string spot = R"({"type": "spot", "intensity": 8,
                               "spot": {"innerConeAngle": 0.2, "outerConeAngle": 0.3}})";
  const std::string spot_node =
      R"({"translation": [0, 0, 2], "extensions": {"KHR_lights_punctual": {"light": 0}}})";
  EXPECT_NEAR(lit_quad_radiance(spot, spot_node, 0.f), rho / M_PI * 2.0, 1e-5);
  {
    const double a = 0.25, x = 2.0 * std::tan(a), d2 = 4.0 + x * x;
    const double t = (std::cos(a) - std::cos(0.3)) / (std::cos(0.2) - std::cos(0.3));
    EXPECT_NEAR(lit_quad_radiance(spot, spot_node, float(x)),
                rho / M_PI * 8.0 * t * t * std::cos(a) / d2, 1e-4);
  }
  EXPECT_EQ(lit_quad_radiance(spot, spot_node, 0.8f), 0.0);
  // Directional light tilted by 0.5 rad about X: E = E0 cos(0.5).
  const double s = std::sin(0.25), c = std::cos(0.25);
  EXPECT_NEAR(lit_quad_radiance(R"({"type": "directional", "intensity": 3})",
                                R"({"rotation": [)" + std::to_string(s) + ", 0, 0, " +
                                    std::to_string(c) +
                                    R"(], "extensions": {"KHR_lights_punctual": {"light": 0}}})",
                                0.f),
              rho / M_PI * 3.0 * std::cos(0.5), 1e-5);
}

// The Cornell box with a half-metal back wall, a metal left wall, a dispersive glass right wall
// (each path that meets it carries a wavelength from there on) and three
// punctual lights (point, spot, directional) besides its emissive ceiling.
std::unique_ptr<Scene> varied_cornell_box(float glass_roughness = 0.f) {
  std::vector<std::string> warnings;
  SceneDescription desc =
      load_gltf(std::string(RENDERFARM_EXAMPLES_DIR) + "/cornell-box.gltf", &warnings);
  EXPECT_GE(desc.materials.size(), 3u);
  desc.materials[0].metallic = 0.5f;
  desc.materials[0].roughness = 0.6f;
  desc.materials[1].metallic = 1.f;
  desc.materials[1].roughness = 0.3f;
  desc.materials[2].transmission = 1.f;
  desc.materials[2].roughness = glass_roughness;
  // With rough glass, the metal brushed too (KHR_materials_anisotropy: its own frame).
  if (glass_roughness > 0.f) {
    desc.materials[1].anisotropy = 0.7f;
    desc.materials[1].anisotropy_rotation = 0.5f;
    desc.materials[0].iridescence = 0.8f;  // and a thin film on the half metal
    // which lets a share of its diffuse light through (KHR_materials_diffuse_transmission):
    // the sky and the lights outside the box reach in through the walls.
    desc.materials[0].diffuse_transmission = 0.6f;
    desc.materials[0].diffuse_transmission_color = Vec3(0.9f, 0.5f, 0.3f);
  }
  desc.materials[2].absorption = Vec3(0.9f, 2.f, 0.3f);  // KHR_materials_volume
  desc.materials[2].dispersion = 0.8f;                   // KHR_materials_dispersion
  for (Material& m : desc.materials)  // the light's back face, towards the ceiling, emits too
    if (m.is_emissive()) m.double_sided = true;
  PunctualLight point;
  point.position = Vec3(0.2f, 0.4f, 0.2f);
  point.intensity = Vec3(0.3f, 0.27f, 0.24f);
  PunctualLight spot;
  spot.type = PunctualType::Spot;
  spot.position = Vec3(0.3f, 0.5f, 0.1f);
  spot.direction = Vec3(0.f, -1.f, 0.f);
  spot.intensity = Vec3(0.5f, 0.9f, 1.f);
  spot.cos_inner = std::cos(0.2f);
  spot.cos_outer = std::cos(0.5f);
  PunctualLight sun;
  sun.type = PunctualType::Directional;
  sun.direction = normalize(Vec3(0.2f, -1.f, 0.5f));
  sun.intensity = Vec3(0.4f, 0.4f, 0.3f);
  desc.punctual_lights = {point, spot, sun};
  return std::make_unique<Scene>(std::move(desc));
}

// The varied box with surfaces that let rays through (glTF alphaMode): a BLEND pane, a MASK
// pane cut out along a diagonal by its vertex alpha (COLOR_0), a small BLEND emitter facing
// down, and a BLEND pane used by two instances that overlap in the view (their surfaces are
// passed independently: the hash includes the instance).
std::unique_ptr<Scene> transparent_cornell_box() {
  std::vector<std::string> warnings;
  SceneDescription desc =
      load_gltf(std::string(RENDERFARM_EXAMPLES_DIR) + "/cornell-box.gltf", &warnings);
  desc.materials[0].metallic = 0.5f;
  desc.materials[0].roughness = 0.6f;
  desc.materials[1].metallic = 1.f;
  desc.materials[1].roughness = 0.3f;
  const uint32_t pane = uint32_t(desc.materials.size());
  Material blend{"pane", {0.8f, 0.7f, 0.6f}, {0.f, 0.f, 0.f}};
  blend.alpha_mode = AlphaMode::Blend;
  blend.alpha = 0.4f;
  Material mask{"stencil", {0.7f, 0.7f, 0.7f}, {0.f, 0.f, 0.f}};
  mask.alpha_mode = AlphaMode::Mask;
  mask.alpha_cutoff = 0.5f;
  mask.specular = 0.5f;
  Material lamp{"veiled lamp", {0.f, 0.f, 0.f}, {2.f, 2.f, 1.5f}};
  lamp.alpha_mode = AlphaMode::Blend;
  lamp.alpha = 0.5f;
  Material glass_pane{"instanced pane", {0.3f, 0.6f, 0.9f}, {0.f, 0.f, 0.f}};
  glass_pane.alpha_mode = AlphaMode::Blend;
  glass_pane.alpha = 0.6f;
  glass_pane.roughness = 0.4f;
  desc.materials.insert(desc.materials.end(), {blend, mask, lamp, glass_pane});
  // The panes face the camera (at z = -0.8, looking down +z): counter-clockwise seen from -z.
  testing::add_quad(&desc, {0.3f, 0.05f, 0.25f}, {0.1f, 0.05f, 0.25f}, {0.1f, 0.35f, 0.25f},
                    {0.3f, 0.35f, 0.25f}, pane);
  const size_t stencil_first = desc.world.positions.size();
  testing::add_quad(&desc, {0.5f, 0.1f, 0.35f}, {0.25f, 0.1f, 0.35f}, {0.25f, 0.45f, 0.35f},
                    {0.5f, 0.45f, 0.35f}, pane + 1);
  // The lamp faces down (-y): counter-clockwise seen from below.
  testing::add_quad(&desc, {0.35f, 0.4f, 0.1f}, {0.45f, 0.4f, 0.1f}, {0.45f, 0.4f, 0.2f},
                    {0.35f, 0.4f, 0.2f}, pane + 2);
  // Vertex alpha: 1 at the stencil's corners p0 and p3, 0 at p1 (and p2 is 1/2): the
  // interpolated alpha crosses the cutoff inside the pane.
  desc.world.colors.assign(desc.world.positions.size(), Rgba{});
  const float stencil_alpha[6] = {1.f, 0.f, 0.5f, 1.f, 0.5f, 1.f};  // triangles p0 p1 p2, p0 p2 p3
  for (size_t k = 0; k < 6; ++k) desc.world.colors[stencil_first + k].a = stencil_alpha[k];
  Mesh mesh;
  mesh.name = "pane";
  {
    SceneDescription part;
    testing::add_quad(&part, {0.05f, -0.05f, 0.f}, {-0.05f, -0.05f, 0.f}, {-0.05f, 0.05f, 0.f},
                      {0.05f, 0.05f, 0.f}, pane + 3);
    mesh.geometry = part.world;
  }
  desc.meshes = {mesh};
  for (float z : {0.15f, 0.2f}) {
    Instance inst;
    inst.to_world.m[3][0] = 0.3;
    inst.to_world.m[3][1] = 0.25;
    inst.to_world.m[3][2] = z;
    desc.instances.push_back(inst);
  }
  // A point light whose shadow rays cross the panes.
  PunctualLight point;
  point.position = Vec3(0.2f, 0.45f, 0.05f);
  point.intensity = Vec3(0.2f, 0.2f, 0.18f);
  desc.punctual_lights = {point};
  auto scene = std::make_unique<Scene>(std::move(desc));
  EXPECT_TRUE(scene->has_transparency());
  return scene;
}

uint64_t double_bits(double x) {
  uint64_t u;
  std::memcpy(&u, &x, sizeof u);
  return u;
}

// render_rect (sixteen samples of a pixel traced together, their BSDF values, light-sample
// geometry and MIS weights computed four lanes at a time) gives exactly the sums of
// trace_sample_reference (one path at a time, scalar code), for every sampler and integrator,
// with an environment map and a thin lens: every radiance sum, luminance M2, AOV sum (the
// first-hit depth and position too) and ray count equal to the last bit.
void expect_packet_tracer_equals_the_scalar_reference(const std::unique_ptr<Scene>& scene) {
  // A sky brighter towards +y with a small hot spot, so that environment sampling matters.
  const uint32_t w = 32, h = 16;
  std::vector<float> sky(3 * w * h);
  for (uint32_t y = 0; y < h; ++y)
    for (uint32_t x = 0; x < w; ++x) {
      const bool spot = x >= 5 && x < 7 && y >= 2 && y < 4;
      sky[3 * (y * w + x) + 0] = spot ? 40.f : 0.2f + 0.8f * float(y < h / 3);
      sky[3 * (y * w + x) + 1] = spot ? 35.f : 0.5f;
      sky[3 * (y * w + x) + 2] = spot ? 30.f : 0.3f + float(x) / w;
    }
  const auto env = std::make_shared<Environment>(sky, w, h, 0.5f, 30.f);
  struct Case {
    SamplerType sampler;
    IntegratorType integrator;
    bool environment;
    float aperture;
    uint32_t max_depth;
  };
  const Case cases[] = {{SamplerType::Sobol, IntegratorType::Path, false, 0.f, 8},
                        {SamplerType::Sobol, IntegratorType::Path, true, 0.f, 12},
                        {SamplerType::Halton, IntegratorType::Direct, true, 0.f, 8},
                        {SamplerType::Independent, IntegratorType::Path, true, 0.02f, 8},
                        {SamplerType::Stratified, IntegratorType::Path, false, 0.f, 5}};
  uint64_t rays = 0;
  for (const Case& c : cases) {
    RenderSettings settings;
    settings.width = settings.height = 24;
    settings.seed = 7;
    settings.sampler = c.sampler;
    settings.integrator = c.integrator;
    settings.max_depth = c.max_depth;
    settings.aperture_radius = c.aperture;
    settings.focus_distance = 0.8f;
    if (c.environment) settings.environment = env;
    const PixelRect rect{5, 3, 14, 17};
    const uint64_t start = 16;
    const uint32_t count = 40;  // two full packets and a partial one
    TileBuffer tile;
    ASSERT_TRUE(render_rect(*scene, settings, rect, start, count, &tile));
    const Sampler sampler(settings.sampler, settings.seed);
    uint64_t ref_rays = 0;
    for (uint32_t ty = 0; ty < rect.height; ++ty)
      for (uint32_t tx = 0; tx < rect.width; ++tx) {
        const uint32_t x = rect.x0 + tx, y = rect.y0 + ty;
        const PixelSampler pixel(sampler, uint64_t(y) * settings.width + x);
        double sum[3] = {0.0, 0.0, 0.0};
        float albedo[3] = {0.f, 0.f, 0.f}, normal[3] = {0.f, 0.f, 0.f}, depth = 0.f;
        // The Depth and Position rows (their window aside: render_rect sums what it is asked
        // for): the planar depth, 1e10 on a miss, and the position, 0 on a miss.
        float planar = 0.f, position[3] = {0.f, 0.f, 0.f};
        RunningStats luminance;
        for (uint32_t k = 0; k < count; ++k) {
          const SampleResult r =
              trace_sample_reference(*scene, settings, pixel, x, y, uint32_t(start + k));
          ref_rays += r.rays;
          ASSERT_TRUE(is_finite(r.radiance));
          for (int ch = 0; ch < 3; ++ch) {
            sum[ch] += double(r.radiance[ch]);
            albedo[ch] += r.albedo[ch];
            normal[ch] += r.normal[ch];
            position[ch] += r.depth > 0.f ? r.position[ch] : 0.f;
          }
          depth += r.depth;
          planar += r.depth > 0.f ? r.z : 1e10f;
          luminance.add(0.2126 * double(r.radiance.x) + 0.7152 * double(r.radiance.y) +
                        0.0722 * double(r.radiance.z));
        }
        const size_t i = size_t(ty) * rect.width + tx;
        for (int ch = 0; ch < 3; ++ch) {
          ASSERT_EQ(double_bits(tile.rgb_sum[3 * i + ch]), double_bits(sum[ch]))
              << "pixel " << x << "," << y << " channel " << ch;
          ASSERT_EQ(tile.sum(channels::Id::Albedo)[3 * i + ch], albedo[ch]);
          ASSERT_EQ(tile.sum(channels::Id::Normal)[3 * i + ch], normal[ch]);
          ASSERT_EQ(tile.sum(channels::Id::Position)[3 * i + ch], position[ch]);
        }
        ASSERT_EQ(tile.sum(channels::Id::Depth)[i], planar);
        ASSERT_EQ(double_bits(tile.luminance_m2[i]), double_bits(luminance.m2));
        ASSERT_EQ(tile.depth_sum[i], depth);
      }
    EXPECT_EQ(tile.rays, ref_rays);
    EXPECT_EQ(tile.nonfinite_samples, 0u);
    rays += ref_rays;
  }
  EXPECT_GT(rays, 100000u);  // the comparison covered many bounces
}

// With glass, metals, punctual and area lights.
TEST(PathIntegrator, PacketTracerEqualsTheScalarReferenceBitForBit) {
  expect_packet_tracer_equals_the_scalar_reference(varied_cornell_box());
}

// With the glass rough: its lobe sampled through visible normals, and evaluated for the
// punctual lights on either side (two-sided light selection, shadow rays through the surface
// in the volume's medium); the metal anisotropic (its BSDF in a frame of its own); and the
// half metal with a thin film and a diffuse BTDF.
TEST(PathIntegrator, PacketTracerEqualsTheScalarReferenceWithRoughGlass) {
  expect_packet_tracer_equals_the_scalar_reference(varied_cornell_box(0.4f));
}

// With surfaces that let rays through (alphaMode MASK and BLEND, on camera, indirect and
// shadow rays, in the world and in instances).
TEST(PathIntegrator, PacketTracerEqualsTheScalarReferenceWithTransparentSurfaces) {
  expect_packet_tracer_equals_the_scalar_reference(transparent_cornell_box());
}

// Russian roulette keeps a path with the square root of its largest throughput channel (at
// most 0.95), and refractions do not change that chance: a path inside glass at ior 1.5
// carries radiance scaled by 1 / 1.5^2, which its way out undoes, so it goes on as often as
// the same path outside.
TEST(RussianRoulette, SurvivalIsTheSquareRootOfTheThroughputAcrossGlass) {
  EXPECT_FLOAT_EQ(roulette_survival(Vec3(0.25f, 0.1f, 0.04f), 1.f), 0.5f);
  EXPECT_FLOAT_EQ(roulette_survival(Vec3(0.01f, 0.16f, 0.f), 1.f), 0.4f);
  EXPECT_FLOAT_EQ(roulette_survival(Vec3(0.95f, 0.95f, 0.95f), 1.f), 0.95f);
  EXPECT_FLOAT_EQ(roulette_survival(Vec3(3.f, 1.f, 1.f), 1.f), 0.95f);
  BsdfParams glass;  // smooth, clear glass of ior 1.5
  glass.alpha = kMinAlpha;
  glass.specular = 1.f;
  glass.transmission = 1.f;
  glass.ior = 1.5f;
  const Vec3 beta(0.3f, 0.2f, 0.1f);
  const Vec3 wo = normalize(Vec3(0.3f, 0.f, 0.9f));
  const BsdfLobes lobes = bsdf_lobes(glass, wo);
  // Refracting into the glass (u_fresnel above its reflectance at this angle, about 0.04).
  BsdfSample in;
  ASSERT_TRUE(bsdf_sample(glass, lobes, wo, {0.5f, 0.5f}, 0.f, 0.99f, &in));
  ASSERT_TRUE(in.transmitted);
  const Vec3 inside = beta * in.weight;
  EXPECT_NEAR(max_component(inside), 0.3f / 2.25f, 1e-6f);
  EXPECT_NEAR(roulette_survival(inside, in.eta2), std::sqrt(0.3f), 1e-6f);
  // And out of it again: the throughput is beta's once more, and so is the chance.
  glass.front = false;
  const BsdfLobes back = bsdf_lobes(glass, wo);
  BsdfSample out;
  ASSERT_TRUE(bsdf_sample(glass, back, wo, {0.5f, 0.5f}, 0.f, 0.99f, &out));
  ASSERT_TRUE(out.transmitted);
  EXPECT_NEAR(max_component(inside * out.weight), 0.3f, 1e-6f);
  EXPECT_NEAR(roulette_survival(inside * out.weight, in.eta2 * out.eta2), std::sqrt(0.3f),
              1e-6f);
}

}  // namespace
}  // namespace rf
