// Environment light: an equirectangular (latitude-longitude) HDR map at infinity, read with
// OpenImageIO, importance-sampled with a 2D piecewise-constant distribution proportional to
// luminance x sin(theta) (pbrt's ImageInfiniteLight).
//
// Mapping (world space, +Y up): theta = acos(d.y) from +Y, v = theta / pi (row 0 = +Y);
// phi = atan2(d.x, -d.z), u = 0.5 + phi / (2 pi), so the image center looks along -Z (the
// default glTF camera's view) and u grows towards +X. rotation_deg turns the map about +Y:
// a feature at azimuth phi moves to phi + rotation (counter-clockwise seen from above).
// Radiance is the texel's (nearest texel, the same piecewise-constant function the sampling
// distribution is built from) times intensity.
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "sampling/sampling.h"
#include "math/vecmath.h"

namespace rf {

class Environment {
 public:
  // Loads an .hdr/.exr (any OIIO-readable image; RGB, or gray replicated). Throws
  // std::runtime_error naming the file on failure.
  static std::shared_ptr<Environment> load(const std::string& path, float intensity,
                                           float rotation_deg);
  // Uniform radiance (the furnace test's environment), as an nu x nv map.
  static std::shared_ptr<Environment> constant(Vec3 radiance, uint32_t nu = 64,
                                               uint32_t nv = 32);
  // From linear RGB texels (row-major, 3 floats each).
  Environment(std::vector<float> rgb, uint32_t width, uint32_t height, float intensity,
              float rotation_deg);

  // Radiance arriving from direction d (unit, world space; d points away from the scene).
  Vec3 eval(Vec3 d) const;
  // Samples a direction; *pdf is per unit solid angle (0 if the sample is unusable).
  Vec3 sample(Point2 u, float* pdf) const;
  float pdf(Vec3 d) const;
  // u of sample() that produces d (for the round-trip tests).
  Point2 invert(Vec3 d) const;
  // Mean luminance over the sphere (solid-angle weighted), for light selection by power.
  float mean_luminance() const { return mean_luminance_; }
  uint32_t width() const { return width_; }
  uint32_t height() const { return height_; }

  // Map coordinates <-> world direction (with the rotation applied).
  Point2 direction_to_uv(Vec3 d) const;
  Vec3 uv_to_direction(Point2 uv) const;

 private:
  std::vector<float> rgb_;
  uint32_t width_ = 0, height_ = 0;
  float intensity_ = 1.f;
  float cos_rot_ = 1.f, sin_rot_ = 0.f;
  Distribution2D distribution_;
  float mean_luminance_ = 0.f;
};

}  // namespace rf
