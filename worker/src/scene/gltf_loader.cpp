// glTF 2.0 -> SceneDescription via tinygltf. Every index read from the file is range-checked
// before use, so a malformed file produces a SceneError naming the offending part, never a
// crash.
//
// This file holds the loader's driver (Loader::run), its messages, the node hierarchy and its
// traversal (transforms, KHR_node_visibility, meshes placed or instanced, the animated
// layout), tinygltf's configuration and the public API (parse_gltf, describe_gltf, load_gltf,
// ...). The rest of Loader (gltf_loader_internal.h) is in the gltf_*.cpp files of its
// concerns: materials, geometry, lights_cameras, animation and limits; compressed geometry is
// decoded before any of it (gltf_compression.cpp).
#include "scene/gltf_loader_internal.h"

#include <tiny_gltf.h>

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <map>
#include <memory>
#include <optional>
#include <set>
#include <string>
#include <utility>
#include <vector>

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

}  // namespace

namespace gltf_detail {

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
      "KHR_materials_diffuse_transmission", "KHR_materials_dispersion", "KHR_animation_pointer",
      // Metadata, which the renderer does not read: the server copies the asset's packet into
      // the EXR header (server/renderfarm/domain/scenes/metadata.py); KHR_xmp is its draft.
      "KHR_xmp_json_ld", "KHR_xmp",
      // The triangles are the mesh; the extension only records which of them made n-gons
      // (for editors that rebuild the polygons), which changes nothing in the image.
      "FB_ngon_encoding"};
  return s;
}

float number_or(const tinygltf::Value& obj, const char* key, float fallback) {
  if (!obj.IsObject() || !obj.Has(key)) return fallback;
  const tinygltf::Value& v = obj.Get(key);
  return v.IsNumber() ? float(v.GetNumberAsDouble()) : fallback;
}

Loader::Loader(const tinygltf::Model& model, std::string source,
               std::vector<std::string>* warnings, const LoadOptions& options)
    : model_(model), source_(std::move(source)), warnings_(warnings), options_(options) {}

