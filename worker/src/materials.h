// Materials of the first renderer version: Lambertian diffuse reflection plus one-sided
// emission. Radiance and emission are linear RGB in the scene's units (W sr^-1 m^-2 up to an
// arbitrary overall scale); albedo components are reflectances in [0, 1].
#pragma once

#include <string>

#include "sampling.h"
#include "vecmath.h"

namespace rf {

struct Material {
  std::string name;
  Vec3 albedo{1.f, 1.f, 1.f};  // glTF baseColorFactor rgb (default white)
  Vec3 emission{0.f, 0.f, 0.f};  // emissiveFactor * KHR_materials_emissive_strength
  bool is_emissive() const { return !is_zero(emission); }
};

// Lambertian BRDF f = albedo / pi, independent of directions (units sr^-1).
inline Vec3 lambert_f(const Material& m) { return m.albedo * kInvPi; }

// Solid-angle pdf of cosine-weighted sampling about the shading normal n_s for direction wi
// (unit, world space); 0 for directions below it, which the sampler never produces.
inline float lambert_pdf(Vec3 n_s, Vec3 wi) {
  const float c = dot(n_s, wi);
  return c > 0.f ? c * kInvPi : 0.f;
}

}  // namespace rf
