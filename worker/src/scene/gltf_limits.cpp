// The glTF loader's limits (Loader, gltf_loader_internal.h): the vertex and triangle counts of
// meshes, to reserve TriangleMesh arrays exactly, and the scene's depth, triangles over every
// mesh use and memory estimate, checked against SceneLimits before any geometry is allocated.
#include "scene/gltf_loader_internal.h"

#include <algorithm>
#include <cstdint>
#include <set>
#include <string>
#include <utility>
#include <vector>

namespace rf::gltf_detail {

size_t Loader::accessor_count(int index) const {
  if (index < 0 || index >= int(model_.accessors.size())) return 0;
  return accessor_problem(model_.accessors[size_t(index)]).empty()
             ? model_.accessors[size_t(index)].count
             : 0;
}

Loader::Counts Loader::mesh_counts(size_t mesh_index) const {
  Counts c;
  std::set<VertexKey> seen;
  for (const tinygltf::Primitive& prim : model_.meshes[mesh_index].primitives) {
    const auto pos = prim.attributes.find("POSITION");
    if (pos == prim.attributes.end()) continue;
    const size_t nv = accessor_count(pos->second);
    if (!is_triangles(prim.mode)) {
      // Points and lines: an element per point or segment, which the Scene makes two
      // triangles (ThinGeometry), per use of the mesh.
      const size_t n = prim.indices >= 0 ? accessor_count(prim.indices) : nv;
      c.thin += prim.mode == TINYGLTF_MODE_POINTS      ? n
                : prim.mode == TINYGLTF_MODE_LINE       ? n / 2
                : prim.mode == TINYGLTF_MODE_LINE_LOOP  ? n
                                                        : (n > 0 ? n - 1 : 0);
      continue;
    }
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
Loader::Counts Loader::world_counts(const std::vector<int>& roots) const {
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

void Loader::reserve(const Counts& c, TriangleMesh* mesh) {
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

// Depth, triangles over every mesh use and the memory estimate of what the roots reach,
// checked against the limits before any geometry is allocated.
void Loader::check_cost(const std::vector<int>& roots, SceneStats* stats) const {
  const SceneLimits& limits = options_.limits;
  std::vector<std::pair<int, uint32_t>> stack;  // (node, depth)
  for (int r : roots) stack.push_back({r, 1});
  std::vector<uint64_t> uses(model_.meshes.size(), 0), copies(model_.meshes.size(), 0);
  std::vector<uint64_t> mesh_triangles(model_.meshes.size(), UINT64_MAX);
  std::vector<uint64_t> thin_drawn(model_.meshes.size(), 0);
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
      if (tris == UINT64_MAX) {
        const Counts c = mesh_counts(size_t(node.mesh));
        tris = c.triangles + 2 * c.thin;
      }
      // A skinned or morphed node has its own copy of the mesh; the others share one.
      if (is_deformed(i)) ++copies[size_t(node.mesh)];
      else uses[size_t(node.mesh)] = 1;
      // EXT_mesh_gpu_instancing: the mesh once, drawn once per instance.
      const int64_t gpu = gpu_instance_count(node, i);
      const uint64_t drawn = gpu >= 0 ? uint64_t(gpu) : 1;
      thin_drawn[size_t(node.mesh)] += drawn;  // points and lines are copied per use
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
  // A triangle's own arrays: indices 12, material 4, node 4 (a world triangle's; counted for
  // every mesh), flags 1, face normal 12.
  constexpr double kTriangleBytes = 12.0 + 4.0 + 4.0 + 1.0 + 12.0;
  double bytes = 0.0;
  for (size_t m = 0; m < model_.meshes.size(); ++m) {
    if (!uses[m] && !copies[m]) continue;
    const Counts c = mesh_counts(m);
    const double per_vertex = 12.0 + (c.normals ? 12.0 : 0.0) + (c.colors ? 16.0 : 0.0) +
                              (c.tangents ? 16.0 : 0.0) + 8.0 * double(c.uv.size());
    bytes += double(uses[m] + copies[m]) *
             (double(c.vertices) * per_vertex +
              double(c.triangles) * (kTriangleBytes + bvh_bytes));
    // Points and lines: per use, their vertices and elements, then four vertices and two
    // triangles each.
    bytes += double(thin_drawn[m]) * double(c.thin) *
             (2.0 * per_vertex + 16.0 + 4.0 * per_vertex +
              2.0 * (kTriangleBytes + bvh_bytes));
  }
  bytes += double(instances) * 256.0;
  for (const tinygltf::Buffer& b : model_.buffers) bytes += double(b.data.size());
  stats->estimated_bytes = uint64_t(bytes);
  if (limits.max_memory_bytes && stats->estimated_bytes > limits.max_memory_bytes)
    fail("meshes: the scene needs about " + format_bytes(stats->estimated_bytes) +
         " of memory once loaded, over the limit of " + format_bytes(limits.max_memory_bytes));
}

}  // namespace rf::gltf_detail
