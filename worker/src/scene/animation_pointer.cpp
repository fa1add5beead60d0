#include "scene/animation_pointer.h"

#include <tiny_gltf.h>

#include <set>

namespace rf {

namespace {

// The reference tokens of an RFC 6901 pointer ("" is the whole document: no tokens); false if
// it does not start with '/' or has a '~' that is not ~0 or ~1.
bool split_pointer(const std::string& pointer, std::vector<std::string>* tokens) {
  tokens->clear();
  if (pointer.empty()) return true;
  if (pointer[0] != '/') return false;
  std::string token;
  for (size_t i = 1; i <= pointer.size(); ++i) {
    if (i == pointer.size() || pointer[i] == '/') {
      tokens->push_back(token);
      token.clear();
    } else if (pointer[i] == '~') {
      if (i + 1 >= pointer.size() || (pointer[i + 1] != '0' && pointer[i + 1] != '1'))
        return false;
      token += pointer[i + 1] == '0' ? '~' : '/';
      ++i;
    } else {
      token += pointer[i];
    }
  }
  return true;
}

// An array index token: "0" or digits without a leading zero, below `size`.
bool array_index(const std::string& token, size_t size, int* out) {
  if (token.empty() || token.size() > 9 || (token.size() > 1 && token[0] == '0')) return false;
  for (char c : token)
    if (c < '0' || c > '9') return false;
  const size_t i = std::stoul(token);
  if (i >= size) return false;
  *out = int(i);
  return true;
}

// Material extensions the renderer reads, whose properties a pointer may animate.
const std::set<std::string>& material_extensions() {
  static const std::set<std::string> s = {
      "KHR_materials_emissive_strength", "KHR_materials_transmission", "KHR_materials_ior",
      "KHR_materials_specular",          "KHR_materials_volume",       "KHR_materials_clearcoat",
      "KHR_materials_sheen",             "KHR_materials_anisotropy",   "KHR_materials_iridescence",
      "KHR_materials_diffuse_transmission", "KHR_materials_dispersion"};
  return s;
}

// Extension properties that are colours (float3) by the extension texts; the others the
// renderer reads are floats.
bool is_colour(const std::string& property) {
  return property == "sheenColorFactor" || property == "specularColorFactor" ||
         property == "attenuationColor" || property == "diffuseTransmissionColorFactor";
}

// KHR_texture_transform's animatable properties and their sizes.
bool texture_transform_property(const std::string& p, size_t* components) {
  if (p == "offset" || p == "scale") {
    *components = 2;
    return true;
  }
  if (p == "rotation") {
    *components = 1;
    return true;
  }
  return false;
}

// The extensions of the core material's texture reference named by the first tokens of t
// (pbrMetallicRoughness/baseColorTexture, normalTexture, ...), *used of them; null if t does
// not start with one. Mat is tinygltf::Material, const or not.
template <class Mat>
auto core_texture_extensions(Mat& m, const std::vector<std::string>& t, size_t* used)
    -> decltype(&m.normalTexture.extensions) {
  if (t.size() >= 2 && t[0] == "pbrMetallicRoughness") {
    *used = 2;
    if (t[1] == "baseColorTexture") return &m.pbrMetallicRoughness.baseColorTexture.extensions;
    if (t[1] == "metallicRoughnessTexture")
      return &m.pbrMetallicRoughness.metallicRoughnessTexture.extensions;
    return nullptr;
  }
  *used = 1;
  if (t.empty()) return nullptr;
  if (t[0] == "normalTexture") return &m.normalTexture.extensions;
  if (t[0] == "occlusionTexture") return &m.occlusionTexture.extensions;
  if (t[0] == "emissiveTexture") return &m.emissiveTexture.extensions;
  return nullptr;
}

bool resolve_material(const tinygltf::Material& m, const std::vector<std::string>& t,
                      PointerTarget* out, std::string* why, bool* missing) {
  auto path = [&] {
    std::string s;
    for (const std::string& x : t) s += "/" + x;
    return s;
  };
  out->components = 1;
  if (t.size() == 2 && t[0] == "pbrMetallicRoughness" &&
      (t[1] == "baseColorFactor" || t[1] == "metallicFactor" || t[1] == "roughnessFactor")) {
    out->components = t[1] == "baseColorFactor" ? 4 : 1;
    return true;
  }
  if (t.size() == 1 && (t[0] == "emissiveFactor" || t[0] == "alphaCutoff")) {
    out->components = t[0] == "emissiveFactor" ? 3 : 1;
    return true;
  }
  if (t.size() == 2 && ((t[0] == "normalTexture" && t[1] == "scale") ||
                        (t[0] == "occlusionTexture" && t[1] == "strength"))) {
    const int index = t[0] == "normalTexture" ? m.normalTexture.index : m.occlusionTexture.index;
    if (index < 0) {
      *missing = true;
      *why = "the material has no " + t[0];
      return false;
    }
    return true;
  }
  // A texture reference's KHR_texture_transform: .../extensions/KHR_texture_transform/PROP.
  if (t.size() >= 4 && t[t.size() - 3] == "extensions" &&
      t[t.size() - 2] == "KHR_texture_transform") {
    if (!texture_transform_property(t.back(), &out->components)) {
      *why = "KHR_texture_transform." + t.back() + " is not animatable here";
      return false;
    }
    const std::vector<std::string> info(t.begin(), t.end() - 3);
    size_t used = 0;
    bool present = false;
    if (const tinygltf::ExtensionMap* ext = core_texture_extensions(m, info, &used)) {
      present = used == info.size() && ext->count("KHR_texture_transform") > 0;
    } else if (info.size() == 3 && info[0] == "extensions") {
      // An extension's texture: extensions/EXT/NAME.
      const auto e = m.extensions.find(info[1]);
      if (e != m.extensions.end() && e->second.IsObject() && e->second.Has(info[2])) {
        const tinygltf::Value& tex = e->second.Get(info[2]);
        present = tex.IsObject() && tex.Has("extensions") &&
                  tex.Get("extensions").IsObject() &&
                  tex.Get("extensions").Has("KHR_texture_transform");
      }
    }
    if (!present) {
      *missing = true;
      *why = "the material has no KHR_texture_transform at " + path();
      return false;
    }
    return true;
  }
  if (t.size() == 3 && t[0] == "extensions") {
    if (!material_extensions().count(t[1])) {
      *why = t[1] + " is not an extension the renderer reads";
      return false;
    }
    const auto e = m.extensions.find(t[1]);
    if (e == m.extensions.end() || !e->second.IsObject()) {
      *missing = true;
      *why = "the material has no " + t[1];
      return false;
    }
    if (e->second.Has(t[2])) {
      const tinygltf::Value& v = e->second.Get(t[2]);
      if (v.IsNumber()) return true;
      if (v.IsArray() && v.ArrayLen() >= 1 && v.ArrayLen() <= 4) {
        out->components = v.ArrayLen();
        return true;
      }
      *why = t[1] + "." + t[2] + " is not a number or a colour";
      return false;
    }
    out->components = is_colour(t[2]) ? 3 : 1;
    return true;
  }
  *why = "materials" + path() + " is not animatable here";
  return false;
}

// Sets obj[key] to v: a number, or an array of n numbers.
void set_member(tinygltf::Value* obj, const std::string& key, const double* v, size_t n,
                bool array) {
  if (!obj->IsObject()) *obj = tinygltf::Value(tinygltf::Value::Object());
  tinygltf::Value::Object& o = obj->Get<tinygltf::Value::Object>();
  if (!array) {
    o[key] = tinygltf::Value(v[0]);
    return;
  }
  tinygltf::Value::Array a;
  for (size_t i = 0; i < n; ++i) a.push_back(tinygltf::Value(v[i]));
  o[key] = tinygltf::Value(std::move(a));
}

}  // namespace

bool resolve_pointer(const tinygltf::Model& model, const std::string& pointer,
                     PointerTarget* out, std::string* why, bool* missing) {
  *missing = false;
  *out = PointerTarget{};
  std::vector<std::string> t;
  if (!split_pointer(pointer, &t)) {
    *missing = true;
    *why = "'" + pointer + "' is not a JSON pointer";
    return false;
  }
  auto nothing = [&](const std::string& what, size_t size) {
    *missing = true;
    *why = "refers to missing " + what + " (the scene has " + std::to_string(size) + ")";
    return false;
  };
  if (t.size() >= 2 && t[0] == "nodes") {
    if (!array_index(t[1], model.nodes.size(), &out->index))
      return nothing("node " + t[1], model.nodes.size());
    out->path.assign(t.begin() + 2, t.end());
    const std::vector<std::string>& p = out->path;
    if (p.size() == 1 && p[0] == "translation") {
      out->kind = PointerTarget::Kind::NodeTranslation;
      out->components = 3;
    } else if (p.size() == 1 && p[0] == "rotation") {
      out->kind = PointerTarget::Kind::NodeRotation;
      out->components = 4;
    } else if (p.size() == 1 && p[0] == "scale") {
      out->kind = PointerTarget::Kind::NodeScale;
      out->components = 3;
    } else if (p.size() == 1 && p[0] == "weights") {
      out->kind = PointerTarget::Kind::NodeWeights;
      out->components = 0;
    } else if (p.size() == 3 && p[0] == "extensions" && p[1] == "KHR_node_visibility" &&
               p[2] == "visible") {
      out->kind = PointerTarget::Kind::NodeVisible;
      out->boolean = true;
    } else {
      *why = pointer + " is not animatable here";
      return false;
    }
    return true;
  }
  if (t.size() >= 2 && t[0] == "materials") {
    if (!array_index(t[1], model.materials.size(), &out->index))
      return nothing("material " + t[1], model.materials.size());
    out->kind = PointerTarget::Kind::Material;
    out->path.assign(t.begin() + 2, t.end());
    return resolve_material(model.materials[size_t(out->index)], out->path, out, why, missing);
  }
  if (t.size() >= 4 && t[0] == "extensions" && t[1] == "KHR_lights_punctual" &&
      t[2] == "lights") {
    // The lights as the loader reads them: the extension's list.
    static const tinygltf::Value kNone;
    const auto ext = model.extensions.find("KHR_lights_punctual");
    const tinygltf::Value& list =
        ext != model.extensions.end() && ext->second.Has("lights") ? ext->second.Get("lights")
                                                                   : kNone;
    const size_t count = list.IsArray() ? list.ArrayLen() : 0;
    if (!array_index(t[3], count, &out->index)) return nothing("light " + t[3], count);
    out->kind = PointerTarget::Kind::Light;
    out->path.assign(t.begin() + 4, t.end());
    const std::vector<std::string>& p = out->path;
    const tinygltf::Value& light = list.Get(out->index);
    const bool spot = light.Has("type") && light.Get("type").IsString() &&
                      light.Get("type").Get<std::string>() == "spot";
    if (p.size() == 1 && (p[0] == "color" || p[0] == "intensity" || p[0] == "range")) {
      out->components = p[0] == "color" ? 3 : 1;
      return true;
    }
    if (p.size() == 2 && p[0] == "spot" &&
        (p[1] == "innerConeAngle" || p[1] == "outerConeAngle")) {
      if (!spot) {
        *missing = true;
        *why = "light " + t[3] + " is not a spot light";
        return false;
      }
      return true;
    }
    *why = pointer + " is not animatable here";
    return false;
  }
  if (t.size() >= 2 && t[0] == "cameras") {
    if (!array_index(t[1], model.cameras.size(), &out->index))
      return nothing("camera " + t[1], model.cameras.size());
    out->kind = PointerTarget::Kind::Camera;
    out->path.assign(t.begin() + 2, t.end());
    const std::vector<std::string>& p = out->path;
    const tinygltf::Camera& cam = model.cameras[size_t(out->index)];
    if (p.size() == 2 && (p[0] == "perspective" || p[0] == "orthographic")) {
      const bool perspective = p[0] == "perspective";
      const bool known = perspective ? (p[1] == "yfov" || p[1] == "aspectRatio" ||
                                        p[1] == "znear" || p[1] == "zfar")
                                     : (p[1] == "xmag" || p[1] == "ymag" || p[1] == "znear" ||
                                        p[1] == "zfar");
      if (!known) {
        *why = pointer + " is not animatable here";
        return false;
      }
      if (cam.type != p[0]) {
        *missing = true;
        *why = "camera " + t[1] + " is not " + p[0];
        return false;
      }
      // Properties without a default must be in the file (tinygltf reads them as 0).
      if (perspective && ((p[1] == "zfar" && !(cam.perspective.zfar > 0.0)) ||
                          (p[1] == "aspectRatio" && !(cam.perspective.aspectRatio > 0.0)))) {
        *missing = true;
        *why = "camera " + t[1] + " has no " + p[1];
        return false;
      }
      return true;
    }
    *why = pointer + " is not animatable here";
    return false;
  }
  *why = pointer + " is not animatable here";
  return false;
}

void apply_pointer(const PointerTarget& target, const double* v, tinygltf::Material* m) {
  const std::vector<std::string>& t = target.path;
  const size_t n = target.components;
  if (t.size() == 2 && t[0] == "pbrMetallicRoughness") {
    if (t[1] == "baseColorFactor") m->pbrMetallicRoughness.baseColorFactor.assign(v, v + 4);
    if (t[1] == "metallicFactor") m->pbrMetallicRoughness.metallicFactor = v[0];
    if (t[1] == "roughnessFactor") m->pbrMetallicRoughness.roughnessFactor = v[0];
    return;
  }
  if (t.size() == 1) {
    if (t[0] == "emissiveFactor") m->emissiveFactor.assign(v, v + 3);
    if (t[0] == "alphaCutoff") m->alphaCutoff = v[0];
    return;
  }
  if (t.size() == 2 && t[0] == "normalTexture" && t[1] == "scale") {
    m->normalTexture.scale = v[0];
    return;
  }
  if (t.size() == 2 && t[0] == "occlusionTexture" && t[1] == "strength") {
    m->occlusionTexture.strength = v[0];
    return;
  }
  if (t.size() >= 4 && t[t.size() - 2] == "KHR_texture_transform") {
    const std::vector<std::string> info(t.begin(), t.end() - 3);
    size_t used = 0;
    tinygltf::Value* transform = nullptr;
    if (tinygltf::ExtensionMap* ext = core_texture_extensions(*m, info, &used)) {
      transform = &ext->at("KHR_texture_transform");
    } else {
      tinygltf::Value::Object& e = m->extensions.at(info[1]).Get<tinygltf::Value::Object>();
      tinygltf::Value::Object& tex = e.at(info[2]).Get<tinygltf::Value::Object>();
      tinygltf::Value::Object& exts = tex.at("extensions").Get<tinygltf::Value::Object>();
      transform = &exts.at("KHR_texture_transform");
    }
    set_member(transform, t.back(), v, n, n > 1);
    return;
  }
  if (t.size() == 3 && t[0] == "extensions") {
    tinygltf::Value& ext = m->extensions.at(t[1]);
    const bool array = n > 1 || (ext.Has(t[2]) && ext.Get(t[2]).IsArray());
    set_member(&ext, t[2], v, n, array);
  }
}

void apply_pointer(const PointerTarget& target, const double* v, tinygltf::Value* light) {
  const std::vector<std::string>& t = target.path;
  if (t.size() == 1) {
    set_member(light, t[0], v, target.components, t[0] == "color");
  } else if (t.size() == 2 && t[0] == "spot") {
    if (!light->IsObject()) *light = tinygltf::Value(tinygltf::Value::Object());
    tinygltf::Value& spot = light->Get<tinygltf::Value::Object>()["spot"];
    set_member(&spot, t[1], v, 1, false);
  }
}

void apply_pointer(const PointerTarget& target, const double* v, tinygltf::Camera* c) {
  const std::vector<std::string>& t = target.path;
  if (t.size() != 2) return;
  if (t[0] == "perspective") {
    if (t[1] == "yfov") c->perspective.yfov = v[0];
    if (t[1] == "aspectRatio") c->perspective.aspectRatio = v[0];
    if (t[1] == "znear") c->perspective.znear = v[0];
    if (t[1] == "zfar") c->perspective.zfar = v[0];
  } else {
    if (t[1] == "xmag") c->orthographic.xmag = v[0];
    if (t[1] == "ymag") c->orthographic.ymag = v[0];
    if (t[1] == "znear") c->orthographic.znear = v[0];
    if (t[1] == "zfar") c->orthographic.zfar = v[0];
  }
}

}  // namespace rf
