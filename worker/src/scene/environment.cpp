#include "scene/environment.h"

#include <OpenImageIO/imageio.h>

#include <cmath>
#include <stdexcept>

namespace rf {

std::shared_ptr<Environment> Environment::load(const std::string& path, float intensity,
                                               float rotation_deg) {
  auto in = OIIO::ImageInput::open(path);
  if (!in) throw std::runtime_error(path + ": cannot open environment map: " + OIIO::geterror());
  const OIIO::ImageSpec spec = in->spec();
  if (spec.width <= 0 || spec.height <= 0 || spec.nchannels <= 0)
    throw std::runtime_error(path + ": environment map has no pixels");
  if (uint64_t(spec.width) * uint64_t(spec.height) > (uint64_t(1) << 27))
    throw std::runtime_error(path + ": environment map larger than 2^27 pixels");
  const int nc = spec.nchannels;
  std::vector<float> pixels(size_t(spec.width) * size_t(spec.height) * size_t(nc));
  if (!in->read_image(0, 0, 0, nc, OIIO::TypeDesc::FLOAT, pixels.data()))
    throw std::runtime_error(path + ": cannot read environment map: " + in->geterror());
  in->close();
  std::vector<float> rgb(size_t(spec.width) * size_t(spec.height) * 3);
  for (size_t i = 0; i < size_t(spec.width) * size_t(spec.height); ++i)
    for (size_t c = 0; c < 3; ++c) {
      const float v = pixels[i * size_t(nc) + std::min(c, size_t(nc) - 1)];
      rgb[3 * i + c] = std::isfinite(v) && v > 0.f ? v : 0.f;  // NaN/negative texels: black
    }
  return std::make_shared<Environment>(std::move(rgb), uint32_t(spec.width),
                                       uint32_t(spec.height), intensity, rotation_deg);
}

std::shared_ptr<Environment> Environment::constant(Vec3 radiance, uint32_t nu, uint32_t nv) {
  std::vector<float> rgb(size_t(nu) * nv * 3);
  for (size_t i = 0; i < size_t(nu) * nv; ++i) {
    rgb[3 * i] = radiance.x;
    rgb[3 * i + 1] = radiance.y;
    rgb[3 * i + 2] = radiance.z;
  }
  return std::make_shared<Environment>(std::move(rgb), nu, nv, 1.f, 0.f);
}

Environment::Environment(std::vector<float> rgb, uint32_t width, uint32_t height,
                         float intensity, float rotation_deg)
    : rgb_(std::move(rgb)), width_(width), height_(height), intensity_(intensity) {
  const float r = rotation_deg * (kPi / 180.f);
  cos_rot_ = std::cos(r);
  sin_rot_ = std::sin(r);
  std::vector<float> weights(size_t(width) * height);
  double sum = 0.0, solid = 0.0;
  for (uint32_t y = 0; y < height; ++y) {
    const float sin_theta = std::sin(kPi * (float(y) + 0.5f) / float(height));
    for (uint32_t x = 0; x < width; ++x) {
      const size_t i = size_t(y) * width + x;
      const float lum = luminance({rgb_[3 * i], rgb_[3 * i + 1], rgb_[3 * i + 2]});
      weights[i] = lum * sin_theta;
      sum += double(lum) * sin_theta;
      solid += sin_theta;
    }
  }
  mean_luminance_ = solid > 0.0 ? float(sum / solid) * intensity_ : 0.f;
  distribution_ = Distribution2D(weights, width, height);
}

Point2 Environment::direction_to_uv(Vec3 d) const {
  // Undo the rotation about +Y (rotate by -r), then map.
  const float x = cos_rot_ * d.x - sin_rot_ * d.z;
  const float z = sin_rot_ * d.x + cos_rot_ * d.z;
  const float theta = std::acos(std::min(1.f, std::max(-1.f, d.y)));
  float u = 0.5f + std::atan2(x, -z) * (0.5f * kInvPi);
  if (u >= 1.f) u -= 1.f;
  if (u < 0.f) u += 1.f;
  return {u, theta * kInvPi};
}

Vec3 Environment::uv_to_direction(Point2 uv) const {
  const float theta = uv.y * kPi, phi = (uv.x - 0.5f) * 2.f * kPi;
  const float st = std::sin(theta);
  const float x = st * std::sin(phi), z = -st * std::cos(phi), y = std::cos(theta);
  // Rotate by +r about +Y.
  return {cos_rot_ * x + sin_rot_ * z, y, -sin_rot_ * x + cos_rot_ * z};
}

Vec3 Environment::eval(Vec3 d) const {
  const Point2 uv = direction_to_uv(d);
  const uint32_t x = std::min(width_ - 1, uint32_t(uv.x * float(width_)));
  const uint32_t y = std::min(height_ - 1, uint32_t(uv.y * float(height_)));
  const size_t i = 3 * (size_t(y) * width_ + x);
  return Vec3(rgb_[i], rgb_[i + 1], rgb_[i + 2]) * intensity_;
}

Vec3 Environment::sample(Point2 u, float* pdf) const {
  float pdf_uv = 0.f;
  const Point2 uv = distribution_.sample(u, &pdf_uv);
  const float sin_theta = std::sin(uv.y * kPi);
  // d(omega) = sin(theta) dtheta dphi = 2 pi^2 sin(theta) du dv.
  *pdf = sin_theta > 0.f ? pdf_uv / (2.f * kPi * kPi * sin_theta) : 0.f;
  return uv_to_direction(uv);
}

float Environment::pdf(Vec3 d) const {
  const Point2 uv = direction_to_uv(d);
  const float sin_theta = std::sin(uv.y * kPi);
  if (!(sin_theta > 0.f)) return 0.f;
  return distribution_.pdf(uv) / (2.f * kPi * kPi * sin_theta);
}

Point2 Environment::invert(Vec3 d) const { return distribution_.invert(direction_to_uv(d)); }

}  // namespace rf
