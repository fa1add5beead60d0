// Materials: glTF 2.0 metallic-roughness as a Lambert diffuse base plus a GGX microfacet
// specular layer (Smith height-correlated masking-shadowing, visible-normal sampling),
// emission (with KHR_materials_emissive_strength), KHR_materials_specular's specularFactor,
// and KHR_materials_transmission + KHR_materials_ior as smooth dielectric glass.
//
// Radiance and emission are linear RGB in the scene's units (W sr^-1 m^-2 up to an arbitrary
// overall scale); base colors are reflectances in [0, 1]. Directions in the BSDF functions are
// unit vectors in the local shading frame (normal = +z), wo towards the viewer, wi towards the
// light.
#pragma once

#include <string>

#include "sampling.h"
#include "vecmath.h"

namespace rf {

// A texture slot of a material: which texture, which TEXCOORD set, and the optional
// KHR_texture_transform (uv' = offset + Rotation(rotation) * (scale * uv), as in the spec).
struct TextureRef {
  int texture = -1;       // index into the scene's textures; -1 = no texture
  uint32_t texcoord = 0;  // TEXCOORD_<n>, n in {0, 1}
  float offset[2] = {0.f, 0.f};
  float rotation = 0.f;  // radians, counter-clockwise in uv space
  float scale[2] = {1.f, 1.f};
  bool valid() const { return texture >= 0; }
  Point2 apply(Point2 uv) const {
    const float su = uv.x * scale[0], sv = uv.y * scale[1];
    const float c = std::cos(rotation), s = std::sin(rotation);
    // KHR_texture_transform's matrix: [c s; -s c] in its column-major notation, i.e.
    // u' = c u + s v, v' = -s u + c v.
    return {offset[0] + c * su + s * sv, offset[1] - s * su + c * sv};
  }
};

// Constant defaults are a pure white Lambertian (no specular layer): what the tests build
// by hand. The glTF loader sets the glTF defaults (metallic = roughness = specular = 1).
struct Material {
  std::string name;
  Vec3 albedo{1.f, 1.f, 1.f};    // glTF baseColorFactor rgb (default white)
  Vec3 emission{0.f, 0.f, 0.f};  // emissiveFactor * KHR_materials_emissive_strength
  float metallic = 0.f;          // metallicFactor
  float roughness = 1.f;         // roughnessFactor (perceptual; GGX alpha = roughness^2)
  float specular = 0.f;          // KHR_materials_specular specularFactor: dielectric layer
  float ior = 1.5f;              // KHR_materials_ior
  float transmission = 0.f;      // KHR_materials_transmissionFactor
  float normal_scale = 1.f;      // normalTexture.scale
  TextureRef base_color_tex{}, metallic_roughness_tex{}, normal_tex{}, emissive_tex{};
  bool is_emissive() const { return !is_zero(emission); }
  // True if shading reads texture coordinates at the hit point (the emissive texture is read
  // by Scene::emission, which interpolates its own).
  bool reads_uv() const {
    return base_color_tex.valid() || metallic_roughness_tex.valid() || normal_tex.valid();
  }
};

// Material parameters at one surface point, after texture lookups.
struct BsdfParams {
  Vec3 base{1.f, 1.f, 1.f};
  float metallic = 0.f;
  float alpha = 1.f;  // GGX alpha = roughness^2, clamped to >= kMinAlpha
  float specular = 0.f;
  float ior = 1.5f;
  float transmission = 0.f;
  bool front = true;  // wo on the front side of the geometric normal (outside the glass)
};

// Smallest GGX alpha: below it the lobe is too narrow for float precision; such surfaces
// render as very slightly rough mirrors.
constexpr float kMinAlpha = 2e-3f;

struct BsdfSample {
  Vec3 wi;             // local frame
  Vec3 weight;         // f cos / pdf (for delta lobes: the lobe's reflectance / probability)
  float pdf = 0.f;     // solid-angle density of wi among the non-delta lobes; 0 if delta
  bool delta = false;  // chosen from the glass (specular) lobe
  bool transmitted = false;
};

// Lambert + GGX as in the glTF spec (Appendix B): with F_d the dielectric Schlick Fresnel
// (f0 = specular * ((ior - 1)/(ior + 1))^2) and F_m the conductor Schlick Fresnel (f0 = base),
//   f = (1 - m)(1 - t)((1 - F_d) base / pi + F_d spec) + m (F_m spec + f_ms),
//   spec = D G2 / (4 |cos_o cos_i|),
// where (1 - m) t is the weight of the delta glass lobe and f_ms the metal's multiple-
// scattering compensation (Kulla & Conty 2017), which makes a white rough metal conserve
// energy exactly (up to its table). eval returns f times |cos_i| for the non-delta part only
// (0 if wo or wi is below the surface).
// Lobe selection probabilities, a function of (params, wo) only; the path tracer computes them
// once per vertex and passes them to the overloads below (the same values as without them).
// With them come the wo-dependent terms of the evaluation, so that evaluating several
// directions at one vertex (light sample, BSDF sample) computes them once.
struct BsdfLobes {
  float glass = 0.f;  // probability of the delta glass lobe
  float spec = 0.f;   // probability of GGX among the non-delta lobes
  float wd = 0.f;     // (1 - metallic)(1 - transmission): weight of the dielectric base
  float f0d = 0.f;    // dielectric Fresnel at normal incidence, specular * ((ior-1)/(ior+1))^2
  float root_o = 0.f;  // sqrt(cos_o^2 + alpha^2 (1 - cos_o^2)) = 2 cos_o (Lambda(wo) + 1/2)
  float pdf_k = 0.f;   // 1 / (2 (cos_o + root_o)) = G1(wo) / (4 cos_o): GGX pdf = D pdf_k
  Vec3 ms;             // metal multiple scattering without its (1 - E(mu_i)) factor (0 if
                       // not metallic)
};
BsdfLobes bsdf_lobes(const BsdfParams& p, Vec3 wo);

Vec3 bsdf_eval_cos(const BsdfParams& p, Vec3 wo, Vec3 wi);
// Solid-angle density with which bsdf_sample produces wi among the non-delta lobes.
float bsdf_pdf(const BsdfParams& p, Vec3 wo, Vec3 wi);
// Both at once (sharing the half vector and Smith terms): returns f |cos_i|, sets *pdf.
Vec3 bsdf_eval_pdf(const BsdfParams& p, Vec3 wo, Vec3 wi, float* pdf);
// u: BSDF direction pair, u_lobe: lobe choice, u_fresnel: glass reflect/refract choice.
// Returns false if no direction was produced (the path ends).
bool bsdf_sample(const BsdfParams& p, Vec3 wo, Point2 u, float u_lobe, float u_fresnel,
                 BsdfSample* out);
Vec3 bsdf_eval_pdf(const BsdfParams& p, const BsdfLobes& lobes, Vec3 wo, Vec3 wi, float* pdf);
bool bsdf_sample(const BsdfParams& p, const BsdfLobes& lobes, Vec3 wo, Point2 u, float u_lobe,
                 float u_fresnel, BsdfSample* out);
// True if the BSDF has a non-delta component (next-event estimation is useful).
inline bool bsdf_has_smooth_part(const BsdfParams& p) {
  return (1.f - (1.f - p.metallic) * p.transmission) > 0.f;
}

// Directional albedo E(mu, alpha) of single-scattering GGX with F = 1 (the table behind the
// metal lobe's multiple-scattering compensation).
float metal_single_scattering_albedo(float mu, float alpha);

// Unpolarized Fresnel reflectance of a smooth dielectric interface; cos_i > 0 on the side of
// the normal, eta = n_other / n_this (ior when entering from outside).
float fresnel_dielectric(float cos_i, float eta);

}  // namespace rf
