#include "render/shading.h"

namespace rf {

namespace {

// Tangent-space normal map (glTF 3.9.3): n = normalize((2c - 1) * (scale, scale, 1)) in the
// frame (T, B, N) of the interpolated normal N, with T the uv tangent made orthogonal to N.
// The interpolated normal where the map cannot be read.
Vec3 normal_mapped(const Scene& scene, const Hit& hit, const TextureRef& ref, float scale) {
  const Vec3 ns = hit.ns;
  float c[4];
  if (!(length(hit.dpdu) > 0.f) ||
      !scene.textures().lookup(ref.texture, texcoord(scene, hit, ref), 3, c))
    return ns;
  const Vec3 tn((2.f * c[0] - 1.f) * scale, (2.f * c[1] - 1.f) * scale, 2.f * c[2] - 1.f);
  Vec3 t = hit.dpdu - ns * dot(ns, hit.dpdu);
  const float tl = length(t);
  if (!(tl > 0.f) || !std::isfinite(tl)) return ns;
  t = t / tl;
  const Vec3 b = cross(ns, t) * hit.tangent_sign;
  const Vec3 n = t * tn.x + b * tn.y + ns * tn.z;
  const float nl = length(n);
  return nl > 0.f && std::isfinite(nl) ? n / nl : ns;
}

// KHR_materials_clearcoat and KHR_materials_sheen parameters at the hit, into sp->params
// (after the shading normal is final: the coat normal is stored in its local frame).
// Out of line: most materials have no layers, and the common path stays small.
__attribute__((noinline)) void add_layers(const Scene& scene, const Hit& hit, Vec3 wo,
                                          ShadingPoint* sp) {
  const Material& mat = scene.materials()[hit.material];
  const TextureSet& tex = scene.textures();
  BsdfParams& bp = sp->params;
  float c[4];
  if (mat.clearcoat > 0.f) {
    float coat = mat.clearcoat, roughness = mat.clearcoat_roughness;
    if (mat.clearcoat_tex.valid() &&
        tex.lookup(mat.clearcoat_tex.texture, texcoord(scene, hit, mat.clearcoat_tex), 3, c))
      coat *= c[0];
    if (mat.clearcoat_roughness_tex.valid() &&
        tex.lookup(mat.clearcoat_roughness_tex.texture,
                   texcoord(scene, hit, mat.clearcoat_roughness_tex), 3, c))
      roughness *= c[1];
    bp.clearcoat = std::min(1.f, std::max(0.f, coat));
    const float r = std::min(1.f, std::max(0.f, roughness));
    bp.clearcoat_alpha = std::max(kMinAlpha, r * r);
    // The coat's normal: its own map, else the interpolated normal (not the base's map), on
    // the side of wo; one that wo sees from below falls back to the shading normal.
    Vec3 nc = mat.clearcoat_normal_tex.valid()
                  ? normal_mapped(scene, hit, mat.clearcoat_normal_tex, mat.clearcoat_normal_scale)
                  : hit.ns;
    if (dot(nc, sp->ng) < 0.f) nc = -nc;
    if (dot(nc, wo) > 1e-4f) {
      const Vec3 local = sp->frame().to_local(nc);
      const float l = length(local);
      if (l > 0.f && std::isfinite(l) && local.z > 0.f) bp.clearcoat_n = local / l;
    }
  }
  if (!is_zero(mat.sheen_color)) {
    Vec3 color = mat.sheen_color;
    float roughness = mat.sheen_roughness;
    if (mat.sheen_color_tex.valid() &&
        tex.lookup(mat.sheen_color_tex.texture, texcoord(scene, hit, mat.sheen_color_tex), 3, c))
      color = color * Vec3(c[0], c[1], c[2]);  // linear: decoded from sRGB before filtering
    if (mat.sheen_roughness_tex.valid() &&
        tex.lookup(mat.sheen_roughness_tex.texture,
                   texcoord(scene, hit, mat.sheen_roughness_tex), 4, c))
      roughness *= c[3];
    for (int k = 0; k < 3; ++k) color[k] = std::min(1.f, std::max(0.f, color[k]));
    bp.sheen = color;
    const float r = std::min(1.f, std::max(0.f, roughness));
    bp.sheen_alpha = std::max(kMinSheenAlpha, r * r);
  }
}

// KHR_materials_anisotropy: the direction (anisotropyRotation applied to the texture's RG, or
// to the tangent) in the hit's tangent frame (TANGENT, else the texture coordinates'), and the
// alpha along it, mix(alpha, 1, strength^2) with strength = anisotropyStrength x texture B.
// Without a tangent frame (no TANGENT and no texture coordinates) the direction is taken
// from an arbitrary frame around the normal.
void anisotropy(const Scene& scene, const Hit& hit, ShadingPoint* sp) {
  const Material& mat = scene.materials()[hit.material];
  float strength = mat.anisotropy;
  float dx = 1.f, dy = 0.f;
  float c[4];
  if (mat.anisotropy_tex.valid() &&
      scene.textures().lookup(mat.anisotropy_tex.texture,
                              texcoord(scene, hit, mat.anisotropy_tex), 3, c)) {
    dx = 2.f * c[0] - 1.f;
    dy = 2.f * c[1] - 1.f;
    const float l = std::sqrt(dx * dx + dy * dy);
    if (l > 0.f) {
      dx /= l;
      dy /= l;
    } else {
      dx = 1.f;
      dy = 0.f;
    }
    strength *= c[2];
  }
  strength = std::min(1.f, std::max(0.f, strength));
  if (!(strength > 0.f)) return;
  const float cr = std::cos(mat.anisotropy_rotation), sr = std::sin(mat.anisotropy_rotation);
  const float rx = cr * dx - sr * dy, ry = sr * dx + cr * dy;  // counter-clockwise
  const Vec3 ns = sp->ns;
  Vec3 t = hit.dpdu - ns * dot(ns, hit.dpdu);
  float tl = length(t);
  float sign = hit.tangent_sign;
  if (!(tl > 0.f) || !std::isfinite(tl)) {
    t = Frame(ns).s;
    tl = 1.f;
    sign = 1.f;
  }
  t = t / tl;
  const Vec3 b = cross(ns, t) * sign;
  const Vec3 dir = t * rx + b * ry;
  const float dl = length(dir);
  if (!(dl > 0.f)) return;
  sp->tangent = dir / dl;
  const float a = sp->params.alpha;
  sp->params.alpha_t = a * (1.f - strength * strength) + strength * strength;
}

// KHR_materials_pbrSpecularGlossiness: the extension's BRDF inputs, c_diff = diffuse (1 -
// max(specular)), F0 = specular, alpha = (1 - glossiness)^2, as a dielectric of ior 1.5 whose
// specular colour gives that F0 (F0 = 0.04 x colour; specular = 1, so f90 = 1). bp->base holds
// the diffuse colour (factor x texture x COLOR_0).
void specular_glossiness(const Scene& scene, const Hit& hit, BsdfParams* bp) {
  const Material& mat = scene.materials()[hit.material];
  Vec3 specular = mat.specular_color;
  float glossiness = mat.glossiness;
  float c[4];
  if (mat.specular_color_tex.valid() &&
      scene.textures().lookup(mat.specular_color_tex.texture,
                              texcoord(scene, hit, mat.specular_color_tex), 4, c)) {
    specular = specular * Vec3(c[0], c[1], c[2]);  // linear: decoded from sRGB
    glossiness *= c[3];                            // linear
  }
  for (int k = 0; k < 3; ++k) specular[k] = std::min(1.f, std::max(0.f, specular[k]));
  const float rough = 1.f - std::min(1.f, std::max(0.f, glossiness));
  bp->metallic = 0.f;
  bp->alpha = std::max(kMinAlpha, rough * rough);
  bp->base = bp->base * (1.f - std::max(specular.x, std::max(specular.y, specular.z)));
  bp->specular = 1.f;
  bp->ior = 1.5f;
  bp->specular_color = specular * (1.f / 0.04f);
}

}  // namespace

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
  bp.specular_color = mat.specular_color;
  bp.ior = mat.ior;
  if (mat.specular_glossiness) {
    specular_glossiness(scene, hit, &bp);
  } else {
    // KHR_materials_specular: specularFactor x specularTexture.a (linear), specularColorFactor
    // x specularColorTexture.rgb (sRGB, decoded before filtering).
    if (mat.specular_tex.valid() && mat.specular > 0.f &&
        tex.lookup(mat.specular_tex.texture, texcoord(scene, hit, mat.specular_tex), 4, c))
      bp.specular = std::min(1.f, std::max(0.f, mat.specular * c[3]));
    if (mat.specular_color_tex.valid() &&
        tex.lookup(mat.specular_color_tex.texture,
                   texcoord(scene, hit, mat.specular_color_tex), 3, c))
      bp.specular_color = mat.specular_color * Vec3(c[0], c[1], c[2]);
  }
  if (mat.iridescence > 0.f) {
    // KHR_materials_iridescence: iridescenceFactor x iridescenceTexture.r; the thickness
    // between minimum and maximum by iridescenceThicknessTexture.g, else the maximum (linear).
    bp.iridescence = mat.iridescence;
    bp.iridescence_ior = mat.iridescence_ior;
    bp.iridescence_thickness = mat.iridescence_thickness_max;
    if (mat.iridescence_tex.valid() &&
        tex.lookup(mat.iridescence_tex.texture, texcoord(scene, hit, mat.iridescence_tex), 3, c))
      bp.iridescence = std::min(1.f, std::max(0.f, mat.iridescence * c[0]));
    if (mat.iridescence_thickness_tex.valid() &&
        tex.lookup(mat.iridescence_thickness_tex.texture,
                   texcoord(scene, hit, mat.iridescence_thickness_tex), 3, c))
      bp.iridescence_thickness =
          mat.iridescence_thickness_min +
          (mat.iridescence_thickness_max - mat.iridescence_thickness_min) * c[1];
  }
  bp.transmission = mat.transmission;
  // KHR_materials_transmission: transmissionFactor x transmissionTexture.r (linear).
  if (mat.transmission_tex.valid() && mat.transmission > 0.f &&
      tex.lookup(mat.transmission_tex.texture, texcoord(scene, hit, mat.transmission_tex), 3, c))
    bp.transmission = std::min(1.f, std::max(0.f, mat.transmission * c[0]));
  // KHR_materials_dispersion where light goes through: the path tracer picks the wavelength.
  if (mat.dispersion > 0.f && bp.transmission > 0.f && bp.metallic < 1.f)
    bp.dispersion = mat.dispersion;
  if (mat.diffuse_transmission > 0.f) {
    // KHR_materials_diffuse_transmission: diffuseTransmissionFactor x
    // diffuseTransmissionTexture.a (linear), diffuseTransmissionColorFactor x
    // diffuseTransmissionColorTexture.rgb (sRGB, decoded before filtering).
    bp.diffuse_transmission = mat.diffuse_transmission;
    bp.diffuse_transmission_color = mat.diffuse_transmission_color;
    if (mat.diffuse_transmission_tex.valid() &&
        tex.lookup(mat.diffuse_transmission_tex.texture,
                   texcoord(scene, hit, mat.diffuse_transmission_tex), 4, c))
      bp.diffuse_transmission = std::min(1.f, std::max(0.f, mat.diffuse_transmission * c[3]));
    if (mat.diffuse_transmission_color_tex.valid() &&
        tex.lookup(mat.diffuse_transmission_color_tex.texture,
                   texcoord(scene, hit, mat.diffuse_transmission_color_tex), 3, c))
      bp.diffuse_transmission_color = mat.diffuse_transmission_color * Vec3(c[0], c[1], c[2]);
  }
  sp.albedo = bp.base;

  Vec3 ns = hit.ns;
  if (mat.normal_tex.valid()) ns = normal_mapped(scene, hit, mat.normal_tex, mat.normal_scale);
  bp.front = dot(hit.ng, wo) >= 0.f;
  sp.ng = bp.front ? hit.ng : -hit.ng;
  sp.ns = dot(ns, sp.ng) >= 0.f ? ns : -ns;
  // A shading normal that puts wo below its hemisphere cannot be used (the BSDF would see
  // wo.z <= 0 and the path would end black): fall back to the geometric normal.
  if (dot(sp.ns, wo) <= 1e-4f) sp.ns = sp.ng;
  if (mat.anisotropy > 0.f) anisotropy(scene, hit, &sp);
  // The layers are on the outside of a transmissive material: a ray inside meets none.
  if (bp.front || (1.f - bp.metallic) * bp.transmission <= 0.f) add_layers(scene, hit, wo, &sp);
  sp.p = hit.p;
  sp.eps = ray_epsilon(hit.p);
  return sp;
}

}  // namespace rf
