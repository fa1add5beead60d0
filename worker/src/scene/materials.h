// Materials: glTF 2.0 metallic-roughness as a Lambert diffuse base plus a GGX microfacet
// specular layer (Smith height-correlated masking-shadowing, visible-normal sampling),
// emission (with KHR_materials_emissive_strength), KHR_materials_specular's specularFactor,
// KHR_materials_transmission + KHR_materials_ior as dielectric glass (smooth, or with the
// material's roughness a GGX microfacet BSDF after Walter et al. 2007), and the layers
// of KHR_materials_sheen (Charlie sheen over the base, albedo-scaled) and
// KHR_materials_clearcoat (a GGX coat over everything, Fresnel-weighted). KHR_materials_unlit
// materials are not shaded at all (Material::unlit; the path tracers handle them).
//
// Radiance and emission are linear RGB in the scene's units (W sr^-1 m^-2 up to an arbitrary
// overall scale); base colors are reflectances in [0, 1]. Directions in the BSDF functions are
// unit vectors in the local shading frame (normal = +z), wo towards the viewer, wi towards the
// light.
#pragma once

#include <cstdint>
#include <new>
#include <string>

#include "sampling/sampling.h"
#include "math/vecmath.h"

namespace rf {

// A texture slot of a material: which texture, which TEXCOORD set, and the optional
// KHR_texture_transform (uv' = offset + Rotation(rotation) * (scale * uv), as in the spec).
struct TextureRef {
  int texture = -1;       // index into the scene's textures; -1 = no texture
  // The TEXCOORD set (KHR_texture_transform's texCoord if it has one), as the index of its
  // array in TriangleMesh::uv: sets 0 and 1 are arrays 0 and 1; the glTF loader gives the
  // other sets materials read arrays from 2 up.
  uint32_t texcoord = 0;
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

// glTF alphaMode (3.9.4): opaque, cut out below alphaCutoff, or blended (see Scene).
enum class AlphaMode : uint8_t { Opaque, Mask, Blend };

// Constant defaults are a pure white Lambertian (no specular layer): what the tests build
// by hand. The glTF loader sets the glTF defaults (metallic = roughness = specular = 1).
struct Material {
  std::string name;
  Vec3 albedo{1.f, 1.f, 1.f};    // glTF baseColorFactor rgb (default white)
  Vec3 emission{0.f, 0.f, 0.f};  // emissiveFactor * KHR_materials_emissive_strength
  float metallic = 0.f;          // metallicFactor
  float roughness = 1.f;         // roughnessFactor (perceptual; GGX alpha = roughness^2)
  float specular = 0.f;          // KHR_materials_specular specularFactor: dielectric layer
  Vec3 specular_color{1.f, 1.f, 1.f};  // specularColorFactor (>= 0, scales F0)
  TextureRef specular_tex{};        // specularTexture: its A channel (linear) multiplies
  TextureRef specular_color_tex{};  // specularColorTexture: RGB (sRGB) multiply the colour
  float ior = 1.5f;              // KHR_materials_ior
  float dispersion = 0.f;        // KHR_materials_dispersion: 20 / the Abbe number (0: none)
  float transmission = 0.f;      // KHR_materials_transmission transmissionFactor
  TextureRef transmission_tex{};  // transmissionTexture: its R channel (linear) multiplies
  // KHR_materials_diffuse_transmission: diffuseTransmissionFactor (x the texture's A, linear)
  // and diffuseTransmissionColorFactor (x the colour texture's RGB, sRGB).
  float diffuse_transmission = 0.f;
  Vec3 diffuse_transmission_color{1.f, 1.f, 1.f};
  TextureRef diffuse_transmission_tex{}, diffuse_transmission_color_tex{};
  float normal_scale = 1.f;      // normalTexture.scale
  TextureRef base_color_tex{}, metallic_roughness_tex{}, normal_tex{}, emissive_tex{};
  // KHR_materials_clearcoat: clearcoat = clearcoatFactor x clearcoatTexture.r, roughness =
  // clearcoatRoughnessFactor x clearcoatRoughnessTexture.g, both linear; the coat's own normal
  // map (none: the interpolated normal, not the base's normal map).
  float clearcoat = 0.f;
  float clearcoat_roughness = 0.f;
  float clearcoat_normal_scale = 1.f;
  TextureRef clearcoat_tex{}, clearcoat_roughness_tex{}, clearcoat_normal_tex{};
  // KHR_materials_sheen: sheenColor = sheenColorFactor x sheenColorTexture.rgb (sRGB-encoded),
  // sheenRoughness = sheenRoughnessFactor x sheenRoughnessTexture.a (linear).
  Vec3 sheen_color{0.f, 0.f, 0.f};
  float sheen_roughness = 0.f;
  TextureRef sheen_color_tex{}, sheen_roughness_tex{};
  // KHR_materials_unlit: the surface shows its base colour (factor x texture x COLOR_0) as
  // radiance towards any ray that meets its front (either face if double-sided), and reflects
  // and transmits nothing; alpha coverage applies as for any material.
  bool unlit = false;
  // Points and lines without NORMAL (glTF 2.0, "Point and Line Materials") are unlit and show
  // "the sum of the base color value and the emissive value": an unlit material whose emission
  // (factor x texture) is added to that base colour.
  bool unlit_adds_emission = false;
  // KHR_materials_pbrSpecularGlossiness (archived): specular_color holds specularFactor (F0
  // itself), glossiness glossinessFactor, specular_color_tex specularGlossinessTexture (RGB
  // sRGB: F0; A linear: glossiness), albedo and base_color_tex the diffuse factor and texture.
  // Shading turns them into the BRDF inputs the extension defines (shading.cpp).
  bool specular_glossiness = false;
  float glossiness = 1.f;
  // KHR_materials_anisotropy: strength (anisotropyStrength), rotation (radians, counter-
  // clockwise from the tangent) and texture (RG direction in [-1, 1], B strength; linear).
  float anisotropy = 0.f;
  float anisotropy_rotation = 0.f;
  TextureRef anisotropy_tex{};
  // KHR_materials_iridescence: iridescenceFactor (x iridescenceTexture.r), the film's ior and
  // its thickness in nm, between minimum and maximum by iridescenceThicknessTexture.g (the
  // maximum without that texture).
  float iridescence = 0.f;
  float iridescence_ior = 1.3f;
  float iridescence_thickness_min = 100.f, iridescence_thickness_max = 400.f;
  TextureRef iridescence_tex{}, iridescence_thickness_tex{};
  AlphaMode alpha_mode = AlphaMode::Opaque;
  float alpha = 1.f;         // baseColorFactor alpha
  float alpha_cutoff = 0.5f;  // alphaCutoff (MASK)
  // KHR_materials_volume: the absorption coefficient per world unit of the medium inside the
  // mesh, -ln(attenuationColor) / attenuationDistance per channel (0: none; a thin-walled
  // material, thicknessFactor 0, has none). Light crossing a length d inside is multiplied by
  // exp(-absorption d) (Beer-Lambert).
  Vec3 absorption{0.f, 0.f, 0.f};
  // glTF doubleSided: the back face is lit as the front with the normal reversed (3.9.5), and
  // so an emissive back face emits like the front; otherwise only the front face emits.
  bool double_sided = false;
  // Its index in the glTF's "materials", set by the loader (a points-and-lines variant keeps
  // that of the material it copies), -1 for none (the default material of primitives without
  // one, and materials not from a glTF file): the Material row is this plus one.
  int32_t gltf_index = -1;
  bool has_volume() const { return !is_zero(absorption); }
  // An unlit material's emission is never used (it shows its base colour instead).
  bool is_emissive() const { return !unlit && !is_zero(emission); }
  bool is_opaque() const { return alpha_mode == AlphaMode::Opaque; }
  // The material's texture slots: the one list of them that the scene's texture registration
  // and reads_uv walk. `srgb`: texels are sRGB-encoded colours, decoded before filtering
  // (glTF 3.9.2, and sheenColorTexture); otherwise linear data. `at_hit`: shading reads it at
  // the hit's texture coordinates (the emissive texture is read by Scene::emission, which
  // interpolates its own).
  struct TextureSlot {
    TextureRef Material::*ref;
    const char* name;  // the glTF property
    bool srgb, at_hit;
  };
  static constexpr int kTextureSlots = 17;
  static const TextureSlot (&texture_slots())[kTextureSlots];
  // True if shading reads texture coordinates at the hit point.
  bool reads_uv() const {
    for (const TextureSlot& slot : texture_slots())
      if (slot.at_hit && (this->*slot.ref).valid()) return true;
    return false;
  }
  // The texture whose TEXCOORD set gives the hit's tangent (Hit::dpdu) when the mesh has no
  // TANGENT: the base's normal map, else the clear coat's, else the anisotropy texture.
  const TextureRef& tangent_map() const {
    return normal_tex.valid()              ? normal_tex
           : clearcoat_normal_tex.valid() ? clearcoat_normal_tex
                                          : anisotropy_tex;
  }
  // Shading needs a tangent frame: a normal map, or anisotropy (whose direction is given in
  // the tangent frame; without a texture, from TEXCOORD_0's).
  bool needs_tangent() const { return tangent_map().valid() || anisotropy > 0.f; }
};

// Smallest GGX alpha: below it the lobe is too narrow for float precision; such surfaces
// render as very slightly rough mirrors.
constexpr float kMinAlpha = 2e-3f;
// Smallest Charlie sheen alpha (sheenRoughness^2; the distribution is a delta at 0): sheen
// roughness below 0.07 renders as 0.07.
constexpr float kMinSheenAlpha = 0.0049f;

// Material parameters at one surface point, after texture lookups.
struct BsdfParams {
  Vec3 base{1.f, 1.f, 1.f};
  float metallic = 0.f;
  float alpha = 1.f;  // GGX alpha = roughness^2, clamped to >= kMinAlpha
  // KHR_materials_anisotropy: GGX alpha along the local x axis (the anisotropy direction),
  // mix(alpha, 1, strength^2); 0: isotropic (alpha in every direction).
  float alpha_t = 0.f;
  bool anisotropic() const { return alpha_t > 0.f; }
  // KHR_materials_iridescence: the weight of the thin film's Fresnel (0: none), its ior and
  // thickness (nm) at this point.
  float iridescence = 0.f;
  float iridescence_ior = 1.3f;
  float iridescence_thickness = 400.f;
  float specular = 0.f;
  Vec3 specular_color{1.f, 1.f, 1.f};  // KHR_materials_specular's colour (scales F0)
  float ior = 1.5f;
  // KHR_materials_dispersion: 20 / the Abbe number (0: none), on transmissive materials; the
  // path tracer sets ior to the index at the path's wavelength (sampling/spectrum.h).
  float dispersion = 0.f;
  float transmission = 0.f;
  // KHR_materials_diffuse_transmission: the share of the diffuse base transmitted (0: none)
  // and the transmitted light's colour.
  float diffuse_transmission = 0.f;
  Vec3 diffuse_transmission_color{1.f, 1.f, 1.f};
  bool front = true;  // wo on the front side of the geometric normal (outside the glass)
  // KHR_materials_clearcoat: the coat's weight (0: none), GGX alpha and normal (a unit vector
  // in the local shading frame, on the side of wo).
  float clearcoat = 0.f;
  float clearcoat_alpha = kMinAlpha;
  Vec3 clearcoat_n{0.f, 0.f, 1.f};
  // KHR_materials_sheen: sheen colour (0: none) and Charlie alpha (sheenRoughness^2).
  Vec3 sheen{0.f, 0.f, 0.f};
  float sheen_alpha = kMinSheenAlpha;
  bool layered() const { return clearcoat > 0.f || !is_zero(sheen); }
};

// The lobe a BSDF sample came from: the evaluated lobes (the mixture bsdf_eval_pdf evaluates
// and bsdf_pdf is the density of), or one of the sampled-only lobes, the glass lobe (smooth
// or rough; reflected or transmitted) and the diffuse BTDF. The `lobes` rows share out what a
// path brings by it (render/packet_tracer.h, PathLobes).
enum class SampledLobe : uint8_t { Evaluated, Glass, DiffuseBtdf };

struct BsdfSample {
  Vec3 wi;             // local frame
  Vec3 weight;         // f cos / pdf (for delta lobes: the lobe's reflectance / probability)
  float pdf = 0.f;     // solid-angle density of wi among the non-delta lobes; 0 if delta
  bool delta = false;  // chosen from the glass (specular) lobe
  bool transmitted = false;
  SampledLobe lobe = SampledLobe::Evaluated;
  // eta^2 of a refraction through the glass lobe (eta the ratio of the indices in the
  // direction of travel), whose weight scales radiance by 1 / eta2; 1 for every other sample.
  float eta2 = 1.f;
};

// The layers (glTF extension texts, implementation sections), on the base f_base below:
//   f = (1 - c F_c(wo)) (f_sheen + f_base s) + c F_c(wo) f_coat,
//   F_c(wo) = 0.04 + 0.96 (1 - |wo . n_c|)^5 (KHR_materials_clearcoat: Schlick at ior 1.5 on
//   the coat normal's N.V, so the coated material is not reciprocal unless wo . n_c = wi . n_c),
//   f_coat = D(alpha_c) G2 / (4 |wo . n_c| |wi . n_c|) on the coat normal, times wi . n_c in
//   the cosine-weighted value eval returns (the base and sheen lobes take wi.z),
//   f_sheen = sheenColor D_charlie V_charlie / max(1, E(wo.z), E(wi.z)) (KHR_materials_sheen,
//   Conty and Kulla 2017; E the lobe's directional albedo, sheen_albedo: the spec's lobe where
//   E <= 1, scaled down where it would reflect more than it receives, at grazing angles for
//   sheen roughness below about 0.3),
//   s = min(1 - max3(sheenColor) E'(wo.z), 1 - max3(sheenColor) E'(wi.z)), E' = min(1, E)
//   (the extension's reciprocal albedo scaling).
// The delta glass lobe is weighted (1 - c F_c(wo)) (1 - max3(sheenColor) E(wo.z)).
// Sampling picks the coat, the sheen (cosine-weighted) or the base by estimates of their
// albedos at wo (BsdfLobes::coat, ::sheen), and the pdf of a direction is the mixture of the
// three lobes' densities (one-sample MIS with the balance heuristic).
//
// Lambert + GGX as in the glTF spec (Appendix B): with F_d the dielectric Schlick Fresnel
// (f0 = specular * ((ior - 1)/(ior + 1))^2) and F_m the conductor Schlick Fresnel (f0 = base),
//   f = (1 - m)(1 - t)((1 - F_d) base / pi + F_d spec) + m (F_m spec + f_ms),
//   spec = D G2 / (4 |cos_o cos_i|),
// and with KHR_materials_diffuse_transmission (d = diffuseTransmission, C =
// diffuseTransmissionColor) the diffuse term becomes the extension's mix of a Lambert BRDF and
// a Lambert BTDF under the same Fresnel weight:
//   (1 - F_d) ((1 - d) base / pi  for wi above the surface,  d C / pi  for wi below),
// with F_d below at the half vector of wo and wi mirrored to the upper side, (wi.x, wi.y,
// -wi.z) (the extension leaves the BTDF's Fresnel angle open; this choice keeps the lobe
// reciprocal and makes d = 1 with C = base transmit exactly what d = 0 reflects). The BTDF
// is sampled (cosine-weighted below the surface), never evaluated, as the rough glass lobe
// below; punctual lights reach it through through_eval_cos.
// where (1 - m) t is the weight of the glass lobe (smooth: a delta, reflection with the exact
// dielectric Fresnel F(wo.n) and refraction tinted by the base colour; rough, alpha above
// kMinAlpha: KHR_materials_transmission's microfacet BTDF with the reflection it pairs with,
// F(wo.m) D G2 / (4 |cos_o cos_i|) and base (1 - F(wo.m)) D G2 |wi.m| |wo.m| /
// (|cos_o cos_i| (wo.m + eta wi.m)^2) / eta^2 (Walter et al. 2007, radiance scaled by
// 1/eta^2); sampled through visible normals with weight G2 / G1, never evaluated: like the
// smooth lobe it is reached by BSDF sampling only, so light sampling and MIS leave it out and
// the estimate stays unbiased) and f_ms the metal's multiple-
// scattering compensation (Kulla & Conty 2017), which makes a white rough metal conserve
// energy exactly (up to its table). eval returns f times |cos_i| for the non-delta part only
// (0 if wo or wi is below the surface).
// Lobe selection probabilities, a function of (params, wo) only; the path tracer computes them
// once per vertex and passes them to the overloads below (the same values as without them).
// With them come the wo-dependent terms of the evaluation, so that evaluating several
// directions at one vertex (light sample, BSDF sample) computes them once.
struct BsdfLobes {
  // Probability of the sampled-only lobes: the glass lobe ((1 - metallic) transmission) and
  // after it the diffuse BTDF (diffuse_bt of it).
  float glass = 0.f;
  float diffuse_bt = 0.f;
  float spec = 0.f;   // probability of GGX among the non-delta lobes
  float wd = 0.f;     // (1 - metallic)(1 - transmission): weight of the dielectric base
  // Dielectric Fresnel at normal incidence per channel, specular x min(1, specularColor x
  // ((ior-1)/(ior+1))^2) (KHR_materials_specular).
  Vec3 f0d{0.f, 0.f, 0.f};
  float root_o = 0.f;  // sqrt(cos_o^2 + alpha^2 (1 - cos_o^2)) = 2 cos_o (Lambda(wo) + 1/2)
  float pdf_k = 0.f;   // 1 / (2 (cos_o + root_o)) = G1(wo) / (4 cos_o): GGX pdf = D pdf_k
  Vec3 ms;             // metal multiple scattering without its (1 - E(mu_i)) factor (0 if
                       // not metallic)
  // Layered materials only (BsdfParams::layered): the probabilities of picking the coat and
  // the sheen lobe (the base gets the rest, base_pick; glass and spec above are then the
  // base's own choices), c F_c(wo), max3(sheenColor) min(1, E(wo.z)) and max(1, E(wo.z)).
  bool layered = false;
  // An anisotropic GGX lobe (BsdfParams::alpha_t), a thin film's Fresnel (iridescence) or a
  // diffuse BTDF: evaluated by the general formulas, not the isotropic rearrangement
  // (root_o, pdf_k are unused).
  bool general = false;
  float coat = 0.f, sheen = 0.f, base_pick = 1.f;
  float coat_f = 0.f, sheen_e = 0.f, sheen_norm = 1.f;
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
// bsdf_sample in two halves, for callers that evaluate many BSDFs together (BsdfEvalBatch):
// bsdf_sample_direction chooses the lobe and the direction. It returns Failed (no direction:
// the path ends), Done (the glass lobe: *out is complete) or NeedsEval: out->wi is set to
// the direction before normalization (with z > 0), and bsdf_sample_finish(f, pdf, out) with
// (f, pdf) = bsdf_eval_pdf(p, lobes, wo, normalize(out->wi)) completes *out (false: the path
// ends) but for out->wi, which the caller sets to normalize(out->wi). Together they give
// bsdf_sample's result exactly.
enum class BsdfSampleStep { Failed, Done, NeedsEval };
// The direction pair u enters as its warps, disks = bsdf_disks(u).
BsdfSampleStep bsdf_sample_direction(const BsdfParams& p, const BsdfLobes& lobes, Vec3 wo,
                                     const BsdfDisks& disks, float u_lobe, float u_fresnel,
                                     BsdfSample* out);
bool bsdf_sample_finish(Vec3 f, float pdf, BsdfSample* out);

// The bsdf_eval_pdf evaluations of up to kLanes vertices (a packet's paths), two directions
// each (a light sample and a BSDF sample), computed together with bit for bit the same
// results. One evaluation is a chain of two square roots and two divisions that waits on
// itself; here the inputs are stored as one array per quantity, so that the arithmetic runs
// in 4-wide SIMD lanes over independent evaluations, every operation in the scalar function's
// order (IEEE arithmetic then rounds each lane exactly as the scalar code does). A vertex's
// parameters are stored once for both of its directions.
class BsdfEvalBatch {
 public:
  static constexpr int kLanes = 16;
  // Slot `lane` is the vertex's first direction, slot kLanes + lane its second.
  static constexpr int kSlots = 2 * kLanes;
  // Forgets the queued evaluations.
  void clear() {
    used_ = 0;
    layered_ = 0;
  }
  // The vertex of `lane`: its BSDF, lobes (bsdf_lobes(p, wo)), wo and shading frame, for the
  // directions queued for it until the next clear.
  void set_vertex(int lane, const BsdfParams& p, const BsdfLobes& lobes, Vec3 wo,
                  const Frame& frame) {
    const Vec3* axes[3] = {&frame.s, &frame.t, &frame.n};
    for (int a = 0; a < 3; ++a) {
      frame_[a][0][lane] = axes[a]->x;
      frame_[a][1][lane] = axes[a]->y;
      frame_[a][2][lane] = axes[a]->z;
    }
    wo_[0][lane] = wo.x;
    wo_[1][lane] = wo.y;
    wo_[2][lane] = wo.z;
    base_[0][lane] = p.base.x;
    base_[1][lane] = p.base.y;
    base_[2][lane] = p.base.z;
    ms_[0][lane] = lobes.ms.x;
    ms_[1][lane] = lobes.ms.y;
    ms_[2][lane] = lobes.ms.z;
    metallic_[lane] = p.metallic;
    alpha_[lane] = p.alpha;
    specular_[lane] = p.specular;
    f0d_[0][lane] = lobes.f0d.x;
    f0d_[1][lane] = lobes.f0d.y;
    f0d_[2][lane] = lobes.f0d.z;
    wd_[lane] = lobes.wd;
    glass_[lane] = lobes.glass;
    spec_[lane] = lobes.spec;
    root_o_[lane] = lobes.root_o;
    pdf_k_[lane] = lobes.pdf_k;
    // A layered or anisotropic BSDF is evaluated by bsdf_eval_pdf itself after the SIMD
    // blocks.
    const uint32_t bit = uint32_t(1) << lane;
    if (lobes.layered || lobes.general) {
      layered_ |= bit;
      new (&layered_storage_[lane]) LayeredVertex{p, lobes, wo};
    } else {
      layered_ &= ~bit;
    }
  }
  // Queues bsdf_eval_pdf(p, lobes, wo, wi) for lane's vertex as its first direction (a light
  // sample) and returns its slot.
  int add_light(int lane, Vec3 wi) { return add(lane, lane, wi); }
  // Queues the second direction, a sampled one not yet normalized (bsdf_sample_direction's
  // NeedsEval): evaluate normalizes it, evaluates bsdf_eval_pdf(p, lobes, wo, normalize(wi))
  // and computes the world-space direction normalize(frame.to_world(normalize(wi))), which
  // world() returns.
  int add_sampled(int lane, Vec3 wi) { return add(lane, kLanes + lane, wi); }
  // add_light for each lane in the bit mask `lanes`, with the direction given in world space
  // (w[c][lane], c = x, y, z): the queued direction is frame.to_local of it, computed four
  // lanes at a time.
  void add_lights_world(uint32_t lanes, const float (*w)[kLanes]);
  // Evaluates the queued slots; f, pdf and world read their results until the next clear.
  void evaluate();
  // The first directions' results as arrays over the lanes, for reading four at a time.
  const float* light_f(int channel) const { return f_[channel]; }
  const float* light_pdf() const { return pdf_; }
  Vec3 f(int slot) const { return {f_[0][slot], f_[1][slot], f_[2][slot]}; }
  float pdf(int slot) const { return pdf_[slot]; }
  Vec3 world(int slot) const {
    return {world_[0][slot - kLanes], world_[1][slot - kLanes], world_[2][slot - kLanes]};
  }

