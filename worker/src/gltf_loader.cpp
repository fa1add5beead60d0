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
#include <optional>
#include <fstream>
#include <functional>
#include <map>
#include <set>

#include "scene.h"

namespace rf {
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
      "KHR_materials_specular",          "KHR_texture_transform",      "KHR_lights_punctual"};
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
    load_textures(&desc);
    load_materials(&desc);
    load_lights();
    count_mesh_uses();

    if (model_.nodes.size() > options_.limits.max_nodes)
      fail("nodes: the scene has " + std::to_string(model_.nodes.size()) +
           " nodes, over the limit of " + std::to_string(options_.limits.max_nodes));
    const std::vector<int> parent = check_hierarchy();
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
    check_cost(roots, &desc.stats);
    reserve(world_counts(roots), &desc.world);
    for (int root : roots) visit(root, Mat4::identity(), &desc, 0);
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
      for (const auto& ext : gt.extensions)
        warn(src.name + ": extension '" + ext.first + "' is not supported; using 'source'");
      if (gt.sampler >= 0 && gt.sampler < int(model_.samplers.size())) {
        src.wrap_s = wrap(model_.samplers[size_t(gt.sampler)].wrapS);
        src.wrap_t = wrap(model_.samplers[size_t(gt.sampler)].wrapT);
      }
      if (gt.source < 0 || gt.source >= int(model_.images.size())) {
        warn(src.name + ": missing image; texture ignored");
        src.path.clear();
      } else {
        const tinygltf::Image& img = model_.images[size_t(gt.source)];
        src.bytes = img.image;
        src.mime_type = img.mimeType;
        if (src.bytes.empty()) {
          warn(src.name + ": image " + std::to_string(gt.source) +
               " could not be loaded (uri '" + img.uri + "'); texture ignored");
        }
      }
      desc->textures.push_back(std::move(src));
    }
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
    if (ref.texcoord > 1) {
      warn(where + ": TEXCOORD_" + std::to_string(ref.texcoord) +
           " is not supported (only 0 and 1); texture ignored");
      ref.texture = -1;
    }
    return ref;
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

  // The accessors of a primitive's vertex attributes (POSITION, NORMAL, TEXCOORD_0,
  // TEXCOORD_1; -1 where absent). Primitives of one mesh with the same key share their
  // vertices (exporters often give every material's primitive the whole vertex buffer).
  using VertexKey = std::array<int, 4>;
  static VertexKey vertex_key(const tinygltf::Primitive& prim) {
    VertexKey key{-1, -1, -1, -1};
    const char* names[4] = {"POSITION", "NORMAL", "TEXCOORD_0", "TEXCOORD_1"};
    for (size_t i = 0; i < 4; ++i) {
      const auto it = prim.attributes.find(names[i]);
      if (it != prim.attributes.end()) key[i] = it->second;
    }
    return key;
  }

  // Vertex and triangle counts of meshes, for reserving TriangleMesh arrays exactly (no
  // growth slack, no copies while a scene of millions of triangles loads). Accessors that are
  // invalid count as empty here; add_mesh reports them.
  struct Counts {
    size_t vertices = 0, triangles = 0;
    bool normals = false, uv[2] = {false, false};
    void operator+=(const Counts& o) {
      vertices += o.vertices;
      triangles += o.triangles;
      normals = normals || o.normals;
      uv[0] = uv[0] || o.uv[0];
      uv[1] = uv[1] || o.uv[1];
    }
  };
  size_t accessor_count(int index) const {
    if (index < 0 || index >= int(model_.accessors.size())) return 0;
    return accessor_problem(model_.accessors[size_t(index)]).empty()
               ? model_.accessors[size_t(index)].count
               : 0;
  }

  // Why an accessor's data is not all in its buffer ("" if it is). check_accessor reports it.
  std::string accessor_problem(const tinygltf::Accessor& acc) const {
    if (acc.sparse.isSparse) return "sparse accessors are not supported";
    if (acc.bufferView < 0 || acc.bufferView >= int(model_.bufferViews.size()))
      return "missing or invalid 'bufferView'";
    const tinygltf::BufferView& bv = model_.bufferViews[size_t(acc.bufferView)];
    if (bv.buffer < 0 || bv.buffer >= int(model_.buffers.size()))
      return "buffer view refers to a missing buffer";
    const tinygltf::Buffer& buf = model_.buffers[size_t(bv.buffer)];
    const int ncomp = tinygltf::GetNumComponentsInType(uint32_t(acc.type));
    const int csize = tinygltf::GetComponentSizeInBytes(uint32_t(acc.componentType));
    if (ncomp <= 0 || csize <= 0) return "unsupported 'type' or 'componentType'";
    const size_t elem = size_t(ncomp) * size_t(csize);
    const size_t stride = bv.byteStride ? bv.byteStride : elem;
    if (stride < elem) return "'byteStride' smaller than the element";
    if (bv.byteOffset > buf.data.size() || bv.byteLength > buf.data.size() - bv.byteOffset)
      return "buffer view exceeds its buffer";
    if (acc.count > 0) {
      // In bytes, without overflow: count - 1 strides and one element after byteOffset.
      if (acc.byteOffset > bv.byteLength || elem > bv.byteLength - acc.byteOffset ||
          (acc.count - 1) > (bv.byteLength - acc.byteOffset - elem) / stride)
        return "data exceeds its buffer view";
    }
    return {};
  }
  Counts mesh_counts(size_t mesh_index) const {
    Counts c;
    std::set<VertexKey> seen;
    for (const tinygltf::Primitive& prim : model_.meshes[mesh_index].primitives) {
      if (prim.mode != TINYGLTF_MODE_TRIANGLES && prim.mode != -1) continue;
      const auto pos = prim.attributes.find("POSITION");
      if (pos == prim.attributes.end()) continue;
      const size_t nv = accessor_count(pos->second);
      if (seen.insert(vertex_key(prim)).second) c.vertices += nv;
      c.triangles += (prim.indices >= 0 ? accessor_count(prim.indices) : nv) / 3;
      c.normals = c.normals || prim.attributes.count("NORMAL");
      c.uv[0] = c.uv[0] || prim.attributes.count("TEXCOORD_0");
      c.uv[1] = c.uv[1] || prim.attributes.count("TEXCOORD_1");
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
          mesh_uses_[size_t(node.mesh)] == 1)
        c += mesh_counts(size_t(node.mesh));
      stack.insert(stack.end(), node.children.begin(), node.children.end());
    }
    return c;
  }
  static void reserve(const Counts& c, TriangleMesh* mesh) {
    // One vertex more: Embree reads the last vertex with a 16-byte load.
    mesh->positions.reserve(c.vertices + 1);
    if (c.normals) mesh->normals.reserve(c.vertices);
    for (int set = 0; set < 2; ++set)
      if (c.uv[set]) mesh->uv[set].reserve(c.vertices);
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
    std::vector<uint64_t> uses(model_.meshes.size(), 0);
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
        ++uses[size_t(node.mesh)];
        ++instances;
        stats->instanced_triangles += tris;
        if (stats->instanced_triangles > limits.max_instanced_triangles)
          fail(where + ": the scene's mesh uses add up to more than " +
               std::to_string(limits.max_instanced_triangles) + " triangles (the limit)");
      }
      for (int c : node.children) stack.push_back({c, depth + 1});
    }
    // Memory: each mesh once (a mesh used by several nodes is instanced, not copied), its
    // arrays as TriangleMesh holds them, Embree's BVH (README: about 70 bytes per triangle,
    // 45 for the compact layout), the instances, and the file's buffers, which the loader
    // holds until the scene is built.
    const double bvh_bytes = options_.bvh == BvhLayout::Compact ? 45.0 : 70.0;
    double bytes = 0.0;
    for (size_t m = 0; m < model_.meshes.size(); ++m) {
      if (!uses[m]) continue;
      const Counts c = mesh_counts(m);
      const double per_vertex = 12.0 + (c.normals ? 12.0 : 0.0) + (c.uv[0] ? 8.0 : 0.0) +
                                (c.uv[1] ? 8.0 : 0.0);
      bytes += double(c.vertices) * per_vertex +
               double(c.triangles) * (12.0 + 4.0 + 1.0 + 12.0 + bvh_bytes);
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
    for (const auto& node : model_.nodes)
      if (node.mesh >= 0 && node.mesh < int(model_.meshes.size())) ++mesh_uses_[size_t(node.mesh)];
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
                   path == "scene" || path == "meshes"
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
      m.metallic = float(gm.pbrMetallicRoughness.metallicFactor);
      m.roughness = float(gm.pbrMetallicRoughness.roughnessFactor);
      m.specular = 1.f;
      if (!(m.metallic >= 0.f && m.metallic <= 1.f))
        fail(where + ": pbrMetallicRoughness.metallicFactor must be in [0, 1]");
      if (!(m.roughness >= 0.f && m.roughness <= 1.f))
        fail(where + ": pbrMetallicRoughness.roughnessFactor must be in [0, 1]");
      for (const auto& e : gm.extensions)
        if (!supported_extensions().count(e.first) && warned_material_ext_.insert(e.first).second)
          warn(where + ": material extension '" + e.first + "' is not supported; ignoring it");
      auto tr = gm.extensions.find("KHR_materials_transmission");
      if (tr != gm.extensions.end()) {
        m.transmission = number_or(tr->second, "transmissionFactor", 0.f);
        if (tr->second.Has("transmissionTexture"))
          warn(where + ": KHR_materials_transmission.transmissionTexture is not supported; "
                       "using transmissionFactor");
        if (m.transmission > 0.f && m.roughness > 0.f && warned_rough_glass_.insert(i).second)
          warn(where + ": transmission is rendered as smooth glass (roughness ignored for it)");
      }
      if (!(m.transmission >= 0.f && m.transmission <= 1.f))
        fail(where + ": KHR_materials_transmission.transmissionFactor must be in [0, 1]");
      auto io = gm.extensions.find("KHR_materials_ior");
      if (io != gm.extensions.end()) m.ior = number_or(io->second, "ior", 1.5f);
      if (!(m.ior >= 1.f && m.ior < 10.f)) {
        warn(where + ": KHR_materials_ior.ior " + std::to_string(m.ior) +
             " outside [1, 10) is not supported; using 1.5");
        m.ior = 1.5f;
      }
      auto sp = gm.extensions.find("KHR_materials_specular");
      if (sp != gm.extensions.end()) {
        m.specular = std::min(1.f, std::max(0.f, number_or(sp->second, "specularFactor", 1.f)));
        if (sp->second.Has("specularColorFactor") || sp->second.Has("specularTexture") ||
            sp->second.Has("specularColorTexture"))
          warn(where + ": KHR_materials_specular color and textures are not supported; "
                       "using specularFactor");
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
      if (gm.alphaMode != "OPAQUE" && !gm.alphaMode.empty() && !warned_alpha_) {
        warn(where + " (and possibly others): alphaMode '" + gm.alphaMode +
             "' is not supported; rendering opaque");
        warned_alpha_ = true;
      }
      const auto& base = gm.pbrMetallicRoughness.baseColorFactor;
      if (base.size() >= 3)
        m.albedo = Vec3(float(base[0]), float(base[1]), float(base[2]));
      for (int k = 0; k < 3; ++k)
        if (!(m.albedo[k] >= 0.f && m.albedo[k] <= 1.f))
          fail(where + ": pbrMetallicRoughness.baseColorFactor must be in [0, 1]");
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
      desc->materials.push_back(m);
    }
    default_material_ = uint32_t(desc->materials.size());
    // Primitives without a material: white Lambertian (the glTF default material would be a
    // white metal, which surprises more than it helps).
    Material def;
    def.name = "default";
    desc->materials.push_back(def);
  }

  Mat4 local_transform(const tinygltf::Node& node, const std::string& where) const {
    if (node.matrix.size() == 16) {
      Mat4 m;
      for (int i = 0; i < 16; ++i) m.m[size_t(i / 4)][size_t(i % 4)] = node.matrix[size_t(i)];
      return m;
    }
    if (!node.matrix.empty()) fail(where + ": 'matrix' must have 16 elements");
    Mat4 t = Mat4::identity(), r = Mat4::identity(), s = Mat4::identity();
    if (!node.translation.empty()) {
      if (node.translation.size() != 3) fail(where + ": 'translation' must have 3 elements");
      for (int i = 0; i < 3; ++i) t.m[3][size_t(i)] = node.translation[size_t(i)];
    }
    if (!node.rotation.empty()) {
      if (node.rotation.size() != 4) fail(where + ": 'rotation' must have 4 elements");
      double x = node.rotation[0], y = node.rotation[1], z = node.rotation[2],
             w = node.rotation[3];
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
    if (!node.scale.empty()) {
      if (node.scale.size() != 3) fail(where + ": 'scale' must have 3 elements");
      for (int i = 0; i < 3; ++i) s.m[size_t(i)][size_t(i)] = node.scale[size_t(i)];
    }
    return t * r * s;
  }

  void visit(int index, const Mat4& parent, SceneDescription* desc, int depth) {
    if (index < 0 || index >= int(model_.nodes.size()))
      fail("reference to missing node " + std::to_string(index));
    // glTF node graphs are trees; a deeper chain than the node count means a cycle.
    if (depth > int(model_.nodes.size())) fail("node hierarchy contains a cycle");
    const tinygltf::Node& node = model_.nodes[size_t(index)];
    const std::string where = "nodes[" + std::to_string(index) + "]" + named(node.name);
    const Mat4 world = parent * local_transform(node, where);
    if (node.camera >= 0 && !desc->camera) take_camera(node, world, where, desc);
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
    if (node.mesh >= 0) {
      if (node.mesh >= int(model_.meshes.size()))
        fail(where + ": 'mesh' refers to missing mesh " + std::to_string(node.mesh));
      if (mesh_uses_[size_t(node.mesh)] > 1) {
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
        desc->instances.push_back({uint32_t(slot), world});
      } else {
        add_mesh(size_t(node.mesh), world, &desc->world);
      }
    }
    for (int child : node.children) visit(child, world, desc, depth + 1);
  }

  void take_camera(const tinygltf::Node& node, const Mat4& world, const std::string& where,
                   SceneDescription* desc) {
    if (node.camera >= int(model_.cameras.size()))
      fail(where + ": 'camera' refers to missing camera " + std::to_string(node.camera));
    const tinygltf::Camera& gc = model_.cameras[size_t(node.camera)];
    if (gc.type != "perspective") return;  // only the first *perspective* camera counts
    Camera cam;
    cam.yfov = float(gc.perspective.yfov);
    if (!(cam.yfov > 0.f && cam.yfov < kPi))
      fail("cameras[" + std::to_string(node.camera) + "].perspective.yfov: " +
           std::to_string(gc.perspective.yfov) + " is outside (0, pi) (camera of " + where + ")");
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

  // Reads element i (component c) of an accessor as a double; range-checked by the caller's
  // prior call to check_accessor.
  struct View {
    const unsigned char* base = nullptr;
    size_t stride = 0;
    int component_type = 0;
    size_t count = 0;
    bool normalized = false;
    double get(size_t i, int c) const {
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
        case TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE:
          return p[c];
        default:
          return 0.0;
      }
    }
  };

  View check_accessor(int index, int want_type, const std::set<int>& component_types,
                      const std::string& where) const {
    if (index < 0 || index >= int(model_.accessors.size()))
      fail(where + " refers to missing accessor " + std::to_string(index));
    const tinygltf::Accessor& acc = model_.accessors[size_t(index)];
    const std::string aw = "accessors[" + std::to_string(index) + "] (" + where + ")";
    if (acc.type != want_type) fail(aw + ": unexpected accessor 'type'");
    if (!component_types.count(acc.componentType))
      fail(aw + ": unsupported 'componentType' " + std::to_string(acc.componentType));
    const std::string problem = accessor_problem(acc);
    if (!problem.empty()) fail(aw + ": " + problem);
    const tinygltf::BufferView& bv = model_.bufferViews[size_t(acc.bufferView)];
    const tinygltf::Buffer& buf = model_.buffers[size_t(bv.buffer)];
    const size_t elem = size_t(tinygltf::GetNumComponentsInType(uint32_t(acc.type))) *
                        size_t(tinygltf::GetComponentSizeInBytes(uint32_t(acc.componentType)));
    View v;
    v.component_type = acc.componentType;
    v.count = acc.count;
    v.stride = bv.byteStride ? bv.byteStride : elem;
    v.normalized = acc.normalized;
    v.base = buf.data.data() + bv.byteOffset + acc.byteOffset;
    return v;
  }

  // Appends a primitive's vertices to *out, transformed by world: *first is the index of the
  // first, bad_normal[i] tells the vertices whose normal does not survive the transform (zero
  // or non-finite), which take the normals of the triangles that use them away.
  void append_vertices(const View& pos, const View* nrm, const View uvs[2], const bool has_uv[2],
                       const Mat4& world, TriangleMesh* out, uint32_t* first,
                       std::vector<bool>* bad_normal, const std::string& where) {
    *first = uint32_t(out->positions.size());
    if (size_t(*first) + pos.count > size_t(UINT32_MAX))
      fail(where + ": more than 2^32 vertices in one mesh");
    // Attribute arrays are written for every vertex once any primitive has them (zeros
    // where a primitive has not).
    const bool write_normals = out->use_normals(nrm != nullptr);
    const bool write_uv[2] = {out->use_uv(0, has_uv[0]), out->use_uv(1, has_uv[1])};
    if (nrm) bad_normal->assign(pos.count, false);
    for (size_t vi = 0; vi < pos.count; ++vi) {
      out->positions.push_back(world.transform_point(
          {float(pos.get(vi, 0)), float(pos.get(vi, 1)), float(pos.get(vi, 2))}));
      if (write_normals) {
        Vec3 n;
        if (nrm) {
          n = world.transform_normal(
              {float(nrm->get(vi, 0)), float(nrm->get(vi, 1)), float(nrm->get(vi, 2))});
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
      for (int set = 0; set < 2; ++set)
        if (write_uv[set])
          out->uv[set].push_back(has_uv[set] ? uv_at(uvs[set], vi) : Point2{0.f, 0.f});
    }
  }

  void add_mesh(size_t mesh_index, const Mat4& world, TriangleMesh* out) {
    const tinygltf::Mesh& mesh = model_.meshes[mesh_index];
    const bool mirror = world.det3() < 0.0;
    // Vertices already appended for this mesh by an earlier primitive with the same
    // attribute accessors: their first index, and which of them lost their normal.
    struct Appended {
      uint32_t first = 0;
      std::vector<bool> bad_normal;
    };
    std::map<VertexKey, Appended> appended;
    for (size_t pi = 0; pi < mesh.primitives.size(); ++pi) {
      const tinygltf::Primitive& prim = mesh.primitives[pi];
      const std::string where = "meshes[" + std::to_string(mesh_index) + "].primitives[" +
                                std::to_string(pi) + "]" + named(mesh.name);
      if (prim.mode != TINYGLTF_MODE_TRIANGLES && prim.mode != -1) {
        warn(where + ": mode " + std::to_string(prim.mode) +
             " is not TRIANGLES (4); primitive skipped");
        continue;
      }
      const auto pos_it = prim.attributes.find("POSITION");
      if (pos_it == prim.attributes.end()) fail(where + ": missing required attribute POSITION");
      const View pos = check_accessor(pos_it->second, TINYGLTF_TYPE_VEC3,
                                      {TINYGLTF_COMPONENT_TYPE_FLOAT}, where + " POSITION");
      View nrm;
      bool has_normals = false;
      const auto nrm_it = prim.attributes.find("NORMAL");
      if (nrm_it != prim.attributes.end()) {
        nrm = check_accessor(nrm_it->second, TINYGLTF_TYPE_VEC3,
                             {TINYGLTF_COMPONENT_TYPE_FLOAT}, where + " NORMAL");
        if (nrm.count != pos.count) fail(where + ": NORMAL and POSITION counts differ");
        has_normals = true;
      }
      View uvs[2];
      bool has_uv[2] = {false, false};
      for (int set = 0; set < 2; ++set) {
        const auto uv_it = prim.attributes.find("TEXCOORD_" + std::to_string(set));
        if (uv_it == prim.attributes.end()) continue;
        uvs[set] = check_accessor(uv_it->second, TINYGLTF_TYPE_VEC2,
                                  {TINYGLTF_COMPONENT_TYPE_FLOAT,
                                   TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE,
                                   TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT},
                                  where + " TEXCOORD_" + std::to_string(set));
        if (uvs[set].count != pos.count)
          fail(where + ": TEXCOORD_" + std::to_string(set) + " and POSITION counts differ");
        has_uv[set] = true;
      }
      uint32_t material = default_material_;
      if (prim.material >= 0) {
        if (prim.material >= int(model_.materials.size()))
          fail(where + ": 'material' refers to missing material " +
               std::to_string(prim.material));
        material = uint32_t(prim.material);
      }
      std::vector<uint32_t> indices;
      if (prim.indices >= 0) {
        const View idx = check_accessor(
            prim.indices, TINYGLTF_TYPE_SCALAR,
            {TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE, TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT,
             TINYGLTF_COMPONENT_TYPE_UNSIGNED_INT},
            where + " indices");
        indices.resize(idx.count);
        for (size_t i = 0; i < idx.count; ++i) {
          const double v = idx.get(i, 0);
          if (v >= double(pos.count))
            fail(where + ": index " + std::to_string(uint64_t(v)) + " out of range (" +
                 std::to_string(pos.count) + " vertices)");
          indices[i] = uint32_t(v);
        }
      } else {
        indices.resize(pos.count);
        for (size_t i = 0; i < pos.count; ++i) indices[i] = uint32_t(i);
      }
      if (indices.size() % 3 != 0)
        warn(where + ": index count is not a multiple of 3; trailing indices ignored");
      // The primitive's vertices, each transformed once, appended after the mesh's others
      // (or those of an earlier primitive with the same attribute accessors).
      const auto [entry, fresh] = appended.try_emplace(vertex_key(prim));
      if (fresh) append_vertices(pos, has_normals ? &nrm : nullptr, uvs, has_uv, world, out,
                                 &entry->second.first, &entry->second.bad_normal, where);
      const uint32_t first = entry->second.first;
      const std::vector<bool>& bad_normal = entry->second.bad_normal;
      const uint8_t base_flags = uint8_t((has_uv[0] ? TriangleMesh::kHasUv0 : 0) |
                                         (has_uv[1] ? TriangleMesh::kHasUv1 : 0));
      for (size_t t = 0; t + 2 < indices.size(); t += 3) {
        bool normals_ok = has_normals;
        for (int k = 0; k < 3; ++k) {
          // A mirroring transform flips the winding (glTF spec, "Transformations"): swap two
          // vertices so that counter-clockwise stays the front face in world space.
          const int src = mirror ? (k == 0 ? 0 : 3 - k) : k;
          const uint32_t vi = indices[t + size_t(src)];
          if (has_normals && bad_normal[vi]) normals_ok = false;
          out->indices.push_back(first + vi);
        }
        out->material.push_back(material);
        out->flags.push_back(uint8_t(base_flags | (normals_ok ? TriangleMesh::kHasNormals : 0)));
      }
      // Degenerate triangles are dropped by Scene.
    }
  }

  // Texture coordinates; normalized integer components map to [0, 1] (glTF 3.7.2.1).
  static Point2 uv_at(const View& v, size_t i) {
    double scale = 1.0;
    if (v.component_type == TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE) scale = 1.0 / 255.0;
    if (v.component_type == TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT) scale = 1.0 / 65535.0;
    return {float(v.get(i, 0) * scale), float(v.get(i, 1) * scale)};
  }

  std::vector<std::optional<PunctualLight>> lights_;
  std::vector<int> mesh_uses_;
  std::vector<int> mesh_slot_;
  std::set<std::string> warned_material_ext_;
  std::set<size_t> warned_rough_glass_;
  bool warned_occlusion_ = false, warned_alpha_ = false;
  const tinygltf::Model& model_;
  std::string source_;
  std::vector<std::string>* warnings_;
  const LoadOptions& options_;
  uint32_t default_material_ = 0;
};

SceneDescription finish(bool ok, const tinygltf::Model& model, const std::string& err,
                        const std::string& warn, const std::string& source,
                        std::vector<std::string>* warnings, const LoadOptions& options) {
  if (!warn.empty() && warnings) warnings->push_back(source + ": " + warn);
  if (!ok) throw SceneError(source + ": cannot parse glTF: " + (err.empty() ? "unknown" : err));
  return Loader(model, source, warnings, options).run();
}

// Uploads are self-contained: a file system whose every read is refused, so that a URI in a
// farm scene can never read a file of the worker's (or of the server's, when it inspects one).
// Files "exist" so that tinygltf asks to read them and the refusal says why.
bool no_file_exists(const std::string&, void*) { return true; }
std::string keep_path(const std::string& path, void*) { return path; }
bool no_file_read(std::vector<unsigned char>*, std::string* err, const std::string& path, void*) {
  if (err) *err += "external file '" + path + "' refused: farm scenes must be self-contained\n";
  return false;
}
bool no_file_write(std::string*, const std::string&, const std::vector<unsigned char>&, void*) {
  return false;
}

void configure(tinygltf::TinyGLTF* gltf, const LoadOptions& options) {
  gltf->SetImageLoader(keep_encoded_image, nullptr);
  if (!options.allow_external_files)
    gltf->SetFsCallbacks({no_file_exists, keep_path, no_file_read, no_file_write, nullptr});
}

}  // namespace

SceneDescription load_gltf(const std::string& path, std::vector<std::string>* warnings,
                           const LoadOptions& options) {
  const std::string source = options.display_name.empty() ? path : options.display_name;
  // Read here rather than by tinygltf, whose file callbacks may refuse every file.
  std::ifstream in(path, std::ios::binary);
  if (!in) throw SceneError(source + ": cannot open file");
  const std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  if (in.bad()) throw SceneError(source + ": cannot read file");
  const bool binary = bytes.size() >= 4 && std::memcmp(bytes.data(), "glTF", 4) == 0;
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
  return finish(ok, model, err, warn, source, warnings, options);
}

SceneDescription load_gltf_from_string(const std::string& json, const std::string& base_dir,
                                       const std::string& name,
                                       std::vector<std::string>* warnings,
                                       const LoadOptions& options) {
  tinygltf::TinyGLTF gltf;
  configure(&gltf, options);
  tinygltf::Model model;
  std::string err, warn;
  const bool ok = gltf.LoadASCIIFromString(&model, &err, &warn, json.c_str(),
                                           unsigned(json.size()), base_dir);
  return finish(ok, model, err, warn, name, warnings, options);
}

}  // namespace rf