SceneDescription Loader::run() {
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
  if (model_.nodes.size() > options_.limits.max_nodes)
    fail("nodes: the scene has " + std::to_string(model_.nodes.size()) +
         " nodes, over the limit of " + std::to_string(options_.limits.max_nodes));
  const std::vector<int> parent = check_hierarchy();
  parent_ = parent;
  // animation.h: the pose at options_.time, and the materials, lights, cameras and visibility
  // KHR_animation_pointer animates, before they are read.
  evaluate_animations();
  if (!pose_only) load_textures(&desc);  // a pose uses its static part's textures
  load_materials(&desc);
  for (const auto& [index, material] : animated_materials_)
    desc.animated_materials.push_back(uint32_t(index));
  variant_ = selected_variant();
  derive_thin_materials(&desc);
  load_lights();
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
    desc.world.node.reserve(desc.world.material.capacity());  // every world triangle has one
  }
  for (int root : roots) visit(root, Mat4::identity(), &desc, 0);
  desc.image_height = options_.image_height;
  if (split_ && has_thin_) {
    // Points and lines of an animated scene: a mesh that each pose fills in world space with
    // its own, for its camera (Scene's posing constructor), placed at the identity.
    desc.thin_mesh = int(desc.meshes.size());
    Mesh mesh;
    mesh.name = "points and lines";
    desc.meshes.push_back(std::move(mesh));
    // Its triangles carry their nodes (TriangleMesh::node), the instance none.
    desc.instances.push_back({uint32_t(desc.thin_mesh), kNoNode, Mat4::identity()});
  }
  if (split_) {
    split_->deformed_mesh.assign(desc.meshes.size(), 0);
    for (int slot : deformed_slots_) split_->deformed_mesh[size_t(slot)] = 1;
    if (desc.thin_mesh >= 0) split_->deformed_mesh[size_t(desc.thin_mesh)] = 1;
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

// glTF 2.0, 3.5.3: "the node hierarchy must be a set of disjoint strict trees": no node has
// two parents, none is its own ancestor. Checked before anything walks the graph, which is
// then a forest: a walk from the roots visits each node once. (A graph that shares children
// would make the walk exponential: 40 nodes that each list the next one twice are 2^40
// visits.) Returns each node's parent, -1 for none.
std::vector<int> Loader::check_hierarchy() const {
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

void Loader::check_roots(const std::vector<int>& roots, const std::string& path,
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

void Loader::count_mesh_uses() {
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

[[noreturn]] void Loader::fail(const std::string& what) const {
  throw SceneError(source_ + ": " + what, leading_path(what));
}

std::string Loader::leading_path(const std::string& what) {
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

std::string Loader::named(const std::string& name) {
  return name.empty() ? std::string() : " ('" + name + "')";
}

void Loader::warn(const std::string& what) {
  if (warnings_) warnings_->push_back(source_ + ": " + what);
}

// The node's transform; pose (its animation at the load's time, or null) replaces the paths
// it animates.
Mat4 Loader::local_transform(const tinygltf::Node& node, const std::string& where,
                             const NodePose* pose) const {
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
Mat4 Loader::trs(const double* translation, const double* rotation, const double* scale,
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

// KHR_node_visibility: the node's own `visible` (true when absent), as animated by
// KHR_animation_pointer at the load's time where a channel targets it.
bool Loader::node_visible(const tinygltf::Node& node, int index) const {
  const auto animated = visible_at_.find(index);
  if (animated != visible_at_.end()) return animated->second;
  auto ext = node.extensions.find("KHR_node_visibility");
  if (ext == node.extensions.end() || !ext->second.Has("visible")) return true;
  const tinygltf::Value& v = ext->second.Get("visible");
  if (!v.IsBool())
    fail("nodes[" + std::to_string(index) + "].extensions.KHR_node_visibility.visible" +
         named(node.name) + ": must be true or false");
  return v.Get<bool>();
}

// Whether a mesh may emit light: it has points or lines (unlit without normals), or a triangle
// primitive whose material (the selected variant's) emits or is unlit.
bool Loader::mesh_may_emit(size_t mesh_index, const SceneDescription& desc) {
  if (mesh_emits_.empty()) mesh_emits_.assign(model_.meshes.size(), -1);
  int8_t& known = mesh_emits_[mesh_index];
  if (known >= 0) return known != 0;
  known = 0;
  const tinygltf::Mesh& mesh = model_.meshes[mesh_index];
  for (size_t pi = 0; pi < mesh.primitives.size() && !known; ++pi) {
    const tinygltf::Primitive& prim = mesh.primitives[pi];
    if (!is_triangles(prim.mode)) {
      known = 1;
      continue;
    }
    const std::string where = "meshes[" + std::to_string(mesh_index) + "].primitives[" +
                              std::to_string(pi) + "]" + named(mesh.name);
    const uint32_t m = primitive_material(prim, mesh_index, pi, where);
    if (m < desc.materials.size() && (desc.materials[m].is_emissive() || desc.materials[m].unlit))
      known = 1;
  }
  return known != 0;
}

// `visible`: no ancestor is hidden by KHR_node_visibility. A hidden node and everything
// below it render nothing (meshes, lights), "even any nodes below that have a value of
// true"; cameras are not affected (the extension's text), so the walk goes on for them.
void Loader::visit(int index, const Mat4& parent, SceneDescription* desc, int depth, bool visible) {
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
  // In an animated layout, a hidden node that moves still has its mesh slot (a pose where it
  // is visible has the same meshes), without an instance.
  const bool hidden_slot = !visible && split_ && moving_[size_t(index)] && node.mesh >= 0 &&
                           node.mesh < int(model_.meshes.size());
  if (!visible && !hidden_slot) {
    for (int child : node.children) visit(child, world, desc, depth + 1, false);
    return;
  }
  if (hidden_slot) {
    if (gpu_instancing(node)) {
      int& slot = mesh_slot_[size_t(node.mesh)];
      if (slot < 0) {
        Mesh mesh;
        mesh.name = model_.meshes[size_t(node.mesh)].name;
        if (!split_->pose_only) {
          reserve(mesh_counts(size_t(node.mesh)), &mesh.geometry);
          add_mesh(size_t(node.mesh), Mat4::identity(), &mesh.geometry);
        }
        slot = int(desc->meshes.size());
        desc->meshes.push_back(std::move(mesh));
      }
    } else {
      visit_split(index, node, world, where, desc, false);
    }
    for (int child : node.children) visit(child, world, desc, depth + 1, false);
    return;
  }
  auto light_ext = node.extensions.find("KHR_lights_punctual");
  const bool has_light =
      light_ext != node.extensions.end() && light_ext->second.Has("light");
  // The name of a node that may emit light, for the light groups' messages.
  if (!node.name.empty() &&
      (has_light || (node.mesh >= 0 && node.mesh < int(model_.meshes.size()) &&
                     mesh_may_emit(size_t(node.mesh), *desc))))
    desc->node_names.emplace(uint32_t(index), node.name);
  if (has_light) {
    const int li = light_ext->second.Get("light").GetNumberAsInt();
    if (li < 0 || li >= int(lights_.size()))
      fail(where + ": KHR_lights_punctual.light refers to missing light " + std::to_string(li));
    if (lights_[size_t(li)]) {
      PunctualLight light = *lights_[size_t(li)];
      light.position = world.transform_point({0.f, 0.f, 0.f});
      const Vec3 dir = world.transform_vector({0.f, 0.f, -1.f});
      if (!(length(dir) > 0.f)) fail(where + ": light transform is singular");
      light.direction = normalize(dir);
      light.node = uint32_t(index);
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
      desc->instances.push_back({uint32_t(slot), uint32_t(index), world * local});
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
      add_mesh(size_t(node.mesh), world, &desc->world, &deformation, uint32_t(index));
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
      desc->instances.push_back({uint32_t(slot), uint32_t(index), world});
    } else {
      range.first_vertex = uint32_t(desc->world.positions.size());
      add_mesh(size_t(node.mesh), world, &desc->world, nullptr, uint32_t(index));
      range.count = uint32_t(desc->world.positions.size()) - range.first_vertex;
    }
    if (options_.pose_report) options_.pose_report->ranges.push_back(range);
  }
  if (node.mesh >= 0) visit_thin(index, node, world, where, desc);
  for (int child : node.children) visit(child, world, desc, depth + 1);
}

// A mesh node in an animated layout (AnimatedLayout): a varying deformed node gets a mesh of
// its own at the identity, a moving one an instance of its mesh in the mesh's own space, the
// others go where a still puts them. Each mode fills its own meshes only (the numbering is
// the same in both).
void Loader::visit_split(int index, const tinygltf::Node& node, const Mat4& world,
                         const std::string& where, SceneDescription* desc, bool visible) {
  const bool pose_only = split_->pose_only;
  const size_t mi = size_t(node.mesh);
  if (varying_[size_t(index)]) {
    Mesh mesh;
    mesh.name = model_.meshes[mi].name + " (" + where + ")";
    if (pose_only && visible) {
      const Deformation deformation = deformation_of(index, where);
      add_mesh(mi, world, &mesh.geometry, &deformation);
    }
    const int slot = int(desc->meshes.size());
    desc->meshes.push_back(std::move(mesh));
    deformed_slots_.push_back(slot);
    if (visible) desc->instances.push_back({uint32_t(slot), uint32_t(index), Mat4::identity()});
    return;
  }
  if (moving_[size_t(index)] || (!is_deformed(index) && mesh_uses_[mi] > 1)) {
    if (moving_[size_t(index)] && visible) ++moving_mesh_nodes_;
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
    if (visible) desc->instances.push_back({uint32_t(slot), uint32_t(index), world});
    return;
  }
  if (pose_only) return;  // static world triangles: the static part's
  if (is_deformed(index)) {
    const Deformation deformation = deformation_of(index, where);
    add_mesh(mi, world, &desc->world, &deformation, uint32_t(index));
  } else {
    add_mesh(mi, world, &desc->world, nullptr, uint32_t(index));
  }
}

// moving_ and varying_ per node (AnimatedLayout): from the channels the chosen animations
// have, whatever their values at the time.
void Loader::classify_nodes() {
  const size_t n = model_.nodes.size();
  moving_.assign(n, 0);
  varying_.assign(n, 0);
  // A node moves if its TRS or its visibility (KHR_animation_pointer) is animated, or its
  // parent moves (parents first: memoized walk). A node that a pose may hide is placed by an
  // instance, as a moving one is, so that each pose shows or omits it.
  std::vector<char> known(n, 0), hideable(n, 0);
  for (size_t i = 0; i < n; ++i) {
    std::vector<int> chain;
    int j = int(i);
    while (j >= 0 && !known[size_t(j)]) {
      chain.push_back(j);
      j = parent_[size_t(j)];
    }
    char moves = j >= 0 ? moving_[size_t(j)] : 0, hides = j >= 0 ? hideable[size_t(j)] : 0;
    for (auto it = chain.rbegin(); it != chain.rend(); ++it) {
      hides = char(hides || visibility_animated_.count(*it));
      moves = char(moves || hides || trs_animated_.count(*it));
      moving_[size_t(*it)] = moves;
      hideable[size_t(*it)] = hides;
      known[size_t(*it)] = 1;
    }
  }
  for (size_t i = 0; i < n; ++i) {
    const tinygltf::Node& node = model_.nodes[i];
    if (node.mesh < 0 || node.mesh >= int(model_.meshes.size())) continue;
    bool varies = morph_target_count(node.mesh) > 0 &&
                  (weights_animated_.count(int(i)) || (moving_[i] && is_deformed(int(i))));
    // A skinned or morphed node a pose may hide: a deformed mesh of its own per pose.
    if (hideable[i] && is_deformed(int(i))) varies = true;
    if (node.skin >= 0 && node.skin < int(model_.skins.size()))
      for (int j : model_.skins[size_t(node.skin)].joints)
        if (j >= 0 && j < int(n) && moving_[size_t(j)]) varies = true;
    // A skinned node's own transform is not used: it does not move the skinned mesh.
    if (node.skin >= 0 && !varies) moving_[i] = 0;
    varying_[i] = char(varies);
  }
}

}  // namespace gltf_detail

namespace {

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
    prepare_glb(&bytes, &fallbacks);
  else
    prepare_json(&bytes, &fallbacks);
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
  return gltf_detail::Loader(document.model, document.source, warnings, options).run();
}

std::vector<std::string> gltf_variant_names(const GltfDocument& document) {
  return gltf_detail::Loader::variant_names(document.model);
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
  prepare_json(&text, &fallbacks);
  const bool ok = gltf.LoadASCIIFromString(&model, &err, &warn, text.c_str(),
                                           unsigned(text.size()), base_dir);
  return describe_gltf(*parsed(ok, &model, err, warn, name, warnings, options, fallbacks),
                       warnings, options);
}

}  // namespace rf
