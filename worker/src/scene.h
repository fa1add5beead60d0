// Scene: triangles in world space, materials, emissive-triangle lights and a camera, with an
// Embree BVH for ray queries. Units are the glTF file's (metres by convention).
#pragma once

#include <cstdint>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

#include "lights.h"
#include "materials.h"
#include "vecmath.h"

namespace rf {

// Thrown when a scene cannot be loaded or built; the message names the file and the part of
// it (node, mesh, accessor, field) that is wrong.
class SceneError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// Pinhole camera. forward is the viewing direction (glTF camera local -Z), up its +Y,
// right its +X, all unit length and world space. yfov in radians, in (0, pi).
struct Camera {
  Vec3 position;
  Vec3 right{1.f, 0.f, 0.f}, up{0.f, 1.f, 0.f}, forward{0.f, 0.f, -1.f};
  float yfov = 0.8f;
  // Unit direction through image position (px, py) in pixels (x right, y down, continuous:
  // pixel (x, y) covers [x, x+1) x [y, y+1)) for an image of width x height pixels.
  Vec3 ray_direction(float px, float py, uint32_t width, uint32_t height) const;
};

struct Triangle {
  Vec3 p[3];                // world-space vertices in glTF winding order
  Vec3 n[3];                // world-space unit vertex normals (valid if has_normals)
  bool has_normals = false;
  uint32_t material = 0;    // index into Scene::materials()
  Vec3 ng;                  // unit geometric normal normalize(cross(p1-p0, p2-p0)): the front
  float area = 0.f;
};

// Everything needed to build a Scene; filled by the glTF loader or directly by tests.
struct SceneDescription {
  std::string source;  // file name or description, used in messages
  std::vector<Triangle> triangles;
  std::vector<Material> materials;  // at least one if there are triangles
  std::optional<Camera> camera;     // none: the Scene frames the bounding box from +Z
};

struct Hit {
  float t = 0.f;       // ray parameter (distance for unit directions)
  uint32_t prim = 0;   // triangle index
  float b1 = 0.f, b2 = 0.f;  // barycentrics of vertices 1 and 2
  Vec3 p;              // world position
  Vec3 ng;             // unit geometric normal (front side, see Triangle::ng)
  Vec3 ns;             // unit shading normal (interpolated, or ng without vertex normals)
};

class Scene {
 public:
  // Builds the BVH; throws SceneError if the description has no usable triangle.
  // Warnings (e.g. missing camera) are appended to *warnings if given.
  explicit Scene(SceneDescription desc, std::vector<std::string>* warnings = nullptr);
  ~Scene();
  Scene(const Scene&) = delete;
  Scene& operator=(const Scene&) = delete;

  // Closest hit along o + t d for t in (0, tmax); d need not be unit (t is then in units of d).
  bool intersect(Vec3 o, Vec3 d, float tmax, Hit* hit) const;
  // True if anything blocks o + t d for t in (0, tmax).
  bool occluded(Vec3 o, Vec3 d, float tmax) const;

  const std::string& source() const { return desc_.source; }
  const std::vector<Triangle>& triangles() const { return desc_.triangles; }
  const Material& material(uint32_t prim) const {
    return desc_.materials[desc_.triangles[prim].material];
  }
  const Camera& camera() const { return camera_; }
  bool has_file_camera() const { return desc_.camera.has_value(); }
  const LightSet& lights() const { return lights_; }
  Vec3 bounds_min() const { return bmin_; }
  Vec3 bounds_max() const { return bmax_; }
  float diagonal() const { return length(bmax_ - bmin_); }

 private:
  SceneDescription desc_;
  Camera camera_;
  LightSet lights_;
  Vec3 bmin_, bmax_;
  struct Embree;
  std::unique_ptr<Embree> embree_;
};

// Loads a .gltf (embedded data: URIs or files next to it) or .glb. Throws SceneError naming
// the file and the offending node/mesh/accessor/field. Warnings go to *warnings.
SceneDescription load_gltf(const std::string& path, std::vector<std::string>* warnings);
// Same, from the text of a .gltf; external URIs are resolved against base_dir.
SceneDescription load_gltf_from_string(const std::string& json, const std::string& base_dir,
                                       const std::string& name,
                                       std::vector<std::string>* warnings);
// load_gltf + Scene construction.
std::unique_ptr<Scene> load_scene(const std::string& path, std::vector<std::string>* warnings);

}  // namespace rf
