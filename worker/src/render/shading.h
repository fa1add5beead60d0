// The path tracers' surface interaction (internal to src/render): a hit turned into a shading
// point (textures, normal map, oriented normals, ray offsets) and the small geometric helpers
// every integrator shares. Used by the packet tracer, ambient occlusion and the reference.
#pragma once

#include <algorithm>
#include <cmath>
#include <limits>

#include "math/vecmath.h"
#include "scene/materials.h"
#include "scene/scene.h"

namespace rf {

constexpr float kInfinity = std::numeric_limits<float>::infinity();

// Offset for spawned rays: floating-point error of a hit position grows with its magnitude,
// so the offset along the geometric normal scales with it (with a floor near the origin).
inline float ray_epsilon(Vec3 p) { return 3e-5f * std::max(max_abs_component(p), 1e-2f); }

// A surface point ready for shading: material parameters after textures, normals oriented
// towards wo, and the ray origins for leaving on either side.
struct ShadingPoint {
  BsdfParams params;
  Vec3 albedo;  // base color, the albedo AOV
  Vec3 ng;      // geometric normal on the side of wo
  Vec3 ns;      // shading normal (normal-mapped) on the same side as ng
  // KHR_materials_anisotropy: the direction of the anisotropy (the local frame's x axis, along
  // which GGX has alpha params.alpha_t); zero for an isotropic BSDF (any frame around ns).
  Vec3 tangent;
  Vec3 p;
  float eps = 0.f;
  // The BSDF's local frame: BsdfParams directions are in it.
  Frame frame() const { return is_zero(tangent) ? Frame(ns) : Frame(ns, tangent); }
  Vec3 above() const { return p + ng * eps; }
  Vec3 below() const { return p - ng * eps; }
};

// The texture coordinates of a texture slot at the hit: TEXCOORD_0 and _1 come with the hit,
// other sets are interpolated when asked for.
inline Point2 texcoord(const Scene& scene, const Hit& hit, const TextureRef& ref) {
  return ref.apply(ref.texcoord < 2 ? hit.uv[ref.texcoord] : scene.texcoord(hit, ref.texcoord));
}

// The shading point of hit seen from direction wo.
ShadingPoint make_shading_point(const Scene& scene, const Hit& hit, Vec3 wo);

// The normal of an area light's sample point on the side facing `origin`: its front normal, or
// the back face's for a double-sided emitter seen from behind (both faces emit).
inline Vec3 facing_light_normal(const Scene& scene, const LightSample& ls, Vec3 origin) {
  if (dot(ls.n, origin - ls.p) >= 0.f || !scene.material(ls.slot, ls.prim).double_sided)
    return ls.n;
  return -ls.n;
}

// The cosine between a hit's geometric normal and wo on the emitting side (<= 0: the hit
// face does not emit towards wo).
inline float emitting_cosine(const Material& m, Vec3 ng, Vec3 wo) {
  const float c = dot(ng, wo);
  return m.double_sided ? std::abs(c) : c;
}

// exp(-sigma t) per channel: what a medium of absorption sigma lets through over a length t
// (t may be infinite: a ray that leaves through an open mesh is absorbed entirely).
inline Vec3 transmittance(Vec3 sigma, float t) {
  Vec3 out{1.f, 1.f, 1.f};
  for (int k = 0; k < 3; ++k)
    if (sigma[k] > 0.f) out[k] = std::exp(-sigma[k] * t);
  return out;
}

// The medium after a transmission at a vertex of material m seen from the front (entering the
// mesh) or not (leaving it); media are not nested: leaving a volume returns to none.
inline Vec3 medium_after(const Material& m, bool front, Vec3 medium) {
  if (!m.has_volume()) return medium;
  return front ? m.absorption : Vec3{0.f, 0.f, 0.f};
}

// Directions on the wrong side of the geometric surface (possible with shading normals)
// would leak light through it: the path ends there.
inline bool wrong_side(Vec3 wi, Vec3 ng, bool transmitted) {
  const float side = dot(wi, ng);
  return transmitted ? side >= 0.f : side <= 0.f;
}

}  // namespace rf
