// glTF 2.0 -> SceneDescription via tinygltf. Every index read from the file is range-checked
// before use, so a malformed file produces a SceneError naming the offending part, never a
// crash.
#include <tiny_gltf.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <cctype>
#include <cstring>
#include <filesystem>
#include <iterator>
#include <limits>
#include <optional>
#include <fstream>
#include <functional>
#include <iomanip>
#include <map>
#include <set>
#include <sstream>

#include "scene/animation.h"
#include "scene/gltf_compression.h"
#include "scene/scene.h"

namespace rf {

struct GltfDocument {
  tinygltf::Model model;
  std::string source;  // the name messages use
};

namespace {

// Images are decoded by OpenImageIO later (TextureSystem), not by tinygltf: keep the encoded
// bytes tinygltf hands us (from a data: URI, a file next to the .gltf or a GLB buffer view).
bool keep_encoded_image(tinygltf::Image* image, const int, std::string*, std::string*, int,
                        int, const unsigned char* bytes, int size, void*) {
  if (bytes && size > 0) image->image.assign(bytes, bytes + size);
  image->as_is = true;
  return true;
}

// Extensions the renderer implements.
const std::set<std::string>& supported_extensions() {
  static const std::set<std::string> s = {
      "KHR_materials_emissive_strength", "KHR_materials_transmission", "KHR_materials_ior",
      "KHR_materials_specular",          "KHR_texture_transform",      "KHR_lights_punctual",
      "KHR_mesh_quantization",           "EXT_meshopt_compression",    "KHR_draco_mesh_compression",
      "KHR_materials_volume",            "KHR_materials_clearcoat",    "KHR_materials_sheen",
      "KHR_materials_unlit",             "EXT_texture_webp",           "EXT_texture_avif",
      "KHR_node_visibility",             "EXT_mesh_gpu_instancing",
      "KHR_materials_pbrSpecularGlossiness", "KHR_materials_anisotropy",
      "KHR_materials_iridescence",       "KHR_materials_variants",
      "KHR_materials_diffuse_transmission", "KHR_materials_dispersion",
      // Metadata, which the renderer does not read: the server copies the asset's packet into
      // the EXR header (server/renderfarm/domain/scenes/metadata.py).
      "KHR_xmp_json_ld"};
  return s;
}

float number_or(const tinygltf::Value& obj, const char* key, float fallback) {
  if (!obj.IsObject() || !obj.Has(key)) return fallback;
  const tinygltf::Value& v = obj.Get(key);
  return v.IsNumber() ? float(v.GetNumberAsDouble()) : fallback;
}

class Loader {
 public:
  Loader(const tinygltf::Model& model, std::string source, std::vector<std::string>* warnings,
         const LoadOptions& options)
      : model_(model), source_(std::move(source)), warnings_(warnings), options_(options) {}

  SceneDescription run() {
    SceneDescription desc;
    desc.source = source_;
    desc.limits = options_.limits;
    desc.stats.nodes = model_.nodes.size();
    desc.stats.extensions_used = model_.extensionsUsed;
    // glTF 2.0, 3.12: "loaders must not load an asset that requires an extension they do not
    // support".
    for (size_t i = 0; i < model_.extensionsRequired.size(); ++i) {
      const std::string& ext = model_.extensionsRequired[i];
      if (!supported_extensions().count(ext)) {
        std::string list;
        for (const std::string& s : supported_extensions()) list += (list.empty() ? "" : ", ") + s;
        fail("extensionsRequired[" + std::to_string(i) + "]: the scene requires extension '" +
             ext + "', which this renderer does not implement (it implements " + list + ")");
      }
    }
    for (const std::string& ext : model_.extensionsUsed)
      if (!supported_extensions().count(ext) &&
          std::find(model_.extensionsRequired.begin(), model_.extensionsRequired.end(), ext) ==
              model_.extensionsRequired.end())
        warn("extension '" + ext + "' is not supported; ignoring it");
    for (const std::vector<std::string>* list :
         {&model_.extensionsUsed, &model_.extensionsRequired})
      if (std::find(list->begin(), list->end(), "KHR_mesh_quantization") != list->end())
        quantization_ = true;
    split_ = options_.layout && options_.animated() ? options_.layout : nullptr;
    const bool pose_only = split_ && split_->pose_only;
    if (!pose_only) load_textures(&desc);  // a pose uses its static part's textures
    load_materials(&desc);
    variant_ = selected_variant();
    load_lights();

    if (model_.nodes.size() > options_.limits.max_nodes)
      fail("nodes: the scene has " + std::to_string(model_.nodes.size()) +
           " nodes, over the limit of " + std::to_string(options_.limits.max_nodes));
    const std::vector<int> parent = check_hierarchy();
    parent_ = parent;
    evaluate_animations();  // animation.h: the pose at options_.time
    if (split_) classify_nodes();
    count_mesh_uses();
    std::vector<int> roots;
    std::string roots_path;
    if (!model_.scenes.empty()) {
      const int scene_index = model_.defaultScene >= 0 ? model_.defaultScene : 0;
      if (scene_index >= int(model_.scenes.size()))
        fail("scene: refers to missing scene " + std::to_string(scene_index));
      roots = model_.scenes[size_t(scene_index)].nodes;
      roots_path = "scenes[" + std::to_string(scene_index) + "].nodes";
    } else {
      // No scenes: render every node that is nobody's child.
      for (size_t i = 0; i < model_.nodes.size(); ++i)
        if (parent[i] < 0) roots.push_back(int(i));
      roots_path = "nodes";
    }
    check_roots(roots, roots_path, parent);
    if (!pose_only) {
      check_cost(roots, &desc.stats);
      reserve(world_counts(roots), &desc.world);
    }
    for (int root : roots) visit(root, Mat4::identity(), &desc, 0);
    if (split_) {
      split_->deformed_mesh.assign(desc.meshes.size(), 0);
      for (int slot : deformed_slots_) split_->deformed_mesh[size_t(slot)] = 1;
      split_->moving_nodes = moving_mesh_nodes_;
      split_->deformed_nodes = uint32_t(deformed_slots_.size());
    }
    if (options_.pose_report) {
      options_.pose_report->node_world.clear();
      for (size_t i = 0; i < model_.nodes.size(); ++i)
        options_.pose_report->node_world.push_back(global_transform(int(i)));
    }
    return desc;
  }

