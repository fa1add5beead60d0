// The glTF loader's textures and materials (Loader, gltf_loader_internal.h): textures and the
// images they show (EXT_texture_webp, EXT_texture_avif, KHR_texture_basisu's fallback), texture
// slots with KHR_texture_transform, the metallic-roughness material and every material
// extension the renderer reads (transmission, diffuse transmission, ior, dispersion, volume,
// specular, emissive strength, anisotropy, iridescence, pbrSpecularGlossiness, clearcoat,
// sheen, unlit), the checks of [0, 1] factors, and KHR_materials_variants.
#include "scene/gltf_loader_internal.h"

#include <algorithm>
#include <cmath>
#include <iomanip>
#include <limits>
#include <sstream>
#include <string>
#include <vector>

namespace rf::gltf_detail {

// glTF textures -> TextureSource list (one per glTF texture, same indices).
void Loader::load_textures(SceneDescription* desc) {
  auto wrap = [](int mode) {
    if (mode == TINYGLTF_TEXTURE_WRAP_CLAMP_TO_EDGE) return TextureWrap::Clamp;
    if (mode == TINYGLTF_TEXTURE_WRAP_MIRRORED_REPEAT) return TextureWrap::Mirror;
    return TextureWrap::Repeat;
  };
  for (size_t i = 0; i < model_.textures.size(); ++i) {
    const tinygltf::Texture& gt = model_.textures[i];
    TextureSource src;
    src.name = "textures[" + std::to_string(i) + "]" + named(gt.name);
    const int image = texture_image(gt, i);
    if (gt.sampler >= 0 && gt.sampler < int(model_.samplers.size())) {
      src.wrap_s = wrap(model_.samplers[size_t(gt.sampler)].wrapS);
      src.wrap_t = wrap(model_.samplers[size_t(gt.sampler)].wrapT);
      // glTF 3.8.4: magFilter NEAREST or LINEAR (bilinear, also when undefined). The
      // minification filter is the pixel integral itself: samples spread over the pixel
      // average the texels it covers, which a MIP level would blur beyond it.
      src.nearest =
          model_.samplers[size_t(gt.sampler)].magFilter == TINYGLTF_TEXTURE_FILTER_NEAREST;
    }
    if (image < 0 || image >= int(model_.images.size())) {
      warn(src.name + ": missing image; texture ignored");
      src.path.clear();
    } else {
      const tinygltf::Image& img = model_.images[size_t(image)];
      src.bytes = img.image;
      src.mime_type = img.mimeType;
      if (src.bytes.empty()) {
        warn(src.name + ": image " + std::to_string(image) +
             " could not be loaded (uri '" + img.uri + "'); texture ignored");
      }
    }
    desc->textures.push_back(std::move(src));
  }
}

// The image a texture shows (an index into images, -1: none). EXT_texture_webp and
// EXT_texture_avif name their image in the extension's `source`, which replaces the
// texture's own (OpenImageIO decodes both: libwebp, and libheif for AV1). KHR_texture_basisu
// has no decoder here (docs/scenes.md says what was searched): the texture's own `source` is
// the fallback the extension text provides for viewers without it, and a texture without
// one is refused with its path, since it cannot be rendered as its author meant.
int Loader::texture_image(const tinygltf::Texture& gt, size_t i) {
  const std::string at = "textures[" + std::to_string(i) + "]";
  for (const char* name : {"EXT_texture_webp", "EXT_texture_avif"}) {
    auto it = gt.extensions.find(name);
    if (it == gt.extensions.end()) continue;
    const std::string where = at + ".extensions." + name + ".source";
    if (!it->second.Has("source") || !it->second.Get("source").IsNumber())
      fail(where + named(gt.name) + ": must be an image index");
    const int source = it->second.Get("source").GetNumberAsInt();
    if (source < 0 || source >= int(model_.images.size()))
      fail(where + named(gt.name) + ": refers to missing image " + std::to_string(source));
    return source;
  }
  for (const auto& ext : gt.extensions) {
    if (ext.first == "KHR_texture_basisu") {
      if (gt.source < 0)
        fail(at + ".extensions.KHR_texture_basisu" + named(gt.name) +
             ": a KTX2/Basis Universal image without a fallback 'source'; this renderer "
             "has no Basis Universal decoder (re-export the texture as PNG, JPEG or WebP)");
      if (warned_texture_ext_.insert(ext.first).second)
        warn(at + named(gt.name) + " (and possibly others): KHR_texture_basisu is not "
                  "decoded; using the texture's fallback 'source' image");
    } else if (warned_texture_ext_.insert(ext.first).second) {
      warn(at + named(gt.name) + ": extension '" + ext.first +
           "' is not supported; using 'source'");
    }
  }
  return gt.source;
}

// KHR_materials_volume: the medium inside the mesh. Its thickness (factor and texture) is
// for renderers that cannot measure the path inside; a path tracer has the real length, so
// only thicknessFactor > 0 (not thin-walled) is read from it.
void Loader::load_volume(const tinygltf::Value& ext, const std::string& where,
                         const std::string& name, Material* m) const {
  const float thickness = number_or(ext, "thicknessFactor", 0.f);
  if (!(thickness >= 0.f)) fail(where + ".thicknessFactor" + name + ": must be >= 0");
  float distance = std::numeric_limits<float>::infinity();
  if (ext.Has("attenuationDistance")) {
    distance = number_or(ext, "attenuationDistance", -1.f);
    if (!(distance > 0.f))
      fail(where + ".attenuationDistance" + name + ": must be a number > 0");
  }
  Vec3 color{1.f, 1.f, 1.f};
  if (ext.Has("attenuationColor")) {
    const tinygltf::Value& c = ext.Get("attenuationColor");
    if (!c.IsArray() || c.ArrayLen() != 3)
      fail(where + ".attenuationColor" + name + ": must be an array of 3 numbers");
    for (int k = 0; k < 3; ++k) {
      const tinygltf::Value& v = c.Get(k);
      color[k] = v.IsNumber() ? float(v.GetNumberAsDouble()) : -1.f;
      if (!(color[k] >= 0.f && color[k] <= 1.f))
        fail(where + ".attenuationColor" + name + ": must be 3 numbers in [0, 1]");
    }
  }
  if (thickness == 0.f || std::isinf(distance)) return;  // thin-walled, or clear
  for (int k = 0; k < 3; ++k)
    // A colour of 0 absorbs everything: a coefficient large enough that any length inside
    // gives 0 (exp underflows), without an infinity that 0 lengths would turn into NaN.
    m->absorption[k] = color[k] > 0.f ? -std::log(color[k]) / distance : 1e30f;
}

// A material's texture slot, with KHR_texture_transform.
TextureRef Loader::texture_ref(int index, int texcoord, const tinygltf::ExtensionMap& extensions,
                               const std::string& where) {
  TextureRef ref;
  if (index < 0) return ref;
  if (index >= int(model_.textures.size()))
    fail(where + ": refers to missing texture " + std::to_string(index));
  ref.texture = index;
  ref.texcoord = uint32_t(std::max(0, texcoord));
  auto it = extensions.find("KHR_texture_transform");
  if (it != extensions.end()) {
    const tinygltf::Value& t = it->second;
    if (t.Has("offset") && t.Get("offset").IsArray() && t.Get("offset").ArrayLen() == 2) {
      ref.offset[0] = float(t.Get("offset").Get(0).GetNumberAsDouble());
      ref.offset[1] = float(t.Get("offset").Get(1).GetNumberAsDouble());
    }
    if (t.Has("scale") && t.Get("scale").IsArray() && t.Get("scale").ArrayLen() == 2) {
      ref.scale[0] = float(t.Get("scale").Get(0).GetNumberAsDouble());
      ref.scale[1] = float(t.Get("scale").Get(1).GetNumberAsDouble());
    }
    ref.rotation = number_or(t, "rotation", 0.f);
    if (t.Has("texCoord") && t.Get("texCoord").IsNumber())
      ref.texcoord = uint32_t(std::max(0, t.Get("texCoord").GetNumberAsInt()));
  }
  // The TriangleMesh::uv array of the set: sets 0 and 1 are arrays 0 and 1, the others get
  // arrays from 2 up in the order materials first read them (so that a set numbered in the
  // millions costs one array, not millions).
  if (ref.texcoord >= 2)
    ref.texcoord =
        uv_array_of_set_.try_emplace(ref.texcoord, uint32_t(2 + uv_array_of_set_.size()))
            .first->second;
  return ref;
}

// A textureInfo (or normalTextureInfo) object inside a material extension: index, texCoord and
// its own KHR_texture_transform, as texture_ref reads them from tinygltf's parsed slots.
TextureRef Loader::texture_ref(const tinygltf::Value& ext, const char* key,
                               const std::string& where, float* scale) {
  if (!ext.Has(key)) return TextureRef{};
  const tinygltf::Value& info = ext.Get(key);
  const std::string at = where + "." + key;
  if (!info.IsObject() || !info.Has("index") || !info.Get("index").IsNumber())
    fail(at + ": a texture reference needs a numeric index");
  const int index = info.Get("index").GetNumberAsInt();
  if (index < 0) fail(at + ": index " + std::to_string(index) + " is negative");
  int texcoord = 0;
  if (info.Has("texCoord")) {
    if (!info.Get("texCoord").IsNumber()) fail(at + ".texCoord is not a number");
    texcoord = info.Get("texCoord").GetNumberAsInt();
  }
  if (scale) *scale = number_or(info, "scale", 1.f);
  tinygltf::ExtensionMap extensions;
  if (info.Has("extensions") && info.Get("extensions").IsObject()) {
    const tinygltf::Value& e = info.Get("extensions");
    for (const std::string& k : e.Keys()) extensions[k] = e.Get(k);
  }
  return texture_ref(index, texcoord, extensions, at);
}

// A factor the spec bounds to [0, 1], at glTF path `field`. Exporters write values a
// rounding error outside (a baseColorFactor of 1.0000001, or 1.004 after a colour-space
// round trip): within kFactorSlack of the range the author's intent is clear, and the value
// is clamped with a warning naming the field; anything further out, or not finite, is
// refused.
float Loader::unit_number(double x, const std::string& field, const std::string& name) {
  if (x >= 0.0 && x <= 1.0) return float(x);
  if (x >= -kFactorSlack && x <= 1.0 + kFactorSlack) {
    const double c = std::min(1.0, std::max(0.0, x));
    std::ostringstream msg;
    msg << field << named(name) << ": " << std::setprecision(9) << x
        << " is outside [0, 1]; clamped to " << c;
    warn(msg.str());
    return float(c);
  }
  std::ostringstream msg;
  msg << field << named(name) << ": must be a number in [0, 1], not " << std::setprecision(9)
      << x;
  fail(msg.str());
}

// A number in [0, 1] of a material extension (fallback when absent).
float Loader::unit_factor(const tinygltf::Value& ext, const char* key, float fallback,
                          const std::string& where) {
  if (!ext.Has(key)) return fallback;
  const tinygltf::Value& v = ext.Get(key);
  if (!v.IsNumber()) fail(where + "." + key + " must be a number in [0, 1]");
  return unit_number(v.GetNumberAsDouble(), where + "." + key, "");
}

// An RGB colour of numbers in [0, 1] of a material extension (fallback when absent).
Vec3 Loader::unit_color(const tinygltf::Value& ext, const char* key, Vec3 fallback,
                        const std::string& where) {
  if (!ext.Has(key)) return fallback;
  const tinygltf::Value& v = ext.Get(key);
  if (!v.IsArray() || v.ArrayLen() != 3)
    fail(where + "." + key + " must be an array of 3 numbers in [0, 1]");
  Vec3 c;
  for (int k = 0; k < 3; ++k) {
    const std::string at = where + "." + key + "[" + std::to_string(k) + "]";
    if (!v.Get(k).IsNumber()) fail(at + " must be a number in [0, 1]");
    c[k] = unit_number(v.Get(k).GetNumberAsDouble(), at, "");
  }
  return c;
}

// KHR_materials_pbrSpecularGlossiness (archived, still in older assets): it replaces the
// metallic-roughness parameters ("a client that supports the extension should always render
// the asset using the specular-glossiness material properties"). The factors are stored as
// given and turned into BRDF inputs at shading (shading.cpp, specular_glossiness).
void Loader::load_specular_glossiness(const tinygltf::Value& ext, size_t i, const std::string& name,
                                      Material* m) {
  const std::string where =
      "materials[" + std::to_string(i) + "].extensions.KHR_materials_pbrSpecularGlossiness";
  auto numbers = [&](const char* key, size_t n, float* out) {
    if (!ext.Has(key)) return;
    const tinygltf::Value& v = ext.Get(key);
    if (!v.IsArray() || v.ArrayLen() != n)
      fail(where + "." + key + named(name) + ": must be an array of " + std::to_string(n) +
           " numbers");
    for (size_t k = 0; k < n; ++k) {
      const tinygltf::Value& x = v.Get(int(k));
      if (!x.IsNumber()) fail(where + "." + key + named(name) + ": must hold numbers");
      out[k] = unit_number(x.GetNumberAsDouble(),
                           where + "." + key + "[" + std::to_string(k) + "]", name);
    }
  };
  float diffuse[4] = {1.f, 1.f, 1.f, 1.f}, specular[3] = {1.f, 1.f, 1.f};
  numbers("diffuseFactor", 4, diffuse);
  numbers("specularFactor", 3, specular);
  m->specular_glossiness = true;
  m->albedo = Vec3(diffuse[0], diffuse[1], diffuse[2]);
  m->alpha = diffuse[3];
  m->specular_color = Vec3(specular[0], specular[1], specular[2]);
  m->glossiness = unit_factor(ext, "glossinessFactor", 1.f, where);
  m->metallic = 0.f;
  m->roughness = 1.f - m->glossiness;
  m->specular = 1.f;
  m->ior = 1.5f;
  m->metallic_roughness_tex = TextureRef{};
  m->specular_tex = TextureRef{};
  m->base_color_tex = texture_ref(ext, "diffuseTexture", where);
  m->specular_color_tex = texture_ref(ext, "specularGlossinessTexture", where);
}

// KHR_materials_clearcoat, KHR_materials_sheen and KHR_materials_unlit of material i.
void Loader::load_layers(const tinygltf::Material& gm, size_t i, Material* m) {
  const std::string base = "materials[" + std::to_string(i) + "].extensions.";
  auto unlit = gm.extensions.find("KHR_materials_unlit");
  if (unlit != gm.extensions.end()) {
    // Shadeless: the base colour term alone (the extension text); the other properties
    // are a fallback for viewers without the extension.
    m->unlit = true;
    m->emission = Vec3(0.f, 0.f, 0.f);
    m->emissive_tex = TextureRef{};
    if (gm.extensions.count("KHR_materials_clearcoat") ||
        gm.extensions.count("KHR_materials_sheen"))
      warn("materials[" + std::to_string(i) + "]" + named(gm.name) +
           ": KHR_materials_unlit excludes clearcoat and sheen; the material is unlit");
    return;
  }
  auto cc = gm.extensions.find("KHR_materials_clearcoat");
  if (cc != gm.extensions.end()) {
    const tinygltf::Value& e = cc->second;
    const std::string where = base + "KHR_materials_clearcoat";
    m->clearcoat = unit_factor(e, "clearcoatFactor", 0.f, where);
    m->clearcoat_roughness = unit_factor(e, "clearcoatRoughnessFactor", 0.f, where);
    m->clearcoat_tex = texture_ref(e, "clearcoatTexture", where);
    m->clearcoat_roughness_tex = texture_ref(e, "clearcoatRoughnessTexture", where);
    m->clearcoat_normal_tex =
        texture_ref(e, "clearcoatNormalTexture", where, &m->clearcoat_normal_scale);
    if (m->normal_tex.valid() && m->clearcoat_normal_tex.valid() &&
        m->normal_tex.texcoord != m->clearcoat_normal_tex.texcoord)
      warn(where + named(gm.name) +
           ": clearcoatNormalTexture uses another TEXCOORD set than normalTexture; its "
           "tangents are those of normalTexture's set");
  }
  auto sh = gm.extensions.find("KHR_materials_sheen");
  if (sh != gm.extensions.end()) {
    const tinygltf::Value& e = sh->second;
    const std::string where = base + "KHR_materials_sheen";
    if (e.Has("sheenColorFactor")) {
      const tinygltf::Value& v = e.Get("sheenColorFactor");
      if (!v.IsArray() || v.ArrayLen() != 3)
        fail(where + ".sheenColorFactor must be an array of 3 numbers in [0, 1]");
      for (int k = 0; k < 3; ++k) {
        const float x = v.Get(k).IsNumber() ? float(v.Get(k).GetNumberAsDouble()) : -1.f;
        if (!(x >= 0.f && x <= 1.f))
          fail(where + ".sheenColorFactor must be an array of 3 numbers in [0, 1]");
        m->sheen_color[k] = x;
      }
    }
    m->sheen_roughness = unit_factor(e, "sheenRoughnessFactor", 0.f, where);
    m->sheen_color_tex = texture_ref(e, "sheenColorTexture", where);
    m->sheen_roughness_tex = texture_ref(e, "sheenRoughnessTexture", where);
  }
}

void Loader::load_materials(SceneDescription* desc) {
  for (size_t i = 0; i < model_.materials.size(); ++i) {
    const tinygltf::Material& gm = material_source(i);  // as animated at the load's time
    const std::string where = "materials[" + std::to_string(i) + "]" + named(gm.name);
    Material m;
    m.name = gm.name;
    m.gltf_index = int32_t(i);
    // glTF defaults: metallic = roughness = 1, a dielectric specular layer of ior 1.5.
    const std::string at_pmr = "materials[" + std::to_string(i) + "].pbrMetallicRoughness";
    m.metallic = unit_number(gm.pbrMetallicRoughness.metallicFactor,
                             at_pmr + ".metallicFactor", gm.name);
    m.roughness = unit_number(gm.pbrMetallicRoughness.roughnessFactor,
                              at_pmr + ".roughnessFactor", gm.name);
    m.specular = 1.f;
    for (const auto& e : gm.extensions)
      if (!supported_extensions().count(e.first) && warned_material_ext_.insert(e.first).second)
        warn(where + ": material extension '" + e.first + "' is not supported; ignoring it");
    auto tr = gm.extensions.find("KHR_materials_transmission");
    if (tr != gm.extensions.end()) {
      m.transmission = unit_factor(
          tr->second, "transmissionFactor", 0.f,
          "materials[" + std::to_string(i) + "].extensions.KHR_materials_transmission");
      m.transmission_tex = texture_ref(
          tr->second, "transmissionTexture",
          "materials[" + std::to_string(i) + "].extensions.KHR_materials_transmission");
    }
    if (!(m.transmission >= 0.f && m.transmission <= 1.f))
      fail(where + ": KHR_materials_transmission.transmissionFactor must be in [0, 1]");
    auto dt = gm.extensions.find("KHR_materials_diffuse_transmission");
    if (dt != gm.extensions.end()) {
      const std::string at_dt =
          "materials[" + std::to_string(i) + "].extensions.KHR_materials_diffuse_transmission";
      m.diffuse_transmission = unit_factor(dt->second, "diffuseTransmissionFactor", 0.f, at_dt);
      m.diffuse_transmission_color = unit_color(dt->second, "diffuseTransmissionColorFactor",
                                                Vec3(1.f, 1.f, 1.f), at_dt);
      m.diffuse_transmission_tex = texture_ref(dt->second, "diffuseTransmissionTexture", at_dt);
      m.diffuse_transmission_color_tex =
          texture_ref(dt->second, "diffuseTransmissionColorTexture", at_dt);
    }
    auto io = gm.extensions.find("KHR_materials_ior");
    if (io != gm.extensions.end()) m.ior = number_or(io->second, "ior", 1.5f);
    // The schema's minimum is 1; any larger index renders as given (a very large one is a
    // near-perfect mirror: F0 -> 1).
    if (!(m.ior >= 1.f) || !std::isfinite(m.ior)) {
      warn(where + ": KHR_materials_ior.ior " + std::to_string(m.ior) +
           " is below the extension's minimum of 1; using 1.5");
      m.ior = 1.5f;
    }
    auto disp = gm.extensions.find("KHR_materials_dispersion");
    if (disp != gm.extensions.end() && disp->second.IsObject() &&
        disp->second.Has("dispersion")) {
      // 20 / the Abbe number, any value >= 0 (above 1 exaggerates the effect).
      const tinygltf::Value& v = disp->second.Get("dispersion");
      const double x = v.IsNumber() ? v.GetNumberAsDouble() : -1.0;
      if (!(x >= 0.0) || !std::isfinite(x))
        fail("materials[" + std::to_string(i) +
             "].extensions.KHR_materials_dispersion.dispersion" + named(gm.name) +
             ": must be a finite number >= 0");
      m.dispersion = float(x);
    }
    auto vol = gm.extensions.find("KHR_materials_volume");
    if (vol != gm.extensions.end())
      load_volume(vol->second,
                  "materials[" + std::to_string(i) + "].extensions.KHR_materials_volume",
                  named(gm.name), &m);
    auto sp = gm.extensions.find("KHR_materials_specular");
    if (sp != gm.extensions.end()) {
      const std::string at_sp =
          "materials[" + std::to_string(i) + "].extensions.KHR_materials_specular";
      m.specular = unit_factor(sp->second, "specularFactor", 1.f, at_sp);
      if (sp->second.Has("specularColorFactor")) {
        const tinygltf::Value& c = sp->second.Get("specularColorFactor");
        if (!c.IsArray() || c.ArrayLen() != 3)
          fail(at_sp + ".specularColorFactor" + named(gm.name) +
               ": must be an array of 3 numbers");
        for (int k = 0; k < 3; ++k) {
          const tinygltf::Value& v = c.Get(k);
          // The extension's range is [0, inf): the colour scales F0 = ((ior-1)/(ior+1))^2,
          // which is then clamped to 1.
          m.specular_color[k] = v.IsNumber() ? float(v.GetNumberAsDouble()) : -1.f;
          if (!(m.specular_color[k] >= 0.f) || !std::isfinite(m.specular_color[k]))
            fail(at_sp + ".specularColorFactor" + named(gm.name) +
                 ": must be 3 finite numbers >= 0");
        }
      }
      m.specular_tex = texture_ref(sp->second, "specularTexture", at_sp);
      m.specular_color_tex = texture_ref(sp->second, "specularColorTexture", at_sp);
    }
    const auto& pmr = gm.pbrMetallicRoughness;
    m.base_color_tex = texture_ref(pmr.baseColorTexture.index, pmr.baseColorTexture.texCoord,
                                   pmr.baseColorTexture.extensions, where + " baseColorTexture");
    m.metallic_roughness_tex =
        texture_ref(pmr.metallicRoughnessTexture.index, pmr.metallicRoughnessTexture.texCoord,
                    pmr.metallicRoughnessTexture.extensions, where + " metallicRoughnessTexture");
    m.normal_tex = texture_ref(gm.normalTexture.index, gm.normalTexture.texCoord,
                               gm.normalTexture.extensions, where + " normalTexture");
    m.normal_scale = float(gm.normalTexture.scale);
    m.emissive_tex = texture_ref(gm.emissiveTexture.index, gm.emissiveTexture.texCoord,
                                 gm.emissiveTexture.extensions, where + " emissiveTexture");
    if (gm.occlusionTexture.index >= 0 && !warned_occlusion_) {
      warn(where + " (and possibly others): occlusionTexture is ignored (a path tracer "
                   "computes occlusion)");
      warned_occlusion_ = true;
    }
    const std::string at = "materials[" + std::to_string(i) + "]";
    if (gm.alphaMode == "MASK") {
      m.alpha_mode = AlphaMode::Mask;
    } else if (gm.alphaMode == "BLEND") {
      m.alpha_mode = AlphaMode::Blend;
    } else if (gm.alphaMode != "OPAQUE" && !gm.alphaMode.empty()) {
      fail(at + ".alphaMode" + named(gm.name) + ": '" + gm.alphaMode +
           "' is not OPAQUE, MASK or BLEND");
    }
    m.double_sided = gm.doubleSided;
    m.alpha_cutoff = float(gm.alphaCutoff);
    if (!(gm.alphaCutoff >= 0.0))
      fail(at + ".alphaCutoff" + named(gm.name) + ": " + std::to_string(gm.alphaCutoff) +
           " is negative");
    const auto& base = gm.pbrMetallicRoughness.baseColorFactor;
    for (size_t k = 0; k < std::min<size_t>(4, base.size()); ++k) {
      const float v = unit_number(base[k], at_pmr + ".baseColorFactor[" + std::to_string(k) + "]",
                                  gm.name);
      if (k < 3)
        m.albedo[int(k)] = v;
      else
        m.alpha = v;
    }
    float strength = 1.f;
    auto ext = gm.extensions.find("KHR_materials_emissive_strength");
    if (ext != gm.extensions.end() && ext->second.Has("emissiveStrength")) {
      const tinygltf::Value& v = ext->second.Get("emissiveStrength");
      if (!v.IsNumber())
        fail(where + ": KHR_materials_emissive_strength.emissiveStrength is not a number");
      strength = float(v.GetNumberAsDouble());
    }
    if (gm.emissiveFactor.size() >= 3)
      m.emission = Vec3(float(gm.emissiveFactor[0]), float(gm.emissiveFactor[1]),
                        float(gm.emissiveFactor[2])) *
                   strength;
    for (int k = 0; k < 3; ++k)
      if (!(m.emission[k] >= 0.f) || !std::isfinite(m.emission[k]))
        fail(where + ": emissiveFactor x emissiveStrength must be finite and >= 0");
    auto an = gm.extensions.find("KHR_materials_anisotropy");
    if (an != gm.extensions.end()) {
      const std::string at_an =
          "materials[" + std::to_string(i) + "].extensions.KHR_materials_anisotropy";
      m.anisotropy = unit_factor(an->second, "anisotropyStrength", 0.f, at_an);
      if (an->second.Has("anisotropyRotation")) {
        const tinygltf::Value& r = an->second.Get("anisotropyRotation");
        if (!r.IsNumber() || !std::isfinite(r.GetNumberAsDouble()))
          fail(at_an + ".anisotropyRotation" + named(gm.name) + ": must be a finite number");
        m.anisotropy_rotation = float(r.GetNumberAsDouble());
      }
      m.anisotropy_tex = texture_ref(an->second, "anisotropyTexture", at_an);
    }
    auto ir = gm.extensions.find("KHR_materials_iridescence");
    if (ir != gm.extensions.end()) {
      const std::string at_ir =
          "materials[" + std::to_string(i) + "].extensions.KHR_materials_iridescence";
      m.iridescence = unit_factor(ir->second, "iridescenceFactor", 0.f, at_ir);
      auto positive = [&](const char* key, float fallback, float lowest) {
        if (!ir->second.Has(key)) return fallback;
        const tinygltf::Value& v = ir->second.Get(key);
        const double x = v.IsNumber() ? v.GetNumberAsDouble() : -1.0;
        if (!(x >= lowest) || !std::isfinite(x))
          fail(at_ir + "." + key + named(gm.name) + ": must be a finite number >= " +
               std::to_string(int(lowest)));
        return float(x);
      };
      // The ratified schema's name; drafts (and some exporters) wrote iridescenceIOR.
      m.iridescence_ior = ir->second.Has("iridescenceIor")
                              ? positive("iridescenceIor", 1.3f, 1.f)
                              : positive("iridescenceIOR", 1.3f, 1.f);
      m.iridescence_thickness_min = positive("iridescenceThicknessMinimum", 100.f, 0.f);
      m.iridescence_thickness_max = positive("iridescenceThicknessMaximum", 400.f, 0.f);
      m.iridescence_tex = texture_ref(ir->second, "iridescenceTexture", at_ir);
      m.iridescence_thickness_tex = texture_ref(ir->second, "iridescenceThicknessTexture", at_ir);
    }
    auto sg = gm.extensions.find("KHR_materials_pbrSpecularGlossiness");
    if (sg != gm.extensions.end()) load_specular_glossiness(sg->second, i, gm.name, &m);
    load_layers(gm, i, &m);
    desc->materials.push_back(m);
  }
  default_material_ = uint32_t(desc->materials.size());
  // Primitives without a material: white Lambertian (the glTF default material would be a
  // white metal, which surprises more than it helps).
  Material def;
  def.name = "default";
  desc->materials.push_back(def);
}

// KHR_materials_variants: the variant options_.variant names (an index, or a name of
// extensions.KHR_materials_variants.variants), -1 for the default materials; a variant the
// scene does not have is refused, listing those it has.
int Loader::selected_variant() const {
  const std::vector<std::string> names = variant_names(model_);
  const std::string& v = options_.variant;
  if (v.empty()) return -1;
  if (std::all_of(v.begin(), v.end(), [](char c) { return c >= '0' && c <= '9'; }) &&
      v.size() < 10) {
    const int index = std::stoi(v);
    if (index < int(names.size())) return index;
  }
  for (size_t i = 0; i < names.size(); ++i)
    if (names[i] == v) return int(i);
  std::string known;
  for (size_t i = 0; i < names.size(); ++i)
    known += (i ? ", " : "") + std::to_string(i) + " '" + names[i] + "'";
  fail("extensions.KHR_materials_variants: the scene has no variant '" + v.substr(0, 100) +
       "' (" + (names.empty() ? std::string("it has none") : "its variants: " + known) + ")");
}

std::vector<std::string> Loader::variant_names(const tinygltf::Model& model) {
  std::vector<std::string> names;
  auto ext = model.extensions.find("KHR_materials_variants");
  if (ext == model.extensions.end() || !ext->second.Has("variants")) return names;
  const tinygltf::Value& list = ext->second.Get("variants");
  for (size_t i = 0; list.IsArray() && i < list.ArrayLen(); ++i) {
    const tinygltf::Value& v = list.Get(int(i));
    names.push_back(v.IsObject() && v.Has("name") && v.Get("name").IsString()
                        ? v.Get("name").Get<std::string>()
                        : std::string());
  }
  return names;
}

// The material a primitive's KHR_materials_variants mappings give the selected variant, or
// -1 (the primitive's own material). Mappings that name a missing material or variant are
// refused with their path.
int Loader::variant_material(const tinygltf::Primitive& prim, size_t mesh_index, size_t pi) const {
  auto ext = prim.extensions.find("KHR_materials_variants");
  if (ext == prim.extensions.end()) return -1;
  const std::string where = "meshes[" + std::to_string(mesh_index) + "].primitives[" +
                            std::to_string(pi) + "].extensions.KHR_materials_variants.mappings";
  if (!ext->second.Has("mappings") || !ext->second.Get("mappings").IsArray())
    fail(where + ": must be an array");
  const tinygltf::Value& mappings = ext->second.Get("mappings");
  const size_t variants = variant_names(model_).size();
  int found = -1;
  for (size_t k = 0; k < mappings.ArrayLen(); ++k) {
    const std::string at = where + "[" + std::to_string(k) + "]";
    const tinygltf::Value& m = mappings.Get(int(k));
    if (!m.IsObject() || !m.Has("material") || !m.Get("material").IsNumber() ||
        !m.Has("variants") || !m.Get("variants").IsArray())
      fail(at + ": needs a material index and a variants array");
    const int material = m.Get("material").GetNumberAsInt();
    if (material < 0 || material >= int(model_.materials.size()))
      fail(at + ".material: refers to missing material " + std::to_string(material));
    const tinygltf::Value& list = m.Get("variants");
    for (size_t j = 0; j < list.ArrayLen(); ++j) {
      const int v = list.Get(int(j)).IsNumber() ? list.Get(int(j)).GetNumberAsInt() : -1;
      if (v < 0 || size_t(v) >= variants)
        fail(at + ".variants[" + std::to_string(j) + "]: refers to missing variant " +
             std::to_string(v));
      if (v == variant_ && found < 0) found = material;
    }
  }
  return found;
}

}  // namespace rf::gltf_detail
