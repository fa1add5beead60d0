#include "testing/references.h"

#include <gtest/gtest.h>

#include <cmath>

#include "render/film.h"

namespace rf {
namespace testing {

double form_factor_corner(double a, double b, double c) {
  const double X = a / c, Y = b / c;
  const double sx = std::sqrt(1 + X * X), sy = std::sqrt(1 + Y * Y);
  return (X / sx * std::atan(Y / sx) + Y / sy * std::atan(X / sy)) / (2 * M_PI);
}

namespace {
double signed_corner(double a, double b, double c) {
  return (a < 0 ? -1 : 1) * (b < 0 ? -1 : 1) * form_factor_corner(std::fabs(a), std::fabs(b), c);
}
}  // namespace

double form_factor(double px, double py, double x0, double x1, double y0, double y1, double c) {
  return signed_corner(x1 - px, y1 - py, c) - signed_corner(x0 - px, y1 - py, c) -
         signed_corner(x1 - px, y0 - py, c) + signed_corner(x0 - px, y0 - py, c);
}

Material plain_material(const char* name, float base, float metallic, float roughness,
                        float specular, float transmission, float emission) {
  Material m;
  m.name = name;
  m.albedo = Vec3(base, base, base);
  m.metallic = metallic;
  m.roughness = roughness;
  m.specular = specular;
  m.transmission = transmission;
  m.emission = Vec3(emission, emission, emission);
  return m;
}

std::vector<PixelStats> pixel_stats(const Scene& scene, const RenderSettings& settings,
                                    uint32_t spp) {
  TileBuffer tile;
  EXPECT_TRUE(render_rect(scene, settings, {0, 0, settings.width, settings.height}, 0, spp,
                          &tile));
  EXPECT_EQ(tile.nonfinite_samples, 0u);
  std::vector<PixelStats> out(tile.rect.pixel_count());
  for (size_t i = 0; i < out.size(); ++i) {
    out[i].mean = tile.rgb_sum[3 * i] / spp;
    out[i].standard_error = std::sqrt(tile.luminance_m2[i] / (spp - 1) / spp);
  }
  return out;
}

}  // namespace testing
}  // namespace rf