  // glTF textures -> TextureSource list (one per glTF texture, same indices).
  void load_textures(SceneDescription* desc) {
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
  int texture_image(const tinygltf::Texture& gt, size_t i) {
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
  void load_volume(const tinygltf::Value& ext, const std::string& where, const std::string& name,
                   Material* m) const {
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
  TextureRef texture_ref(int index, int texcoord, const tinygltf::ExtensionMap& extensions,
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
  TextureRef texture_ref(const tinygltf::Value& ext, const char* key, const std::string& where,
                         float* scale = nullptr) {
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
  static constexpr double kFactorSlack = 0.01;
  float unit_number(double x, const std::string& field, const std::string& name) {
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
  float unit_factor(const tinygltf::Value& ext, const char* key, float fallback,
                    const std::string& where) {
    if (!ext.Has(key)) return fallback;
    const tinygltf::Value& v = ext.Get(key);
    if (!v.IsNumber()) fail(where + "." + key + " must be a number in [0, 1]");
    return unit_number(v.GetNumberAsDouble(), where + "." + key, "");
  }

  // An RGB colour of numbers in [0, 1] of a material extension (fallback when absent).
  Vec3 unit_color(const tinygltf::Value& ext, const char* key, Vec3 fallback,
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
  void load_specular_glossiness(const tinygltf::Value& ext, size_t i, const std::string& name,
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
  void load_layers(const tinygltf::Material& gm, size_t i, Material* m) {
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

  void load_lights() {
    auto it = model_.extensions.find("KHR_lights_punctual");
    if (it == model_.extensions.end()) return;
    const tinygltf::Value& root = it->second;
    if (!root.Has("lights") || !root.Get("lights").IsArray()) return;
    const tinygltf::Value& list = root.Get("lights");
    for (size_t i = 0; i < list.ArrayLen(); ++i) {
      const tinygltf::Value& l = list.Get(int(i));
      PunctualLight light;
      const std::string where = "extensions.KHR_lights_punctual.lights[" + std::to_string(i) + "]";
      const std::string type = l.Has("type") && l.Get("type").IsString()
                                   ? l.Get("type").Get<std::string>()
                                   : std::string();
      if (type == "point") light.type = PunctualType::Point;
      else if (type == "spot") light.type = PunctualType::Spot;
      else if (type == "directional") light.type = PunctualType::Directional;
      else {
        warn(where + ": unknown type '" + type + "'; light ignored");
        lights_.push_back(std::nullopt);
        continue;
      }
      Vec3 color(1.f, 1.f, 1.f);
      if (l.Has("color") && l.Get("color").IsArray() && l.Get("color").ArrayLen() == 3)
        for (int c = 0; c < 3; ++c)
          color[c] = float(l.Get("color").Get(c).GetNumberAsDouble());
      const float intensity = number_or(l, "intensity", 1.f);
      light.intensity = color * intensity;
      if (!is_finite(light.intensity) || light.intensity.x < 0.f || light.intensity.y < 0.f ||
          light.intensity.z < 0.f)
        fail(where + ": color x intensity must be finite and >= 0");
      if (l.Has("range")) warn(where + ": 'range' is ignored (physically based falloff)");
      if (light.type == PunctualType::Spot) {
        const tinygltf::Value spot = l.Has("spot") ? l.Get("spot") : tinygltf::Value();
        const float inner = number_or(spot, "innerConeAngle", 0.f);
        const float outer = number_or(spot, "outerConeAngle", kPi / 4.f);
        if (!(inner >= 0.f && inner < outer && outer <= kPi / 2.f))
          fail(where + ": spot cone angles must satisfy 0 <= inner < outer <= pi/2");
        light.cos_inner = std::cos(inner);
        light.cos_outer = std::cos(outer);
      }
      lights_.push_back(light);
    }
  }

  // The vertex attributes the renderer reads: POSITION, NORMAL, COLOR_0, TEXCOORD_0 and _1,
  // and the other TEXCOORD_<n> that a material reads.
  bool reads_attribute(const std::string& name) const {
    if (name == "POSITION" || name == "NORMAL" || name == "COLOR_0" || name == "TANGENT")
      return true;
    uint32_t array = 0;
    return uv_array(name, &array);
  }
  // For a TEXCOORD_<n> attribute the renderer reads: the TriangleMesh::uv array it goes to.
  bool uv_array(const std::string& name, uint32_t* array) const {
    uint32_t set = 0;
    if (!texcoord_set(name, &set)) return false;
    if (set < 2) {
      *array = set;
      return true;
    }
    const auto it = uv_array_of_set_.find(set);
    if (it == uv_array_of_set_.end()) return false;
    *array = it->second;
    return true;
  }
  // n of an attribute named TEXCOORD_<n>.
  static bool texcoord_set(const std::string& name, uint32_t* set) {
    static const std::string prefix = "TEXCOORD_";
    if (name.compare(0, prefix.size(), prefix) != 0 || name.size() == prefix.size() ||
        name.size() > prefix.size() + 9)
      return false;
    uint32_t n = 0;
    for (size_t i = prefix.size(); i < name.size(); ++i) {
      if (!std::isdigit(static_cast<unsigned char>(name[i]))) return false;
      n = 10 * n + uint32_t(name[i] - '0');
    }
    // glTF attribute names have no leading zeros ("TEXCOORD_01" is not set 1).
    if (name.size() > prefix.size() + 1 && name[prefix.size()] == '0') return false;
    *set = n;
    return true;
  }

  // The accessors of the attributes a primitive has that the renderer reads. Primitives of one
  // mesh with the same key share their vertices (exporters often give every material's
  // primitive the whole vertex buffer).
  using VertexKey = std::map<std::string, int>;
  VertexKey vertex_key(const tinygltf::Primitive& prim) const {
    VertexKey key;
    for (const auto& [name, accessor] : prim.attributes)
      if (reads_attribute(name)) key.emplace(name, accessor);
    return key;
  }

  // Vertex and triangle counts of meshes, for reserving TriangleMesh arrays exactly (no
  // growth slack, no copies while a scene of millions of triangles loads). Accessors that are
  // invalid count as empty here; add_mesh reports them.
  struct Counts {
    size_t vertices = 0, triangles = 0;
    bool normals = false, colors = false, tangents = false;
    std::set<uint32_t> uv;  // TriangleMesh::uv arrays
    void operator+=(const Counts& o) {
      vertices += o.vertices;
      triangles += o.triangles;
      normals = normals || o.normals;
      colors = colors || o.colors;
      tangents = tangents || o.tangents;
      uv.insert(o.uv.begin(), o.uv.end());
    }
  };
  size_t accessor_count(int index) const {
    if (index < 0 || index >= int(model_.accessors.size())) return 0;
    return accessor_problem(model_.accessors[size_t(index)]).empty()
               ? model_.accessors[size_t(index)].count
               : 0;
  }

  // Whether bytes [offset, offset + count - 1 strides + elem) lie in a buffer view of length
  // `length`, without overflow.
  static bool fits(size_t length, size_t offset, size_t count, size_t elem, size_t stride) {
    if (count == 0) return offset <= length;
    return offset <= length && elem <= length - offset &&
           (count - 1) <= (length - offset - elem) / stride;
  }
  // "" if buffer view `index` exists and lies in its buffer, otherwise why not.
  std::string view_problem(int index) const {
    if (index < 0 || index >= int(model_.bufferViews.size()))
      return "refers to missing buffer view " + std::to_string(index);
    const tinygltf::BufferView& bv = model_.bufferViews[size_t(index)];
    if (bv.buffer < 0 || bv.buffer >= int(model_.buffers.size()))
      return "buffer view refers to a missing buffer";
    const tinygltf::Buffer& buf = model_.buffers[size_t(bv.buffer)];
    if (bv.byteOffset > buf.data.size() || bv.byteLength > buf.data.size() - bv.byteOffset)
      return "buffer view exceeds its buffer";
    return {};
  }

  // Why an accessor's data is not all in its buffers ("" if it is): its own buffer view (none:
  // zeros, glTF 2.0 3.6.2.3) and a sparse accessor's indices and values. check_accessor
  // reports it.
  std::string accessor_problem(const tinygltf::Accessor& acc) const {
    const int ncomp = tinygltf::GetNumComponentsInType(uint32_t(acc.type));
    const int csize = tinygltf::GetComponentSizeInBytes(uint32_t(acc.componentType));
    if (ncomp <= 0 || csize <= 0) return "unsupported 'type' or 'componentType'";
    const size_t elem = size_t(ncomp) * size_t(csize);
    if (acc.bufferView >= 0 || !acc.sparse.isSparse) {
      if (acc.bufferView < 0 || acc.bufferView >= int(model_.bufferViews.size()))
        return "missing or invalid 'bufferView'";
      const std::string view = view_problem(acc.bufferView);
      if (!view.empty()) return view;
      const tinygltf::BufferView& bv = model_.bufferViews[size_t(acc.bufferView)];
      const size_t stride = bv.byteStride ? bv.byteStride : elem;
      if (stride < elem) return "'byteStride' smaller than the element";
      if (!fits(bv.byteLength, acc.byteOffset, acc.count, elem, stride))
        return "data exceeds its buffer view";
    }
    if (!acc.sparse.isSparse) return {};
    const auto& sp = acc.sparse;
    if (sp.count < 1 || size_t(sp.count) > acc.count)
      return "sparse.count " + std::to_string(sp.count) + " is not in [1, count = " +
             std::to_string(acc.count) + "]";
    const int isize = tinygltf::GetComponentSizeInBytes(uint32_t(sp.indices.componentType));
    if (sp.indices.componentType != TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE &&
        sp.indices.componentType != TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT &&
        sp.indices.componentType != TINYGLTF_COMPONENT_TYPE_UNSIGNED_INT)
      return "sparse.indices.componentType must be 5121, 5123 or 5125";
    const struct {
      const char* name;
      int view, offset;
      size_t elem;
    } parts[2] = {{"sparse.indices", sp.indices.bufferView, sp.indices.byteOffset, size_t(isize)},
                  {"sparse.values", sp.values.bufferView, sp.values.byteOffset, elem}};
    for (const auto& part : parts) {
      const std::string view = view_problem(part.view);
      if (!view.empty()) return std::string(part.name) + ": " + view;
      if (part.offset < 0) return std::string(part.name) + ".byteOffset is negative";
      const tinygltf::BufferView& bv = model_.bufferViews[size_t(part.view)];
      if (!fits(bv.byteLength, size_t(part.offset), size_t(sp.count), part.elem, part.elem))
        return std::string(part.name) + ": data exceeds its buffer view";
    }
    return {};
  }
  Counts mesh_counts(size_t mesh_index) const {
    Counts c;
    std::set<VertexKey> seen;
    for (const tinygltf::Primitive& prim : model_.meshes[mesh_index].primitives) {
      if (!is_triangles(prim.mode)) continue;
      const auto pos = prim.attributes.find("POSITION");
      if (pos == prim.attributes.end()) continue;
      const size_t nv = accessor_count(pos->second);
      if (seen.insert(vertex_key(prim)).second) c.vertices += nv;
      c.triangles +=
          triangle_count(prim.mode, prim.indices >= 0 ? accessor_count(prim.indices) : nv);
      for (const auto& attribute : prim.attributes) {
        uint32_t array = 0;
        if (attribute.first == "NORMAL") c.normals = true;
        if (attribute.first == "COLOR_0") c.colors = true;
        if (attribute.first == "TANGENT") c.tangents = true;
        if (uv_array(attribute.first, &array)) c.uv.insert(array);
      }
    }
    return c;
  }
  // What visit() will flatten into the world mesh: meshes used by one node, for the nodes
  // reachable from the roots.
  Counts world_counts(const std::vector<int>& roots) const {
    Counts c;
    std::vector<bool> seen(model_.nodes.size(), false);
    std::vector<int> stack(roots.begin(), roots.end());
    while (!stack.empty()) {
      const int i = stack.back();
      stack.pop_back();
      if (i < 0 || i >= int(model_.nodes.size()) || seen[size_t(i)]) continue;
      seen[size_t(i)] = true;
      const tinygltf::Node& node = model_.nodes[size_t(i)];
      if (node.mesh >= 0 && node.mesh < int(model_.meshes.size()) &&
          (mesh_uses_[size_t(node.mesh)] == 1 || is_deformed(i)))
        c += mesh_counts(size_t(node.mesh));
      stack.insert(stack.end(), node.children.begin(), node.children.end());
    }
    return c;
  }
  static void reserve(const Counts& c, TriangleMesh* mesh) {
    // One vertex more: Embree reads the last vertex with a 16-byte load.
    mesh->positions.reserve(c.vertices + 1);
    if (c.normals) mesh->normals.reserve(c.vertices);
    if (c.colors) mesh->colors.reserve(c.vertices);
    if (c.tangents) mesh->tangents.reserve(c.vertices);
    for (uint32_t set : c.uv) {
      if (mesh->uv.size() <= set) mesh->uv.resize(set + 1);
      mesh->uv[set].reserve(c.vertices);
    }
    mesh->indices.reserve(3 * c.triangles);
    mesh->material.reserve(c.triangles);
    mesh->flags.reserve(c.triangles);
  }

  // glTF 2.0, 3.5.3: "the node hierarchy must be a set of disjoint strict trees": no node has
  // two parents, none is its own ancestor. Checked before anything walks the graph, which is
  // then a forest: a walk from the roots visits each node once. (A graph that shares children
  // would make the walk exponential: 40 nodes that each list the next one twice are 2^40
  // visits.) Returns each node's parent, -1 for none.
  std::vector<int> check_hierarchy() const {
    const int n = int(model_.nodes.size());
    std::vector<int> parent(size_t(n), -1);
    for (int i = 0; i < n; ++i) {
      const std::vector<int>& children = model_.nodes[size_t(i)].children;
      for (size_t k = 0; k < children.size(); ++k) {
        const int c = children[k];
        const std::string at =
            "nodes[" + std::to_string(i) + "].children[" + std::to_string(k) + "]: ";
        if (c < 0 || c >= n) fail(at + "refers to missing node " + std::to_string(c));
        if (c == i) fail(at + "node " + std::to_string(i) + " lists itself as its child");
        if (parent[size_t(c)] >= 0)
          fail(at + "node " + std::to_string(c) + " is already a child of node " +
               std::to_string(parent[size_t(c)]) +
               "; glTF node hierarchies are disjoint strict trees (a node has at most one "
               "parent)");
        parent[size_t(c)] = i;
      }
    }
    // With one parent each, a cycle is a loop of parent links: follow them from every node,
    // marking the nodes on the current walk (1) and those known to reach a root (2).
    std::vector<uint8_t> state(size_t(n), 0);
    std::vector<int> walk;
    for (int i = 0; i < n; ++i) {
      walk.clear();
      int j = i;
      while (j >= 0 && state[size_t(j)] == 0) {
        state[size_t(j)] = 1;
        walk.push_back(j);
        j = parent[size_t(j)];
      }
      if (j >= 0 && state[size_t(j)] == 1)
        fail("nodes[" + std::to_string(parent[size_t(j)]) + "].children: the node hierarchy " +
             "has a cycle through node " + std::to_string(j));
      for (int w : walk) state[size_t(w)] = 2;
    }
    return parent;
  }

  void check_roots(const std::vector<int>& roots, const std::string& path,
                   const std::vector<int>& parent) const {
    std::set<int> seen;
    for (size_t k = 0; k < roots.size(); ++k) {
      const int r = roots[k];
      const std::string at = path + "[" + std::to_string(k) + "]: ";
      if (r < 0 || r >= int(model_.nodes.size()))
        fail(at + "refers to missing node " + std::to_string(r));
      if (parent[size_t(r)] >= 0)
        fail(at + "node " + std::to_string(r) + " is a child of node " +
             std::to_string(parent[size_t(r)]) + " and cannot also be a root");
      if (!seen.insert(r).second) fail(at + "node " + std::to_string(r) + " is listed twice");
    }
  }

  // Depth, triangles over every mesh use and the memory estimate of what the roots reach,
  // checked against the limits before any geometry is allocated.
  void check_cost(const std::vector<int>& roots, SceneStats* stats) const {
    const SceneLimits& limits = options_.limits;
    std::vector<std::pair<int, uint32_t>> stack;  // (node, depth)
    for (int r : roots) stack.push_back({r, 1});
    std::vector<uint64_t> uses(model_.meshes.size(), 0), copies(model_.meshes.size(), 0);
    std::vector<uint64_t> mesh_triangles(model_.meshes.size(), UINT64_MAX);
    uint64_t instances = 0;
    while (!stack.empty()) {
      const auto [i, depth] = stack.back();
      stack.pop_back();
      const tinygltf::Node& node = model_.nodes[size_t(i)];
      const std::string where = "nodes[" + std::to_string(i) + "]";
      if (depth > limits.max_depth)
        fail(where + ": the node hierarchy is deeper than the limit of " +
             std::to_string(limits.max_depth) + " levels");
      stats->depth = std::max(stats->depth, depth);
      if (node.mesh >= 0) {
        if (node.mesh >= int(model_.meshes.size()))
          fail(where + ".mesh: refers to missing mesh " + std::to_string(node.mesh));
        uint64_t& tris = mesh_triangles[size_t(node.mesh)];
        if (tris == UINT64_MAX) tris = mesh_counts(size_t(node.mesh)).triangles;
        // A skinned or morphed node has its own copy of the mesh; the others share one.
        if (is_deformed(i)) ++copies[size_t(node.mesh)];
        else uses[size_t(node.mesh)] = 1;
        // EXT_mesh_gpu_instancing: the mesh once, drawn once per instance.
        const int64_t gpu = gpu_instance_count(node, i);
        const uint64_t drawn = gpu >= 0 ? uint64_t(gpu) : 1;
        instances += drawn;
        stats->instanced_triangles += tris * drawn;
        if (stats->instanced_triangles > limits.max_instanced_triangles)
          fail(where + ": the scene's mesh uses add up to more than " +
               std::to_string(limits.max_instanced_triangles) + " triangles (the limit)");
      }
      for (int c : node.children) stack.push_back({c, depth + 1});
    }
    // Memory: each mesh once (a mesh used by several nodes is instanced, not copied), its
    // arrays as TriangleMesh holds them, Embree's BVH (docs/architecture.md: about 70 bytes a
    // triangle, 45 for the compact layout), the instances, and the file's buffers, which the loader
    // holds until the scene is built.
    const double bvh_bytes = options_.bvh == BvhLayout::Compact ? 45.0 : 70.0;
    double bytes = 0.0;
    for (size_t m = 0; m < model_.meshes.size(); ++m) {
      if (!uses[m] && !copies[m]) continue;
      const Counts c = mesh_counts(m);
      const double per_vertex = 12.0 + (c.normals ? 12.0 : 0.0) + (c.colors ? 16.0 : 0.0) +
                                (c.tangents ? 16.0 : 0.0) + 8.0 * double(c.uv.size());
      bytes += double(uses[m] + copies[m]) *
               (double(c.vertices) * per_vertex +
                double(c.triangles) * (12.0 + 4.0 + 1.0 + 12.0 + bvh_bytes));
    }
    bytes += double(instances) * 256.0;
    for (const tinygltf::Buffer& b : model_.buffers) bytes += double(b.data.size());
    stats->estimated_bytes = uint64_t(bytes);
    if (limits.max_memory_bytes && stats->estimated_bytes > limits.max_memory_bytes)
      fail("meshes: the scene needs about " + format_bytes(stats->estimated_bytes) +
           " of memory once loaded, over the limit of " + format_bytes(limits.max_memory_bytes));
  }

  void count_mesh_uses() {
    mesh_uses_.assign(model_.meshes.size(), 0);
    for (size_t i = 0; i < model_.nodes.size(); ++i) {
      const tinygltf::Node& node = model_.nodes[i];
      // Skinned and morphed nodes are flattened (their vertices are their own): they do not
      // count as uses of a shared mesh. Nor, in an animated layout, do the nodes that move or
      // deform with time (whose is_deformed may change with it).
      if (node.mesh >= 0 && node.mesh < int(model_.meshes.size()) && !is_deformed(int(i)) &&
          !(split_ && (moving_[i] || varying_[i])))
        mesh_uses_[size_t(node.mesh)] += gpu_instancing(node) ? 2 : 1;  // instanced either way
    }
    mesh_slot_.assign(model_.meshes.size(), -1);
  }

 private:
  // what starts with the glTF path of the offending part ("nodes[3] ('Cube'): ..."): that path
  // becomes the error's path().
  [[noreturn]] void fail(const std::string& what) const {
    throw SceneError(source_ + ": " + what, leading_path(what));
  }
  static std::string leading_path(const std::string& what) {
    size_t end = 0;
    while (end < what.size() && (std::isalnum(static_cast<unsigned char>(what[end])) ||
                                 what[end] == '_' || what[end] == '.' || what[end] == '[' ||
                                 what[end] == ']'))
      ++end;
    const std::string path = what.substr(0, end);
    return path.find('[') != std::string::npos || path == "nodes" || path == "scenes" ||
                   path == "scene" || path == "meshes" || path.rfind("extensions.", 0) == 0
               ? path
               : std::string();
  }
  static std::string named(const std::string& name) {
    return name.empty() ? std::string() : " ('" + name + "')";
  }
  void warn(const std::string& what) {
    if (warnings_) warnings_->push_back(source_ + ": " + what);
  }

  void load_materials(SceneDescription* desc) {
    for (size_t i = 0; i < model_.materials.size(); ++i) {
      const tinygltf::Material& gm = model_.materials[i];
      const std::string where = "materials[" + std::to_string(i) + "]" + named(gm.name);
      Material m;
      m.name = gm.name;
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
      if (!(m.ior >= 1.f && m.ior < 10.f)) {
        warn(where + ": KHR_materials_ior.ior " + std::to_string(m.ior) +
             " outside [1, 10) is not supported; using 1.5");
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

  // The node's transform; pose (its animation at the load's time, or null) replaces the paths
  // it animates.
  Mat4 local_transform(const tinygltf::Node& node, const std::string& where,
                       const NodePose* pose = nullptr) const {
    if (node.matrix.size() == 16) {
      Mat4 m;
      for (int i = 0; i < 16; ++i) m.m[size_t(i / 4)][size_t(i % 4)] = node.matrix[size_t(i)];
      return m;
    }
    if (!node.matrix.empty()) fail(where + ": 'matrix' must have 16 elements");
    if (!node.translation.empty() && node.translation.size() != 3)
      fail(where + ": 'translation' must have 3 elements");
    if (!node.rotation.empty() && node.rotation.size() != 4)
      fail(where + ": 'rotation' must have 4 elements");
    if (!node.scale.empty() && node.scale.size() != 3)
      fail(where + ": 'scale' must have 3 elements");
    // The values in use: the pose's, else the node's (null: the identity).
    auto pick = [](bool posed, const double* from_pose, const std::vector<double>& own) {
      return posed ? from_pose : own.empty() ? nullptr : own.data();
    };
    const double* translation =
        pick(pose && pose->has_translation, pose ? pose->translation.data() : nullptr,
             node.translation);
    const double* rotation =
        pick(pose && pose->has_rotation, pose ? pose->rotation.data() : nullptr, node.rotation);
    const double* scale =
        pick(pose && pose->has_scale, pose ? pose->scale.data() : nullptr, node.scale);
    return trs(translation, rotation, scale, where);
  }

  // T R S (glTF 3.5.3) from a translation, a rotation quaternion (x, y, z, w; normalized
  // here) and a scale, each null for the identity.
  Mat4 trs(const double* translation, const double* rotation, const double* scale,
           const std::string& where) const {
    Mat4 t = Mat4::identity(), r = Mat4::identity(), s = Mat4::identity();
    if (translation) {
      for (int i = 0; i < 3; ++i) t.m[3][size_t(i)] = translation[i];
    }
    if (rotation) {
      double x = rotation[0], y = rotation[1], z = rotation[2], w = rotation[3];
      const double n = std::sqrt(x * x + y * y + z * z + w * w);
      if (!(n > 0.0)) fail(where + ": 'rotation' is not a valid quaternion");
      x /= n, y /= n, z /= n, w /= n;
      // Unit quaternion to rotation matrix (column-major m[col][row]).
      r.m[0][0] = 1 - 2 * (y * y + z * z);
      r.m[0][1] = 2 * (x * y + z * w);
      r.m[0][2] = 2 * (x * z - y * w);
      r.m[1][0] = 2 * (x * y - z * w);
      r.m[1][1] = 1 - 2 * (x * x + z * z);
      r.m[1][2] = 2 * (y * z + x * w);
      r.m[2][0] = 2 * (x * z + y * w);
      r.m[2][1] = 2 * (y * z - x * w);
      r.m[2][2] = 1 - 2 * (x * x + y * y);
    }
    if (scale) {
      for (int i = 0; i < 3; ++i) s.m[size_t(i)][size_t(i)] = scale[i];
    }
    return t * r * s;
  }

  // EXT_mesh_gpu_instancing: the node's mesh is drawn once per instance, at the node's
  // transform times the instance's T R S (TRANSLATION, ROTATION, SCALE accessors of one
  // count; a missing one is the identity), and not at the node's own transform. -1 when the
  // node has no such extension. The accessors' counts are checked here; their formats and
  // values when the transforms are read (gpu_instances).
  const tinygltf::Value* gpu_instancing(const tinygltf::Node& node) const {
    auto ext = node.extensions.find("EXT_mesh_gpu_instancing");
    if (ext == node.extensions.end() || node.mesh < 0) return nullptr;
    return &ext->second;
  }
  static constexpr const char* kInstanceAttributes[3] = {"TRANSLATION", "ROTATION", "SCALE"};
  int64_t gpu_instance_count(const tinygltf::Node& node, int index) const {
    const tinygltf::Value* ext = gpu_instancing(node);
    if (!ext) return -1;
    const std::string where =
        "nodes[" + std::to_string(index) + "].extensions.EXT_mesh_gpu_instancing.attributes";
    if (!ext->Has("attributes") || !ext->Get("attributes").IsObject())
      fail(where + named(node.name) + ": must be an object of accessors");
    const tinygltf::Value& attrs = ext->Get("attributes");
    int64_t count = -1;
    for (const char* name : kInstanceAttributes) {
      if (!attrs.Has(name)) continue;
      const tinygltf::Value& a = attrs.Get(name);
      const int acc = a.IsNumber() ? a.GetNumberAsInt() : -1;
      if (acc < 0 || acc >= int(model_.accessors.size()))
        fail(where + "." + name + named(node.name) + ": refers to missing accessor " +
             std::to_string(acc));
      const int64_t n = int64_t(model_.accessors[size_t(acc)].count);
      if (count >= 0 && n != count)
        fail(where + "." + name + named(node.name) + ": " + std::to_string(n) +
             " instances, but another attribute has " + std::to_string(count));
      count = n;
    }
    if (count < 0)
      fail(where + named(node.name) + ": needs TRANSLATION, ROTATION or SCALE");
    return count;
  }
  // The instances' transforms in the node's space (gpu_instance_count's order).
  std::vector<Mat4> gpu_instances(const tinygltf::Node& node, int index) {
    const int64_t count = gpu_instance_count(node, index);
    const std::string where =
        "nodes[" + std::to_string(index) + "].extensions.EXT_mesh_gpu_instancing.attributes";
    const tinygltf::Value& attrs = gpu_instancing(node)->Get("attributes");
    std::optional<View> views[3];
    const Attribute kinds[3] = {Attribute::AnimationVec3, Attribute::AnimationRotation,
                                Attribute::AnimationVec3};
    for (int k = 0; k < 3; ++k)
      if (attrs.Has(kInstanceAttributes[k]))
        views[k] = check_accessor(attrs.Get(kInstanceAttributes[k]).GetNumberAsInt(), kinds[k],
                                  where + "." + kInstanceAttributes[k]);
    std::vector<Mat4> out;
    out.reserve(size_t(count));
    for (size_t i = 0; i < size_t(count); ++i) {
      double v[3][4];
      for (int k = 0; k < 3; ++k) {
        if (!views[k]) continue;
        for (int c = 0; c < views[k]->components; ++c) {
          v[k][c] = views[k]->get(i, c);
          if (!std::isfinite(v[k][c]))
            fail(where + "." + kInstanceAttributes[k] + named(node.name) + ": element " +
                 std::to_string(i) + " is not finite");
        }
      }
      out.push_back(trs(views[0] ? v[0] : nullptr, views[1] ? v[1] : nullptr,
                        views[2] ? v[2] : nullptr,
                        where + " (instance " + std::to_string(i) + ")"));
    }
    return out;
  }

  // KHR_materials_variants: the variant options_.variant names (an index, or a name of
  // extensions.KHR_materials_variants.variants), -1 for the default materials; a variant the
  // scene does not have is refused, listing those it has.
  int selected_variant() const {
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

 public:
  static std::vector<std::string> variant_names(const tinygltf::Model& model) {
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

 private:
  // The material a primitive's KHR_materials_variants mappings give the selected variant, or
  // -1 (the primitive's own material). Mappings that name a missing material or variant are
  // refused with their path.
  int variant_material(const tinygltf::Primitive& prim, size_t mesh_index, size_t pi) const {
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

  // KHR_node_visibility: the node's own `visible` (true when absent).
  bool node_visible(const tinygltf::Node& node, int index) const {
    auto ext = node.extensions.find("KHR_node_visibility");
    if (ext == node.extensions.end() || !ext->second.Has("visible")) return true;
    const tinygltf::Value& v = ext->second.Get("visible");
    if (!v.IsBool())
      fail("nodes[" + std::to_string(index) + "].extensions.KHR_node_visibility.visible" +
           named(node.name) + ": must be true or false");
    return v.Get<bool>();
  }

  // `visible`: no ancestor is hidden by KHR_node_visibility. A hidden node and everything
  // below it render nothing (meshes, lights), "even any nodes below that have a value of
  // true"; cameras are not affected (the extension's text), so the walk goes on for them.
  void visit(int index, const Mat4& parent, SceneDescription* desc, int depth,
             bool visible = true) {
    if (index < 0 || index >= int(model_.nodes.size()))
      fail("reference to missing node " + std::to_string(index));
    // glTF node graphs are trees; a deeper chain than the node count means a cycle.
    if (depth > int(model_.nodes.size())) fail("node hierarchy contains a cycle");
    const tinygltf::Node& node = model_.nodes[size_t(index)];
    const std::string where = "nodes[" + std::to_string(index) + "]" + named(node.name);
    const Mat4 world = parent * local_transform(node, where, pose_of(index));
    visible = node_visible(node, index) && visible;
    if (node.camera >= 0 && !desc->camera) {
      take_camera(node, world, where, desc);
      if (options_.pose_report) options_.pose_report->camera_node = index;
    }
    if (!visible) {
      for (int child : node.children) visit(child, world, desc, depth + 1, false);
      return;
    }
    auto light_ext = node.extensions.find("KHR_lights_punctual");
    if (light_ext != node.extensions.end() && light_ext->second.Has("light")) {
      const int li = light_ext->second.Get("light").GetNumberAsInt();
      if (li < 0 || li >= int(lights_.size()))
        fail(where + ": KHR_lights_punctual.light refers to missing light " + std::to_string(li));
      if (lights_[size_t(li)]) {
        PunctualLight light = *lights_[size_t(li)];
        light.position = world.transform_point({0.f, 0.f, 0.f});
        const Vec3 dir = world.transform_vector({0.f, 0.f, -1.f});
        if (!(length(dir) > 0.f)) fail(where + ": light transform is singular");
        light.direction = normalize(dir);
        desc->punctual_lights.push_back(light);
      }
    }
    if (node.mesh >= 0 && node.mesh < int(model_.meshes.size()) && gpu_instancing(node)) {
      if (is_deformed(index) || (split_ && varying_[size_t(index)]))
        fail(where + ".extensions.EXT_mesh_gpu_instancing: instancing a skinned or morphed "
                     "mesh is not supported");
      // One mesh in its own space, an instance per element (moving with the node in an
      // animated layout: both of its modes place the same instances in the same order).
      int& slot = mesh_slot_[size_t(node.mesh)];
      if (slot < 0) {
        Mesh mesh;
        mesh.name = model_.meshes[size_t(node.mesh)].name;
        if (!(split_ && split_->pose_only)) {
          reserve(mesh_counts(size_t(node.mesh)), &mesh.geometry);
          add_mesh(size_t(node.mesh), Mat4::identity(), &mesh.geometry);
        }
        slot = int(desc->meshes.size());
        desc->meshes.push_back(std::move(mesh));
      }
      if (split_ && moving_[size_t(index)]) ++moving_mesh_nodes_;
      for (const Mat4& local : gpu_instances(node, index))
        desc->instances.push_back({uint32_t(slot), world * local});
    } else if (node.mesh >= 0 && split_) {
      if (node.mesh >= int(model_.meshes.size()))
        fail(where + ": 'mesh' refers to missing mesh " + std::to_string(node.mesh));
      visit_split(index, node, world, where, desc);
    } else if (node.mesh >= 0) {
      if (node.mesh >= int(model_.meshes.size()))
        fail(where + ": 'mesh' refers to missing mesh " + std::to_string(node.mesh));
      PoseReport::Range range;
      range.node = index;
      range.mesh = node.mesh;
      if (is_deformed(index)) {
        // Skinned or morphed: vertices of its own, in world space.
        const Deformation deformation = deformation_of(index, where);
        range.first_vertex = uint32_t(desc->world.positions.size());
        range.skinned = deformation.skin >= 0;
        range.morphed = !deformation.weights.empty();
        add_mesh(size_t(node.mesh), world, &desc->world, &deformation);
        range.count = uint32_t(desc->world.positions.size()) - range.first_vertex;
      } else if (mesh_uses_[size_t(node.mesh)] > 1) {
        // Shared mesh: built once in its own space, placed by an instance.
        int& slot = mesh_slot_[size_t(node.mesh)];
        if (slot < 0) {
          Mesh mesh;
          mesh.name = model_.meshes[size_t(node.mesh)].name;
          reserve(mesh_counts(size_t(node.mesh)), &mesh.geometry);
          add_mesh(size_t(node.mesh), Mat4::identity(), &mesh.geometry);
          slot = int(desc->meshes.size());
          desc->meshes.push_back(std::move(mesh));
        }
        range.instance = int(desc->instances.size());
        range.mesh_slot = slot;
        range.count = uint32_t(desc->meshes[size_t(slot)].geometry.positions.size());
        desc->instances.push_back({uint32_t(slot), world});
      } else {
        range.first_vertex = uint32_t(desc->world.positions.size());
        add_mesh(size_t(node.mesh), world, &desc->world);
        range.count = uint32_t(desc->world.positions.size()) - range.first_vertex;
      }
      if (options_.pose_report) options_.pose_report->ranges.push_back(range);
    }
    for (int child : node.children) visit(child, world, desc, depth + 1);
  }

  // A mesh node in an animated layout (AnimatedLayout): a varying deformed node gets a mesh of
  // its own at the identity, a moving one an instance of its mesh in the mesh's own space, the
  // others go where a still puts them. Each mode fills its own meshes only (the numbering is
  // the same in both).
  void visit_split(int index, const tinygltf::Node& node, const Mat4& world,
                   const std::string& where, SceneDescription* desc) {
    const bool pose_only = split_->pose_only;
    const size_t mi = size_t(node.mesh);
    if (varying_[size_t(index)]) {
      Mesh mesh;
      mesh.name = model_.meshes[mi].name + " (" + where + ")";
      if (pose_only) {
        const Deformation deformation = deformation_of(index, where);
        add_mesh(mi, world, &mesh.geometry, &deformation);
      }
      const int slot = int(desc->meshes.size());
      desc->meshes.push_back(std::move(mesh));
      deformed_slots_.push_back(slot);
      desc->instances.push_back({uint32_t(slot), Mat4::identity()});
      return;
    }
    if (moving_[size_t(index)] || (!is_deformed(index) && mesh_uses_[mi] > 1)) {
      if (moving_[size_t(index)]) ++moving_mesh_nodes_;
      int& slot = mesh_slot_[mi];
      if (slot < 0) {
        Mesh mesh;
        mesh.name = model_.meshes[mi].name;
        if (!pose_only) {
          reserve(mesh_counts(mi), &mesh.geometry);
          add_mesh(mi, Mat4::identity(), &mesh.geometry);
        }
        slot = int(desc->meshes.size());
        desc->meshes.push_back(std::move(mesh));
      }
      desc->instances.push_back({uint32_t(slot), world});
      return;
    }
    if (pose_only) return;  // static world triangles: the static part's
    if (is_deformed(index)) {
      const Deformation deformation = deformation_of(index, where);
      add_mesh(mi, world, &desc->world, &deformation);
    } else {
      add_mesh(mi, world, &desc->world);
    }
  }

  // moving_ and varying_ per node (AnimatedLayout): from the channels the chosen animations
  // have, whatever their values at the time.
  void classify_nodes() {
    const size_t n = model_.nodes.size();
    moving_.assign(n, 0);
    varying_.assign(n, 0);
    // A node moves if its TRS is animated or its parent moves (parents first: memoized walk).
    std::vector<char> known(n, 0);
    for (size_t i = 0; i < n; ++i) {
      std::vector<int> chain;
      int j = int(i);
      while (j >= 0 && !known[size_t(j)]) {
        chain.push_back(j);
        j = parent_[size_t(j)];
      }
      char moves = j >= 0 ? moving_[size_t(j)] : 0;
      for (auto it = chain.rbegin(); it != chain.rend(); ++it) {
        moves = char(moves || trs_animated_.count(*it));
        moving_[size_t(*it)] = moves;
        known[size_t(*it)] = 1;
      }
    }
    for (size_t i = 0; i < n; ++i) {
      const tinygltf::Node& node = model_.nodes[i];
      if (node.mesh < 0 || node.mesh >= int(model_.meshes.size())) continue;
      bool varies = morph_target_count(node.mesh) > 0 &&
                    (weights_animated_.count(int(i)) || (moving_[i] && is_deformed(int(i))));
      if (node.skin >= 0 && node.skin < int(model_.skins.size()))
        for (int j : model_.skins[size_t(node.skin)].joints)
          if (j >= 0 && j < int(n) && moving_[size_t(j)]) varies = true;
      // A skinned node's own transform is not used: it does not move the skinned mesh.
      if (node.skin >= 0 && !varies) moving_[i] = 0;
      varying_[i] = char(varies);
    }
  }

  // The first camera the walk from the roots meets, of either type (glTF 2.0, 3.10).
  void take_camera(const tinygltf::Node& node, const Mat4& world, const std::string& where,
                   SceneDescription* desc) {
    if (node.camera >= int(model_.cameras.size()))
      fail(where + ": 'camera' refers to missing camera " + std::to_string(node.camera));
    const tinygltf::Camera& gc = model_.cameras[size_t(node.camera)];
    const std::string at = "cameras[" + std::to_string(node.camera) + "]";
    const std::string of = " (camera of " + where + ")";
    Camera cam;
    double znear = 0.0, zfar = 0.0;
    if (gc.type == "perspective") {
      cam.yfov = float(gc.perspective.yfov);
      if (!(cam.yfov > 0.f && cam.yfov < kPi))
        fail(at + ".perspective.yfov: " + std::to_string(gc.perspective.yfov) +
             " is outside (0, pi)" + of);
      znear = gc.perspective.znear;
      zfar = gc.perspective.zfar;  // 0: absent, an infinite projection
      if (!(znear >= 0.0 && std::isfinite(znear)))
        fail(at + ".perspective.znear: " + std::to_string(znear) + " is not >= 0" + of);
      if (zfar != 0.0 && !(zfar > znear))
        fail(at + ".perspective.zfar: " + std::to_string(zfar) + " is not greater than znear" +
             of);
    } else if (gc.type == "orthographic") {
      const tinygltf::OrthographicCamera& o = gc.orthographic;
      cam.orthographic = true;
      cam.xmag = float(o.xmag);
      cam.ymag = float(o.ymag);
      if (!(cam.xmag != 0.f && std::isfinite(cam.xmag)))
        fail(at + ".orthographic.xmag: " + std::to_string(o.xmag) + " must be finite and not 0" +
             of);
      if (!(cam.ymag != 0.f && std::isfinite(cam.ymag)))
        fail(at + ".orthographic.ymag: " + std::to_string(o.ymag) + " must be finite and not 0" +
             of);
      znear = o.znear;
      zfar = o.zfar;
      if (!(znear >= 0.0 && std::isfinite(znear)))
        fail(at + ".orthographic.znear: " + std::to_string(znear) + " is not >= 0" + of);
      if (!(zfar > znear && std::isfinite(zfar)))
        fail(at + ".orthographic.zfar: " + std::to_string(zfar) +
             " is not finite and greater than znear" + of);
    } else {
      fail(at + ".type: '" + gc.type + "' is not perspective or orthographic" + of);
    }
    cam.znear = float(znear);
    if (zfar != 0.0) cam.zfar = float(zfar);
    cam.position = world.transform_point({0.f, 0.f, 0.f});
    const Vec3 fwd = world.transform_vector({0.f, 0.f, -1.f});
    const Vec3 up = world.transform_vector({0.f, 1.f, 0.f});
    if (!(length(fwd) > 0.f) || !(length(cross(fwd, up)) > 0.f))
      fail(where + ": camera transform is singular");
    cam.forward = normalize(fwd);
    // Re-orthogonalize in case of shear: right = fwd x up, up = right x fwd.
    cam.right = normalize(cross(cam.forward, up));
    cam.up = cross(cam.right, cam.forward);
    desc->camera = cam;
  }

  // Element i, component c of an accessor's data (range-checked by check_accessor, which made
  // the view).
  struct View {
    const unsigned char* base = nullptr;
    size_t stride = 0;
    int component_type = 0;
    int components = 0;
    size_t count = 0;
    bool normalized = false;
    // The stored number.
    double raw(size_t i, int c) const {
      const unsigned char* p = base + i * stride;
      switch (component_type) {
        case TINYGLTF_COMPONENT_TYPE_FLOAT: {
          float f;
          std::memcpy(&f, p + 4 * c, 4);
          return f;
        }
        case TINYGLTF_COMPONENT_TYPE_UNSIGNED_INT: {
          uint32_t u;
          std::memcpy(&u, p + 4 * c, 4);
          return u;
        }
        case TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT: {
          uint16_t u;
          std::memcpy(&u, p + 2 * c, 2);
          return u;
        }
        case TINYGLTF_COMPONENT_TYPE_SHORT: {
          int16_t v;
          std::memcpy(&v, p + 2 * c, 2);
          return v;
        }
        case TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE:
          return p[c];
        case TINYGLTF_COMPONENT_TYPE_BYTE:
          return double(int8_t(p[c]));
        default:
          return 0.0;
      }
    }
    // The attribute value: a normalized integer as glTF 2.0 (3.11) maps it to [0, 1] or
    // [-1, 1] (c / 255, c / 65535, max(c / 127, -1), max(c / 32767, -1)), any other number as
    // it is (quantized data that a node transform or KHR_texture_transform dequantizes).
    float get(size_t i, int c) const {
      const double v = raw(i, c);
      if (!normalized) return float(v);
      switch (component_type) {
        case TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE:
          return float(v / 255.0);
        case TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT:
          return float(v / 65535.0);
        case TINYGLTF_COMPONENT_TYPE_BYTE:
          return float(std::max(v / 127.0, -1.0));
        case TINYGLTF_COMPONENT_TYPE_SHORT:
          return float(std::max(v / 32767.0, -1.0));
        default:
          return float(v);
      }
    }
  };

  // What an accessor holds: vertex attributes and indices (3.7.2.1), animation sampler inputs
  // and outputs (3.11), skin joints, weights and inverse bind matrices (3.7.3), and morph
  // target displacements (3.7.2.2).
  enum class Attribute {
    Position, Normal, Texcoord, Color, Indices,
    AnimationInput, AnimationVec3, AnimationRotation, AnimationWeights,
    Joints, Weights, InverseBindMatrices, MorphPosition, MorphNormal, Tangent
  };
  static const char* component_name(int type) {
    switch (type) {
      case TINYGLTF_COMPONENT_TYPE_BYTE: return "byte";
      case TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE: return "unsigned byte";
      case TINYGLTF_COMPONENT_TYPE_SHORT: return "short";
      case TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT: return "unsigned short";
      case TINYGLTF_COMPONENT_TYPE_UNSIGNED_INT: return "unsigned int";
      case TINYGLTF_COMPONENT_TYPE_FLOAT: return "float";
      default: return "unknown";
    }
  }
  // "" if the accessor's type, componentType and normalized suit the attribute (glTF 2.0,
  // 3.7.2.1, and KHR_mesh_quantization's table when the scene uses the extension), otherwise
  // why not.
  std::string format_problem(Attribute kind, const tinygltf::Accessor& acc) const {
    const int ct = acc.componentType;
    const bool norm = acc.normalized;
    const bool small_int = ct == TINYGLTF_COMPONENT_TYPE_BYTE ||
                           ct == TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE ||
                           ct == TINYGLTF_COMPONENT_TYPE_SHORT ||
                           ct == TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT;
    const bool unsigned_norm =
        norm && (ct == TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE ||
                 ct == TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT);
    const bool float_type = ct == TINYGLTF_COMPONENT_TYPE_FLOAT;
    const bool signed_small =
        ct == TINYGLTF_COMPONENT_TYPE_BYTE || ct == TINYGLTF_COMPONENT_TYPE_SHORT;
    bool type_ok = false, ok = false;
    const char* allowed = "";
    switch (kind) {
      case Attribute::Position:
        type_ok = acc.type == TINYGLTF_TYPE_VEC3;
        ok = ct == TINYGLTF_COMPONENT_TYPE_FLOAT || (quantization_ && small_int);
        allowed = "float (8- and 16-bit integers with KHR_mesh_quantization)";
        break;
      case Attribute::Normal:
        type_ok = acc.type == TINYGLTF_TYPE_VEC3;
        ok = ct == TINYGLTF_COMPONENT_TYPE_FLOAT ||
             (quantization_ && norm &&
              (ct == TINYGLTF_COMPONENT_TYPE_BYTE || ct == TINYGLTF_COMPONENT_TYPE_SHORT));
        allowed = "float (normalized byte and short with KHR_mesh_quantization)";
        break;
      case Attribute::Texcoord:
        type_ok = acc.type == TINYGLTF_TYPE_VEC2;
        ok = ct == TINYGLTF_COMPONENT_TYPE_FLOAT || unsigned_norm || (quantization_ && small_int);
        allowed = "float, normalized unsigned byte or short (any 8- and 16-bit integers with "
                  "KHR_mesh_quantization)";
        break;
      case Attribute::Color:
        type_ok = acc.type == TINYGLTF_TYPE_VEC3 || acc.type == TINYGLTF_TYPE_VEC4;
        ok = ct == TINYGLTF_COMPONENT_TYPE_FLOAT || unsigned_norm;
        allowed = "float, normalized unsigned byte or short";
        break;
      case Attribute::Indices:
        type_ok = acc.type == TINYGLTF_TYPE_SCALAR;
        ok = ct == TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE ||
             ct == TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT ||
             ct == TINYGLTF_COMPONENT_TYPE_UNSIGNED_INT;
        allowed = "unsigned byte, short or int";
        break;
      case Attribute::AnimationInput:
        type_ok = acc.type == TINYGLTF_TYPE_SCALAR;
        ok = float_type;
        allowed = "float (keyframe times in seconds)";
        break;
      case Attribute::AnimationVec3:  // translation, scale
        type_ok = acc.type == TINYGLTF_TYPE_VEC3;
        ok = float_type;
        allowed = "float";
        break;
      case Attribute::AnimationRotation:
      case Attribute::AnimationWeights:
        type_ok = acc.type == (kind == Attribute::AnimationRotation ? TINYGLTF_TYPE_VEC4
                                                                    : TINYGLTF_TYPE_SCALAR);
        ok = float_type || (norm && small_int);
        allowed = "float or a normalized byte, unsigned byte, short or unsigned short";
        break;
      case Attribute::Joints:
        type_ok = acc.type == TINYGLTF_TYPE_VEC4;
        ok = !norm && (ct == TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE ||
                       ct == TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT);
        allowed = "unsigned byte or unsigned short";
        break;
      case Attribute::Weights:
        type_ok = acc.type == TINYGLTF_TYPE_VEC4;
        ok = float_type || unsigned_norm;
        allowed = "float, normalized unsigned byte or short";
        break;
      case Attribute::InverseBindMatrices:
        type_ok = acc.type == TINYGLTF_TYPE_MAT4;
        ok = float_type;
        allowed = "float";
        break;
      case Attribute::MorphPosition:
        type_ok = acc.type == TINYGLTF_TYPE_VEC3;
        ok = float_type || (quantization_ && signed_small);
        allowed = "float (byte and short, normalized or not, with KHR_mesh_quantization)";
        break;
      case Attribute::Tangent:
        type_ok = acc.type == TINYGLTF_TYPE_VEC4;
        ok = ct == TINYGLTF_COMPONENT_TYPE_FLOAT ||
             (quantization_ && norm &&
              (ct == TINYGLTF_COMPONENT_TYPE_BYTE || ct == TINYGLTF_COMPONENT_TYPE_SHORT));
        allowed = "float (normalized byte and short with KHR_mesh_quantization)";
        break;
      case Attribute::MorphNormal:
        type_ok = acc.type == TINYGLTF_TYPE_VEC3;
        ok = float_type || (quantization_ && norm && signed_small);
        allowed = "float (normalized byte and short with KHR_mesh_quantization)";
        break;
    }
    if (!type_ok) return "unexpected accessor 'type'";
    if (ok) return {};
    return std::string("componentType ") + std::to_string(ct) + " (" + component_name(ct) +
           (small_int ? (norm ? ", normalized" : ", not normalized") : "") +
           ") is not allowed here: it must be " + allowed;
  }

  View check_accessor(int index, Attribute kind, const std::string& where) {
    if (index < 0 || index >= int(model_.accessors.size()))
      fail(where + " refers to missing accessor " + std::to_string(index));
    const tinygltf::Accessor& acc = model_.accessors[size_t(index)];
    const std::string aw = "accessors[" + std::to_string(index) + "] (" + where + ")";
    const std::string format = format_problem(kind, acc);
    if (!format.empty()) fail(aw + ": " + format);
    const std::string problem = accessor_problem(acc);
    if (!problem.empty()) fail(aw + ": " + problem);
    const size_t elem = size_t(tinygltf::GetNumComponentsInType(uint32_t(acc.type))) *
                        size_t(tinygltf::GetComponentSizeInBytes(uint32_t(acc.componentType)));
    View v;
    v.component_type = acc.componentType;
    v.components = tinygltf::GetNumComponentsInType(uint32_t(acc.type));
    v.count = acc.count;
    v.normalized = acc.normalized;
    if (acc.sparse.isSparse) {
      auto [it, fresh] = sparse_data_.try_emplace(index);
      if (fresh) it->second = materialize_sparse(index, elem, where);
      v.base = it->second.data();
      v.stride = elem;
    } else {
      const tinygltf::BufferView& bv = model_.bufferViews[size_t(acc.bufferView)];
      const tinygltf::Buffer& buf = model_.buffers[size_t(bv.buffer)];
      v.stride = bv.byteStride ? bv.byteStride : elem;
      v.base = buf.data.data() + bv.byteOffset + acc.byteOffset;
    }
    return v;
  }

  // A sparse accessor's elements (glTF 2.0, 3.6.2.3): those of its buffer view, or zeros
  // without one, with the elements its sparse indices name replaced by its sparse values;
  // packed (stride = elem). accessor_problem has checked that every byte read is there.
  std::vector<unsigned char> materialize_sparse(int index, size_t elem,
                                                const std::string& where) const {
    const tinygltf::Accessor& acc = model_.accessors[size_t(index)];
    std::vector<unsigned char> data(acc.count * elem, 0);
    if (acc.bufferView >= 0) {
      const tinygltf::BufferView& bv = model_.bufferViews[size_t(acc.bufferView)];
      const unsigned char* base =
          model_.buffers[size_t(bv.buffer)].data.data() + bv.byteOffset + acc.byteOffset;
      const size_t stride = bv.byteStride ? bv.byteStride : elem;
      for (size_t i = 0; i < acc.count; ++i) std::memcpy(&data[i * elem], base + i * stride, elem);
    }
    auto start = [&](int view, int offset) {
      const tinygltf::BufferView& bv = model_.bufferViews[size_t(view)];
      return model_.buffers[size_t(bv.buffer)].data.data() + bv.byteOffset + size_t(offset);
    };
    View indices;
    indices.base = start(acc.sparse.indices.bufferView, acc.sparse.indices.byteOffset);
    indices.component_type = acc.sparse.indices.componentType;
    indices.stride = size_t(tinygltf::GetComponentSizeInBytes(uint32_t(indices.component_type)));
    const unsigned char* values = start(acc.sparse.values.bufferView, acc.sparse.values.byteOffset);
    double previous = -1.0;
    for (size_t k = 0; k < size_t(acc.sparse.count); ++k) {
      const double i = indices.raw(k, 0);
      if (!(i > previous) || !(i < double(acc.count)))
        fail("accessors[" + std::to_string(index) + "].sparse.indices (" + where + "): index " +
             std::to_string(k) + " is " + std::to_string(uint64_t(i)) +
             (i < double(acc.count) ? ", not above the one before it (sparse indices strictly "
                                      "increase)"
                                    : ", out of range (count " + std::to_string(acc.count) + ")"));
      std::memcpy(&data[size_t(i) * elem], values + k * elem, elem);
      previous = i;
    }
    return data;
  }

  // A primitive's vertex attributes that the renderer reads, checked.
  struct VertexAttributes {
    View position;
    std::optional<View> normal, color, tangent;
    std::vector<std::pair<uint32_t, View>> uv;  // (TriangleMesh::uv array, view), ascending
  };

  // ---- Animation, skins and morph targets (glTF 2.0, 3.11, 3.7.3, 3.7.2.2; animation.h).

  // A deformed mesh node: its morph target weights (empty: none apply) and, if it is skinned,
  // its skin's joint matrices globalTransform(joints[j]) * inverseBindMatrices[j].
  struct Deformation {
    std::vector<double> weights;
    int skin = -1;
    std::vector<Mat4> joint_matrices;
  };
  // A deformed primitive's vertices in world space: positions, normals (not normalized;
  // empty without NORMAL) and, for skinned ones, whether each vertex's skin matrix mirrors.
  struct PosedVertices {
    std::vector<Vec3> positions, normals;
    std::vector<uint8_t> mirrored;
  };

  // The animations' pose at options_.time (none without a time): every channel of the chosen
  // animations, checked and evaluated. Channels of paths other than the four of glTF 2.0
  // (KHR_animation_pointer's) are ignored with a warning.
  void evaluate_animations() {
    if (!options_.animated()) return;
    std::vector<int> chosen = options_.animations;
    if (chosen.empty())
      for (size_t a = 0; a < model_.animations.size(); ++a) chosen.push_back(int(a));
    std::vector<ChannelTrack> channels;
    for (const int a : chosen) {
      const std::string at = "animations[" + std::to_string(a) + "]";
      if (a < 0 || a >= int(model_.animations.size()))
        fail(at + ": no such animation (the scene has " +
             std::to_string(model_.animations.size()) + ")");
      const tinygltf::Animation& anim = model_.animations[size_t(a)];
      for (size_t k = 0; k < anim.channels.size(); ++k) {
        const tinygltf::AnimationChannel& ch = anim.channels[k];
        const std::string cw = at + ".channels[" + std::to_string(k) + "]";
        ChannelTrack track;
        if (ch.target_path == "translation") {
          track.path = AnimationPath::Translation;
        } else if (ch.target_path == "rotation") {
          track.path = AnimationPath::Rotation;
        } else if (ch.target_path == "scale") {
          track.path = AnimationPath::Scale;
        } else if (ch.target_path == "weights") {
          track.path = AnimationPath::Weights;
        } else {
          warn(cw + ".target.path: '" + ch.target_path +
               "' is not translation, rotation, scale or weights; channel ignored");
          continue;
        }
        const int n = ch.target_node;
        if (n < 0 || n >= int(model_.nodes.size()))
          fail(cw + ".target.node: refers to missing node " + std::to_string(n));
        const tinygltf::Node& node = model_.nodes[size_t(n)];
        if (!node.matrix.empty())
          fail(cw + ".target.node: node " + std::to_string(n) +
               " has a 'matrix'; glTF 2.0 (3.11) allows animating only nodes whose transform "
               "is translation, rotation and scale");
        size_t components = track.path == AnimationPath::Rotation ? 4 : 3;
        if (track.path == AnimationPath::Weights) {
          components = node.mesh >= 0 && node.mesh < int(model_.meshes.size())
                           ? morph_target_count(node.mesh)
                           : 0;
          if (components == 0) {
            warn(cw + ": node " + std::to_string(n) +
                 " has no mesh with morph targets; weights channel ignored");
            continue;
          }
        }
        if (ch.sampler < 0 || ch.sampler >= int(anim.samplers.size()))
          fail(cw + ".sampler: refers to missing sampler " + std::to_string(ch.sampler));
        track.node = n;
        track.track = read_sampler(a, ch.sampler, track.path, components);
        (track.path == AnimationPath::Weights ? weights_animated_ : trs_animated_)
            .insert(track.node);
        channels.push_back(std::move(track));
      }
    }
    poses_ = evaluate_pose(channels, options_.time);
  }

  // Sampler j of animation a as keyframes of `components` numbers (glTF 2.0, 3.11): float
  // times that strictly increase, and one output element per keyframe (three with
  // CUBICSPLINE: in-tangent, value, out-tangent), dequantized.
  KeyframeTrack read_sampler(int a, int j, AnimationPath path, size_t components) {
    const tinygltf::AnimationSampler& s = model_.animations[size_t(a)].samplers[size_t(j)];
    const std::string sw = "animations[" + std::to_string(a) + "].samplers[" + std::to_string(j) + "]";
    KeyframeTrack track;
    track.components = components;
    track.rotation = path == AnimationPath::Rotation;
    if (!parse_interpolation(s.interpolation, &track.interpolation))
      fail(sw + ".interpolation: '" + s.interpolation + "' is not STEP, LINEAR or CUBICSPLINE");
    const View input = check_accessor(s.input, Attribute::AnimationInput, sw + ".input");
    const std::string in_at = sw + ".input (accessors[" + std::to_string(s.input) + "])";
    if (input.count == 0) fail(in_at + ": no keyframes");
    track.times.resize(input.count);
    for (size_t k = 0; k < input.count; ++k) {
      const double t = input.get(k, 0);
      if (!std::isfinite(t)) fail(in_at + ": keyframe time " + std::to_string(k) + " is not finite");
      if (k > 0 && !(t > track.times[k - 1]))
        fail(in_at + ": keyframe time " + std::to_string(k) + " (" + std::to_string(t) +
             ") is not greater than the one before it (" + std::to_string(track.times[k - 1]) +
             "); glTF 2.0 (3.11) requires strictly increasing times");
      track.times[k] = t;
    }
    const Attribute kind = path == AnimationPath::Rotation  ? Attribute::AnimationRotation
                           : path == AnimationPath::Weights ? Attribute::AnimationWeights
                                                            : Attribute::AnimationVec3;
    const View output = check_accessor(s.output, kind, sw + ".output");
    const std::string out_at = sw + ".output (accessors[" + std::to_string(s.output) + "])";
    const size_t per_key = track.interpolation == Interpolation::CubicSpline ? 3 : 1;
    // Weights outputs are scalars, `components` (the morph target count) per element.
    const size_t per_element = path == AnimationPath::Weights ? components : 1;
    const size_t expected = input.count * per_key * per_element;
    if (output.count != expected)
      fail(out_at + ": " + std::to_string(output.count) + " elements, expected " +
           std::to_string(expected) + " (" + std::to_string(input.count) + " keyframes" +
           (per_key == 3 ? " x 3 for CUBICSPLINE" : "") +
           (per_element > 1 ? " x " + std::to_string(per_element) + " morph targets" : "") + ")");
    track.values.resize(input.count * per_key * components);
    const int nc = output.components;
    for (size_t e = 0; e < output.count; ++e)
      for (int c = 0; c < nc; ++c) {
        const double v = output.get(e, c);
        if (!std::isfinite(v)) fail(out_at + ": element " + std::to_string(e) + " is not finite");
        track.values[e * size_t(nc) + size_t(c)] = v;
      }
    return track;
  }

  const NodePose* pose_of(int node) const {
    if (poses_.empty()) return nullptr;
    const auto it = poses_.find(node);
    return it == poses_.end() ? nullptr : &it->second;
  }
  size_t morph_target_count(int mesh) const {
    size_t n = 0;
    for (const tinygltf::Primitive& prim : model_.meshes[size_t(mesh)].primitives)
      n = std::max(n, prim.targets.size());
    return n;
  }
  // A mesh node's morph target weights (3.7.2.2): animated, else the node's, else the mesh's
  // (missing ones are 0).
  const std::vector<double>& morph_weights(int index) const {
    const NodePose* pose = pose_of(index);
    if (pose && pose->has_weights) return pose->weights;
    const tinygltf::Node& node = model_.nodes[size_t(index)];
    if (!node.weights.empty()) return node.weights;
    return model_.meshes[size_t(node.mesh)].weights;
  }
  // Whether a node's mesh is skinned, or morphed by a weight other than 0: the node then has
  // vertices of its own (flattened into the world mesh, never an instance of a shared mesh).
  bool is_deformed(int index) const {
    const tinygltf::Node& node = model_.nodes[size_t(index)];
    if (node.mesh < 0 || node.mesh >= int(model_.meshes.size())) return false;
    if (node.skin >= 0) return true;
    if (morph_target_count(node.mesh) == 0) return false;
    const std::vector<double>& w = morph_weights(index);
    return std::any_of(w.begin(), w.end(), [](double x) { return x != 0.0; });
  }

  // A node's world matrix at the pose, as visit() composes it (parent * local from the root
  // down), for nodes visit() may not have reached yet (joints) or at all.
  Mat4 global_transform(int index) {
    std::vector<int> chain;
    for (int j = index; j >= 0 && !global_.count(j); j = parent_[size_t(j)]) chain.push_back(j);
    for (auto it = chain.rbegin(); it != chain.rend(); ++it) {
      const int j = *it, p = parent_[size_t(j)];
      const tinygltf::Node& node = model_.nodes[size_t(j)];
      const Mat4 parent = p >= 0 ? global_.at(p) : Mat4::identity();
      global_.emplace(j, parent * local_transform(node, "nodes[" + std::to_string(j) + "]" +
                                                            named(node.name),
                                                  pose_of(j)));
    }
    return global_.at(index);
  }

  // Skin s's joint matrices (3.7.3): globalTransform(joints[j]) * inverseBindMatrices[j]
  // (the identity without inverseBindMatrices). The skinned node's own transform is not used.
  const std::vector<Mat4>& joint_matrices(int s) {
    const auto found = joint_matrices_.find(s);
    if (found != joint_matrices_.end()) return found->second;
    const tinygltf::Skin& skin = model_.skins[size_t(s)];
    const std::string at = "skins[" + std::to_string(s) + "]" + named(skin.name);
    std::optional<View> ibm;
    if (skin.inverseBindMatrices >= 0) {
      ibm = check_accessor(skin.inverseBindMatrices, Attribute::InverseBindMatrices,
                           at + ".inverseBindMatrices");
      if (ibm->count < skin.joints.size())
        fail("skins[" + std::to_string(s) + "].inverseBindMatrices (accessors[" +
             std::to_string(skin.inverseBindMatrices) + "]): " + std::to_string(ibm->count) +
             " matrices for " + std::to_string(skin.joints.size()) + " joints");
    }
    std::vector<Mat4> out;
    for (size_t k = 0; k < skin.joints.size(); ++k) {
      const int j = skin.joints[k];
      if (j < 0 || j >= int(model_.nodes.size()))
        fail("skins[" + std::to_string(s) + "].joints[" + std::to_string(k) +
             "]: refers to missing node " + std::to_string(j));
      Mat4 inverse_bind = Mat4::identity();
      if (ibm)
        for (int c = 0; c < 16; ++c) inverse_bind.m[size_t(c / 4)][size_t(c % 4)] = ibm->get(k, c);
      out.push_back(global_transform(j) * inverse_bind);
    }
    return joint_matrices_.emplace(s, std::move(out)).first->second;
  }

  Deformation deformation_of(int index, const std::string& where) {
    const tinygltf::Node& node = model_.nodes[size_t(index)];
    Deformation d;
    if (morph_target_count(node.mesh) > 0) {
      d.weights = morph_weights(index);
      if (std::all_of(d.weights.begin(), d.weights.end(), [](double w) { return w == 0.0; }))
        d.weights.clear();
    }
    if (node.skin >= 0) {
      if (node.skin >= int(model_.skins.size()))
        fail(where + ": 'skin' refers to missing skin " + std::to_string(node.skin));
      d.skin = node.skin;
      d.joint_matrices = joint_matrices(node.skin);
    }
    return d;
  }

  // The accessors a deformed primitive's vertices also depend on: primitives that share their
  // vertex attributes but not these get vertices of their own.
  static void add_deformation_key(const tinygltf::Primitive& prim, VertexKey* key) {
    for (const auto& [name, accessor] : prim.attributes)
      if (name.rfind("JOINTS_", 0) == 0 || name.rfind("WEIGHTS_", 0) == 0)
        key->emplace(name, accessor);
    for (size_t t = 0; t < prim.targets.size(); ++t)
      for (const auto& [name, accessor] : prim.targets[t])
        key->emplace("targets[" + std::to_string(t) + "]." + name, accessor);
  }

  // A deformed primitive's vertices: the morph targets' POSITION and NORMAL displacements
  // added with the weights (3.7.2.2), then the skin matrix sum_i w_i jointMatrix[j_i] over
  // every JOINTS_n / WEIGHTS_n set (3.7.3.3), or world for an unskinned node; normals with
  // the inverse transpose of that matrix.
  PosedVertices pose_vertices(const tinygltf::Primitive& prim, const VertexAttributes& a,
                              const Deformation& d, const Mat4& world, const std::string& where) {
    const size_t n = a.position.count;
    const View* nrm = a.normal ? &*a.normal : nullptr;
    std::vector<double> p(3 * n), nn(nrm ? 3 * n : 0);
    for (size_t vi = 0; vi < n; ++vi)
      for (int c = 0; c < 3; ++c) {
        p[3 * vi + size_t(c)] = a.position.get(vi, c);
        if (nrm) nn[3 * vi + size_t(c)] = nrm->get(vi, c);
      }
    for (size_t t = 0; t < prim.targets.size() && t < d.weights.size(); ++t) {
      const double w = d.weights[t];
      if (w == 0.0) continue;
      for (const auto& [name, accessor] : prim.targets[t]) {
        const bool position = name == "POSITION";
        if (!position && !(name == "NORMAL" && nrm)) continue;  // TANGENT etc.: not read
        const std::string tw = where + " targets[" + std::to_string(t) + "]." + name;
        const View v = check_accessor(
            accessor, position ? Attribute::MorphPosition : Attribute::MorphNormal, tw);
        if (v.count != n) fail(tw + ": count differs from POSITION's");
        std::vector<double>& dst = position ? p : nn;
        for (size_t vi = 0; vi < n; ++vi)
          for (int c = 0; c < 3; ++c) dst[3 * vi + size_t(c)] += w * v.get(vi, c);
      }
    }
    // The skin's influences: every JOINTS_n / WEIGHTS_n pair from n = 0 up.
    std::vector<std::pair<View, View>> sets;
    std::vector<int> joint_accessors;
    if (d.skin >= 0) {
      for (int set = 0;; ++set) {
        const std::string js = "JOINTS_" + std::to_string(set), ws = "WEIGHTS_" + std::to_string(set);
        const auto j = prim.attributes.find(js), w = prim.attributes.find(ws);
        if (j == prim.attributes.end() && w == prim.attributes.end()) break;
        if (j == prim.attributes.end() || w == prim.attributes.end())
          fail(where + ": " + (j == prim.attributes.end() ? ws + " without " + js
                                                          : js + " without " + ws));
        const View jv = check_accessor(j->second, Attribute::Joints, where + " " + js);
        const View wv = check_accessor(w->second, Attribute::Weights, where + " " + ws);
        if (jv.count != n || wv.count != n)
          fail(where + ": " + js + ", " + ws + " and POSITION counts differ");
        sets.push_back({jv, wv});
        joint_accessors.push_back(j->second);
      }
      if (sets.empty() && !warned_unskinned_) {
        warn(where + " (and possibly others): the node has a skin but the primitive no "
                     "JOINTS_0 and WEIGHTS_0; it is placed by its node, unskinned");
        warned_unskinned_ = true;
      }
    }
    PosedVertices out;
    out.positions.resize(n);
    if (nrm) out.normals.resize(n);
    if (!sets.empty()) out.mirrored.resize(n);
    const size_t joint_count = d.joint_matrices.size();
    std::vector<uint32_t> joints(4 * sets.size());
    std::vector<double> weights(4 * sets.size());
    for (size_t vi = 0; vi < n; ++vi) {
      Mat4 m = world;
      if (!sets.empty()) {
        for (size_t k = 0; k < sets.size(); ++k)
          for (int c = 0; c < 4; ++c) {
            const double j = sets[k].first.raw(vi, c);
            if (!(j < double(joint_count)))
              fail("accessors[" + std::to_string(joint_accessors[k]) + "] (" + where +
                   " JOINTS_" + std::to_string(k) + "): vertex " + std::to_string(vi) +
                   " refers to joint " + std::to_string(uint64_t(j)) + ", but skins[" +
                   std::to_string(d.skin) + "] has " + std::to_string(joint_count) + " joints");
            joints[4 * k + size_t(c)] = uint32_t(j);
            weights[4 * k + size_t(c)] = sets[k].second.get(vi, c);
          }
        m = blend_skin_matrix(d.joint_matrices, joints.data(), weights.data(), joints.size());
        out.mirrored[vi] = m.det3() < 0.0;
      }
      out.positions[vi] = transform_point(m, &p[3 * vi]);
      if (nrm) out.normals[vi] = transform_normal(m, &nn[3 * vi]);
    }
    return out;
  }

  // Appends a primitive's vertices to *out, transformed by world: *first is the index of the
  // first, bad_normal[i] tells the vertices whose normal does not survive the transform (zero
  // or non-finite), which take the normals of the triangles that use them away.
  // posed: the vertices' world positions and normals when a skin or morph targets deform
  // them (world is then not used).
  void append_vertices(const VertexAttributes& a, const Mat4& world, TriangleMesh* out,
                       uint32_t* first, std::vector<bool>* bad_normal, const std::string& where,
                       const PosedVertices* posed = nullptr) {
    const View& pos = a.position;
    const View* nrm = a.normal ? &*a.normal : nullptr;
    const View* col = a.color ? &*a.color : nullptr;
    *first = uint32_t(out->positions.size());
    if (size_t(*first) + pos.count > size_t(UINT32_MAX))
      fail(where + ": more than 2^32 vertices in one mesh");
    // Attribute arrays are written for every vertex once any primitive has them (zeros, or
    // white for colours, where a primitive has not).
    const bool write_normals = out->use_normals(nrm != nullptr);
    const bool write_colors = out->use_colors(col != nullptr);
    const View* tan = a.tangent ? &*a.tangent : nullptr;
    const bool write_tangents = out->use_tangents(tan != nullptr);
    // A tangent is a direction on the surface: transformed as positions' differences are;
    // a mirroring transform reverses the bitangent cross(normal, tangent), so the handedness
    // turns (the winding, which add_mesh swaps, does not enter it).
    const float handedness = world.det3() < 0.0 ? -1.f : 1.f;
    std::vector<const View*> uv_of;  // per set: this primitive's view, or null
    for (const auto& [set, view] : a.uv) {
      out->use_uv(set, true);
      if (uv_of.size() <= set) uv_of.resize(set + 1, nullptr);
      uv_of[set] = &view;
    }
    uv_of.resize(out->uv.size(), nullptr);
    std::vector<uint32_t> write_uv;  // the sets to write
    for (uint32_t set = 0; set < out->uv.size(); ++set)
      if (uv_of[set] || !out->uv[set].empty()) write_uv.push_back(set);
    if (nrm) bad_normal->assign(pos.count, false);
    for (size_t vi = 0; vi < pos.count; ++vi) {
      out->positions.push_back(
          posed ? posed->positions[vi]
                : world.transform_point({pos.get(vi, 0), pos.get(vi, 1), pos.get(vi, 2)}));
      if (write_normals) {
        Vec3 n;
        if (nrm) {
          n = posed ? posed->normals[vi]
                    : world.transform_normal({nrm->get(vi, 0), nrm->get(vi, 1), nrm->get(vi, 2)});
          const float len = length(n);
          if (len > 0.f && std::isfinite(len)) {
            n = n / len;
          } else {
            n = Vec3();
            (*bad_normal)[vi] = true;
          }
        }
        out->normals.push_back(n);
      }
      for (uint32_t set : write_uv)
        out->uv[set].push_back(uv_of[set] ? Point2{uv_of[set]->get(vi, 0), uv_of[set]->get(vi, 1)}
                                          : Point2{0.f, 0.f});
      if (write_colors)
        out->colors.push_back(col ? Rgba{col->get(vi, 0), col->get(vi, 1), col->get(vi, 2),
                                         col->components == 4 ? col->get(vi, 3) : 1.f}
                                  : Rgba{});
      if (write_tangents) {
        TriangleMesh::Tangent t;
        if (tan) {
          t.xyz = world.transform_vector({tan->get(vi, 0), tan->get(vi, 1), tan->get(vi, 2)});
          const float w = tan->get(vi, 3);
          t.w = std::isfinite(length(t.xyz)) && w != 0.f ? (w < 0.f ? -handedness : handedness)
                                                         : 0.f;
        }
        out->tangents.push_back(t);
      }
    }
  }

  // glTF primitive modes that are surfaces: TRIANGLES (the default), TRIANGLE_STRIP and
  // TRIANGLE_FAN.
  static bool is_triangles(int mode) {
    return mode == -1 || mode == TINYGLTF_MODE_TRIANGLES ||
           mode == TINYGLTF_MODE_TRIANGLE_STRIP || mode == TINYGLTF_MODE_TRIANGLE_FAN;
  }
  static size_t triangle_count(int mode, size_t indices) {
    if (mode == TINYGLTF_MODE_TRIANGLE_STRIP || mode == TINYGLTF_MODE_TRIANGLE_FAN)
      return indices >= 3 ? indices - 2 : 0;
    return indices / 3;
  }
  // Vertex k (0, 1, 2) of triangle t of a primitive of that mode with these indices (glTF
  // 2.0, 3.7.2.1, "Topology types"): strips alternate their winding so that every triangle
  // keeps the first one's orientation; fans turn around their first vertex.
  static uint32_t corner(int mode, const std::vector<uint32_t>& indices, size_t t, int k) {
    if (mode == TINYGLTF_MODE_TRIANGLE_STRIP) {
      const size_t odd = t % 2;
      return indices[t + (k == 0 ? 0 : k == 1 ? 1 + odd : 2 - odd)];
    }
    if (mode == TINYGLTF_MODE_TRIANGLE_FAN) return indices[k == 2 ? 0 : t + size_t(k) + 1];
    return indices[3 * t + size_t(k)];
  }

  // deform: the node's skin and morph target weights (null: none; world places the mesh).
  void add_mesh(size_t mesh_index, const Mat4& world, TriangleMesh* out,
                const Deformation* deform = nullptr) {
    const tinygltf::Mesh& mesh = model_.meshes[mesh_index];
    const bool mirror = world.det3() < 0.0;
    // Vertices already appended for this mesh by an earlier primitive with the same
    // attribute accessors: their first index, and which of them lost their normal.
    struct Appended {
      uint32_t first = 0;
      std::vector<bool> bad_normal;
      std::vector<uint8_t> mirrored;  // skinned: per vertex, whether its skin matrix mirrors
    };
    std::map<VertexKey, Appended> appended;
    for (size_t pi = 0; pi < mesh.primitives.size(); ++pi) {
      const tinygltf::Primitive& prim = mesh.primitives[pi];
      const std::string where = "meshes[" + std::to_string(mesh_index) + "].primitives[" +
                                std::to_string(pi) + "]" + named(mesh.name);
      if (!is_triangles(prim.mode)) {
        warn(where + ": mode " + std::to_string(prim.mode) +
             " is points or lines, not triangles (4, 5 or 6); primitive skipped");
        continue;
      }
      const auto pos_it = prim.attributes.find("POSITION");
      if (pos_it == prim.attributes.end()) fail(where + ": missing required attribute POSITION");
      VertexAttributes attrs;
      attrs.position = check_accessor(pos_it->second, Attribute::Position, where + " POSITION");
      const View& pos = attrs.position;
      for (const auto& [name, accessor] : prim.attributes) {
        if (name == "POSITION" || !reads_attribute(name)) continue;
        if (name == "TANGENT") {
          // Read for rigid meshes; a skinned or morphed one takes its tangents from the
          // texture coordinates (warned below).
          if (deform) continue;
          attrs.tangent = check_accessor(accessor, Attribute::Tangent, where + " TANGENT");
          if (attrs.tangent->count != pos.count)
            fail(where + ": TANGENT and POSITION counts differ");
          continue;
        }
        uint32_t array = 0;
        const bool texcoord = uv_array(name, &array);
        const Attribute kind = name == "NORMAL"    ? Attribute::Normal
                               : name == "COLOR_0" ? Attribute::Color
                                                   : Attribute::Texcoord;
        const View view = check_accessor(accessor, kind, where + " " + name);
        if (view.count != pos.count) fail(where + ": " + name + " and POSITION counts differ");
        if (kind == Attribute::Normal) attrs.normal = view;
        if (kind == Attribute::Color) attrs.color = view;
        if (texcoord) attrs.uv.push_back({array, view});
      }
      std::sort(attrs.uv.begin(), attrs.uv.end(),
                [](const auto& a, const auto& b) { return a.first < b.first; });
      const bool has_normals = attrs.normal.has_value();
      if (deform && prim.attributes.count("TANGENT") && !warned_tangent_ &&
          prim.material >= 0 && prim.material < int(model_.materials.size()) &&
          model_.materials[size_t(prim.material)].normalTexture.index >= 0) {
        warn(where + " (and possibly others): TANGENT of a skinned or morphed mesh is not "
                     "used; its normal maps take their tangents from the texture coordinates");
        warned_tangent_ = true;
      }
      bool has_uv[2] = {false, false};
      for (const auto& uv : attrs.uv)
        if (uv.first < 2) has_uv[uv.first] = true;
      uint32_t material = default_material_;
      if (prim.material >= 0) {
        if (prim.material >= int(model_.materials.size()))
          fail(where + ": 'material' refers to missing material " +
               std::to_string(prim.material));
        material = uint32_t(prim.material);
      }
      const int mapped = variant_material(prim, mesh_index, pi);
      if (mapped >= 0) material = uint32_t(mapped);
      std::vector<uint32_t> indices;
      if (prim.indices >= 0) {
        const View idx = check_accessor(prim.indices, Attribute::Indices, where + " indices");
        indices.resize(idx.count);
        for (size_t i = 0; i < idx.count; ++i) {
          const double v = idx.raw(i, 0);
          if (v >= double(pos.count))
            fail(where + ": index " + std::to_string(uint64_t(v)) + " out of range (" +
                 std::to_string(pos.count) + " vertices)");
          indices[i] = uint32_t(v);
        }
      } else {
        indices.resize(pos.count);
        for (size_t i = 0; i < pos.count; ++i) indices[i] = uint32_t(i);
      }
      if (prim.mode != TINYGLTF_MODE_TRIANGLE_STRIP && prim.mode != TINYGLTF_MODE_TRIANGLE_FAN &&
          indices.size() % 3 != 0)
        warn(where + ": index count is not a multiple of 3; trailing indices ignored");
      // The primitive's vertices, each transformed once, appended after the mesh's others
      // (or those of an earlier primitive with the same attribute accessors).
      VertexKey key = vertex_key(prim);
      if (deform) add_deformation_key(prim, &key);
      const auto [entry, fresh] = appended.try_emplace(key);
      if (fresh && deform) {
        PosedVertices posed = pose_vertices(prim, attrs, *deform, world, where);
        append_vertices(attrs, world, out, &entry->second.first, &entry->second.bad_normal, where,
                        &posed);
        entry->second.mirrored = std::move(posed.mirrored);
      } else if (fresh) {
        append_vertices(attrs, world, out, &entry->second.first, &entry->second.bad_normal, where);
      }
      const uint32_t first = entry->second.first;
      const std::vector<bool>& bad_normal = entry->second.bad_normal;
      const std::vector<uint8_t>& mirrored = entry->second.mirrored;
      const uint8_t base_flags = uint8_t((has_uv[0] ? TriangleMesh::kHasUv0 : 0) |
                                         (has_uv[1] ? TriangleMesh::kHasUv1 : 0) |
                                         (attrs.tangent ? TriangleMesh::kHasTangents : 0));
      const size_t triangles = triangle_count(prim.mode, indices.size());
      for (size_t t = 0; t < triangles; ++t) {
        bool normals_ok = has_normals;
        // A skinned triangle mirrors if its first vertex's skin matrix does.
        const bool flip = mirrored.empty() ? mirror : mirrored[corner(prim.mode, indices, t, 0)];
        for (int k = 0; k < 3; ++k) {
          // A mirroring transform flips the winding (glTF spec, "Transformations"): swap two
          // vertices so that counter-clockwise stays the front face in world space.
          const int src = flip ? (k == 0 ? 0 : 3 - k) : k;
          const uint32_t vi = corner(prim.mode, indices, t, src);
          if (has_normals && bad_normal[vi]) normals_ok = false;
          out->indices.push_back(first + vi);
        }
        out->material.push_back(material);
        out->flags.push_back(uint8_t(base_flags | (normals_ok ? TriangleMesh::kHasNormals : 0)));
      }
      // Degenerate triangles are dropped by Scene.
    }
  }

  std::vector<std::optional<PunctualLight>> lights_;
  std::vector<int> parent_;                   // per node: its parent, -1 for none
  std::map<int, NodePose> poses_;             // the animated nodes' poses at options_.time
  std::map<int, Mat4> global_;                // world matrices global_transform computed
  std::map<int, std::vector<Mat4>> joint_matrices_;  // per skin
  std::vector<int> mesh_uses_;
  std::vector<int> mesh_slot_;
  // The animated layout (AnimatedLayout), if the options ask for one: the nodes whose TRS or
  // weights a chosen channel animates, per node whether it moves and whether its deformation
  // varies, and the meshes of varying deformed nodes.
  AnimatedLayout* split_ = nullptr;
  std::set<int> trs_animated_, weights_animated_;
  std::vector<char> moving_, varying_;
  std::vector<int> deformed_slots_;
  uint32_t moving_mesh_nodes_ = 0;
  std::set<std::string> warned_material_ext_, warned_texture_ext_;
  int variant_ = -1;  // KHR_materials_variants: the selected variant, -1 for none
  bool warned_occlusion_ = false, warned_unskinned_ = false;
  bool warned_tangent_ = false;
  bool quantization_ = false;         // KHR_mesh_quantization's attribute types are allowed
  // The TriangleMesh::uv array of each TEXCOORD set above 1 that a material reads.
  std::map<uint32_t, uint32_t> uv_array_of_set_;
  // Sparse accessors, materialized: each one's elements with its sparse values applied,
  // packed in its componentType.
  std::map<int, std::vector<unsigned char>> sparse_data_;
  const tinygltf::Model& model_;
  std::string source_;
  std::vector<std::string>* warnings_;
  const LoadOptions& options_;
  uint32_t default_material_ = 0;
};

// tinygltf's result, checked, with its compressed geometry decoded: the parsed document.
std::shared_ptr<const GltfDocument> parsed(bool ok, tinygltf::Model* model, const std::string& err,
                                           const std::string& warn, const std::string& source,
                                           std::vector<std::string>* warnings,
                                           const LoadOptions& options,
                                           const std::map<int, size_t>& fallbacks) {
  if (!warn.empty() && warnings) warnings->push_back(source + ": " + warn);
  if (!ok) throw SceneError(source + ": cannot parse glTF: " + (err.empty() ? "unknown" : err));
  decode_compressed_geometry(model, fallbacks, options.limits, source);
  auto document = std::make_shared<GltfDocument>();
  document->model = std::move(*model);
  document->source = source;
  return document;
}

// Uploads are self-contained: a file system whose every read is refused, so that a URI in a
// farm scene can never read a file of the worker's (or of the server's, when it inspects one).
// Files "exist" so that tinygltf asks to read them and the refusal says why.
bool no_file_exists(const std::string&, void*) { return true; }
bool no_file_read(std::vector<unsigned char>*, std::string* err, const std::string& path, void*) {
  if (err) *err += "external file '" + path + "' refused: farm scenes must be self-contained\n";
  return false;
}
bool no_file_write(std::string*, const std::string&, const std::vector<unsigned char>&, void*) {
  return false;
}

// tinygltf decodes the data: URIs of a few MIME types itself (PNG, JPEG, BMP, GIF, buffers)
// and takes any other (image/webp, image/avif, image/ktx2) for a file name, joined to the
// scene's folder. The file callbacks below recognise such a "file" by its data: URI (the
// last "data:" in the path: base64 has no ':') and decode it.
std::optional<std::string> data_uri_payload(const std::string& path) {
  const size_t start = path.rfind("data:");
  if (start == std::string::npos) return std::nullopt;
  const size_t comma = path.find(";base64,", start);
  if (comma == std::string::npos || path.find('/', start) > comma) return std::nullopt;
  return path.substr(comma + 8);
}
// RFC 4648 base64 (tinygltf keeps its decoder to itself); false on a character outside the
// alphabet. tinygltf has URI-decoded the path, which turns '+' into ' ': taken back here.
bool base64_decode(const std::string& text, std::vector<unsigned char>* out) {
  out->clear();
  uint32_t bits = 0;
  int count = 0;
  for (char ch : text) {
    int v;
    if (ch >= 'A' && ch <= 'Z') v = ch - 'A';
    else if (ch >= 'a' && ch <= 'z') v = ch - 'a' + 26;
    else if (ch >= '0' && ch <= '9') v = ch - '0' + 52;
    else if (ch == '+' || ch == ' ') v = 62;
    else if (ch == '/') v = 63;
    else if (ch == '=') break;
    else return false;
    bits = (bits << 6) | uint32_t(v);
    if ((count += 6) >= 8) {
      count -= 8;
      out->push_back(static_cast<unsigned char>((bits >> count) & 0xffu));
    }
  }
  return true;
}
bool file_exists(const std::string& path, void* allow_files) {
  if (data_uri_payload(path)) return true;
  return allow_files ? tinygltf::FileExists(path, nullptr) : no_file_exists(path, nullptr);
}
std::string expand_path(const std::string& path, void* allow_files) {
  if (data_uri_payload(path) || !allow_files) return path;
  return tinygltf::ExpandFilePath(path, nullptr);
}
bool read_file(std::vector<unsigned char>* out, std::string* err, const std::string& path,
               void* allow_files) {
  if (const std::optional<std::string> payload = data_uri_payload(path)) {
    if (!base64_decode(*payload, out) || out->empty()) {
      if (err) *err += "a data: URI that is not base64 data\n";
      return false;
    }
    return true;
  }
  return allow_files ? tinygltf::ReadWholeFile(out, err, path, nullptr)
                     : no_file_read(out, err, path, nullptr);
}

void configure(tinygltf::TinyGLTF* gltf, const LoadOptions& options) {
  gltf->SetImageLoader(keep_encoded_image, nullptr);
  // The user data is only a flag: non-null when the scene may read files beside it.
  static int allow = 1;
  gltf->SetFsCallbacks({file_exists, expand_path, read_file, no_file_write,
                        options.allow_external_files ? &allow : nullptr});
}

}  // namespace

std::shared_ptr<const GltfDocument> parse_gltf(const std::string& path,
                                               std::vector<std::string>* warnings,
                                               const LoadOptions& options) {
  const std::string source = options.display_name.empty() ? path : options.display_name;
  // Read here rather than by tinygltf, whose file callbacks may refuse every file.
  std::ifstream in(path, std::ios::binary);
  if (!in) throw SceneError(source + ": cannot open file");
  std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  if (in.bad()) throw SceneError(source + ": cannot read file");
  const bool binary = bytes.size() >= 4 && std::memcmp(bytes.data(), "glTF", 4) == 0;
  std::map<int, size_t> fallbacks;  // meshopt buffers that only exist to be decoded into
  // (compressed files are rewritten where tinygltf would refuse them: gltf_compression.h)
  if (binary)
    prepare_compressed_glb(&bytes, &fallbacks);
  else
    prepare_compressed_json(&bytes, &fallbacks);
  tinygltf::TinyGLTF gltf;
  configure(&gltf, options);
  tinygltf::Model model;
  std::string err, warn;
  const std::string base_dir = std::filesystem::path(path).parent_path().string();
  const bool ok =
      binary ? gltf.LoadBinaryFromMemory(&model, &err, &warn,
                                         reinterpret_cast<const unsigned char*>(bytes.data()),
                                         unsigned(bytes.size()), base_dir)
             : gltf.LoadASCIIFromString(&model, &err, &warn, bytes.data(), unsigned(bytes.size()),
                                        base_dir);
  return parsed(ok, &model, err, warn, source, warnings, options, fallbacks);
}

SceneDescription describe_gltf(const GltfDocument& document, std::vector<std::string>* warnings,
                               const LoadOptions& options) {
  return Loader(document.model, document.source, warnings, options).run();
}

std::vector<std::string> gltf_variant_names(const GltfDocument& document) {
  return Loader::variant_names(document.model);
}

std::vector<std::string> gltf_animation_names(const GltfDocument& document) {
  std::vector<std::string> names;
  for (const tinygltf::Animation& a : document.model.animations) names.push_back(a.name);
  return names;
}

size_t gltf_document_bytes(const GltfDocument& document) {
  size_t bytes = 0;
  for (const tinygltf::Buffer& b : document.model.buffers) bytes += b.data.size();
  for (const tinygltf::Image& i : document.model.images) bytes += i.image.size();
  return bytes;
}

SceneDescription load_gltf(const std::string& path, std::vector<std::string>* warnings,
                           const LoadOptions& options) {
  return describe_gltf(*parse_gltf(path, warnings, options), warnings, options);
}

SceneDescription load_gltf_from_string(const std::string& json, const std::string& base_dir,
                                       const std::string& name,
                                       std::vector<std::string>* warnings,
                                       const LoadOptions& options) {
  tinygltf::TinyGLTF gltf;
  configure(&gltf, options);
  tinygltf::Model model;
  std::string err, warn;
  std::string text = json;
  std::map<int, size_t> fallbacks;
  prepare_compressed_json(&text, &fallbacks);
  const bool ok = gltf.LoadASCIIFromString(&model, &err, &warn, text.c_str(),
                                           unsigned(text.size()), base_dir);
  return describe_gltf(*parsed(ok, &model, err, warn, name, warnings, options, fallbacks),
                       warnings, options);
}

}  // namespace rf