 private:
  int add(int lane, int slot, Vec3 wi) {
    wi_[0][slot] = wi.x;
    wi_[1][slot] = wi.y;
    wi_[2][slot] = wi.z;
    // The metal term's table lookup is a gather: done here, as bsdf_eval_pdf does it (on the
    // normalized direction: a sampled one is normalized here for it, rarely).
    ms_factor_[slot] = 0.f;
    if (metallic_[lane] > 0.f && wo_[2][lane] > 0.f && wi.z > 0.f)
      ms_factor_[slot] =
          metal_ms_factor(slot >= kLanes ? normalize(wi).z : wi.z, alpha_[lane]);
    used_ |= uint32_t(1) << slot;
    return slot;
  }
  static float metal_ms_factor(float cos_i, float alpha);  // 1 - E(cos_i, alpha)
  void evaluate_block(int first);  // slots first .. first + 3
  uint32_t used_ = 0;              // bit s: slot s queued
  struct LayeredVertex {
    BsdfParams p;
    BsdfLobes lobes;
    Vec3 wo;
  };
  uint32_t layered_ = 0;  // bit lane: its vertex is layered (set_vertex)
  // Storage for the layered vertices, written by set_vertex only for them (never initialized
  // as a whole: the batch is made once per packet and most scenes have no layered material).
  struct alignas(LayeredVertex) LayeredSlot {
    unsigned char bytes[sizeof(LayeredVertex)];
  };
  LayeredSlot layered_storage_[kLanes];
  const LayeredVertex& layered_vertex(int lane) const {
    return *std::launder(reinterpret_cast<const LayeredVertex*>(&layered_storage_[lane]));
  }
  // Vertex inputs by lane and direction inputs by slot. Slots not queued hold zeros or earlier
  // inputs (a dropped light sample's may be NaN): they are computed along and never read.
  alignas(64) float wo_[3][kLanes] = {}, base_[3][kLanes] = {}, ms_[3][kLanes] = {};
  alignas(64) float metallic_[kLanes] = {}, alpha_[kLanes] = {}, specular_[kLanes] = {};
  alignas(64) float f0d_[3][kLanes] = {}, wd_[kLanes] = {}, glass_[kLanes] = {};
  alignas(64) float spec_[kLanes] = {}, root_o_[kLanes] = {}, pdf_k_[kLanes] = {};
  alignas(64) float frame_[3][3][kLanes] = {};  // axis (s, t, n), component, lane
  alignas(64) float wi_[3][kSlots] = {}, ms_factor_[kSlots] = {};
  // Results.
  alignas(64) float f_[3][kSlots] = {}, pdf_[kSlots] = {}, world_[3][kLanes] = {};
};

// The categories of lobes the `lobes` rows split the radiance by (Cycles' passes): diffuse
// (the Lambert base, the diffuse BTDF, the sheen), glossy (the dielectric and metal GGX with
// the metal's multiple scattering and the thin film, the clear coat, the glass's reflection)
// and transmission (the glass's refraction).
enum LobeCategory : int { kDiffuseLobes = 0, kGlossyLobes = 1, kTransmissionLobes = 2 };
constexpr int kLobeCategories = 3;

// bsdf_eval_pdf's f |cos_i| (the evaluated lobes) split by category into out[kDiffuseLobes],
// out[kGlossyLobes] and out[kTransmissionLobes] (always 0: no evaluated lobe transmits),
// whose sum is bsdf_eval_pdf's value up to rounding: the base's Lambert lobe (weighted by
// 1 - diffuseTransmission) and the sheen are diffuse, its GGX lobes (dielectric and metal,
// the metal's multiple-scattering term, iridescence) and the clear coat glossy, each under the
// layers' weights. Computed by the readable formulas (the general ones of anisotropic GGX),
// for the `lobes` rows only; lobes = bsdf_lobes(p, wo).
void bsdf_eval_lobes(const BsdfParams& p, const BsdfLobes& lobes, Vec3 wo, Vec3 wi,
                     Vec3 out[kLobeCategories]);

// True if the glass lobe is rough (KHR_materials_transmission with roughness): sampled like
// the smooth one, and evaluated for punctual lights (through_eval_cos).
inline bool has_rough_glass(const BsdfParams& p) {
  return (1.f - p.metallic) * p.transmission > 0.f && p.alpha > kMinAlpha;
}

// True if the material has a diffuse BTDF (KHR_materials_diffuse_transmission).
inline bool has_diffuse_btdf(const BsdfParams& p) {
  return (1.f - p.metallic) * (1.f - p.transmission) * p.diffuse_transmission > 0.f;
}

// True if light from behind the surface reaches wo through a lobe that is not a delta: a
// rough glass lobe or a diffuse BTDF. Light selection is then two-sided, and punctual lights
// behind the surface are evaluated with through_eval_cos.
inline bool has_through_lobe(const BsdfParams& p) {
  return has_rough_glass(p) || has_diffuse_btdf(p);
}

// True if next-event estimation is useful: the BSDF has a non-delta component, or a rough
// glass lobe (which punctual lights reach by light sampling only).
inline bool bsdf_has_smooth_part(const BsdfParams& p) {
  return (1.f - (1.f - p.metallic) * p.transmission) > 0.f || p.layered() || has_rough_glass(p);
}

// The sampled-only lobes' f |cos_i| (materials.h's formulas), with their weights and the
// layers' over them ((1 - c F_c(wo)) (1 - max3(sheenColor) E(wo.z))): the rough glass lobe
// (wi above the surface: its reflection; below: its transmission, tinted by the base colour
// and divided by eta^2 for radiance) and the diffuse BTDF (wi below). 0 without either. Light
// sampling adds it to bsdf_eval_cos for punctual lights, which BSDF sampling never reaches;
// other lights reach these lobes through BSDF sampling only, as for smooth glass.
Vec3 through_eval_cos(const BsdfParams& p, Vec3 wo, Vec3 wi);
// through_eval_cos split by category and added to out: the diffuse BTDF's part to
// out[kDiffuseLobes], the rough glass lobe's reflection (wi above) to out[kGlossyLobes] and
// its transmission (wi below) to out[kTransmissionLobes].
void through_eval_lobes(const BsdfParams& p, Vec3 wo, Vec3 wi, Vec3 out[kLobeCategories]);

// KHR_materials_clearcoat's layering Fresnel: 0.04 + (1 - 0.04) (1 - |cos_v|)^5.
float clearcoat_fresnel(float cos_v);
// KHR_materials_sheen's Charlie distribution, (2 + 1/alpha) sin^(1/alpha)(theta_h) / (2 pi),
// of cos_h = N.H, and its visibility 1 / ((1 + L(cos_o) + L(cos_i)) 4 cos_o cos_i) with the
// extension's fitted lambda L.
float sheen_charlie_d(float cos_h, float alpha);
float sheen_charlie_visibility(float cos_o, float cos_i, float alpha);
// Directional albedo of the sheen lobe with sheenColor 1, E(mu, alpha) = the integral of
// D V cos_i over the hemisphere: tabulated at first use by quadrature of that integral over
// (mu, sheen roughness) and interpolated bilinearly.
float sheen_albedo(float mu, float alpha);

// Directional albedo E(mu, alpha) of single-scattering GGX with F = 1 (the table behind the
// metal lobe's multiple-scattering compensation).
float metal_single_scattering_albedo(float mu, float alpha);

// KHR_materials_iridescence's F_iridescence (the extension's implementation notes, after
// Belcour and Barla 2017): the reflectance of a thin film of index film_ior and thickness
// thickness_nm over a base of normal-incidence reflectance base_f0, seen from a medium of
// index outside_ior at cos1 = V.H, per Rec. 709 channel.
Vec3 iridescence_fresnel(float outside_ior, float film_ior, float cos1, float thickness_nm,
                         Vec3 base_f0);

// Unpolarized Fresnel reflectance of a smooth dielectric interface; cos_i > 0 on the side of
// the normal, eta = n_other / n_this (ior when entering from outside).
float fresnel_dielectric(float cos_i, float eta);

}  // namespace rf
