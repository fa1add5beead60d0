#include "scene.h"

#include <embree3/rtcore.h>

#include <cmath>
#include <cstddef>
#include <cstdio>
#include <cstring>
#include <limits>

namespace rf {

Camera::Raster Camera::raster(uint32_t width, uint32_t height) const {
  // sx = (2 px / width - 1) aspect tan_half, sy = (1 - 2 py / height) tan_half.
  const float tan_half = std::tan(0.5f * yfov);
  const float aspect = float(width) / float(height);
  Raster r;
  r.right = right;
  r.up = up;
  r.forward = forward;
  r.kx = 2.f * aspect * tan_half / float(width);
  r.bx = -aspect * tan_half;
  r.ky = -2.f * tan_half / float(height);
  r.by = tan_half;
  return r;
}

struct Scene::Embree {
  RTCDevice device = nullptr;
  RTCScene scene = nullptr;
  std::vector<RTCScene> mesh_scenes;
  std::vector<uint32_t> slot_of_geom;  // top-level geometry ID -> slot
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

// Computes ng and area, drops degenerate (zero-area or non-finite) triangles, which have no
// normal and cannot be hit or sampled meaningfully. Returns how many were dropped.
size_t clean_triangles(std::vector<Triangle>* triangles, size_t material_count,
                       const std::string& where) {
  std::vector<Triangle> kept;
  kept.reserve(triangles->size());
  for (Triangle& tri : *triangles) {
    if (tri.material >= material_count)
      throw SceneError(where + ": triangle refers to missing material " +
                       std::to_string(tri.material));
    const Vec3 c = cross(tri.p[1] - tri.p[0], tri.p[2] - tri.p[0]);
    const float len = length(c);
    if (!(len > 0.f) || !std::isfinite(len) || !is_finite(tri.p[0]) || !is_finite(tri.p[1]) ||
        !is_finite(tri.p[2]))
      continue;
    tri.area = 0.5f * len;
    tri.ng = c / len;
    kept.push_back(tri);
  }
  const size_t dropped = triangles->size() - kept.size();
  *triangles = std::move(kept);
  return dropped;
}

RTCGeometry triangle_geometry(RTCDevice device, const std::vector<Triangle>& triangles,
                              const std::string& source) {
  RTCGeometry geom = rtcNewGeometry(device, RTC_GEOMETRY_TYPE_TRIANGLE);
  const size_t n = triangles.size();
  auto* vertices = static_cast<float*>(rtcSetNewGeometryBuffer(
      geom, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3, 3 * sizeof(float), 3 * n));
  auto* indices = static_cast<unsigned*>(rtcSetNewGeometryBuffer(
      geom, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, 3 * sizeof(unsigned), n));
  if (!vertices || !indices) {
    rtcReleaseGeometry(geom);
    throw SceneError(source + ": Embree could not allocate geometry buffers");
  }
  for (size_t i = 0; i < n; ++i) {
    for (int k = 0; k < 3; ++k) {
      const Vec3& p = triangles[i].p[k];
      vertices[9 * i + 3 * size_t(k) + 0] = p.x;
      vertices[9 * i + 3 * size_t(k) + 1] = p.y;
      vertices[9 * i + 3 * size_t(k) + 2] = p.z;
      indices[3 * i + size_t(k)] = unsigned(3 * i + size_t(k));
    }
  }
  rtcCommitGeometry(geom);
  return geom;
}

}  // namespace

Scene::Scene(SceneDescription desc, std::vector<std::string>* warnings)
    : desc_(std::move(desc)), embree_(new Embree) {
  if (desc_.triangles.empty() && desc_.instances.empty())
    throw SceneError(desc_.source + ": the scene contains no (non-degenerate) triangles");
  if (desc_.materials.empty()) desc_.materials.push_back(Material{});
  const size_t nmat = desc_.materials.size();
  size_t dropped = clean_triangles(&desc_.triangles, nmat, desc_.source);
  for (Mesh& mesh : desc_.meshes)
    dropped += clean_triangles(&mesh.triangles, nmat, desc_.source + " mesh '" + mesh.name + "'");
  if (dropped && warnings)
    warnings->push_back(desc_.source + ": skipped " + std::to_string(dropped) +
                        " degenerate triangle(s)");
  for (const Instance& inst : desc_.instances)
    if (inst.mesh >= desc_.meshes.size())
      throw SceneError(desc_.source + ": instance refers to missing mesh " +
                       std::to_string(inst.mesh));

  // Bounds: world triangles, and the transformed corners of each instanced mesh's box.
  bmin_ = Vec3(std::numeric_limits<float>::max(), std::numeric_limits<float>::max(),
               std::numeric_limits<float>::max());
  bmax_ = -bmin_;
  for (const Triangle& tri : desc_.triangles)
    for (const Vec3& p : tri.p) {
      bmin_ = vmin(bmin_, p);
      bmax_ = vmax(bmax_, p);
    }
  std::vector<std::pair<Vec3, Vec3>> mesh_bounds;
  for (const Mesh& mesh : desc_.meshes) {
    Vec3 lo(1e30f, 1e30f, 1e30f), hi = -lo;
    for (const Triangle& tri : mesh.triangles)
      for (const Vec3& p : tri.p) {
        lo = vmin(lo, p);
        hi = vmax(hi, p);
      }
    mesh_bounds.push_back({lo, hi});
  }
  bool any_instance = false;
  for (const Instance& inst : desc_.instances) {
    const auto& b = mesh_bounds[inst.mesh];
    if (desc_.meshes[inst.mesh].triangles.empty()) continue;
    any_instance = true;
    for (int c = 0; c < 8; ++c) {
      const Vec3 corner((c & 1) ? b.second.x : b.first.x, (c & 2) ? b.second.y : b.first.y,
                        (c & 4) ? b.second.z : b.first.z);
      const Vec3 w = inst.to_world.transform_point(corner);
      bmin_ = vmin(bmin_, w);
      bmax_ = vmax(bmax_, w);
    }
  }
  if (desc_.triangles.empty() && !any_instance)
    throw SceneError(desc_.source + ": the scene contains no (non-degenerate) triangles");

  // Textures: an image OpenImageIO cannot read is dropped with a warning naming it; the
  // material then uses its constant factor.
  std::vector<int> texture_index(desc_.textures.size(), -1);
  for (size_t i = 0; i < desc_.textures.size(); ++i) {
    const TextureSource& t = desc_.textures[i];
    std::string err;
    texture_index[i] = t.bytes.empty()
                           ? textures_.add_file(t.path, t.wrap_s, t.wrap_t, &err)
                           : textures_.add_encoded(t.bytes, t.mime_type, t.wrap_s, t.wrap_t, &err);
    if (texture_index[i] < 0 && warnings)
      warnings->push_back(desc_.source + ": texture '" + t.name + "' ignored: " + err);
  }
  for (Material& m : desc_.materials)
    for (TextureRef* ref : {&m.base_color_tex, &m.metallic_roughness_tex, &m.normal_tex,
                            &m.emissive_tex})
      if (ref->texture >= 0)
        ref->texture = size_t(ref->texture) < texture_index.size()
                           ? texture_index[size_t(ref->texture)]
                           : -1;
  desc_.textures.clear();
  desc_.textures.shrink_to_fit();

  // Lights: emissive world triangles and emissive triangles of every instance.
  std::vector<Emitter> emitters;
  for (uint32_t i = 0; i < desc_.triangles.size(); ++i) {
    const Triangle& tri = desc_.triangles[i];
    if (!desc_.materials[tri.material].is_emissive()) continue;
    emitters.push_back({{tri.p[0], tri.p[1], tri.p[2]}, tri.ng, tri.area, kWorldSlot, i,
                        tri.material});
  }
  for (uint32_t k = 0; k < desc_.instances.size(); ++k) {
    const Instance& inst = desc_.instances[k];
    const std::vector<Triangle>& tris = desc_.meshes[inst.mesh].triangles;
    for (uint32_t i = 0; i < tris.size(); ++i) {
      const Triangle& tri = tris[i];
      if (!desc_.materials[tri.material].is_emissive()) continue;
      Emitter e;
      for (int v = 0; v < 3; ++v) e.p[v] = inst.to_world.transform_point(tri.p[v]);
      const Vec3 c = cross(e.p[1] - e.p[0], e.p[2] - e.p[0]);
      const float len = length(c);
      if (!(len > 0.f) || !std::isfinite(len)) continue;
      // The front face stays the front face under mirroring transforms: follow the
      // transformed normal, not the (flipped) winding.
      e.ng = c / len;
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

  if (desc_.camera) {
    camera_ = *desc_.camera;
  } else {
    // Frame the bounding sphere from +Z, looking down -Z with +Y up.
    const Vec3 center = (bmin_ + bmax_) * 0.5f;
    const float radius = std::max(1e-3f, 0.5f * length(bmax_ - bmin_));
    camera_.yfov = 0.6911f;  // 39.6 degrees, a common default
    const float distance = radius / std::sin(0.5f * camera_.yfov);
    camera_.position = center + Vec3(0.f, 0.f, distance);
    if (warnings)
      warnings->push_back(desc_.source +
                          ": no perspective camera in the scene; framing its bounds from +Z");
  }

  embree_->device = rtcNewDevice(nullptr);
  if (!embree_->device) throw SceneError(desc_.source + ": cannot create Embree device");
  rtcSetDeviceErrorFunction(embree_->device, embree_error, nullptr);
  embree_->scene = rtcNewScene(embree_->device);
  if (!desc_.triangles.empty()) {
    RTCGeometry geom = triangle_geometry(embree_->device, desc_.triangles, desc_.source);
    const unsigned id = rtcAttachGeometry(embree_->scene, geom);
    rtcReleaseGeometry(geom);  // the scene holds the reference now
    if (embree_->slot_of_geom.size() <= id) embree_->slot_of_geom.resize(id + 1);
    embree_->slot_of_geom[id] = kWorldSlot;
  }
  // One Embree scene per shared mesh, built once, placed by instance geometries.
  for (const Mesh& mesh : desc_.meshes) {
    RTCScene ms = nullptr;
    if (!mesh.triangles.empty()) {
      ms = rtcNewScene(embree_->device);
      RTCGeometry geom = triangle_geometry(embree_->device, mesh.triangles, desc_.source);
      rtcAttachGeometry(ms, geom);
      rtcReleaseGeometry(geom);
      rtcSetSceneBuildQuality(ms, RTC_BUILD_QUALITY_HIGH);
      rtcCommitScene(ms);
    }
    embree_->mesh_scenes.push_back(ms);
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
}

Scene::~Scene() = default;

uint64_t Scene::world_triangle_count() const {
  uint64_t n = desc_.triangles.size();
  for (const Instance& inst : desc_.instances) n += desc_.meshes[inst.mesh].triangles.size();
  return n;
}

namespace {

thread_local RayLog* tl_ray_log = nullptr;

inline void init_ray(RTCRay* ray, Vec3 o, Vec3 d, float tmax) {
  ray->org_x = o.x;
  ray->org_y = o.y;
  ray->org_z = o.z;
  ray->dir_x = d.x;
  ray->dir_y = d.y;
  ray->dir_z = d.z;
  ray->tnear = 0.f;
  ray->tfar = tmax;
  ray->time = 0.f;
  ray->mask = 0xffffffffu;
  ray->id = 0;
  ray->flags = 0;
}

// Closest hit along o + t d, t in [0, tmax]; hit.geomID is RTC_INVALID_GEOMETRY_ID on a miss.
inline RTCRayHit trace_closest(RTCScene scene, Vec3 o, Vec3 d, float tmax) {
  RTCIntersectContext context;
  rtcInitIntersectContext(&context);
  RTCRayHit rh;
  init_ray(&rh.ray, o, d, tmax);
  rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
  rh.hit.primID = RTC_INVALID_GEOMETRY_ID;
  rh.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
  rtcIntersect1(scene, &context, &rh);
  return rh;
}

}  // namespace

void set_thread_ray_log(RayLog* log) { tl_ray_log = log; }

bool Scene::intersect_t(Vec3 o, Vec3 d, float tmax, float* t) const {
  const RTCRayHit rh = trace_closest(embree_->scene, o, d, tmax);
  if (rh.hit.geomID == RTC_INVALID_GEOMETRY_ID) return false;
  *t = rh.ray.tfar;
  return true;
}

bool Scene::intersect(Vec3 o, Vec3 d, float tmax, Hit* hit) const {
  if (tl_ray_log) tl_ray_log->push_back({o, d, tmax, false});
  const RTCRayHit rh = trace_closest(embree_->scene, o, d, tmax);
  if (rh.hit.geomID == RTC_INVALID_GEOMETRY_ID) return false;
  complete_hit(rh.hit.geomID, rh.hit.instID[0], rh.hit.primID, rh.hit.u, rh.hit.v, rh.ray.tfar,
               hit);
  return true;
}

namespace {

// An Embree packet query's valid flags and rays: a copy of *rays, whose layout is RTCRay8's.
// Active lanes go to the thread's ray log if one is installed.
void fill_packet(RTCRay8* ray, int* valid, const RayPacket& rays, bool shadow) {
  static_assert(offsetof(RayPacket, org_x) == offsetof(RTCRay8, org_x) &&
                    offsetof(RayPacket, tnear) == offsetof(RTCRay8, tnear) &&
                    offsetof(RayPacket, dir_x) == offsetof(RTCRay8, dir_x) &&
                    offsetof(RayPacket, time) == offsetof(RTCRay8, time) &&
                    offsetof(RayPacket, tfar) == offsetof(RTCRay8, tfar) &&
                    offsetof(RayPacket, mask) == offsetof(RTCRay8, mask) &&
                    offsetof(RayPacket, id) == offsetof(RTCRay8, id) &&
                    offsetof(RayPacket, flags) == offsetof(RTCRay8, flags) &&
                    offsetof(RayPacket, active) == sizeof(RTCRay8),
                "RayPacket must have RTCRay8's layout");
  std::memcpy(ray, &rays, sizeof(RTCRay8));
  for (int i = 0; i < kPacketSize; ++i) valid[i] = rays.active[i] ? -1 : 0;
  if (tl_ray_log)
    for (int i = 0; i < kPacketSize; ++i)
      if (rays.active[i])
        tl_ray_log->push_back({rays.origin(i), rays.direction(i), rays.tfar[i], shadow});
}

}  // namespace

static_assert(kPacketSize == 8, "the packet queries are rtcIntersect8 / rtcOccluded8");

void Scene::intersect(const RayPacket& rays, Hit* hits, bool* found) const {
  alignas(32) int valid[kPacketSize];
  alignas(32) RTCRayHit8 rh;
  fill_packet(&rh.ray, valid, rays, false);
  for (int i = 0; i < kPacketSize; ++i) {
    rh.hit.geomID[i] = RTC_INVALID_GEOMETRY_ID;
    rh.hit.primID[i] = RTC_INVALID_GEOMETRY_ID;
    rh.hit.instID[0][i] = RTC_INVALID_GEOMETRY_ID;
  }
  RTCIntersectContext context;
  rtcInitIntersectContext(&context);
  rtcIntersect8(valid, embree_->scene, &context, &rh);
  for (int i = 0; i < kPacketSize; ++i) {
    if (!rays.active[i]) continue;
    found[i] = rh.hit.geomID[i] != RTC_INVALID_GEOMETRY_ID;
    if (!found[i]) continue;
    complete_hit(rh.hit.geomID[i], rh.hit.instID[0][i], rh.hit.primID[i], rh.hit.u[i],
                 rh.hit.v[i], rh.ray.tfar[i], &hits[i]);
  }
}

void Scene::occluded(const RayPacket& rays, bool* blocked) const {
  alignas(32) int valid[kPacketSize];
  alignas(32) RTCRay8 ray;
  fill_packet(&ray, valid, rays, true);
  RTCIntersectContext context;
  rtcInitIntersectContext(&context);
  rtcOccluded8(valid, embree_->scene, &context, &ray);
  // Embree sets tfar to -inf in the lanes where it finds an occluder.
  for (int i = 0; i < kPacketSize; ++i)
    if (rays.active[i]) blocked[i] = ray.tfar[i] < 0.f;
}

void Scene::complete_hit(unsigned geom, unsigned inst, unsigned prim, float u, float v, float t,
                         Hit* hit) const {
  // A hit inside an instance names the instance as the top-level geometry.
  const unsigned top = inst != RTC_INVALID_GEOMETRY_ID ? inst : geom;
  const uint32_t slot = top < embree_->slot_of_geom.size() ? embree_->slot_of_geom[top] : 0;
  const Triangle& tri = triangle(slot, prim);
  hit->t = t;
  hit->prim = prim;
  hit->slot = slot;
  hit->b1 = u;
  hit->b2 = v;
  hit->material = tri.material;
  const float b0 = 1.f - hit->b1 - hit->b2;
  // Barycentric position is more accurate than o + t d far from the origin.
  Vec3 p = tri.p[0] * b0 + tri.p[1] * hit->b1 + tri.p[2] * hit->b2;
  Vec3 ng = tri.ng;
  Vec3 ns = ng;
  if (tri.has_normals) {
    const Vec3 n = tri.n[0] * b0 + tri.n[1] * hit->b1 + tri.n[2] * hit->b2;
    const float len = length(n);
    if (len > 0.f && std::isfinite(len)) ns = n / len;
  }
  // Tangent for normal mapping, from the uv parameterization of the normal map's set.
  const Material& mat = desc_.materials[tri.material];
  const uint32_t set = std::min<uint32_t>(1u, mat.normal_tex.texcoord);
  Vec3 dpdu(0.f, 0.f, 0.f);
  float sign = 1.f;
  const bool reads_uv = mat.reads_uv();
  for (int k = 0; k < 2; ++k) {
    if (!tri.has_uv[k] || !reads_uv) {
      hit->uv[k] = Point2{0.f, 0.f};
      continue;
    }
    hit->uv[k] = Point2{tri.uv[k][0].x * b0 + tri.uv[k][1].x * hit->b1 + tri.uv[k][2].x * hit->b2,
                        tri.uv[k][0].y * b0 + tri.uv[k][1].y * hit->b1 + tri.uv[k][2].y * hit->b2};
  }
  if (mat.normal_tex.valid() && tri.has_uv[set]) {
    // Solve [dp1 dp2] = [dpdu dpdv] [du1 du2; dv1 dv2] (pbrt's triangle derivatives).
    const Vec3 dp1 = tri.p[1] - tri.p[0], dp2 = tri.p[2] - tri.p[0];
    const float du1 = tri.uv[set][1].x - tri.uv[set][0].x, du2 = tri.uv[set][2].x - tri.uv[set][0].x;
    const float dv1 = tri.uv[set][1].y - tri.uv[set][0].y, dv2 = tri.uv[set][2].y - tri.uv[set][0].y;
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
    const Affine3f& m = instance_xf_[slot - 1];
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

bool Scene::occluded(Vec3 o, Vec3 d, float tmax) const {
  if (tl_ray_log) tl_ray_log->push_back({o, d, tmax, true});
  RTCIntersectContext context;
  rtcInitIntersectContext(&context);
  RTCRay ray;
  init_ray(&ray, o, d, tmax);
  rtcOccluded1(embree_->scene, &context, &ray);
  // Embree sets tfar to -inf when an occluder is found.
  return ray.tfar < 0.f;
}

Vec3 Scene::emission(uint32_t slot, uint32_t prim, float b1, float b2) const {
  const Triangle& tri = triangle(slot, prim);
  const Material& m = desc_.materials[tri.material];
  Vec3 e = m.emission;
  if (m.emissive_tex.valid()) {
    const uint32_t set = std::min<uint32_t>(1u, m.emissive_tex.texcoord);
    if (tri.has_uv[set]) {
      const float b0 = 1.f - b1 - b2;
      const Point2 uv{tri.uv[set][0].x * b0 + tri.uv[set][1].x * b1 + tri.uv[set][2].x * b2,
                      tri.uv[set][0].y * b0 + tri.uv[set][1].y * b1 + tri.uv[set][2].y * b2};
      float c[3];
      if (textures_.lookup(m.emissive_tex.texture, m.emissive_tex.apply(uv), 3, c))
        e = e * Vec3(srgb_to_linear(c[0]), srgb_to_linear(c[1]), srgb_to_linear(c[2]));
    }
  }
  return e;
}

std::unique_ptr<Scene> load_scene(const std::string& path, std::vector<std::string>* warnings) {
  return std::make_unique<Scene>(load_gltf(path, warnings), warnings);
}

}  // namespace rf
