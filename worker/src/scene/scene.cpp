#include "scene/scene.h"

#include <embree3/rtcore.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstddef>
#include <cstdio>
#include <cstring>
#include <limits>

#include "sampling/samplers.h"
#include "util/isa.h"

namespace rf {

Camera::Raster Camera::raster(uint32_t width, uint32_t height) const {
  // sx = (2 px / width - 1) half_width, sy = (1 - 2 py / height) half_height.
  float half_width, half_height;
  if (orthographic) {
    half_width = xmag;
    half_height = ymag;
  } else {
    half_height = std::tan(0.5f * yfov);
    half_width = float(width) / float(height) * half_height;
  }
  Raster r;
  r.right = right;
  r.up = up;
  r.forward = forward;
  r.position = position;
  r.orthographic = orthographic;
  r.kx = 2.f * half_width / float(width);
  r.bx = -half_width;
  r.ky = -2.f * half_height / float(height);
  r.by = half_height;
  return r;
}

uint64_t ray_query(uint64_t seed, uint64_t pixel, uint32_t bounce, RayKind kind) {
  return hash4(seed, pixel, bounce, uint64_t(kind));
}

namespace {

// What a query passes to the transparency filters: Embree hands a filter the context its
// query was given, so the key rides behind Embree's own fields. Every query of a Scene uses
// one.
struct QueryContext {
  RTCIntersectContext rtc;
  uint64_t query;
  explicit QueryContext(uint64_t q) : query(q) { rtcInitIntersectContext(&rtc); }
};

}  // namespace

// The user data of a geometry of non-opaque triangles (triangles first, first + 1, ... of
// mesh) and its intersection and occlusion filter: Embree calls it for every candidate hit on
// the geometry, in no particular order, and it rejects those the ray passes. The decision is a
// function of the ray's key and the hit alone, so the closest hit it lets through is the same
// whatever the order.
struct TransparencyFilter {
  const Scene* scene;
  const TriangleMesh* mesh;
  uint32_t first;
  static void filter(const RTCFilterFunctionNArguments* args) {
    const auto* self = static_cast<const TransparencyFilter*>(args->geometryUserPtr);
    const uint64_t query = reinterpret_cast<const QueryContext*>(args->context)->query;
    const unsigned n = args->N;
    for (unsigned i = 0; i < n; ++i) {
      if (args->valid[i] != -1) continue;
      const uint32_t prim = RTCHitN_primID(args->hit, n, i) + self->first;
      if (!self->scene->stops(*self->mesh, prim, RTCHitN_u(args->hit, n, i),
                              RTCHitN_v(args->hit, n, i), query, RTCRayN_id(args->ray, n, i),
                              RTCHitN_instID(args->hit, n, i, 0)))
        args->valid[i] = 0;
    }
  }
};

struct Scene::Embree {
  RTCDevice device = nullptr;
  RTCScene scene = nullptr;
  std::vector<RTCScene> mesh_scenes;
  std::vector<uint32_t> mesh_first_transparent;  // per mesh: its opaque triangle count
  RTCSceneFlags scene_flags = RTC_SCENE_FLAG_NONE;
  std::vector<uint32_t> slot_of_geom;  // top-level geometry ID -> slot
  unsigned world_transparent_geom = RTC_INVALID_GEOMETRY_ID;  // its non-opaque triangles
  std::vector<std::unique_ptr<TransparencyFilter>> filters;  // the filters' user data
  std::atomic<int64_t> bytes{0};       // what the device has allocated (memory monitor)
  ~Embree() {
    if (scene) rtcReleaseScene(scene);
    for (RTCScene s : mesh_scenes)
      if (s) rtcReleaseScene(s);
    if (device) rtcReleaseDevice(device);
  }
};

namespace {

void embree_error(void* /*user*/, RTCError code, const char* message) {
  // Embree reports API misuse and out-of-memory here; there is no useful recovery, but the
  // message must reach the user.
  std::fprintf(stderr, "embree error %d: %s\n", int(code), message ? message : "");
}

// The unit normal of the triangle's front (counter-clockwise) side in *n, and |cross(p1 - p0,
// p2 - p0)|, twice its area; *n is left alone when that is 0 or not finite.
float face_normal(Vec3 p0, Vec3 p1, Vec3 p2, Vec3* n) {
  const Vec3 c = cross(p1 - p0, p2 - p0);
  const float len = length(c);
  if (len > 0.f && std::isfinite(len)) *n = c / len;
  return len;
}

// Makes v's capacity its size + extra, copying it if it has more (or less) than that.
template <typename T>
void fit(std::vector<T>* v, size_t extra) {
  if (v->empty() || v->capacity() == v->size() + extra) return;
  std::vector<T> tight;
  tight.reserve(v->size() + extra);
  tight.assign(v->begin(), v->end());
  v->swap(tight);
}

// Checks a mesh's materials and indices and drops its degenerate triangles (zero area or
// non-finite vertices), which have no normal and cannot be hit or sampled meaningfully.
// Returns how many were dropped. Their vertices stay (unreferenced). With drop false (the
// deformed meshes of a pose, whose triangles must not depend on the time) they stay too, with
// a zero face normal: Embree never hits a triangle of zero area, and emitters skip them.
size_t clean_mesh(TriangleMesh* mesh, size_t material_count, const std::string& where,
                  bool drop = true) {
  const size_t n = mesh->size(), nv = mesh->positions.size();
  if (mesh->indices.size() != 3 * n || mesh->flags.size() != n)
    throw SceneError(where + ": inconsistent triangle mesh: " + std::to_string(n) +
                     " materials, " + std::to_string(mesh->indices.size()) + " indices and " +
                     std::to_string(mesh->flags.size()) + " flags (one material and one flags "
                     "byte per triangle, three indices)");
  if (!mesh->normals.empty() && mesh->normals.size() != nv)
    throw SceneError(where + ": triangle mesh has normals for some vertices only");
  if (mesh->uv.size() < 2) mesh->uv.resize(2);
  for (size_t set = 0; set < mesh->uv.size(); ++set)
    if (!mesh->uv[set].empty() && mesh->uv[set].size() != nv)
      throw SceneError(where + ": triangle mesh has TEXCOORD_" + std::to_string(set) +
                       " for some vertices only");
  if (!mesh->colors.empty() && mesh->colors.size() != nv)
    throw SceneError(where + ": triangle mesh has COLOR_0 for some vertices only");
  if (!mesh->tangents.empty() && mesh->tangents.size() != nv)
    throw SceneError(where + ": triangle mesh has TANGENT for some vertices only");
  if (!mesh->node.empty() && mesh->node.size() != n)
    throw SceneError(where + ": triangle mesh has a node for some triangles only");
  size_t kept = 0;
  mesh->face_normals.assign(n, Vec3());
  for (size_t i = 0; i < n; ++i) {
    if (mesh->material[i] >= material_count)
      throw SceneError(where + ": triangle refers to missing material " +
                       std::to_string(mesh->material[i]));
    const uint32_t* v = &mesh->indices[3 * i];
    if (v[0] >= nv || v[1] >= nv || v[2] >= nv)
      throw SceneError(where + ": triangle " + std::to_string(i) + " refers to a missing vertex");
    uint8_t flags = mesh->flags[i];
    if (mesh->normals.empty()) flags &= uint8_t(~TriangleMesh::kHasNormals);
    if (mesh->uv[0].empty()) flags &= uint8_t(~TriangleMesh::kHasUv0);
    if (mesh->uv[1].empty()) flags &= uint8_t(~TriangleMesh::kHasUv1);
    if (mesh->tangents.empty()) flags &= uint8_t(~TriangleMesh::kHasTangents);
    const Vec3 p0 = mesh->positions[v[0]], p1 = mesh->positions[v[1]], p2 = mesh->positions[v[2]];
    const float len = face_normal(p0, p1, p2, &mesh->face_normals[kept]);
    if (drop && (!(len > 0.f) || !std::isfinite(len) || !is_finite(p0) || !is_finite(p1) ||
                 !is_finite(p2)))
      continue;
    if (kept != i) {
      for (int k = 0; k < 3; ++k) mesh->indices[3 * kept + size_t(k)] = v[k];
      mesh->material[kept] = mesh->material[i];
      if (!mesh->node.empty()) mesh->node[kept] = mesh->node[i];
    }
    mesh->flags[kept] = flags;
    ++kept;
  }
  mesh->indices.resize(3 * kept);
  mesh->material.resize(kept);
  mesh->flags.resize(kept);
  if (!mesh->node.empty()) mesh->node.resize(kept);
  mesh->face_normals.resize(kept);
  // No growth slack is kept for the scene's lifetime (a description built by push_back may
  // hold up to twice its size). Positions keep room for one more vertex: Embree reads the
  // last vertex with a 16-byte load, so the float after it must be readable.
  fit(&mesh->positions, 1);
  fit(&mesh->normals, 0);
  for (std::vector<Point2>& set : mesh->uv) fit(&set, 0);
  fit(&mesh->colors, 0);
  fit(&mesh->tangents, 0);
  fit(&mesh->indices, 0);
  fit(&mesh->material, 0);
  fit(&mesh->flags, 0);
  fit(&mesh->node, 0);
  fit(&mesh->face_normals, 0);
  return n - kept;
}

// Moves the mesh's triangles with non-opaque materials after the opaque ones, each group in
// its order, and returns the number of opaque ones.
uint32_t partition_transparent(TriangleMesh* mesh, const std::vector<Material>& materials) {
  const size_t n = mesh->size();
  std::vector<uint32_t> order;
  order.reserve(n);
  for (int pass = 0; pass < 2; ++pass)
    for (size_t i = 0; i < n; ++i)
      if (materials[mesh->material[i]].is_opaque() == (pass == 0)) order.push_back(uint32_t(i));
  size_t opaque = 0;
  while (opaque < n && materials[mesh->material[order[opaque]]].is_opaque()) ++opaque;
  if (opaque == n || opaque == 0) return uint32_t(opaque);  // nothing moves
  std::vector<uint32_t> indices(3 * n), material(n), node(mesh->node.size());
  std::vector<uint8_t> flags(n);
  std::vector<Vec3> face_normals(n);
  for (size_t k = 0; k < n; ++k) {
    const uint32_t i = order[k];
    for (size_t c = 0; c < 3; ++c) indices[3 * k + c] = mesh->indices[3 * size_t(i) + c];
    material[k] = mesh->material[i];
    flags[k] = mesh->flags[i];
    face_normals[k] = mesh->face_normals[i];
    if (!node.empty()) node[k] = mesh->node[i];
  }
  mesh->indices.swap(indices);
  mesh->material.swap(material);
  mesh->flags.swap(flags);
  mesh->face_normals.swap(face_normals);
  mesh->node.swap(node);
  return uint32_t(opaque);
}

// An Embree triangle geometry of triangles [first, first + count) of the mesh that reads its
// positions and indices in place (clean_mesh left the room after the last vertex that Embree's
// 16-byte loads need).
RTCGeometry triangle_geometry(RTCDevice device, const TriangleMesh& mesh, size_t first,
                              size_t count) {
  RTCGeometry geom = rtcNewGeometry(device, RTC_GEOMETRY_TYPE_TRIANGLE);
  rtcSetSharedGeometryBuffer(geom, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3,
                             mesh.positions.data(), 0, sizeof(Vec3), mesh.positions.size());
  rtcSetSharedGeometryBuffer(geom, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3,
                             mesh.indices.data(), 3 * sizeof(uint32_t) * first,
                             3 * sizeof(uint32_t), count);
  return geom;
}

// A mesh's opaque triangles (the first `opaque`) are one Embree geometry and its others
// another, with the filter functions that test their coverage (against scene's materials):
// rays on opaque geometry run no filter. Returns the geometry IDs in target
// (RTC_INVALID_GEOMETRY_ID for an empty part). refit: the geometries are refit, not rebuilt,
// when their vertices change (the target's build quality must be RTC_BUILD_QUALITY_LOW).
std::pair<unsigned, unsigned> attach_triangles(
    RTCDevice device, RTCScene target, const TriangleMesh& mesh, uint32_t opaque,
    const Scene* scene, std::vector<std::unique_ptr<TransparencyFilter>>* filters, bool refit) {
  std::pair<unsigned, unsigned> ids{RTC_INVALID_GEOMETRY_ID, RTC_INVALID_GEOMETRY_ID};
  if (opaque > 0) {
    RTCGeometry geom = triangle_geometry(device, mesh, 0, opaque);
    if (refit) rtcSetGeometryBuildQuality(geom, RTC_BUILD_QUALITY_REFIT);
    rtcCommitGeometry(geom);
    ids.first = rtcAttachGeometry(target, geom);
    rtcReleaseGeometry(geom);  // the scene holds the reference now
  }
  if (opaque < mesh.size()) {
    RTCGeometry geom = triangle_geometry(device, mesh, opaque, mesh.size() - opaque);
    filters->push_back(
        std::make_unique<TransparencyFilter>(TransparencyFilter{scene, &mesh, opaque}));
    rtcSetGeometryUserData(geom, filters->back().get());
    rtcSetGeometryIntersectFilterFunction(geom, TransparencyFilter::filter);
    rtcSetGeometryOccludedFilterFunction(geom, TransparencyFilter::filter);
    if (refit) rtcSetGeometryBuildQuality(geom, RTC_BUILD_QUALITY_REFIT);
    rtcCommitGeometry(geom);
    ids.second = rtcAttachGeometry(target, geom);
    rtcReleaseGeometry(geom);
  }
  return ids;
}

void grow_bounds(const TriangleMesh& mesh, Vec3* lo, Vec3* hi) {
  for (uint32_t v : mesh.indices) {
    *lo = vmin(*lo, mesh.positions[v]);
    *hi = vmax(*hi, mesh.positions[v]);
  }
}

// Embree's memory monitor: counts the device's allocations (bytes > 0) and frees (< 0).
bool count_embree_bytes(void* user, ssize_t bytes, bool /*post*/) {
  static_cast<std::atomic<int64_t>*>(user)->fetch_add(int64_t(bytes), std::memory_order_relaxed);
  return true;  // never refuse an allocation
}

}  // namespace

bool parse_bvh_layout(const std::string& name, BvhLayout* out) {
  if (name == "fast") {
    *out = BvhLayout::Fast;
  } else if (name == "compact") {
    *out = BvhLayout::Compact;
  } else {
    return false;
  }
  return true;
}

const char* bvh_layout_name(BvhLayout layout) {
  return layout == BvhLayout::Compact ? "compact" : "fast";
}

namespace {

// The camera of a scene without one: it frames the bounding sphere from +Z, looking down -Z
// with +Y up.
Camera framing_camera(Vec3 bmin, Vec3 bmax) {
  Camera camera;
  const Vec3 center = (bmin + bmax) * 0.5f;
  const float radius = std::max(1e-3f, 0.5f * length(bmax - bmin));
  camera.yfov = 0.6911f;  // 39.6 degrees, a common default
  const float distance = radius / std::sin(0.5f * camera.yfov);
  camera.position = center + Vec3(0.f, 0.f, distance);
  return camera;
}

// The bounds of a description's world triangles and of each instance's mesh box, transformed
// (an instance of a missing mesh is left to the caller's checks); *mesh_bounds, if given, gets
// each mesh's own box. Returns whether an instance places a mesh that has triangles.
bool description_bounds(const SceneDescription& d, Vec3* lo, Vec3* hi,
                        std::vector<std::pair<Vec3, Vec3>>* mesh_bounds) {
  *lo = Vec3(std::numeric_limits<float>::max(), std::numeric_limits<float>::max(),
             std::numeric_limits<float>::max());
  *hi = -*lo;
  grow_bounds(d.world, lo, hi);
  std::vector<std::pair<Vec3, Vec3>> boxes;
  for (const Mesh& mesh : d.meshes) {
    Vec3 mlo(1e30f, 1e30f, 1e30f), mhi = -mlo;
    grow_bounds(mesh.geometry, &mlo, &mhi);
    boxes.push_back({mlo, mhi});
  }
  bool any_instance = false;
  for (const Instance& inst : d.instances) {
    if (inst.mesh >= d.meshes.size() || d.meshes[inst.mesh].geometry.empty()) continue;
    any_instance = true;
    const auto& b = boxes[inst.mesh];
    for (int c = 0; c < 8; ++c) {
      const Vec3 corner((c & 1) ? b.second.x : b.first.x, (c & 2) ? b.second.y : b.first.y,
                        (c & 4) ? b.second.z : b.first.z);
      const Vec3 w = inst.to_world.transform_point(corner);
      *lo = vmin(*lo, w);
      *hi = vmax(*hi, w);
    }
  }
  if (mesh_bounds) *mesh_bounds = std::move(boxes);
  return any_instance;
}

// Points and lines (desc->thin) as triangles appended to *out, for the description's camera or,
// without one, the camera that frames bounds grown by their vertices.
// Returns the height they were sized for (0: there are none).
uint32_t add_thin_triangles(SceneDescription* desc, Vec3 bmin, Vec3 bmax, TriangleMesh* out) {
  if (desc->thin.empty()) return 0;
  for (const Vec3& p : desc->thin.vertices.positions) {
    bmin = vmin(bmin, p);
    bmax = vmax(bmax, p);
  }
  const Camera camera = desc->camera ? *desc->camera : framing_camera(bmin, bmax);
  thin_triangles(desc->thin, camera, desc->image_height, out);
  desc->thin = ThinGeometry();
  return desc->image_height ? desc->image_height : kDefaultThinHeight;
}

}  // namespace

void thin_triangles(const ThinGeometry& thin, const Camera& camera, uint32_t height,
                    TriangleMesh* out) {
  if (thin.empty()) return;
  const TriangleMesh& v = thin.vertices;
  const float h = float(height ? height : kDefaultThinHeight);
  // The side of a pixel at p: 2 tan(yfov / 2) / height per unit of depth along the view (a
  // perspective camera), 2 ymag / height (an orthographic one). A point behind the camera (no
  // camera ray meets it) takes its distance for the depth.
  const float per_depth = 2.f * std::tan(0.5f * camera.yfov) / h;
  auto pixel = [&](Vec3 p) {
    if (camera.orthographic) return 2.f * camera.ymag / h;
    float z = dot(p - camera.position, camera.forward);
    if (!(z > 0.f)) z = length(p - camera.position);
    return per_depth * z;
  };
  auto towards_camera = [&](Vec3 p) {
    if (camera.orthographic) return -camera.forward;
    const Vec3 d = camera.position - p;
    const float len = length(d);
    return len > 0.f ? d * (1.f / len) : -camera.forward;
  };
  // A unit vector across `along` as the camera sees it from `view` (the camera's right where
  // along is the view direction itself).
  auto across = [&](Vec3 along, Vec3 view) {
    Vec3 side = cross(along, view);
    float len = length(side);
    if (!(len > 1e-12f * length(along))) {
      side = cross(camera.up, view);
      len = length(side);
      if (!(len > 0.f)) return camera.right;
    }
    return side * (1.f / len);
  };
  // Every attribute array of out that either side has is written for the new vertices.
  const size_t first = out->positions.size(), count = 4 * thin.elements.size();
  out->positions.resize(first + count);
  if (!v.normals.empty()) out->use_normals(true);
  if (!v.tangents.empty()) out->use_tangents(true);
  if (!v.colors.empty()) out->use_colors(true);
  for (size_t set = 0; set < v.uv.size(); ++set)
    if (!v.uv[set].empty()) out->use_uv(set, true);
  if (!out->normals.empty()) out->normals.resize(first + count);
  if (!out->tangents.empty()) out->tangents.resize(first + count);
  if (!out->colors.empty()) out->colors.resize(first + count, Rgba{});
  for (auto& uv : out->uv)
    if (!uv.empty()) uv.resize(first + count);
  auto copy_attributes = [&](size_t dst, uint32_t src) {
    if (!v.normals.empty()) out->normals[dst] = v.normals[src];
    if (!v.tangents.empty()) out->tangents[dst] = v.tangents[src];
    if (!v.colors.empty()) out->colors[dst] = v.colors[src];
    for (size_t set = 0; set < v.uv.size(); ++set)
      if (!v.uv[set].empty()) out->uv[set][dst] = v.uv[set][src];
  };
  out->indices.reserve(out->indices.size() + 6 * thin.elements.size());
  bool nodes = !out->node.empty();
  for (const ThinGeometry::Element& e : thin.elements) nodes = nodes || e.node != kNoNode;
  if (nodes) {
    out->use_nodes(true);
    out->node.reserve(out->node.size() + 2 * thin.elements.size());
  }
  size_t next = first;
  for (const ThinGeometry::Element& e : thin.elements) {
    const Vec3 a = v.positions[e.a], b = v.positions[e.b];
    Vec3 corner[4];
    if (e.a == e.b) {
      // A point: a square of one pixel facing the camera, counter-clockwise seen from it.
      const Vec3 view = towards_camera(a);
      const Vec3 right = across(camera.up, view);
      const Vec3 up = cross(view, right);
      const float r = 0.5f * pixel(a);
      corner[0] = a - (right + up) * r;
      corner[1] = a + (right - up) * r;
      corner[2] = a + (right + up) * r;
      corner[3] = a - (right - up) * r;
    } else {
      // A segment: a ribbon one pixel wide at each end, in the plane through the segment that
      // faces the camera at its middle; cross(side, b - a) points to the camera.
      const Vec3 side = across(b - a, towards_camera((a + b) * 0.5f));
      const float ra = 0.5f * pixel(a), rb = 0.5f * pixel(b);
      corner[0] = a - side * ra;
      corner[1] = a + side * ra;
      corner[2] = b + side * rb;
      corner[3] = b - side * rb;
    }
    for (int k = 0; k < 4; ++k) {
      out->positions[next + size_t(k)] = corner[k];
      copy_attributes(next + size_t(k), k < 2 ? e.a : e.b);
    }
    const uint32_t i0 = uint32_t(next);
    for (uint32_t i : {i0, i0 + 1, i0 + 2, i0, i0 + 2, i0 + 3}) out->indices.push_back(i);
    for (int t = 0; t < 2; ++t) {
      out->material.push_back(e.material);
      out->flags.push_back(e.flags);
      if (nodes) out->node.push_back(e.node);
    }
    next += 4;
  }
}

Scene::Scene(SceneDescription desc, std::vector<std::string>* warnings, BvhLayout bvh)
    : desc_(std::move(desc)), embree_(new Embree) {
  build(warnings, bvh);
}

Scene::Scene(StaticPart, SceneDescription desc, std::vector<std::string>* warnings,
             BvhLayout bvh)
    : desc_(std::move(desc)), embree_(new Embree) {
  static_part_ = true;
  if (!desc_.instances.empty())
    throw SceneError(desc_.source + ": the static part of an animated scene has no instances");
  build(warnings, bvh);
}

void Scene::build(std::vector<std::string>* warnings, BvhLayout bvh) {
  static_assert(sizeof(Vec3) == 3 * sizeof(float) && sizeof(Point2) == 2 * sizeof(float),
                "Embree reads TriangleMesh::positions as packed float triples");
  textures_ = std::make_shared<TextureSet>();
  if (!desc_.thin.empty()) {
    // Points and lines become triangles for the camera, which frames the bounds of everything
    // (these points included) if the scene has none.
    Vec3 lo, hi;
    description_bounds(desc_, &lo, &hi, nullptr);
    thin_height_ = add_thin_triangles(&desc_, lo, hi, &desc_.world);
  }
  if (desc_.world.empty() && desc_.instances.empty() && !static_part_)
    throw SceneError(desc_.source + ": the scene contains no (non-degenerate) triangles");
  if (desc_.materials.empty()) desc_.materials.push_back(Material{});
  const size_t nmat = desc_.materials.size();
  size_t dropped = clean_mesh(&desc_.world, nmat, desc_.source);
  for (Mesh& mesh : desc_.meshes)
    dropped += clean_mesh(&mesh.geometry, nmat, desc_.source + " mesh '" + mesh.name + "'");
  if (dropped && warnings)
    warnings->push_back(desc_.source + ": skipped " + std::to_string(dropped) +
                        " degenerate triangle(s)");
  // Per mesh (the world, then desc_.meshes): the number of opaque triangles, which come first.
  std::vector<uint32_t> first_transparent;
  first_transparent.push_back(partition_transparent(&desc_.world, desc_.materials));
  for (Mesh& mesh : desc_.meshes)
    first_transparent.push_back(partition_transparent(&mesh.geometry, desc_.materials));
  has_transparency_ = first_transparent[0] < desc_.world.size();
  has_vertex_colors_ = !desc_.world.colors.empty();
  for (const Mesh& mesh : desc_.meshes) has_vertex_colors_ |= !mesh.geometry.colors.empty();
  for (size_t m = 0; m < desc_.meshes.size(); ++m)
    has_transparency_ |= first_transparent[1 + m] < desc_.meshes[m].geometry.size();
  for (const Instance& inst : desc_.instances)
    if (inst.mesh >= desc_.meshes.size())
      throw SceneError(desc_.source + ": instance refers to missing mesh " +
                       std::to_string(inst.mesh));

  std::vector<std::pair<Vec3, Vec3>> mesh_bounds;
  const bool any_instance = description_bounds(desc_, &bmin_, &bmax_, &mesh_bounds);
  if (static_part_) mesh_bounds_ = mesh_bounds;
  if (desc_.world.empty() && !any_instance && !static_part_)
    throw SceneError(desc_.source + ": the scene contains no (non-degenerate) triangles");

  // Textures: an image OpenImageIO cannot read is dropped with a warning naming it; the
  // material then uses its constant factor. Each image is registered once for every way its
  // materials read it (Material::texture_slots): colours as sRGB, decoded before filtering
  // (TextureSet::add_encoded), the others as linear data.
  const size_t n = desc_.textures.size();
  std::vector<char> needed[2] = {std::vector<char>(n, 0), std::vector<char>(n, 0)};  // [srgb]
  for (Material& m : desc_.materials)
    for (const Material::TextureSlot& slot : Material::texture_slots()) {
      const TextureRef& ref = m.*slot.ref;
      if (ref.texture >= 0 && size_t(ref.texture) < n) needed[slot.srgb][ref.texture] = 1;
    }
  // A texture no material reads is still registered (header only), so that its pixels count
  // against the limit like any image the scene carries.
  for (size_t i = 0; i < n; ++i)
    if (!needed[0][i] && !needed[1][i]) needed[0][i] = 1;
  std::vector<int> texture_index[2] = {std::vector<int>(n, -1), std::vector<int>(n, -1)};
  for (size_t i = 0; i < n; ++i) {
    const TextureSource& t = desc_.textures[i];
    bool counted = false;
    for (int srgb = 0; srgb < 2; ++srgb) {
      if (!needed[srgb][i]) continue;
      std::string err;
      const int index =
          t.bytes.empty()
              ? textures_->add_file(t.path, t.wrap_s, t.wrap_t, &err, srgb, t.nearest)
              : textures_->add_encoded(t.bytes, t.mime_type, t.wrap_s, t.wrap_t, &err, srgb,
                                      t.nearest);
      texture_index[srgb][i] = index;
      if (index < 0) {
        if (warnings) warnings->push_back(desc_.source + ": " + t.name + " ignored: " + err);
        break;
      }
      if (counted) continue;  // one image, however many ways it is read
      counted = true;
      // Only the image's header has been read so far (OpenImageIO decodes tiles on demand,
      // into a cache of bounded size), so a huge image is refused before it costs anything.
      desc_.stats.texture_pixels += textures_->pixels(index);
      if (desc_.stats.texture_pixels > desc_.limits.max_texture_pixels)
        throw SceneError(desc_.source + ": textures[" + std::to_string(i) + "]: the textures' " +
                             "images hold " + std::to_string(desc_.stats.texture_pixels) +
                             " pixels so far, over the limit of " +
                             std::to_string(desc_.limits.max_texture_pixels),
                         "textures[" + std::to_string(i) + "]");
    }
  }
  for (Material& m : desc_.materials)
    for (const Material::TextureSlot& slot : Material::texture_slots()) {
      TextureRef& ref = m.*slot.ref;
      if (ref.texture >= 0)
        ref.texture = size_t(ref.texture) < n ? texture_index[slot.srgb][ref.texture] : -1;
    }
  desc_.textures.clear();
  desc_.textures.shrink_to_fit();

  // Embree's kernels capped at the worker's instruction set (util/isa.h: AVX2 unless
  // RENDERFARM_ISA says otherwise), so that workers on different CPUs find the same hits.
  const std::string device_config = embree_device_config(isa_cap());
  embree_->device = rtcNewDevice(device_config.empty() ? nullptr : device_config.c_str());
  if (!embree_->device) throw SceneError(desc_.source + ": cannot create Embree device");
  rtcSetDeviceErrorFunction(embree_->device, embree_error, nullptr);
  rtcSetDeviceMemoryMonitorFunction(embree_->device, count_embree_bytes, &embree_->bytes);
  packet_query_width_ =
      rtcGetDeviceProperty(embree_->device, RTC_DEVICE_PROPERTY_NATIVE_RAY16_SUPPORTED) ? 16 : 8;
  const RTCSceneFlags scene_flags =
      bvh == BvhLayout::Compact ? RTC_SCENE_FLAG_COMPACT : RTC_SCENE_FLAG_NONE;
  embree_->scene_flags = scene_flags;
  embree_->mesh_first_transparent.assign(first_transparent.begin() + 1, first_transparent.end());
  embree_->scene = rtcNewScene(embree_->device);
  rtcSetSceneFlags(embree_->scene, scene_flags);
  if (has_transparency_ &&
      !rtcGetDeviceProperty(embree_->device, RTC_DEVICE_PROPERTY_FILTER_FUNCTION_SUPPORTED))
    throw SceneError(desc_.source + ": materials with alphaMode MASK or BLEND need Embree's "
                     "filter functions, which this Embree library was built without");
  auto attach = [&](RTCScene target, const TriangleMesh& mesh, uint32_t opaque) {
    return attach_triangles(embree_->device, target, mesh, opaque, this, &embree_->filters,
                            false);
  };
  if (!desc_.world.empty()) {
    const auto ids = attach(embree_->scene, desc_.world, first_transparent[0]);
    for (unsigned id : {ids.first, ids.second}) {
      if (id == RTC_INVALID_GEOMETRY_ID) continue;
      if (embree_->slot_of_geom.size() <= id) embree_->slot_of_geom.resize(id + 1);
      embree_->slot_of_geom[id] = kWorldSlot;
    }
    embree_->world_transparent_geom = ids.second;
  }
  // One Embree scene per shared mesh, built once, placed by instance geometries. In it, the
  // opaque triangles are geometry 0 if there are any and the others the next geometry.
  for (size_t m = 0; m < desc_.meshes.size(); ++m) {
    RTCScene ms = nullptr;
    if (!desc_.meshes[m].geometry.empty()) {
      ms = rtcNewScene(embree_->device);
      rtcSetSceneFlags(ms, scene_flags);
      attach(ms, desc_.meshes[m].geometry, first_transparent[1 + m]);
      rtcSetSceneBuildQuality(ms, RTC_BUILD_QUALITY_HIGH);
      rtcCommitScene(ms);
    }
    embree_->mesh_scenes.push_back(ms);
  }
  slot_mesh_.push_back(&desc_.world);
  slot_first_transparent_.push_back(first_transparent[0]);
  for (const Instance& inst : desc_.instances) {
    slot_mesh_.push_back(&desc_.meshes[inst.mesh].geometry);
    slot_first_transparent_.push_back(first_transparent[1 + inst.mesh]);
  }
  instance_xf_.reserve(desc_.instances.size());
  for (const Instance& inst : desc_.instances)
    instance_xf_.push_back(Affine3f::from(inst.to_world));
  for (uint32_t k = 0; k < desc_.instances.size(); ++k) {
    const Instance& inst = desc_.instances[k];
    RTCScene ms = embree_->mesh_scenes[inst.mesh];
    if (!ms) continue;
    RTCGeometry geom = rtcNewGeometry(embree_->device, RTC_GEOMETRY_TYPE_INSTANCE);
    rtcSetGeometryInstancedScene(geom, ms);
    float xf[16];
    for (int c = 0; c < 4; ++c)
      for (int r = 0; r < 4; ++r) xf[4 * c + r] = float(inst.to_world.m[size_t(c)][size_t(r)]);
    rtcSetGeometryTransform(geom, 0, RTC_FORMAT_FLOAT4X4_COLUMN_MAJOR, xf);
    rtcCommitGeometry(geom);
    const unsigned id = rtcAttachGeometry(embree_->scene, geom);
    rtcReleaseGeometry(geom);
    if (embree_->slot_of_geom.size() <= id) embree_->slot_of_geom.resize(id + 1);
    embree_->slot_of_geom[id] = 1 + k;
  }
  rtcSetSceneBuildQuality(embree_->scene, RTC_BUILD_QUALITY_HIGH);
  rtcCommitScene(embree_->scene);
  find_material_hit_flags();
  if (static_part_) {
    static_embree_bytes_ =
        size_t(std::max<int64_t>(0, embree_->bytes.load(std::memory_order_relaxed)));
  } else {
    finish_lights_and_camera(warnings);
  }
}

void Scene::find_material_hit_flags() {
  material_hit_flags_.resize(desc_.materials.size());
  for (size_t m = 0; m < desc_.materials.size(); ++m) {
    const Material& mat = desc_.materials[m];
    material_hit_flags_[m] = uint8_t((mat.reads_uv() ? kHitReadsUv : 0) |
                                     (mat.needs_tangent() ? kHitNeedsTangent : 0));
  }
}

void Scene::finish_lights_and_camera(std::vector<std::string>* warnings) {
  // Lights: emissive world triangles and emissive triangles of every instance. The nodes of
  // the triangles that emit or are unlit (emitting_nodes_), each noted once per run of
  // triangles of one node.
  std::vector<char> shows(desc_.materials.size(), 0);
  for (size_t m = 0; m < shows.size(); ++m)
    shows[m] = desc_.materials[m].is_emissive() || desc_.materials[m].unlit;
  emitting_nodes_.clear();
  const auto note = [this](uint32_t node) {
    if (emitting_nodes_.empty() || emitting_nodes_.back() != node)
      emitting_nodes_.push_back(node);
  };
  std::vector<Emitter> emitters;
  const TriangleMesh& world = *slot_mesh_[kWorldSlot];
  for (uint32_t i = 0; i < world.size(); ++i) {
    if (!shows[world.material[i]]) continue;
    note(node(kWorldSlot, i));
    if (!desc_.materials[world.material[i]].is_emissive()) continue;
    const Triangle tri = world.triangle(i);
    emitters.push_back({{tri.p[0], tri.p[1], tri.p[2]}, tri.ng, tri.area, kWorldSlot, i,
                        tri.material});
  }
  for (uint32_t k = 0; k < desc_.instances.size(); ++k) {
    const Instance& inst = desc_.instances[k];
    const TriangleMesh& mesh = *slot_mesh_[1 + k];
    for (uint32_t i = 0; i < mesh.size(); ++i) {
      if (!shows[mesh.material[i]]) continue;
      note(node(1 + k, i));
      if (!desc_.materials[mesh.material[i]].is_emissive()) continue;
      const Triangle tri = mesh.triangle(i);
      Emitter e;
      for (int v = 0; v < 3; ++v) e.p[v] = inst.to_world.transform_point(tri.p[v]);
      const float len = face_normal(e.p[0], e.p[1], e.p[2], &e.ng);
      if (!(len > 0.f) || !std::isfinite(len)) continue;
      // The front face stays the front face under mirroring transforms: follow the
      // transformed normal, not the (flipped) winding.
      if (dot(e.ng, inst.to_world.transform_normal(tri.ng)) < 0.f) e.ng = -e.ng;
      e.area = 0.5f * len;
      e.slot = 1 + k;
      e.prim = i;
      e.material = tri.material;
      emitters.push_back(e);
    }
  }
  lights_ = LightSet(std::move(emitters), desc_.materials, desc_.punctual_lights,
                     std::max(1e-3f, 0.5f * length(bmax_ - bmin_)));
  for (const PunctualLight& light : lights_.punctual()) emitting_nodes_.push_back(light.node);
  std::sort(emitting_nodes_.begin(), emitting_nodes_.end());
  emitting_nodes_.erase(std::unique(emitting_nodes_.begin(), emitting_nodes_.end()),
                        emitting_nodes_.end());
  emitting_nodes_.shrink_to_fit();

  if (desc_.camera) {
    camera_ = *desc_.camera;
  } else {
    camera_ = framing_camera(bmin_, bmax_);
    if (warnings)
      warnings->push_back(desc_.source +
                          ": no camera in the scene; framing its bounds from +Z");
  }
}

Scene::~Scene() = default;

struct DeformedMeshes::Part {
  TriangleMesh mesh;    // its vertices at the pose's time (motion blur: the shutter's opening)
  uint32_t opaque = 0;  // the first `opaque` triangles are opaque (partition_transparent)
  bool finite = true;   // every vertex is finite: the BVH may be refit (else it is rebuilt)
  // Motion blur: the positions and normals at time steps 1, 2, ... (step 0 is mesh's).
  std::vector<std::vector<Vec3>> step_positions, step_normals;
  RTCScene scene = nullptr;
  std::pair<unsigned, unsigned> geoms;
  std::vector<std::unique_ptr<TransparencyFilter>> filters;
  ~Part() {
    if (scene) rtcReleaseScene(scene);
  }
};

DeformedMeshes::DeformedMeshes() = default;
DeformedMeshes::~DeformedMeshes() = default;

size_t DeformedMeshes::memory_bytes() const {
  size_t n = 0;
  for (const auto& part : parts_) {
    if (!part) continue;
    n += part->mesh.memory_bytes();
    for (const auto& v : part->step_positions) n += v.capacity() * sizeof(Vec3);
    for (const auto& v : part->step_normals) n += v.capacity() * sizeof(Vec3);
  }
  return n;
}

namespace {

bool same_triangles(const TriangleMesh& a, const TriangleMesh& b) {
  return a.positions.size() == b.positions.size() && a.normals.size() == b.normals.size() &&
         a.indices == b.indices && a.material == b.material && a.flags == b.flags &&
         a.node == b.node;
}

bool all_finite(const std::vector<Vec3>& points) {
  for (const Vec3& p : points)
    if (!is_finite(p)) return false;
  return true;
}

bool same_matrix(const Mat4& a, const Mat4& b) {
  for (size_t c = 0; c < 4; ++c)
    for (size_t r = 0; r < 4; ++r)
      if (a.m[c][r] != b.m[c][r]) return false;
  return true;
}

// Where time t in [0, 1] falls among `steps` evenly spaced time steps: the step before it
// and the fraction towards the next (Embree's linear motion blur).
inline void time_segment(float t, uint32_t steps, uint32_t* k, float* f) {
  const float x = std::min(std::max(t, 0.f), 1.f) * float(steps - 1);
  *k = std::min(uint32_t(x), steps - 2);
  *f = x - float(*k);
}

Mat4 lerp_matrix(const Mat4& a, const Mat4& b, double f) {
  Mat4 m;
  for (size_t c = 0; c < 4; ++c)
    for (size_t r = 0; r < 4; ++r) m.m[c][r] = a.m[c][r] + (b.m[c][r] - a.m[c][r]) * f;
  return m;
}

void column_major(const Mat4& m, float xf[16]) {
  for (int c = 0; c < 4; ++c)
    for (int r = 0; r < 4; ++r) xf[4 * c + r] = float(m.m[size_t(c)][size_t(r)]);
}

}  // namespace

Scene::Scene(std::shared_ptr<const Scene> base, std::vector<SceneDescription> steps,
             std::shared_ptr<DeformedMeshes> deformed, std::vector<std::string>* warnings)
    : embree_(new Embree) {
  if (steps.empty()) throw SceneError("a pose needs at least one time");
  desc_ = std::move(steps[0]);
  if (!base || !base->static_part_)
    throw SceneError(desc_.source + ": a pose needs the static part of its animated scene");
  base_ = std::move(base);
  deformed_ = deformed ? std::move(deformed) : std::make_shared<DeformedMeshes>();
  const Scene& b = *base_;
  const size_t nmesh = b.desc_.meshes.size();
  const uint32_t nsteps = uint32_t(steps.size());
  for (uint32_t k = 0; k < nsteps; ++k) {
    const SceneDescription& d = k == 0 ? desc_ : steps[k];
    if (d.meshes.size() != nmesh || d.instances.size() != desc_.instances.size())
      throw SceneError(desc_.source + ": a pose has " + std::to_string(d.meshes.size()) +
                       " meshes and " + std::to_string(d.instances.size()) +
                       " instances, its static part " + std::to_string(nmesh) +
                       " meshes and the first time step " +
                       std::to_string(desc_.instances.size()) + " instances");
    for (size_t i = 0; i < d.instances.size(); ++i)
      if (d.instances[i].mesh >= nmesh || d.instances[i].mesh != desc_.instances[i].mesh)
        throw SceneError(desc_.source + ": instance refers to missing mesh " +
                         std::to_string(d.instances[i].mesh));
  }
  // The base's materials, with the texture indices it registered; those KHR_animation_pointer
  // animates take their values at this pose's time (at the shutter's opening), keeping the
  // base's textures and texture coordinate arrays.
  std::vector<Material> posed_materials = std::move(desc_.materials);
  desc_.materials = b.desc_.materials;
  for (uint32_t i : desc_.animated_materials) {
    if (i >= desc_.materials.size() || i >= posed_materials.size()) continue;
    Material m = std::move(posed_materials[i]);
    for (const Material::TextureSlot& slot : Material::texture_slots()) {
      (m.*slot.ref).texture = (desc_.materials[i].*slot.ref).texture;
      (m.*slot.ref).texcoord = (desc_.materials[i].*slot.ref).texcoord;
    }
    desc_.materials[i] = std::move(m);
  }
  // Points and lines: triangles of this pose, for its camera (or, without one, the camera
  // that frames the static part and these points), in the mesh the loader keeps for them.
  if (desc_.thin_mesh >= 0 && size_t(desc_.thin_mesh) < desc_.meshes.size())
    thin_height_ = add_thin_triangles(&desc_, b.bmin_, b.bmax_,
                                      &desc_.meshes[size_t(desc_.thin_mesh)].geometry);
  desc_.textures.clear();
  desc_.limits = b.desc_.limits;
  desc_.stats = b.desc_.stats;
  textures_ = b.textures_;
  has_transparency_ = b.has_transparency_;
  has_vertex_colors_ = b.has_vertex_colors_;
  packet_query_width_ = b.packet_query_width_;
  RTCDevice device = b.embree_->device;
  rtcRetainDevice(device);  // released by ~Embree like a device of the scene's own
  embree_->device = device;
  embree_->scene_flags = b.embree_->scene_flags;
  const bool compact = (embree_->scene_flags & RTC_SCENE_FLAG_COMPACT) != 0;
  bool moves = false;  // anything differs between the time steps

  // The deformed meshes: refit where the set holds the same triangles, built otherwise (and
  // always with motion blur: Embree's refit is for one time step).
  DeformedMeshes& set = *deformed_;
  if (set.base_ != base_) {
    set.parts_.clear();
    set.base_ = base_;
  }
  set.parts_.resize(nmesh);
  set.refits_ = set.builds_ = 0;
  uint64_t deformed_triangles = 0;
  // A pose that fails part way leaves no half-updated mesh in the set.
  try {
    for (size_t m = 0; m < nmesh; ++m) {
      TriangleMesh& fresh = desc_.meshes[m].geometry;
      std::unique_ptr<DeformedMeshes::Part>& part = set.parts_[m];
      if (fresh.empty()) {
        part.reset();
        continue;
      }
      const std::string where = desc_.source + " mesh '" + desc_.meshes[m].name + "'";
      clean_mesh(&fresh, desc_.materials.size(), where, false);
      const uint32_t opaque = partition_transparent(&fresh, desc_.materials);
      has_transparency_ |= opaque < fresh.size();
      has_vertex_colors_ |= !fresh.colors.empty();
      deformed_triangles += fresh.size();
      bool finite = all_finite(fresh.positions);
      // The later steps' vertices, if their triangles are the first's (a winding that flips
      // within the shutter keeps the first step's vertices throughout).
      std::vector<std::vector<Vec3>> step_positions, step_normals;
      for (uint32_t k = 1; k < nsteps; ++k) {
        TriangleMesh& later = steps[k].meshes[m].geometry;
        clean_mesh(&later, desc_.materials.size(), where, false);
        partition_transparent(&later, desc_.materials);
        if (!same_triangles(later, fresh)) {
          step_positions.clear();
          step_normals.clear();
          break;
        }
        finite = finite && all_finite(later.positions);
        later.positions.reserve(later.positions.size() + 1);  // Embree's 16-byte loads
        step_positions.push_back(std::move(later.positions));
        step_normals.push_back(std::move(later.normals));
        later = TriangleMesh();
      }
      bool mesh_moves = false;
      for (const auto& positions : step_positions)
        mesh_moves = mesh_moves || std::memcmp(positions.data(), fresh.positions.data(),
                                               positions.size() * sizeof(Vec3)) != 0;
      if (!mesh_moves) {
        step_positions.clear();
        step_normals.clear();
      }
      moves = moves || mesh_moves;
      if (!mesh_moves && part && part->step_positions.empty() && finite && part->finite &&
          part->opaque == opaque && same_triangles(part->mesh, fresh)) {
        // Embree reads the arrays in place: overwrite them (same sizes) and refit.
        std::copy(fresh.positions.begin(), fresh.positions.end(), part->mesh.positions.begin());
        std::copy(fresh.normals.begin(), fresh.normals.end(), part->mesh.normals.begin());
        std::copy(fresh.face_normals.begin(), fresh.face_normals.end(),
                  part->mesh.face_normals.begin());
        for (unsigned id : {part->geoms.first, part->geoms.second}) {
          if (id == RTC_INVALID_GEOMETRY_ID) continue;
          RTCGeometry geom = rtcGetGeometry(part->scene, id);
          rtcUpdateGeometryBuffer(geom, RTC_BUFFER_TYPE_VERTEX, 0);
          rtcCommitGeometry(geom);
        }
        rtcCommitScene(part->scene);
        ++set.refits_;
      } else {
        part = std::make_unique<DeformedMeshes::Part>();
        part->mesh = std::move(fresh);
        part->opaque = opaque;
        part->finite = finite;
        part->step_positions = std::move(step_positions);
        part->step_normals = std::move(step_normals);
        part->scene = rtcNewScene(device);
        rtcSetSceneFlags(part->scene, embree_->scene_flags);
        // A two-level build (quality LOW) is the one that honours the geometries' REFIT.
        rtcSetSceneBuildQuality(part->scene, RTC_BUILD_QUALITY_LOW);
        const bool blurred = !part->step_positions.empty();
        part->geoms = attach_triangles(device, part->scene, part->mesh, opaque, &b,
                                       &part->filters, !blurred);
        if (blurred)
          for (unsigned id : {part->geoms.first, part->geoms.second}) {
            if (id == RTC_INVALID_GEOMETRY_ID) continue;
            RTCGeometry geom = rtcGetGeometry(part->scene, id);
            rtcSetGeometryTimeStepCount(geom, nsteps);
            rtcSetSharedGeometryBuffer(geom, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3,
                                       part->mesh.positions.data(), 0, sizeof(Vec3),
                                       part->mesh.positions.size());
            for (uint32_t k = 1; k < nsteps; ++k)
              rtcSetSharedGeometryBuffer(geom, RTC_BUFFER_TYPE_VERTEX, k, RTC_FORMAT_FLOAT3,
                                         part->step_positions[k - 1].data(), 0, sizeof(Vec3),
                                         part->mesh.positions.size());
            rtcCommitGeometry(geom);
          }
        rtcCommitScene(part->scene);
        ++set.builds_;
      }
      fresh = TriangleMesh();
    }
  } catch (...) {
    set.parts_.clear();
    throw;
  }

  // The top level: the base's world triangles as one instance at the identity (slot 0, as
  // the world of a scene of one piece), then the pose's instances, with a transform per time
  // step where they move.
  embree_->scene = rtcNewScene(device);
  rtcSetSceneFlags(embree_->scene, embree_->scene_flags);
  bmin_ = b.bmin_;
  bmax_ = b.bmax_;
  bool any = false;
  const Mat4 identity = Mat4::identity();
  auto place = [&](RTCScene instanced, const std::vector<const Mat4*>& xfs, uint32_t slot) {
    RTCGeometry geom = rtcNewGeometry(device, RTC_GEOMETRY_TYPE_INSTANCE);
    rtcSetGeometryInstancedScene(geom, instanced);
    rtcSetGeometryTimeStepCount(geom, unsigned(xfs.size()));
    for (size_t k = 0; k < xfs.size(); ++k) {
      float xf[16];
      column_major(*xfs[k], xf);
      rtcSetGeometryTransform(geom, unsigned(k), RTC_FORMAT_FLOAT4X4_COLUMN_MAJOR, xf);
    }
    rtcCommitGeometry(geom);
    const unsigned id = rtcAttachGeometry(embree_->scene, geom);
    rtcReleaseGeometry(geom);
    if (embree_->slot_of_geom.size() <= id) embree_->slot_of_geom.resize(id + 1);
    embree_->slot_of_geom[id] = slot;
  };
  slot_mesh_.push_back(&b.desc_.world);
  slot_first_transparent_.push_back(b.slot_first_transparent_[kWorldSlot]);
  slot_motion_.push_back(nullptr);
  if (!b.desc_.world.empty()) {
    place(b.embree_->scene, {&identity}, kWorldSlot);
    any = true;
  }
  instance_xf_.reserve(desc_.instances.size());
  instance_motion_.resize(desc_.instances.size());
  for (uint32_t k = 0; k < desc_.instances.size(); ++k) {
    const Instance& inst = desc_.instances[k];
    const DeformedMeshes::Part* part = set.parts_[inst.mesh].get();
    const TriangleMesh& mesh = part ? part->mesh : b.desc_.meshes[inst.mesh].geometry;
    slot_mesh_.push_back(&mesh);
    slot_first_transparent_.push_back(part ? part->opaque
                                           : b.embree_->mesh_first_transparent[inst.mesh]);
    slot_motion_.push_back(part && !part->step_positions.empty() ? part : nullptr);
    instance_xf_.push_back(Affine3f::from(inst.to_world));
    std::vector<const Mat4*> xfs{&inst.to_world};
    for (uint32_t j = 1; j < nsteps; ++j) xfs.push_back(&steps[j].instances[k].to_world);
    bool instance_moves = false;
    for (const Mat4* xf : xfs) instance_moves = instance_moves || !same_matrix(*xf, inst.to_world);
    if (instance_moves) {
      for (const Mat4* xf : xfs) instance_motion_[k].push_back(*xf);
      moves = true;
    } else {
      xfs.resize(1);
    }
    RTCScene ms = part ? part->scene : b.embree_->mesh_scenes[inst.mesh];
    if (!ms || mesh.empty()) continue;
    any = true;
    Vec3 lo(1e30f, 1e30f, 1e30f), hi = -lo;
    if (part) {
      grow_bounds(mesh, &lo, &hi);
      for (const auto& positions : part->step_positions)
        for (uint32_t v : mesh.indices) {
          lo = vmin(lo, positions[v]);
          hi = vmax(hi, positions[v]);
        }
    } else {
      lo = b.mesh_bounds_[inst.mesh].first;
      hi = b.mesh_bounds_[inst.mesh].second;
    }
    for (const Mat4* xf : xfs)
      for (int c = 0; c < 8; ++c) {
        const Vec3 corner((c & 1) ? hi.x : lo.x, (c & 2) ? hi.y : lo.y, (c & 4) ? hi.z : lo.z);
        const Vec3 w = xf->transform_point(corner);
        bmin_ = vmin(bmin_, w);
        bmax_ = vmax(bmax_, w);
      }
    place(ms, xfs, 1 + k);
  }
  if (!any)
    throw SceneError(desc_.source + ": the scene contains no (non-degenerate) triangles");
  rtcSetSceneBuildQuality(embree_->scene, RTC_BUILD_QUALITY_HIGH);
  rtcCommitScene(embree_->scene);
  // The loader's estimate (architecture.md): about 70 bytes a triangle (45 compact) and 256
  // an instance.
  pose_bvh_bytes_ = size_t(double(deformed_triangles) * (compact ? 45.0 : 70.0)) +
                    256 * (desc_.instances.size() + 1);
  desc_.meshes.clear();
  desc_.meshes.shrink_to_fit();
  find_material_hit_flags();
  finish_lights_and_camera(warnings);
  // The camera at every step, if it moves (a scene without a camera frames its bounds at
  // every time alike).
  if (desc_.camera) {
    bool camera_moves = false;
    for (uint32_t k = 1; k < nsteps; ++k) {
      const std::optional<Camera>& c = steps[k].camera;
      if (!c) continue;
      camera_moves = camera_moves || length(c->position - camera_.position) != 0.f ||
                     length(c->forward - camera_.forward) != 0.f ||
                     length(c->up - camera_.up) != 0.f || c->yfov != camera_.yfov ||
                     c->xmag != camera_.xmag || c->ymag != camera_.ymag;
    }
    if (camera_moves) {
      for (uint32_t k = 0; k < nsteps; ++k)
        camera_steps_.push_back(k == 0 || !steps[k].camera ? camera_ : *steps[k].camera);
      moves = true;
    }
  }
  motion_steps_ = moves ? nsteps : 1;
  if (!moves) {
    instance_motion_.clear();
    slot_motion_.clear();
  }
}

Camera Scene::camera_at(float t) const {
  if (camera_steps_.empty()) return camera_;
  uint32_t k;
  float f;
  time_segment(t, uint32_t(camera_steps_.size()), &k, &f);
  const Camera& a = camera_steps_[k];
  const Camera& b = camera_steps_[k + 1];
  auto mix = [f](float x, float y) { return x + (y - x) * f; };
  Camera c = a;
  c.position = a.position + (b.position - a.position) * f;
  c.yfov = mix(a.yfov, b.yfov);
  c.xmag = mix(a.xmag, b.xmag);
  c.ymag = mix(a.ymag, b.ymag);
  // The axes interpolated and made orthonormal again, as the loader makes a camera's.
  const Vec3 forward = a.forward + (b.forward - a.forward) * f;
  const Vec3 up = a.up + (b.up - a.up) * f;
  c.forward = normalize(forward);
  c.right = normalize(cross(c.forward, up));
  c.up = cross(c.right, c.forward);
  return c;
}

uint64_t Scene::world_triangle_count() const {
  uint64_t n = 0;
  for (const TriangleMesh* mesh : slot_mesh_) n += mesh->size();
  return n;
}

namespace {

thread_local RayLog* tl_ray_log = nullptr;

inline void init_ray(RTCRay* ray, Vec3 o, Vec3 d, float tmin, float tmax, uint32_t id,
                     float time = 0.f) {
  ray->org_x = o.x;
  ray->org_y = o.y;
  ray->org_z = o.z;
  ray->dir_x = d.x;
  ray->dir_y = d.y;
  ray->dir_z = d.z;
  ray->tnear = tmin;
  ray->tfar = tmax;
  ray->time = time;
  ray->mask = 0xffffffffu;
  ray->id = id;
  ray->flags = 0;
}

// Closest hit along o + t d, t in [tmin, tmax]; hit.geomID is RTC_INVALID_GEOMETRY_ID on a
// miss.
inline RTCRayHit trace_closest(RTCScene scene, Vec3 o, Vec3 d, float tmin, float tmax,
                               uint64_t query, uint32_t sample, float time = 0.f) {
  QueryContext context(query);
  RTCRayHit rh;
  init_ray(&rh.ray, o, d, tmin, tmax, sample, time);
  rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
  rh.hit.primID = RTC_INVALID_GEOMETRY_ID;
  rh.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
  rtcIntersect1(scene, &context.rtc, &rh);
  return rh;
}

}  // namespace

void set_thread_ray_log(RayLog* log) { tl_ray_log = log; }

bool Scene::intersect_t(Vec3 o, Vec3 d, float tmax, float* t) const {
  const RTCRayHit rh = trace_closest(embree_->scene, o, d, 0.f, tmax, 0, 0);
  if (rh.hit.geomID == RTC_INVALID_GEOMETRY_ID) return false;
  *t = rh.ray.tfar;
  return true;
}

bool Scene::intersect(Vec3 o, Vec3 d, float tmax, Hit* hit, uint64_t query, uint32_t sample,
                      float tmin, float time) const {
  if (tl_ray_log) tl_ray_log->push_back({o, d, tmax, false});
  const RTCRayHit rh = trace_closest(embree_->scene, o, d, tmin, tmax, query, sample, time);
  if (rh.hit.geomID == RTC_INVALID_GEOMETRY_ID) return false;
  complete_hit(rh.hit.geomID, rh.hit.instID[0], rh.hit.primID, rh.hit.u, rh.hit.v, rh.ray.tfar,
               hit, time);
  return true;
}

namespace {

// The valid flags and rays of an Embree packet query of width N (8 or 16) over lanes
// [first, first + N) of *rays. Active lanes go to the thread's ray log if one is installed.
template <int N, typename RayN>
void fill_packet(RayN* ray, int* valid, const RayPacket& rays, int first, bool shadow) {
  static_assert(offsetof(RayPacket, org_x) == offsetof(RTCRay16, org_x) &&
                    offsetof(RayPacket, tnear) == offsetof(RTCRay16, tnear) &&
                    offsetof(RayPacket, dir_x) == offsetof(RTCRay16, dir_x) &&
                    offsetof(RayPacket, time) == offsetof(RTCRay16, time) &&
                    offsetof(RayPacket, tfar) == offsetof(RTCRay16, tfar) &&
                    offsetof(RayPacket, mask) == offsetof(RTCRay16, mask) &&
                    offsetof(RayPacket, id) == offsetof(RTCRay16, id) &&
                    offsetof(RayPacket, flags) == offsetof(RTCRay16, flags) &&
                    offsetof(RayPacket, active) == sizeof(RTCRay16),
                "RayPacket must have RTCRay16's layout");
  static_assert(N == kPacketSize || N == kPacketSize / 2, "a whole packet or half of one");
  if constexpr (N == kPacketSize) {
    std::memcpy(ray, &rays, sizeof(RTCRay16));
  } else {
    // Both layouts are the same twelve 4-byte fields, each an array over the lanes: copy
    // lanes [first, first + N) of each.
    constexpr int kFields = 12;
    static_assert(sizeof(RayN) == kFields * N * 4 && offsetof(RayN, flags) == (kFields - 1) * N * 4,
                  "twelve 4-byte fields of N lanes each");
    const auto* from = reinterpret_cast<const unsigned char*>(&rays);
    auto* to = reinterpret_cast<unsigned char*>(ray);
    for (int f = 0; f < kFields; ++f)
      std::memcpy(to + f * N * 4, from + (f * kPacketSize + first) * 4, N * 4);
  }
  for (int i = 0; i < N; ++i) valid[i] = rays.active[first + i] ? -1 : 0;
  if (tl_ray_log)
    for (int i = first; i < first + N; ++i)
      if (rays.active[i])
        tl_ray_log->push_back({rays.origin(i), rays.direction(i), rays.tfar[i], shadow});
}

bool any_active(const RayPacket& rays, int first, int n) {
  bool any = false;
  for (int i = first; i < first + n; ++i) any |= rays.active[i];
  return any;
}

// The Embree packet query of each width, chosen by overload.
void rtc_intersect(const int* valid, RTCScene scene, RTCIntersectContext* c, RTCRayHit8* rh) {
  rtcIntersect8(valid, scene, c, rh);
}
void rtc_intersect(const int* valid, RTCScene scene, RTCIntersectContext* c, RTCRayHit16* rh) {
  rtcIntersect16(valid, scene, c, rh);
}
void rtc_occluded(const int* valid, RTCScene scene, RTCIntersectContext* c, RTCRay8* ray) {
  rtcOccluded8(valid, scene, c, ray);
}
void rtc_occluded(const int* valid, RTCScene scene, RTCIntersectContext* c, RTCRay16* ray) {
  rtcOccluded16(valid, scene, c, ray);
}

}  // namespace

template <int N, typename RayHitN>
void Scene::intersect_lanes(const RayPacket& rays, int first, Hit* hits, bool* found,
                            bool coherent, uint64_t query) const {
  alignas(64) int valid[N];
  alignas(64) RayHitN rh;
  fill_packet<N>(&rh.ray, valid, rays, first, false);
  for (int i = 0; i < N; ++i) {
    rh.hit.geomID[i] = RTC_INVALID_GEOMETRY_ID;
    rh.hit.primID[i] = RTC_INVALID_GEOMETRY_ID;
    rh.hit.instID[0][i] = RTC_INVALID_GEOMETRY_ID;
  }
  QueryContext context(query);
  context.rtc.flags =
      coherent ? RTC_INTERSECT_CONTEXT_FLAG_COHERENT : RTC_INTERSECT_CONTEXT_FLAG_INCOHERENT;
  rtc_intersect(valid, embree_->scene, &context.rtc, &rh);
  // Which lanes hit, without a branch per lane (whether a lane is active and hits something
  // is data the branch predictor cannot learn); then the hits one after another.
  uint32_t hit_lanes = 0;
  for (int i = 0; i < N; ++i) {
    const bool hit = rays.active[first + i] & (rh.hit.geomID[i] != RTC_INVALID_GEOMETRY_ID);
    found[first + i] = hit;
    hit_lanes |= uint32_t(hit) << i;
  }
  for (; hit_lanes; hit_lanes &= hit_lanes - 1) {
    const int i = __builtin_ctz(hit_lanes);
    complete_hit(rh.hit.geomID[i], rh.hit.instID[0][i], rh.hit.primID[i], rh.hit.u[i],
                 rh.hit.v[i], rh.ray.tfar[i], &hits[first + i], rays.time[first + i]);
  }
}

template <int N, typename RayN>
void Scene::occluded_lanes(const RayPacket& rays, int first, bool* blocked,
                           uint64_t query) const {
  alignas(64) int valid[N];
  alignas(64) RayN ray;
  fill_packet<N>(&ray, valid, rays, first, true);
  QueryContext context(query);
  rtc_occluded(valid, embree_->scene, &context.rtc, &ray);
  // Embree sets tfar to -inf in the lanes where it finds an occluder. Written for every lane
  // (inactive lanes' values mean nothing): cheaper than a branch per lane.
  for (int i = 0; i < N; ++i) blocked[first + i] = ray.tfar[i] < 0.f;
}

void Scene::intersect(const RayPacket& rays, Hit* hits, bool* found, bool coherent,
                      uint64_t query) const {
  if (packet_query_width_ == kPacketSize) {
    intersect_lanes<kPacketSize, RTCRayHit16>(rays, 0, hits, found, coherent, query);
    return;
  }
  for (int first = 0; first < kPacketSize; first += kPacketSize / 2) {
    if (any_active(rays, first, kPacketSize / 2))
      intersect_lanes<kPacketSize / 2, RTCRayHit8>(rays, first, hits, found, coherent, query);
    else
      std::fill(found + first, found + first + kPacketSize / 2, false);
  }
}

void Scene::occluded(const RayPacket& rays, bool* blocked, uint64_t query) const {
  if (packet_query_width_ == kPacketSize) {
    occluded_lanes<kPacketSize, RTCRay16>(rays, 0, blocked, query);
    return;
  }
  for (int first = 0; first < kPacketSize; first += kPacketSize / 2)
    if (any_active(rays, first, kPacketSize / 2))
      occluded_lanes<kPacketSize / 2, RTCRay8>(rays, first, blocked, query);
}

bool Scene::surface_point(uint32_t slot, uint32_t prim, float b1, float b2, float time,
                          Vec3* out) const {
  if (slot >= slot_mesh_.size()) return false;
  const TriangleMesh& mesh = *slot_mesh_[slot];
  if (prim >= mesh.size()) return false;
  const uint32_t* vi = &mesh.indices[3 * size_t(prim)];
  Vec3 p0 = mesh.positions[vi[0]], p1 = mesh.positions[vi[1]], p2 = mesh.positions[vi[2]];
  // As complete_hit_at: a deformed mesh under motion blur where it is at `time`, a moving
  // instance by its transform at `time`.
  const DeformedMeshes::Part* moving = motion_steps_ > 1 ? slot_motion_[slot] : nullptr;
  if (moving) {
    uint32_t step;
    float frac;
    time_segment(time, motion_steps_, &step, &frac);
    const std::vector<Vec3>& pa = step == 0 ? mesh.positions : moving->step_positions[step - 1];
    const std::vector<Vec3>& pb = moving->step_positions[step];
    p0 = pa[vi[0]] + (pb[vi[0]] - pa[vi[0]]) * frac;
    p1 = pa[vi[1]] + (pb[vi[1]] - pa[vi[1]]) * frac;
    p2 = pa[vi[2]] + (pb[vi[2]] - pa[vi[2]]) * frac;
  }
  const Vec3 p = p0 * (1.f - b1 - b2) + p1 * b1 + p2 * b2;
  if (slot == kWorldSlot) {
    *out = p;
  } else if (motion_steps_ > 1 && !instance_motion_[slot - 1].empty()) {
    const std::vector<Mat4>& xfs = instance_motion_[slot - 1];
    uint32_t k;
    float f;
    time_segment(time, uint32_t(xfs.size()), &k, &f);
    *out = Affine3f::from(lerp_matrix(xfs[k], xfs[k + 1], double(f))).point(p);
  } else {
    *out = instance_xf_[slot - 1].point(p);
  }
  return true;
}

void Scene::complete_hit(unsigned geom, unsigned inst, unsigned prim, float u, float v, float t,
                         Hit* hit, float time) const {
  // A scene without motion runs the code without a thought of it.
  if (motion_steps_ > 1)
    complete_hit_at<true>(geom, inst, prim, u, v, t, hit, time);
  else
    complete_hit_at<false>(geom, inst, prim, u, v, t, hit, time);
}

template <bool kMotion>
void Scene::complete_hit_at(unsigned geom, unsigned inst, unsigned prim, float u, float v,
                            float t, Hit* hit, float time) const {
  // A hit inside an instance names the instance as the top-level geometry.
  const bool in_instance = inst != RTC_INVALID_GEOMETRY_ID;
  const unsigned top = in_instance ? inst : geom;
  const uint32_t slot = top < embree_->slot_of_geom.size() ? embree_->slot_of_geom[top] : 0;
  // Non-opaque triangles are a geometry of their own, after the opaque ones: geometry 1 of an
  // instanced mesh (or 0 if it has only those, where the offset is 0), or the world's.
  if (in_instance ? geom != 0 : geom == embree_->world_transparent_geom)
    prim += slot_first_transparent_[slot];
  const TriangleMesh& mesh = *slot_mesh_[slot];
  const uint32_t* vi = &mesh.indices[3 * size_t(prim)];
  const uint8_t flags = mesh.flags[prim];
  hit->t = t;
  hit->prim = prim;
  hit->slot = slot;
  hit->b1 = u;
  hit->b2 = v;
  hit->material = mesh.material[prim];
  const float b0 = 1.f - hit->b1 - hit->b2;
  Vec3 p0 = mesh.positions[vi[0]], p1 = mesh.positions[vi[1]], p2 = mesh.positions[vi[2]];
  Vec3 ng = mesh.face_normals[prim];
  // A deformed mesh under motion blur: its triangle where it is at the ray's time, as Embree
  // interpolates it (linearly between the two time steps around it).
  const DeformedMeshes::Part* moving = nullptr;
  uint32_t step = 0;
  float frac = 0.f;
  if constexpr (kMotion) {
    moving = slot_motion_[slot];
    if (moving) {
      time_segment(time, motion_steps_, &step, &frac);
      const std::vector<Vec3>& pa = step == 0 ? mesh.positions : moving->step_positions[step - 1];
      const std::vector<Vec3>& pb = moving->step_positions[step];
      p0 = pa[vi[0]] + (pb[vi[0]] - pa[vi[0]]) * frac;
      p1 = pa[vi[1]] + (pb[vi[1]] - pa[vi[1]]) * frac;
      p2 = pa[vi[2]] + (pb[vi[2]] - pa[vi[2]]) * frac;
      face_normal(p0, p1, p2, &ng);
    }
  }
  // Barycentric position is more accurate than o + t d far from the origin.
  Vec3 p = p0 * b0 + p1 * hit->b1 + p2 * hit->b2;
  Vec3 ns = ng;
  if (flags & TriangleMesh::kHasNormals) {
    Vec3 n = mesh.normals[vi[0]] * b0 + mesh.normals[vi[1]] * hit->b1 +
             mesh.normals[vi[2]] * hit->b2;
    if constexpr (kMotion) {
      if (moving) {
        const std::vector<Vec3>& na = step == 0 ? mesh.normals : moving->step_normals[step - 1];
        const std::vector<Vec3>& nb = moving->step_normals[step];
        n = Vec3();
        for (int c = 0; c < 3; ++c) {
          const float w = c == 0 ? b0 : c == 1 ? hit->b1 : hit->b2;
          n += (na[vi[c]] + (nb[vi[c]] - na[vi[c]]) * frac) * w;
        }
      }
    }
    const float len = length(n);
    if (len > 0.f && std::isfinite(len)) ns = n / len;
  }
  // Tangent for normal mapping, from the uv parameterization of the normal map's set.
  const uint8_t material_flags = material_hit_flags_[hit->material];
  Vec3 dpdu(0.f, 0.f, 0.f);
  float sign = 1.f;
  const bool reads_uv = material_flags & kHitReadsUv;
  for (int k = 0; k < 2; ++k) {
    if (!(flags & (TriangleMesh::kHasUv0 << k)) || !reads_uv) {
      hit->uv[k] = Point2{0.f, 0.f};
      continue;
    }
    const Point2 t0 = mesh.uv[k][vi[0]], t1 = mesh.uv[k][vi[1]], t2 = mesh.uv[k][vi[2]];
    hit->uv[k] = Point2{t0.x * b0 + t1.x * hit->b1 + t2.x * hit->b2,
                        t0.y * b0 + t1.y * hit->b1 + t2.y * hit->b2};
  }
  const TriangleMesh::Tangent* tangent = nullptr;
  const bool needs_tangent = material_flags & kHitNeedsTangent;
  if (needs_tangent && (flags & TriangleMesh::kHasTangents)) {
    // The supplied TANGENT (glTF 3.7.2.1: MikkTSpace only where it is absent), interpolated;
    // the handedness is the first vertex's (glTF: +-1, the same over a triangle).
    const TriangleMesh::Tangent& a = mesh.tangents[vi[0]];
    const Vec3 along = a.xyz * b0 + mesh.tangents[vi[1]].xyz * hit->b1 +
                       mesh.tangents[vi[2]].xyz * hit->b2;
    if (length(along) > 0.f && a.w != 0.f) {
      dpdu = along;
      sign = a.w < 0.f ? -1.f : 1.f;
      tangent = &a;
    }
  }
  const uint32_t set =
      needs_tangent ? desc_.materials[hit->material].tangent_map().texcoord : 0u;
  if (!tangent && needs_tangent && has_uv(mesh, prim, set)) {
    // Solve [dp1 dp2] = [dpdu dpdv] [du1 du2; dv1 dv2] (pbrt's triangle derivatives).
    const Vec3 dp1 = p1 - p0, dp2 = p2 - p0;
    const Point2 t0 = mesh.uv[set][vi[0]], t1 = mesh.uv[set][vi[1]], t2 = mesh.uv[set][vi[2]];
    const float du1 = t1.x - t0.x, du2 = t2.x - t0.x;
    const float dv1 = t1.y - t0.y, dv2 = t2.y - t0.y;
    const float det = du1 * dv2 - dv1 * du2;
    if (std::fabs(det) > 1e-12f) {
      const float inv = 1.f / det;
      dpdu = (dp1 * dv2 - dp2 * dv1) * inv;
      const Vec3 dpdv = (dp2 * du1 - dp1 * du2) * inv;
      // glTF's uv has v pointing down the image while normal maps' green channel points
      // up: the bitangent is -dpdv. Handedness relative to the geometric normal.
      sign = dot(cross(dpdu, -dpdv), ng) >= 0.f ? 1.f : -1.f;
    }
  }
  if (slot != kWorldSlot) {
    std::optional<Affine3f> blurred;
    if constexpr (kMotion) {
      if (!instance_motion_[slot - 1].empty()) {
        // A moving instance: its transform at the ray's time (Embree interpolates the
        // matrices linearly between the time steps).
        const std::vector<Mat4>& xfs = instance_motion_[slot - 1];
        uint32_t k;
        float f;
        time_segment(time, uint32_t(xfs.size()), &k, &f);
        blurred.emplace(Affine3f::from(lerp_matrix(xfs[k], xfs[k + 1], double(f))));
      }
    }
    const Affine3f& m = kMotion && blurred ? *blurred : instance_xf_[slot - 1];
    p = m.point(p);
    const Vec3 ngw = m.normal(ng), nsw = m.normal(ns);
    const float ngl = length(ngw), nsl = length(nsw);
    ng = ngl > 0.f ? ngw / ngl : ng;
    ns = nsl > 0.f ? nsw / nsl : ng;
    dpdu = m.vector(dpdu);
    if (m.mirror) sign = -sign;
  }
  hit->p = p;
  hit->ng = ng;
  hit->ns = ns;
  hit->dpdu = dpdu;
  hit->tangent_sign = sign;
}

bool Scene::occluded(Vec3 o, Vec3 d, float tmax, uint64_t query, uint32_t sample,
                     float time) const {
  if (tl_ray_log) tl_ray_log->push_back({o, d, tmax, true});
  QueryContext context(query);
  RTCRay ray;
  init_ray(&ray, o, d, 0.f, tmax, sample, time);
  rtcOccluded1(embree_->scene, &context.rtc, &ray);
  // Embree sets tfar to -inf when an occluder is found.
  return ray.tfar < 0.f;
}

const Material& Scene::material(uint32_t slot, uint32_t prim) const {
  return desc_.materials[slot_mesh_[slot]->material[prim]];
}

Vec3 Scene::emission(uint32_t slot, uint32_t prim, float b1, float b2, float cos_view) const {
  const TriangleMesh& mesh = *slot_mesh_[slot];
  const Material& m = desc_.materials[mesh.material[prim]];
  Vec3 e = m.emission;
  if (m.emissive_tex.valid() && has_uv(mesh, prim, m.emissive_tex.texcoord)) {
    const Point2 uv = interpolate_uv(mesh, prim, b1, b2, m.emissive_tex.texcoord);
    float c[3];
    if (textures_->lookup(m.emissive_tex.texture, m.emissive_tex.apply(uv), 3, c))
      e = e * Vec3(c[0], c[1], c[2]);  // linear: decoded from sRGB before filtering
  }
  if (m.clearcoat > 0.f) {
    // KHR_materials_clearcoat, "Emission": the coat is above the emission, which the
    // layering weighs by 1 - clearcoat F_c like the rest of the material.
    float coat = m.clearcoat, c[3];
    if (m.clearcoat_tex.valid() && has_uv(mesh, prim, m.clearcoat_tex.texcoord) &&
        textures_->lookup(m.clearcoat_tex.texture,
                         m.clearcoat_tex.apply(
                             interpolate_uv(mesh, prim, b1, b2, m.clearcoat_tex.texcoord)),
                         3, c))
      coat *= c[0];
    e = e * (1.f - std::min(1.f, std::max(0.f, coat)) * clearcoat_fresnel(cos_view));
  }
  return e;
}

float Scene::coverage(uint32_t slot, uint32_t prim, float b1, float b2) const {
  return coverage(*slot_mesh_[slot], prim, b1, b2);
}

float Scene::coverage(const TriangleMesh& mesh, uint32_t prim, float b1, float b2) const {
  const Material& m = desc_.materials[mesh.material[prim]];
  if (m.is_opaque()) return 1.f;
  // glTF 2.0, 3.9.2: alpha is baseColorFactor.a x baseColorTexture.a x COLOR_0.a (the
  // texture's alpha is linear, not sRGB-encoded).
  float alpha = m.alpha;
  const uint32_t* vi = &mesh.indices[3 * size_t(prim)];
  const float b0 = 1.f - b1 - b2;
  if (!mesh.colors.empty())
    alpha *= mesh.colors[vi[0]].a * b0 + mesh.colors[vi[1]].a * b1 + mesh.colors[vi[2]].a * b2;
  if (m.base_color_tex.valid()) {
    float c[4];
    const Point2 uv = interpolate_uv(mesh, prim, b1, b2, m.base_color_tex.texcoord);
    if (textures_->lookup(m.base_color_tex.texture, m.base_color_tex.apply(uv), 4, c))
      alpha *= c[3];
  }
  if (m.alpha_mode == AlphaMode::Mask) return alpha >= m.alpha_cutoff ? 1.f : 0.f;
  return std::min(1.f, std::max(0.f, alpha));
}

bool Scene::stops(const TriangleMesh& mesh, uint32_t prim, float b1, float b2, uint64_t query,
                  uint32_t sample, uint32_t instance) const {
  const float alpha = coverage(mesh, prim, b1, b2);
  if (alpha >= 1.f) return true;
  if (alpha <= 0.f) return false;
  // A uniform number in [0, 1) per (ray, surface): independent between the surfaces a ray
  // meets (two overlapping layers of alpha 1/2 pass a quarter of the rays), between the rays of
  // a path, and between samples.
  const uint64_t h = hash4(query, sample, instance, prim);
  return fraction_to_float(uint32_t(h >> 32)) < alpha;
}

bool Scene::has_uv(const TriangleMesh& mesh, uint32_t prim, uint32_t set) {
  if (set < 2) return (mesh.flags[prim] & (TriangleMesh::kHasUv0 << set)) != 0;
  return set < mesh.uv.size() && !mesh.uv[set].empty();
}

Point2 Scene::interpolate_uv(const TriangleMesh& mesh, uint32_t prim, float b1, float b2,
                             uint32_t set) {
  if (!has_uv(mesh, prim, set)) return Point2{0.f, 0.f};
  const uint32_t* vi = &mesh.indices[3 * size_t(prim)];
  const std::vector<Point2>& uv = mesh.uv[set];
  const Point2 t0 = uv[vi[0]], t1 = uv[vi[1]], t2 = uv[vi[2]];
  const float b0 = 1.f - b1 - b2;
  return {t0.x * b0 + t1.x * b1 + t2.x * b2, t0.y * b0 + t1.y * b1 + t2.y * b2};
}

Point2 Scene::texcoord(const Hit& hit, uint32_t set) const {
  return interpolate_uv(*slot_mesh_[hit.slot], hit.prim, hit.b1, hit.b2, set);
}

bool Scene::vertex_color(const Hit& hit, Vec3* rgb) const {
  if (!has_vertex_colors_) return false;
  const TriangleMesh& mesh = *slot_mesh_[hit.slot];
  if (mesh.colors.empty()) return false;
  const uint32_t* vi = &mesh.indices[3 * size_t(hit.prim)];
  const float b1 = hit.b1, b2 = hit.b2, b0 = 1.f - b1 - b2;
  const Rgba c0 = mesh.colors[vi[0]], c1 = mesh.colors[vi[1]], c2 = mesh.colors[vi[2]];
  *rgb = Vec3(c0.r * b0 + c1.r * b1 + c2.r * b2, c0.g * b0 + c1.g * b1 + c2.g * b2,
              c0.b * b0 + c1.b * b1 + c2.b * b2);
  return true;
}

size_t TriangleMesh::memory_bytes() const {
  size_t uv_bytes = 0;
  for (const std::vector<Point2>& set : uv) uv_bytes += set.capacity() * sizeof(Point2);
  return positions.capacity() * sizeof(Vec3) + normals.capacity() * sizeof(Vec3) + uv_bytes +
         colors.capacity() * sizeof(Rgba) + tangents.capacity() * sizeof(Tangent) +
         (indices.capacity() + material.capacity() + node.capacity()) * sizeof(uint32_t) +
         flags.capacity() + face_normals.capacity() * sizeof(Vec3);
}

std::string format_bytes(size_t bytes) {
  char text[32];
  const double b = double(bytes);
  if (b < 1e6)
    std::snprintf(text, sizeof text, "%.1f kB", b * 1e-3);
  else if (b < 1e9)
    std::snprintf(text, sizeof text, "%.1f MB", b * 1e-6);
  else
    std::snprintf(text, sizeof text, "%.2f GB", b * 1e-9);
  return text;
}

const std::string& Scene::node_name(uint32_t node) const {
  static const std::string kNone;
  const auto it = desc_.node_names.find(node);
  if (it != desc_.node_names.end()) return it->second;
  if (base_) return base_->node_name(node);
  return kNone;
}

size_t Scene::memory_bytes() const {
  if (base_)
    return lights_.memory_bytes() + instance_xf_.capacity() * sizeof(Affine3f) +
           desc_.instances.capacity() * sizeof(Instance) +
           (deformed_ ? deformed_->memory_bytes() : 0) + pose_bvh_bytes_;
  if (static_part_) {
    size_t n = desc_.world.memory_bytes() + static_embree_bytes_;
    for (const Mesh& mesh : desc_.meshes) n += mesh.geometry.memory_bytes();
    return n;
  }
  size_t n = desc_.world.memory_bytes() + lights_.memory_bytes() +
             instance_xf_.capacity() * sizeof(Affine3f) +
             desc_.instances.capacity() * sizeof(Instance);
  for (const Mesh& mesh : desc_.meshes) n += mesh.geometry.memory_bytes();
  return n + size_t(std::max<int64_t>(0, embree_->bytes.load(std::memory_order_relaxed)));
}

void TriangleMesh::add(const Triangle& t) {
  const bool write_normals = use_normals(t.has_normals);
  const bool write_uv[2] = {use_uv(0, t.has_uv[0]), use_uv(1, t.has_uv[1])};
  if (use_nodes(t.node != kNoNode)) node.push_back(t.node);
  const uint32_t first = uint32_t(positions.size());
  for (int k = 0; k < 3; ++k) {
    positions.push_back(t.p[k]);
    if (write_normals) normals.push_back(t.has_normals ? t.n[k] : Vec3());
    for (int set = 0; set < 2; ++set)
      if (write_uv[set]) uv[set].push_back(t.has_uv[set] ? t.uv[set][k] : Point2{0.f, 0.f});
    // Arrays a Triangle has no value for stay as long as positions.
    for (size_t set = 2; set < uv.size(); ++set)
      if (!uv[set].empty()) uv[set].push_back(Point2{0.f, 0.f});
    if (!colors.empty()) colors.push_back(Rgba{});
    indices.push_back(first + uint32_t(k));
  }
  material.push_back(t.material);
  flags.push_back(uint8_t((t.has_normals ? kHasNormals : 0) | (t.has_uv[0] ? kHasUv0 : 0) |
                          (t.has_uv[1] ? kHasUv1 : 0)));
}

Triangle TriangleMesh::triangle(size_t i) const {
  Triangle t;
  const uint32_t* vi = &indices[3 * i];
  t.material = material[i];
  t.node = node.empty() ? kNoNode : node[i];
  t.has_normals = (flags[i] & kHasNormals) != 0;
  for (int set = 0; set < 2; ++set) t.has_uv[set] = (flags[i] & (kHasUv0 << set)) != 0;
  for (int k = 0; k < 3; ++k) {
    t.p[k] = positions[vi[k]];
    if (t.has_normals) t.n[k] = normals[vi[k]];
    for (int set = 0; set < 2; ++set)
      if (t.has_uv[set]) t.uv[set][k] = uv[set][vi[k]];
  }
  t.area = 0.5f * face_normal(t.p[0], t.p[1], t.p[2], &t.ng);
  return t;
}

std::unique_ptr<Scene> load_scene(const std::string& path, std::vector<std::string>* warnings,
                                  const LoadOptions& options) {
  return std::make_unique<Scene>(load_gltf(path, warnings, options), warnings, options.bvh);
}

std::unique_ptr<Scene> load_scene(const std::string& path, std::vector<std::string>* warnings,
                                  BvhLayout bvh) {
  LoadOptions options;
  options.bvh = bvh;
  return load_scene(path, warnings, options);
}

}  // namespace rf
