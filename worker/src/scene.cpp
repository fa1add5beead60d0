#include "scene.h"

#include <embree3/rtcore.h>

#include <cmath>
#include <cstdio>
#include <limits>

namespace rf {

Vec3 Camera::ray_direction(float px, float py, uint32_t width, uint32_t height) const {
  const float tan_half = std::tan(0.5f * yfov);
  const float aspect = float(width) / float(height);
  // Image plane at distance 1: x in [-aspect tan, aspect tan], y in [-tan, tan], y up.
  const float sx = (2.f * px / float(width) - 1.f) * aspect * tan_half;
  const float sy = (1.f - 2.f * py / float(height)) * tan_half;
  return normalize(forward + right * sx + up * sy);
}

struct Scene::Embree {
  RTCDevice device = nullptr;
  RTCScene scene = nullptr;
  ~Embree() {
    if (scene) rtcReleaseScene(scene);
    if (device) rtcReleaseDevice(device);
  }
};

namespace {

void embree_error(void* /*user*/, RTCError code, const char* message) {
  // Embree reports API misuse and out-of-memory here; there is no useful recovery, but the
  // message must reach the user.
  std::fprintf(stderr, "embree error %d: %s\n", int(code), message ? message : "");
}

}  // namespace

Scene::Scene(SceneDescription desc, std::vector<std::string>* warnings)
    : desc_(std::move(desc)), embree_(new Embree) {
  if (desc_.triangles.empty())
    throw SceneError(desc_.source + ": the scene contains no (non-degenerate) triangles");
  if (desc_.materials.empty()) desc_.materials.push_back(Material{"default", {}, {}});
  bmin_ = Vec3(std::numeric_limits<float>::max(), std::numeric_limits<float>::max(),
               std::numeric_limits<float>::max());
  bmax_ = -bmin_;
  // Degenerate (zero-area or non-finite) triangles have no normal and cannot be hit or
  // sampled meaningfully: drop them.
  std::vector<Triangle> kept;
  kept.reserve(desc_.triangles.size());
  for (Triangle& tri : desc_.triangles) {
    if (tri.material >= desc_.materials.size())
      throw SceneError(desc_.source + ": triangle refers to missing material " +
                       std::to_string(tri.material));
    const Vec3 c = cross(tri.p[1] - tri.p[0], tri.p[2] - tri.p[0]);
    const float len = length(c);
    if (!(len > 0.f) || !std::isfinite(len) || !is_finite(tri.p[0]) || !is_finite(tri.p[1]) ||
        !is_finite(tri.p[2]))
      continue;
    tri.area = 0.5f * len;
    tri.ng = c / len;
    for (const Vec3& p : tri.p) {
      bmin_ = vmin(bmin_, p);
      bmax_ = vmax(bmax_, p);
    }
    kept.push_back(tri);
  }
  if (kept.size() != desc_.triangles.size() && warnings)
    warnings->push_back(desc_.source + ": skipped " +
                        std::to_string(desc_.triangles.size() - kept.size()) +
                        " degenerate triangle(s)");
  desc_.triangles = std::move(kept);
  if (desc_.triangles.empty())
    throw SceneError(desc_.source + ": the scene contains no (non-degenerate) triangles");
  lights_ = LightSet(desc_.triangles, desc_.materials);

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
  RTCGeometry geom = rtcNewGeometry(embree_->device, RTC_GEOMETRY_TYPE_TRIANGLE);
  const size_t n = desc_.triangles.size();
  auto* vertices = static_cast<float*>(rtcSetNewGeometryBuffer(
      geom, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3, 3 * sizeof(float), 3 * n));
  auto* indices = static_cast<unsigned*>(rtcSetNewGeometryBuffer(
      geom, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, 3 * sizeof(unsigned), n));
  if (!vertices || !indices) {
    rtcReleaseGeometry(geom);
    throw SceneError(desc_.source + ": Embree could not allocate geometry buffers");
  }
  for (size_t i = 0; i < n; ++i) {
    for (int k = 0; k < 3; ++k) {
      const Vec3& p = desc_.triangles[i].p[k];
      vertices[9 * i + 3 * k + 0] = p.x;
      vertices[9 * i + 3 * k + 1] = p.y;
      vertices[9 * i + 3 * k + 2] = p.z;
      indices[3 * i + k] = unsigned(3 * i + k);
    }
  }
  rtcCommitGeometry(geom);
  rtcAttachGeometry(embree_->scene, geom);
  rtcReleaseGeometry(geom);  // the scene holds the reference now
  rtcSetSceneBuildQuality(embree_->scene, RTC_BUILD_QUALITY_HIGH);
  rtcCommitScene(embree_->scene);
}

Scene::~Scene() = default;

bool Scene::intersect(Vec3 o, Vec3 d, float tmax, Hit* hit) const {
  RTCIntersectContext context;
  rtcInitIntersectContext(&context);
  RTCRayHit rh;
  rh.ray.org_x = o.x;
  rh.ray.org_y = o.y;
  rh.ray.org_z = o.z;
  rh.ray.dir_x = d.x;
  rh.ray.dir_y = d.y;
  rh.ray.dir_z = d.z;
  rh.ray.tnear = 0.f;
  rh.ray.tfar = tmax;
  rh.ray.time = 0.f;
  rh.ray.mask = 0xffffffffu;
  rh.ray.id = 0;
  rh.ray.flags = 0;
  rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
  rh.hit.primID = RTC_INVALID_GEOMETRY_ID;
  rh.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
  rtcIntersect1(embree_->scene, &context, &rh);
  if (rh.hit.geomID == RTC_INVALID_GEOMETRY_ID) return false;
  const Triangle& tri = desc_.triangles[rh.hit.primID];
  hit->t = rh.ray.tfar;
  hit->prim = rh.hit.primID;
  hit->b1 = rh.hit.u;
  hit->b2 = rh.hit.v;
  const float b0 = 1.f - hit->b1 - hit->b2;
  // Barycentric position is more accurate than o + t d far from the origin.
  hit->p = tri.p[0] * b0 + tri.p[1] * hit->b1 + tri.p[2] * hit->b2;
  hit->ng = tri.ng;
  if (tri.has_normals) {
    const Vec3 ns = tri.n[0] * b0 + tri.n[1] * hit->b1 + tri.n[2] * hit->b2;
    const float len = length(ns);
    hit->ns = len > 0.f && std::isfinite(len) ? ns / len : tri.ng;
  } else {
    hit->ns = tri.ng;
  }
  return true;
}

bool Scene::occluded(Vec3 o, Vec3 d, float tmax) const {
  RTCIntersectContext context;
  rtcInitIntersectContext(&context);
  RTCRay ray;
  ray.org_x = o.x;
  ray.org_y = o.y;
  ray.org_z = o.z;
  ray.dir_x = d.x;
  ray.dir_y = d.y;
  ray.dir_z = d.z;
  ray.tnear = 0.f;
  ray.tfar = tmax;
  ray.time = 0.f;
  ray.mask = 0xffffffffu;
  ray.id = 0;
  ray.flags = 0;
  rtcOccluded1(embree_->scene, &context, &ray);
  // Embree sets tfar to -inf when an occluder is found.
  return ray.tfar < 0.f;
}

std::unique_ptr<Scene> load_scene(const std::string& path, std::vector<std::string>* warnings) {
  return std::make_unique<Scene>(load_gltf(path, warnings), warnings);
}

}  // namespace rf
