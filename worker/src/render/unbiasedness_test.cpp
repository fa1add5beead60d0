// Unbiasedness and calibration of the rendered estimates: white furnaces (diffuse, glass and
// rough metal spheres in a uniform environment), the closed form of the infinite bounce
// series, closed-form irradiance under an emissive rectangle with the independent sampler's
// reported error checked for calibration, and stratified/halton/sobol beating independent
// against a high-spp reference.
#include <gtest/gtest.h>

#include <cmath>

#include "render/integrators.h"
#include "render/render.h"
#include "testing/references.h"
#include "testing/test_scenes.h"

namespace rf {
namespace {

using testing::PixelStats;

using testing::plain_material;

SceneDescription sphere_scene(const Material& m, Vec3 eye, float yfov) {
  SceneDescription desc;
  desc.source = "furnace";
  desc.materials.push_back(m);
  testing::add_sphere(&desc, {0, 0, 0}, 1.f, 0);
  desc.camera = testing::look_at(eye, {0, 0, 0}, yfov);
  return desc;
}

// Uniform environment of radiance 1: an albedo-1 diffuse sphere, a glass sphere (every path
// ends in the environment with throughput 1: reflection 1, refraction 1/eta^2 in and eta^2
// out), a rough white metal sphere (energy-compensated GGX) and white spheres that let all or
// half of their diffuse light through (KHR_materials_diffuse_transmission: what the BTDF
// transmits, the BRDF no longer reflects) render 1 everywhere within the reported error.
TEST(WhiteFurnace, DiffuseGlassAndRoughMetalSpheresRenderOne) {
  const auto env = Environment::constant({1.f, 1.f, 1.f});
  Material translucent = plain_material("translucent", 1.f, 0.f, 1.f, 0.f, 0.f);
  translucent.diffuse_transmission = 1.f;
  Material half_translucent = translucent;
  half_translucent.name = "half-translucent";
  half_translucent.diffuse_transmission = 0.5f;
  for (const Material& m : {plain_material("white", 1.f, 0.f, 1.f, 0.f, 0.f),
                            plain_material("glass", 1.f, 0.f, 0.f, 1.f, 1.f),
                            plain_material("rough-metal", 1.f, 1.f, 0.7f, 1.f, 0.f),
                            translucent, half_translucent}) {
    Scene scene(sphere_scene(m, {0.f, 0.3f, 3.f}, 0.75f));
    RenderSettings settings;
    settings.width = settings.height = 8;
    settings.sampler = SamplerType::Independent;
    settings.max_depth = 64;
    settings.environment = env;
    settings.seed = 3;
    double sum = 0.0, var = 0.0;
    // The metal's energy compensation is tabulated: allow its 0.3% accuracy.
    const double table = m.metallic > 0.f ? 3e-3 : 1e-5;
    for (const PixelStats& p : testing::pixel_stats(scene, settings, 256)) {
      EXPECT_NEAR(p.mean, 1.0, 4.0 * p.standard_error + table) << m.name;
      sum += p.mean;
      var += p.standard_error * p.standard_error;
    }
    EXPECT_NEAR(sum / 64, 1.0, 4.0 * std::sqrt(var) / 64 + table) << m.name;
  }
}

// A dispersive glass sphere (KHR_materials_dispersion 1: Abbe number 20) in the furnace: each
// path that meets it carries one wavelength, its throughput 1 whatever the wavelength (smooth
// glass, base 1), so each channel's expectation is the mean of its wavelength weights, 1. The
// samples are coloured (their weights differ per channel), so the error is estimated from the
// spread of the pixels (independent estimates), not from the luminance M2.
TEST(WhiteFurnace, DispersiveGlassSphereRendersOneInEveryChannel) {
  Material m = plain_material("dispersive-glass", 1.f, 0.f, 0.f, 1.f, 1.f);
  m.dispersion = 1.f;
  Scene scene(sphere_scene(m, {0.f, 0.3f, 3.f}, 0.75f));
  RenderSettings settings;
  settings.width = settings.height = 8;
  settings.sampler = SamplerType::Independent;
  settings.max_depth = 64;
  settings.environment = Environment::constant({1.f, 1.f, 1.f});
  settings.seed = 5;
  const uint32_t spp = 512;
  TileBuffer tile;
  ASSERT_TRUE(render_rect(scene, settings, {0, 0, 8, 8}, 0, spp, &tile));
  EXPECT_EQ(tile.nonfinite_samples, 0u);
  bool coloured = false;
  for (int c = 0; c < 3; ++c) {
    double sum = 0.0, sum2 = 0.0;
    for (size_t i = 0; i < 64; ++i) {
      const double v = tile.rgb_sum[3 * i + size_t(c)] / spp;
      sum += v;
      sum2 += v * v;
      coloured = coloured || std::abs(v - 1.0) > 1e-3;
    }
    const double mean = sum / 64, se = std::sqrt((sum2 / 64 - mean * mean) / 63);
    EXPECT_NEAR(mean, 1.0, 4.0 * se + 1e-4) << "channel " << c;
  }
  EXPECT_TRUE(coloured);  // the wavelengths were sampled: pixels are not exactly 1
}

// A rough glass sphere (roughness 0.5, KHR_materials_transmission's microfacet BSDF) in the
// same furnace: radiance crosses its surface scaled by 1/eta^2 going in and eta^2 coming out,
// so an energy-conserving BSDF would render 1; single-scattering microfacets lose the light
// that meets a second microfacet (1-18 % per interface at this roughness, by side and angle). So every
// pixel is at most 1 (no energy created; a wrong radiance scaling shows as 2.25 or 0.44) and
// the image stays near it.
TEST(WhiteFurnace, RoughGlassSphereCreatesNoEnergy) {
  const Material m = plain_material("rough-glass", 1.f, 0.f, 0.5f, 1.f, 1.f);
  Scene scene(sphere_scene(m, {0.f, 0.3f, 3.f}, 0.75f));
  RenderSettings settings;
  settings.width = settings.height = 8;
  settings.sampler = SamplerType::Independent;
  settings.max_depth = 64;
  settings.environment = Environment::constant({1.f, 1.f, 1.f});
  settings.seed = 11;
  double sum = 0.0;
  for (const PixelStats& p : testing::pixel_stats(scene, settings, 512)) {
    EXPECT_LE(p.mean, 1.0 + 4.0 * p.standard_error);
    sum += p.mean;
  }
  EXPECT_GT(sum / 64, 0.85);
  EXPECT_LT(sum / 64, 1.0);
}

// A rough glass pane (roughness 0.7, ior 1.5) at z = 0 seen straight down, lit only from below
// through it. A point light of intensity I at distance d below is reached by light sampling
// alone (rough_glass_eval_cos): at normal incidence h = n, so the pixel is exactly
//   (1 - F) D(n) G2 |wi.h| (wo.h) / (cos_o (wo.h + eta wi.h)^2) x I / d^2
//   = (1 - 0.04) / (pi alpha^2) / (1 - 1.5)^2 x I / d^2
// (Walter et al.'s BTDF over eta^2, F = ((1.5 - 1) / 2.5)^2, G2 = 1 along the normal). A small
// emissive sphere of radiance Le at the same place is reached by BSDF sampling alone (the lobe
// is not evaluated for area lights): the pixel is Le times the BTDF's f |cos_i| integrated over
// the sphere's cone of directions, by quadrature here (the lobe falls off within the cone, so
// it is not the point light's value).
TEST(RoughGlass, APunctualLightThroughRoughGlassIsTheBtdfsClosedFormAndMatchesBsdfSampling) {
  const float alpha = 0.7f * 0.7f, d = 1.f, radius = 0.05f;
  const Vec3 intensity(1.f, 1.f, 1.f);
  auto pane = [&](bool point_light) {
    SceneDescription desc;
    desc.source = "rough pane";
    desc.materials.push_back(plain_material("rough-glass", 1.f, 0.f, 0.7f, 1.f, 1.f));
    testing::add_quad(&desc, {-2, -2, 0}, {2, -2, 0}, {2, 2, 0}, {-2, 2, 0}, 0);
    if (point_light) {
      PunctualLight light;
      light.position = Vec3(0.f, 0.f, -d);
      light.intensity = intensity;
      desc.punctual_lights.push_back(light);
    } else {
      Material lamp;
      lamp.name = "lamp";
      lamp.albedo = Vec3(0.f, 0.f, 0.f);
      lamp.emission = intensity * (1.f / (kPi * radius * radius));
      desc.materials.push_back(lamp);
      testing::add_sphere(&desc, {0.f, 0.f, -d}, radius, 1, 64, 128);
    }
    desc.camera = testing::look_at({0.f, 0.f, 2.f}, {0.f, 0.f, 0.f}, 1e-4f);
    return desc;
  };
  RenderSettings settings;
  settings.width = settings.height = 1;
  settings.sampler = SamplerType::Independent;
  settings.max_depth = 4;
  settings.seed = 5;
  const double want =
      (1.0 - 0.04) / (M_PI * double(alpha) * double(alpha)) / (0.5 * 0.5) / (double(d) * d);
  const Scene point(pane(true));
  const PixelStats by_light = testing::pixel_stats(point, settings, 64)[0];
  EXPECT_NEAR(by_light.mean, want, 1e-3 * want);
  // The BTDF (radiance) for wo = +z and wi at angle t from -z, in double.
  auto btdf_cos = [&](double t) {
    const double a2 = double(alpha) * alpha, eta = 1.5;
    const double wi[3] = {std::sin(t), 0.0, -std::cos(t)};
    double h[3] = {-wi[0] * eta, 0.0, -(1.0 + eta * wi[2])};
    const double hl = std::sqrt(h[0] * h[0] + h[2] * h[2]);
    h[0] /= hl, h[2] /= hl;
    const double oh = h[2], ih = wi[0] * h[0] + wi[2] * h[2];
    const double ct = std::sqrt(1.0 - (1.0 - oh * oh) / (eta * eta));
    const double rs = (oh - eta * ct) / (oh + eta * ct), rp = (eta * oh - ct) / (eta * oh + ct);
    const double F = 0.5 * (rs * rs + rp * rp);
    const double D = a2 / (M_PI * std::pow(h[2] * h[2] * (a2 - 1.0) + 1.0, 2));
    const double tan2 = std::tan(t) * std::tan(t);
    const double G2 = 1.0 / (1.0 + 0.5 * (-1.0 + std::sqrt(1.0 + a2 * tan2)));
    const double den = oh + eta * ih;
    return (1.0 - F) * D * G2 * std::fabs(ih) * oh / (den * den);
  };
  const double le = 1.0 / (M_PI * double(radius) * radius), cone = std::asin(radius / d);
  double sphere_want = 0.0;
  const int n = 4000;
  for (int i = 0; i < n; ++i) {
    const double t = (i + 0.5) * cone / n;
    sphere_want += le * btdf_cos(t) * 2.0 * M_PI * std::sin(t) * (cone / n);
  }
  EXPECT_NEAR(btdf_cos(0.0), want, 1e-9 * want);  // the two formulas agree at the centre
  const Scene sphere(pane(false));
  const PixelStats by_bsdf = testing::pixel_stats(sphere, settings, 400000)[0];
  // The sphere is faceted (64 x 128 triangles): 0.5 % of slack for its silhouette.
  EXPECT_NEAR(by_bsdf.mean, sphere_want, 4.0 * by_bsdf.standard_error + 5e-3 * sphere_want)
      << "BSDF sampling: " << by_bsdf.mean << " +- " << by_bsdf.standard_error;
  EXPECT_LT(sphere_want, want);
}

// Albedo 0.5 in the same furnace: a convex object is seen by one bounce only, so the pixel is
// 0.5 exactly; and from inside a closed sphere of albedo 0.5 that emits 1 everywhere, the
// infinite bounce series gives L = Le (1 + rho + rho^2 + ...) = Le / (1 - rho) = 2.
TEST(WhiteFurnace, AlbedoHalfSingleBounceAndInfiniteBounceSeries) {
  {
    Scene scene(sphere_scene(plain_material("half", 0.5f, 0.f, 1.f, 0.f, 0.f),
                             {0.f, 0.f, 3.f}, 0.3f));  // every pixel sees the sphere
    RenderSettings settings;
    settings.width = settings.height = 4;
    settings.sampler = SamplerType::Independent;
    settings.environment = Environment::constant({1.f, 1.f, 1.f});
    for (const PixelStats& p : testing::pixel_stats(scene, settings, 256))
      EXPECT_NEAR(p.mean, 0.5, 4.0 * p.standard_error + 1e-5);
  }
  SceneDescription desc;
  desc.source = "closed-sphere";
  Material m = plain_material("glowing", 0.5f, 0.f, 1.f, 0.f, 0.f);
  m.emission = Vec3(1.f, 1.f, 1.f);
  desc.materials.push_back(m);
  testing::add_sphere(&desc, {0, 0, 0}, 1.f, 0, 16, 32);
  // Face inwards: reverse every triangle's winding.
  for (size_t i = 0; i < desc.world.size(); ++i)
    std::swap(desc.world.indices[3 * i + 1], desc.world.indices[3 * i + 2]);
  desc.camera = testing::look_at({0.f, 0.f, 0.f}, {0.f, 0.f, -1.f}, 1.2f);
  Scene scene(std::move(desc));
  RenderSettings settings;
  settings.width = settings.height = 4;
  settings.sampler = SamplerType::Independent;
  settings.max_depth = 200;  // truncation error 0.5^200: none
  double sum = 0.0, var = 0.0;
  for (const PixelStats& p : testing::pixel_stats(scene, settings, 512)) {
    EXPECT_NEAR(p.mean, 2.0, 4.0 * p.standard_error + 1e-5);
    sum += p.mean;
    var += p.standard_error * p.standard_error;
  }
  EXPECT_NEAR(sum / 16, 2.0, 4.0 * std::sqrt(var) / 16);
}

// Rough metal (base 1, metallic 1) in the furnace: a convex object reflects each ray once, so
// the pixel is the BSDF's directional albedo = integral of f cos, computed here by quadrature
// of the BSDF; with the multiple-scattering compensation that albedo is 1 (up to the energy
// table's accuracy), so the sphere renders 1 too.
TEST(WhiteFurnace, RoughMetalSphereRendersItsDirectionalAlbedoOfOne) {
  const Material metal = plain_material("metal", 1.f, 1.f, 0.6f, 1.f, 0.f);
  BsdfParams bp;
  bp.base = Vec3(1.f, 1.f, 1.f);
  bp.metallic = 1.f;
  bp.alpha = 0.36f;
  bp.specular = 1.f;
  for (Vec3 target : {Vec3(0.f, 0.f, 1.f), Vec3(0.6f, 0.1f, 0.79f), Vec3(-0.85f, 0.3f, 0.43f)}) {
    // A narrow camera looking at a point of the sphere from +z.
    const Vec3 eye(target.x, target.y, 4.f);
    SceneDescription desc = sphere_scene(metal, eye, 1e-4f);
    desc.camera = testing::look_at(eye, target, 1e-4f);
    Scene scene(std::move(desc));
    RenderSettings settings;
    settings.width = settings.height = 1;
    settings.sampler = SamplerType::Independent;
    settings.environment = Environment::constant({1.f, 1.f, 1.f});
    TileBuffer tile;
    ASSERT_TRUE(render_rect(scene, settings, {0, 0, 1, 1}, 0, 4096, &tile));
    const std::vector<float>& sums = tile.sum(channels::Id::Normal);
    const Vec3 n(sums[0] / 4096, sums[1] / 4096, sums[2] / 4096);
    const Vec3 wo = normalize(eye - target);
    const float mu = dot(normalize(n), wo);
    const Vec3 wo_local(std::sqrt(std::max(0.f, 1.f - mu * mu)), 0.f, mu);
    double e = 0.0;
    const int q = 600;
    for (int i = 0; i < q; ++i)
      for (int j = 0; j < q; ++j) {
        const double z = (i + 0.5) / q, phi = (j + 0.5) * 2 * M_PI / q, r = std::sqrt(1 - z * z);
        e += bsdf_eval_cos(bp, wo_local,
                           Vec3(float(r * std::cos(phi)), float(r * std::sin(phi)), float(z)))
                 .x *
             (1.0 / q) * (2 * M_PI / q);
      }
    const double mean = tile.rgb_sum[0] / 4096;
    const double se = std::sqrt(tile.luminance_m2[0] / 4095 / 4096);
    EXPECT_NEAR(mean, e, 4.0 * se + 1e-3) << "mu_o " << mu;
    EXPECT_NEAR(e, 1.0, 3e-3) << "mu_o " << mu;
    EXPECT_NEAR(mean, 1.0, 4.0 * se + 3e-3) << "mu_o " << mu;
    // Without the compensation the same sphere would be visibly darker.
    EXPECT_LT(metal_single_scattering_albedo(mu, bp.alpha), 0.99f);
  }
}

// The independent sampler's reported error is calibrated: over 256 pixels of a diffuse plane
// under an emissive square (closed-form irradiance, averaged over each pixel's footprint by
// quadrature), about 95% of the pixel means lie within two reported standard errors
// (per-sample variance / N, the within-batch statistic the worker reports) of the analytic
// value.
TEST(Calibration, IndependentSamplerErrorCoversTheAnalyticValue) {
  const float rho = 0.7f, L = 2.f, c = 1.f;
  SceneDescription desc;
  desc.source = "calibration";
  desc.materials.push_back(plain_material("plane", rho, 0.f, 1.f, 0.f, 0.f));
  Material emitter = plain_material("emitter", 0.f, 0.f, 1.f, 0.f, 0.f);
  emitter.emission = Vec3(L, L, L);
  desc.materials.push_back(emitter);
  testing::add_quad(&desc, {-20, -20, 0}, {20, -20, 0}, {20, 20, 0}, {-20, 20, 0}, 0);
  testing::add_quad(&desc, {-0.5f, -0.5f, c}, {-0.5f, 0.5f, c}, {0.5f, 0.5f, c},
                    {0.5f, -0.5f, c}, 1);
  desc.camera = testing::look_at({0.f, -1.2f, 0.8f}, {0.f, 0.3f, 0.f}, 0.5f);
  Scene scene(std::move(desc));
  RenderSettings settings;
  settings.width = settings.height = 16;
  settings.sampler = SamplerType::Independent;
  settings.max_depth = 1;
  settings.seed = 8;
  const uint32_t spp = 64;
  const std::vector<PixelStats> stats = testing::pixel_stats(scene, settings, spp);
  int within = 0;
  const Camera& cam = scene.camera();
  for (uint32_t y = 0; y < 16; ++y)
    for (uint32_t x = 0; x < 16; ++x) {
      double analytic = 0.0;
      const int sub = 8;
      for (int a = 0; a < sub; ++a)
        for (int b = 0; b < sub; ++b) {
          const Vec3 d = cam.ray_direction(x + (a + 0.5f) / sub, y + (b + 0.5f) / sub, 16, 16);
          ASSERT_LT(d.z, 0.f);
          const float t = -cam.position.z / d.z;
          const Vec3 p = cam.position + d * t;
          analytic +=
              rho * L * testing::form_factor(p.x, p.y, -0.5, 0.5, -0.5, 0.5, c) / (sub * sub);
        }
      const PixelStats& s = stats[y * 16 + x];
      within += std::fabs(s.mean - analytic) <= 2.0 * s.standard_error;
    }
  const double fraction = within / 256.0;
  std::printf("calibration: %.1f%% of pixels within 2 reported standard errors\n",
              100.0 * fraction);
  // Binomial(256, 0.95): standard deviation 1.4%; also guards against overstated errors.
  EXPECT_GT(fraction, 0.90);
  EXPECT_LT(fraction, 0.995);
}

// Stratified, halton and sobol beat independent at equal spp: RMS error of a 16 spp render of
// the Cornell box (direct + one indirect bounce) against a 2048 spp sobol reference.
TEST(Samplers, LowDiscrepancySamplersBeatIndependentOnTheCornellBox) {
  std::vector<std::string> warnings;
  auto scene = load_scene(std::string(RENDERFARM_EXAMPLES_DIR) + "/cornell-box.gltf", &warnings);
  RenderSettings settings;
  settings.width = settings.height = 16;
  settings.max_depth = 2;
  settings.seed = 1000;
  const Image reference = render_image(*scene, settings, 2048, 2, nullptr);
  auto rmse = [&](SamplerType type) {
    double sum = 0.0;
    for (uint64_t seed : {1, 2}) {
      RenderSettings s = settings;
      s.sampler = type;
      s.seed = seed;
      const Image image = render_image(*scene, s, 16, 2, nullptr);
      for (size_t i = 0; i < image.rgb.size(); ++i) {
        const double d = double(image.rgb[i]) - double(reference.rgb[i]);
        sum += d * d;
      }
    }
    return std::sqrt(sum / (2.0 * double(reference.rgb.size())));
  };
  const double independent = rmse(SamplerType::Independent);
  for (SamplerType type : {SamplerType::Stratified, SamplerType::Halton, SamplerType::Sobol}) {
    const double e = rmse(type);
    EXPECT_LT(e, 0.95 * independent) << sampler_type_name(type) << " " << e << " vs " << independent;
    std::printf("cornell 16 spp rmse: %s %.5f (independent %.5f)\n", sampler_type_name(type), e,
                independent);
  }
}

}  // namespace
}  // namespace rf
