// The integrator names of the protocol and the checks of a render request.
#include <cmath>
#include <string>

#include "render/integrators.h"

namespace rf {

bool parse_integrator_type(const std::string& name, IntegratorType* out) {
  if (name == "path") {
    *out = IntegratorType::Path;
    return true;
  }
  if (name == "direct") {
    *out = IntegratorType::Direct;
    return true;
  }
  if (name == "ao") {
    *out = IntegratorType::AmbientOcclusion;
    return true;
  }
  return false;
}

const char* integrator_type_name(IntegratorType t) {
  switch (t) {
    case IntegratorType::Path:
      return "path";
    case IntegratorType::Direct:
      return "direct";
    case IntegratorType::AmbientOcclusion:
      return "ao";
  }
  return "?";
}

std::string validate_render_request(const RenderSettings& settings, PixelRect rect,
                                    uint64_t start, uint64_t count) {
  if (settings.width == 0 || settings.height == 0) return "image width and height must be > 0";
  if (uint64_t(settings.width) * settings.height > (uint64_t(1) << 32))
    return "image has more than 2^32 pixels";
  if (rect.width == 0 || rect.height == 0) return "tile rect is empty";
  if (uint64_t(rect.x0) + rect.width > settings.width ||
      uint64_t(rect.y0) + rect.height > settings.height)
    return "tile rect lies outside the " + std::to_string(settings.width) + "x" +
           std::to_string(settings.height) + " image";
  if (!(settings.aperture_radius >= 0.f) || !std::isfinite(settings.aperture_radius))
    return "aperture_radius must be finite and >= 0";
  if (settings.aperture_radius > 0.f &&
      !(settings.focus_distance > 0.f && std::isfinite(settings.focus_distance)))
    return "focus_distance must be finite and > 0 when aperture_radius > 0";
  if (count == 0) return "sample count must be > 0";
  if (count > kMaxSamplesPerPixel || start > kMaxSamplesPerPixel ||
      start + count > kMaxSamplesPerPixel)
    return "sample indices beyond 2^31 are not supported";
  return {};
}

}  // namespace rf
