#include "render/shading.h"

namespace rf {

ShadingPoint make_shading_point(const Scene& scene, const Hit& hit, Vec3 wo) {
  const Material& mat = scene.materials()[hit.material];
  const TextureSet& tex = scene.textures();
  ShadingPoint sp;
  BsdfParams& bp = sp.params;
  bp.base = mat.albedo;
  float metallic = mat.metallic, roughness = mat.roughness;
  float c[4];
  if (mat.base_color_tex.valid() &&
      tex.lookup(mat.base_color_tex.texture, texcoord(scene, hit, mat.base_color_tex), 3, c))
    bp.base = bp.base * Vec3(c[0], c[1], c[2]);  // linear: decoded from sRGB before filtering
  // glTF 2.0, 3.9.2: COLOR_0 multiplies the base colour.
  Vec3 vertex_rgb;
  if (scene.vertex_color(hit, &vertex_rgb)) bp.base = bp.base * vertex_rgb;
  if (mat.metallic_roughness_tex.valid() &&
      tex.lookup(mat.metallic_roughness_tex.texture,
                 texcoord(scene, hit, mat.metallic_roughness_tex), 3, c)) {
    // glTF: roughness in G, metallic in B, both linear.
    roughness *= c[1];
    metallic *= c[2];
  }
  bp.metallic = std::min(1.f, std::max(0.f, metallic));
  const float r = std::min(1.f, std::max(0.f, roughness));
  bp.alpha = std::max(kMinAlpha, r * r);
  bp.specular = mat.specular;
  bp.ior = mat.ior;
  bp.transmission = mat.transmission;
  sp.albedo = bp.base;

  Vec3 ns = hit.ns;
  if (mat.normal_tex.valid() && length(hit.dpdu) > 0.f &&
      tex.lookup(mat.normal_tex.texture, texcoord(scene, hit, mat.normal_tex), 3, c)) {
    // Tangent-space normal map (glTF 3.9.3): n = normalize((2c - 1) * (scale, scale, 1)) in
    // the frame (T, B, N) with T the uv tangent made orthogonal to N.
    const Vec3 tn((2.f * c[0] - 1.f) * mat.normal_scale, (2.f * c[1] - 1.f) * mat.normal_scale,
                  2.f * c[2] - 1.f);
    Vec3 t = hit.dpdu - ns * dot(ns, hit.dpdu);
    const float tl = length(t);
    if (tl > 0.f && std::isfinite(tl)) {
      t = t / tl;
      const Vec3 b = cross(ns, t) * hit.tangent_sign;
      const Vec3 n = t * tn.x + b * tn.y + ns * tn.z;
      const float nl = length(n);
      if (nl > 0.f && std::isfinite(nl)) ns = n / nl;
    }
  }
  bp.front = dot(hit.ng, wo) >= 0.f;
  sp.ng = bp.front ? hit.ng : -hit.ng;
  sp.ns = dot(ns, sp.ng) >= 0.f ? ns : -ns;
  // A shading normal that puts wo below its hemisphere cannot be used (the BSDF would see
  // wo.z <= 0 and the path would end black): fall back to the geometric normal.
  if (dot(sp.ns, wo) <= 1e-4f) sp.ns = sp.ng;
  sp.p = hit.p;
  sp.eps = ray_epsilon(hit.p);
  return sp;
}

}  // namespace rf
