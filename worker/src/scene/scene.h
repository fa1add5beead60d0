// Scene: triangles in world space plus instanced meshes, materials, textures, lights and a
// camera, with an Embree BVH for ray queries (a mesh used by several nodes is built once as
// its own Embree scene and placed by instance geometries). Units are the glTF file's (metres
// by convention).
#pragma once

#include <cmath>
#include <cstdint>
#include <limits>
#include <map>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

#include "scene/lights.h"
#include "scene/materials.h"
#include "scene/textures.h"
#include "math/vecmath.h"

namespace rf {

// Thrown when a scene cannot be loaded or built; the message names the file and the part of
// it (node, mesh, accessor, field) that is wrong. path() is that part as a path into the glTF
// JSON ("nodes[3].children", "extensionsRequired[0]"), empty when the scene as a whole is
// refused; the server reports it as the refused field (scene.nodes[3].children).
// The layout of a scene's Embree BVH, a worker setting (`--bvh`). Fast: Embree's default
// layout, triangle vertices copied into the BVH's leaves, about 70 bytes per triangle. Compact
// (RTC_SCENE_FLAG_COMPACT): leaves refer to the shared vertex array instead, about 45 bytes per
// triangle and a third less peak memory while building, for 10-20% fewer rays per second.
// Both give the same closest hits.
enum class BvhLayout { Fast, Compact };
bool parse_bvh_layout(const std::string& name, BvhLayout* out);
const char* bvh_layout_name(BvhLayout layout);

class SceneError : public std::runtime_error {
 public:
  explicit SceneError(const std::string& what, std::string path = {})
      : std::runtime_error(what), path_(std::move(path)) {}
  const std::string& path() const { return path_; }

 private:
  std::string path_;
};

// What a scene may cost the process that loads it. The loader checks them on the file's
// declarations before it allocates anything for the geometry, so an accepted scene cannot
// exhaust a worker, and a refused one costs no more than parsing its JSON. The server passes
// its own settings to `renderfarm-worker inspect`; a worker loads farm scenes with the same
// defaults and its memory as the memory limit.
struct SceneLimits {
  uint64_t max_nodes = 1000000;                  // entries of "nodes"
  uint32_t max_depth = 1024;                     // levels of the node hierarchy
  uint64_t max_instanced_triangles = 1000000000;  // triangles over every mesh use
  uint64_t max_texture_pixels = uint64_t(1) << 30;  // summed over the images textures use
  uint64_t max_memory_bytes = 0;                 // estimated scene memory; 0: no limit
};

struct PoseReport;      // animation.h
struct AnimatedLayout;  // animation.h

// How a file is loaded: the name its messages use and whether it may read other files.
struct LoadOptions {
  std::string display_name;  // "" : the path
  // Relative URIs resolved next to the file (the standalone `render` command). Farm workers
  // and `inspect` load uploads, which must be self-contained: they never read another file.
  bool allow_external_files = true;
  SceneLimits limits;
  BvhLayout bvh = BvhLayout::Fast;  // for the memory estimate
  // Animation (glTF 2.0, 3.11): the time in seconds at which the animations pose the scene,
  // NaN (the default) for none: the nodes' own translation, rotation, scale, matrix and
  // weights, as without animations. Skins and morph target weights apply either way.
  double time = std::numeric_limits<double>::quiet_NaN();
  // KHR_animation_pointer's node visibility at this time instead (NaN: at `time`): the time
  // steps of a motion-blurred pose share the shutter opening's visibility.
  double visibility_time = std::numeric_limits<double>::quiet_NaN();
  // The glTF animations that drive the pose (indices into "animations"); empty: all of them.
  std::vector<int> animations;
  // The height in pixels of the images rendered from the scene: points and lines are one
  // pixel wide at it (0: kDefaultThinHeight, for loads that render nothing).
  uint32_t image_height = 0;
  // KHR_materials_variants: the variant whose materials the primitives that map it use, by
  // name or index; "" for the default materials (each primitive's own "material").
  std::string variant;
  // If set, the loader records every node's world matrix and where each mesh node's
  // vertices went (animation.h; the `pose` command).
  PoseReport* pose_report = nullptr;
  // If set (with a time), the loader splits the scene into its static part and what moves,
  // as AnimatedLayout says (animation.h; the AnimatedScene of animated_scene.h).
  AnimatedLayout* layout = nullptr;
  bool animated() const { return !std::isnan(time); }
};

// The image height points and lines are sized for when a load does not say (inspect, pose).
constexpr uint32_t kDefaultThinHeight = 1080;

// Figures of a loaded scene, for `inspect` and the limits.
struct SceneStats {
  uint64_t nodes = 0;                // entries of "nodes"
  uint32_t depth = 0;                // levels of the hierarchy in use (0: no nodes)
  uint64_t instanced_triangles = 0;  // triangles over every mesh use
  uint64_t estimated_bytes = 0;      // the loader's estimate of the scene's memory
  uint64_t texture_pixels = 0;       // summed over the textures' images (set by Scene)
  std::vector<std::string> extensions_used;
};

// The glTF camera: perspective (a pinhole) or orthographic. forward is the viewing direction
// (glTF camera local -Z), up its +Y, right its +X, all unit length and world space. yfov in
// radians, in (0, pi). An orthographic camera sees the box of half width xmag and half height
// ymag around its axis (glTF's projection: the image spans [-xmag, xmag] x [-ymag, ymag]
// whatever its aspect). Camera rays see surfaces between the clipping planes znear and zfar,
// distances along forward (0 and infinity: no clipping).
struct Camera {
  Vec3 position;
  Vec3 right{1.f, 0.f, 0.f}, up{0.f, 1.f, 0.f}, forward{0.f, 0.f, -1.f};
  float yfov = 0.8f;
  bool orthographic = false;
  float xmag = 1.f, ymag = 1.f;
  float znear = 0.f, zfar = std::numeric_limits<float>::infinity();
  // Unit direction through image position (px, py) in pixels (x right, y down, continuous:
  // pixel (x, y) covers [x, x+1) x [y, y+1)) for an image of width x height pixels.
  // The renderer computes raster(width, height) once per render and asks it per sample.
  Vec3 ray_direction(float px, float py, uint32_t width, uint32_t height) const {
    return raster(width, height).direction(px, py);
  }

  // Rays for one image size: the image plane (at distance 1 for a perspective camera, through
  // the position for an orthographic one) spans x in [-sx, sx] and y in [-sy, sy] (y up), with
  // (sx, sy) = (aspect tan(yfov/2), tan(yfov/2)) or (xmag, ymag), and pixel position (px, py)
  // maps to (px kx + bx, py ky + by) on it.
  struct Raster {
    Vec3 right, up, forward, position;
    float kx = 0.f, bx = 0.f, ky = 0.f, by = 0.f;
    bool orthographic = false;
    Vec3 direction(float px, float py) const {
      float axial;
      return direction(px, py, &axial);
    }
    // The same, and in *per_axial the distance along it per unit distance along forward
    // (1 / dot(direction, forward)), which turns the clipping planes into ray distances.
    Vec3 direction(float px, float py, float* per_axial) const {
      if (orthographic) {
        *per_axial = 1.f;
        return forward;
      }
      // forward + ... has length 1 / dot(direction, forward): its part along forward is 1.
      const Vec3 v = forward + right * (px * kx + bx) + up * (py * ky + by);
      *per_axial = length(v);
      return v * (1.f / *per_axial);
    }
    Vec3 origin(float px, float py) const {
      if (!orthographic) return position;
      return position + right * (px * kx + bx) + up * (py * ky + by);
    }
  };
  Raster raster(uint32_t width, uint32_t height) const;
  // The inverse of Raster::direction and origin through the lens centre (the pinhole; the
  // thin lens's depth of field aside): the continuous image position (*px, *py) in pixels (x
  // right from the left edge, y down from the top) where world point p projects. False, and
  // nothing written, where p is behind the camera or on the plane through its position
  // perpendicular to forward.
  static bool project(const Raster& r, Vec3 p, float* px, float* py) {
    const Vec3 v = p - r.position;
    const float z = dot(v, r.forward);
    if (!(z > 0.f)) return false;
    float sx = dot(v, r.right), sy = dot(v, r.up);
    if (!r.orthographic) {
      sx /= z;
      sy /= z;
    }
    *px = (sx - r.bx) / r.kx;
    *py = (sy - r.by) / r.ky;
    return true;
  }
};

// The glTF node of a triangle or instance where the description does not say (a scene built
// by hand, a mesh shared by several nodes): the Instance row reads 0 there.
constexpr uint32_t kNoNode = ~0u;

// One triangle with its attributes, by value: how tests and generated scenes describe
// geometry (TriangleMesh::add) and what TriangleMesh::triangle gathers back.
struct Triangle {
  Vec3 p[3];                // vertices in glTF winding order (world space, or the mesh's
                            // local space for instanced meshes)
  Vec3 n[3];                // unit vertex normals (valid if has_normals)
  Point2 uv[2][3];          // TEXCOORD_0 and TEXCOORD_1 per vertex (valid if has_uv[set])
  bool has_normals = false;
  bool has_uv[2] = {false, false};
  uint32_t material = 0;    // index into the scene's materials
  uint32_t node = kNoNode;  // the glTF node (TriangleMesh::node)
  // Filled by TriangleMesh::triangle (ignored by add): the unit geometric normal
  // normalize(cross(p1 - p0, p2 - p0)), whose side is the front face, and the area.
  Vec3 ng;
  float area = 0.f;
};

// A vertex colour (glTF COLOR_0, linear RGBA; VEC3 colours have alpha 1).
struct Rgba {
  float r = 1.f, g = 1.f, b = 1.f, a = 1.f;
};

// Indexed triangles in glTF's own layout: each vertex is stored once and shared by the
// triangles that use it, and Embree reads the positions and indices in place (shared
// buffers, not copies). About 45 bytes per triangle for a typical closed mesh with normals
// and one uv set (49 with the node of a world triangle), against 148 for a Triangle. Each
// per-vertex attribute array is either empty or as long as positions; a triangle's flags say
// which of normals, TEXCOORD_0 and TEXCOORD_1 it has (a mesh merges primitives with and
// without them). Vertices of a primitive without a texture coordinate set above 1 that
// another primitive has read (0, 0) there, and vertices without COLOR_0 in a mesh that has it
// read white.
struct TriangleMesh {
  enum : uint8_t { kHasNormals = 1, kHasUv0 = 2, kHasUv1 = 4, kHasTangents = 8 };
  std::vector<Vec3> positions;
  std::vector<Vec3> normals;       // unit vertex normals
  // glTF TANGENT: xyz the tangent (along +u of the normal map's texture coordinates), w = +-1
  // the handedness (bitangent = cross(normal, xyz) w); zeros where a primitive has none.
  struct Tangent {
    Vec3 xyz;
    float w = 0.f;
  };
  std::vector<Tangent> tangents;
  // Texture coordinates: TEXCOORD_0 and TEXCOORD_1 (always the two first entries, either may
  // be empty), then the other sets materials read (TextureRef::texcoord numbers them).
  std::vector<std::vector<Point2>> uv = std::vector<std::vector<Point2>>(2);
  std::vector<Rgba> colors;        // COLOR_0
  std::vector<uint32_t> indices;   // 3 per triangle, counter-clockwise = front face
  std::vector<uint32_t> material;  // per triangle: index into the scene's materials
  std::vector<uint8_t> flags;      // per triangle: kHas* bits
  // Per triangle, or empty: the index in the glTF's "nodes" of the node it belongs to
  // (kNoNode: none), for the Instance row. The world's triangles (meshes used by one node,
  // merged) and the points and lines of an animated scene's poses have it; a mesh placed by
  // instances leaves it empty, its node being the Instance's. Read for a camera ray's first
  // hit only (Scene::node), never while tracing: 4 bytes a world triangle.
  std::vector<uint32_t> node;
  // Per triangle: the unit geometric normal normalize(cross(p1 - p0, p2 - p0)). Computed by
  // Scene (which drops the triangles that have none); descriptions leave it empty. Kept
  // rather than recomputed per hit (a square root and a division): 12 bytes a triangle save
  // about 1.5% of the Cornell box's instructions.
  std::vector<Vec3> face_normals;

  size_t size() const { return material.size(); }
  bool empty() const { return material.empty(); }
  // Bytes held by the arrays (their capacity).
  size_t memory_bytes() const;
  // Appends t as a triangle with three vertices of its own.
  void add(const Triangle& t);
  // Triangle i with its attributes, geometric normal and area.
  Triangle triangle(size_t i) const;
  // Before appending vertices that have normals (needed) or not: whether their normals must
  // be appended too. That is so if they have them, or if earlier vertices had them; in the
  // first case the vertices before that had none get zeros, so the array stays as long as
  // positions.
  bool use_normals(bool needed) {
    if (needed) normals.resize(positions.size());
    return needed || !normals.empty();
  }
  // The same for TEXCOORD_<set>.
  bool use_uv(size_t set, bool needed) {
    if (set >= uv.size()) {
      if (!needed) return false;
      uv.resize(set + 1);
    }
    if (needed) uv[set].resize(positions.size());
    return needed || !uv[set].empty();
  }
  // The same for COLOR_0 (earlier vertices get white).
  bool use_colors(bool needed) {
    if (needed) colors.resize(positions.size(), Rgba{});
    return needed || !colors.empty();
  }
  bool use_tangents(bool needed) {
    if (needed) tangents.resize(positions.size());
    return needed || !tangents.empty();
  }
  // The same for the per-triangle node, before a triangle is appended (earlier triangles get
  // kNoNode).
  bool use_nodes(bool needed) {
    if (needed) node.resize(size(), kNoNode);
    return needed || !node.empty();
  }
};

// A mesh shared by several nodes, in its own local space.
struct Mesh {
  std::string name;
  TriangleMesh geometry;
};
struct Instance {
  uint32_t mesh = 0;  // index into SceneDescription::meshes
  // The glTF node it places (EXT_mesh_gpu_instancing: each of the node's instances), kNoNode
  // for none; the mesh's own per-triangle nodes, where it has them, take precedence
  // (Scene::node). In the padding before to_world: an Instance is no larger for it.
  uint32_t node = kNoNode;
  Mat4 to_world = Mat4::identity();
};

// glTF POINTS, LINES, LINE_STRIP and LINE_LOOP primitives (modes 0-3), in world space, as the
// loader reads them: their vertices with the attributes a triangle mesh has (the triangle
// arrays of `vertices` stay empty), and one element per point or line segment. They have no
// area, so the Scene gives them the width the glTF spec recommends, one pixel of the image
// (see thin_triangles), before it builds its BVH.
struct ThinGeometry {
  TriangleMesh vertices;
  struct Element {
    uint32_t a = 0, b = 0;  // vertex indices: a segment's ends, a point's vertex twice
    uint32_t material = 0;  // index into the scene's materials (the loader's thin variant)
    uint8_t flags = 0;      // TriangleMesh::kHas* bits
    uint32_t node = kNoNode;  // the glTF node whose mesh has it
  };
  std::vector<Element> elements;
  bool empty() const { return elements.empty(); }
};

// The triangles that stand for thin geometry in an image of `height` pixels seen by `camera`:
// a segment becomes a ribbon and a point a square, each facing the camera and one pixel wide
// where it is (glTF 2.0, "Point and Line Materials": "widths of 1px in viewport space"), with
// the attributes of its vertices. Appended to *out (world space), front faces towards the
// camera, each with its element's material and node.
void thin_triangles(const ThinGeometry& thin, const Camera& camera, uint32_t height,
                    TriangleMesh* out);

// An image of the scene, by its encoded bytes (embedded) or its file path.
struct TextureSource {
  std::string name;  // for messages
  std::vector<unsigned char> bytes;
  std::string mime_type;
  std::string path;  // used if bytes is empty
  TextureWrap wrap_s = TextureWrap::Repeat, wrap_t = TextureWrap::Repeat;
  bool nearest = false;  // the sampler's magFilter is NEAREST: the closest texel, unfiltered
};

// Everything needed to build a Scene; filled by the glTF loader or directly by tests.
struct SceneDescription {
  std::string source;  // file name or description, used in messages
  TriangleMesh world;  // world space (meshes used by one node end up here)
  std::vector<Material> materials;  // at least one if there are triangles
  std::optional<Camera> camera;     // none: the Scene frames the bounding box from +Z
  std::vector<Mesh> meshes;         // instanced meshes
  std::vector<Instance> instances;
  std::vector<PunctualLight> punctual_lights;
  // Points and lines in world space (the Scene turns them into triangles for its camera; in an
  // animated scene, poses do, into the mesh thin_mesh, an empty mesh placed at the identity).
  ThinGeometry thin;
  int thin_mesh = -1;
  // The height in pixels of the images the scene is rendered at, which sets the width of
  // points and lines (0: kDefaultThinHeight).
  uint32_t image_height = 0;
  // The materials KHR_animation_pointer animates (indices into materials): a pose of an
  // animated scene takes them from its own description, the others from its static part.
  std::vector<uint32_t> animated_materials;
  // Textures referenced by Material::*_tex.texture (indices into this list).
  std::vector<TextureSource> textures;
  SceneLimits limits;  // what Scene construction may still check (texture pixels)
  SceneStats stats;
  // The names of the glTF nodes that may emit light (a punctual light's node, a mesh's with
  // points, lines or an emissive or unlit material), by node index, those that have one: for
  // the light groups' messages (Scene::node_name). Last: read only for messages.
  std::map<uint32_t, std::string> node_names;
};

// Up to kPacketSize rays queried together; lanes with active false are skipped. Each active
// lane's result is the one the single-ray query gives for that ray. The rays are stored as
// arrays in the layout of Embree's RTCRay16, so that a query copies them whole; the fields the
// renderer does not vary are set once, here. Where Embree has native 16-wide packet kernels
// (AVX-512) a query is one rtcIntersect16 / rtcOccluded16; elsewhere it is two 8-wide queries
// on the halves (Embree would otherwise emulate 16-wide packets through its stream interface,
// which is slower).
constexpr int kPacketSize = 16;
struct RayPacket {
  alignas(64) float org_x[kPacketSize] = {};
  float org_y[kPacketSize] = {}, org_z[kPacketSize] = {}, tnear[kPacketSize] = {};
  float dir_x[kPacketSize] = {}, dir_y[kPacketSize] = {}, dir_z[kPacketSize] = {};
  float time[kPacketSize] = {}, tfar[kPacketSize] = {};
  uint32_t mask[kPacketSize] = {~0u, ~0u, ~0u, ~0u, ~0u, ~0u, ~0u, ~0u,
                                ~0u, ~0u, ~0u, ~0u, ~0u, ~0u, ~0u, ~0u};
  // id: the lane's sample index, which the stochastic transparency of BLEND surfaces hashes
  // (see ray_query).
  uint32_t id[kPacketSize] = {}, flags[kPacketSize] = {};
  bool active[kPacketSize] = {};
  // Lane i becomes active with the ray o + t d, t in (0, tmax).
  void set(int i, Vec3 o, Vec3 d, float tmax) {
    org_x[i] = o.x;
    org_y[i] = o.y;
    org_z[i] = o.z;
    dir_x[i] = d.x;
    dir_y[i] = d.y;
    dir_z[i] = d.z;
    tfar[i] = tmax;
    active[i] = true;
  }
  Vec3 origin(int i) const { return {org_x[i], org_y[i], org_z[i]}; }
  Vec3 direction(int i) const { return {dir_x[i], dir_y[i], dir_z[i]}; }
};

// Geometry slot of a hit: 0 for the world triangles, 1 + i for instance i.
constexpr uint32_t kWorldSlot = 0;

struct Hit {
  float t = 0.f;       // ray parameter (distance for unit directions)
  uint32_t prim = 0;   // triangle index within its slot's TriangleMesh
  uint32_t slot = kWorldSlot;
  float b1 = 0.f, b2 = 0.f;  // barycentrics of vertices 1 and 2
  Vec3 p;              // world position
  Vec3 ng;             // unit geometric normal (front side, see Triangle::ng)
  Vec3 ns;             // unit shading normal (interpolated, or ng without vertex normals)
  uint32_t material = 0;
  Point2 uv[2];        // interpolated TEXCOORD_0 and TEXCOORD_1 (0 where the mesh has none,
                       // or where the material reads no texture but the emissive one; other
                       // sets: Scene::texcoord)
  Vec3 dpdu;           // world-space tangent along +u of TEXCOORD_<tangent_map().texcoord> for
                       // normal mapping (0 if undefined)
  float tangent_sign = 1.f;  // handedness of (dpdu, dpdv, ng)
};

// Materials with alphaMode MASK or BLEND (glTF 2.0, 3.9.4) let rays through where their
// coverage says so: MASK where alpha = baseColorFactor.a x baseColorTexture.a x COLOR_0.a is
// below alphaCutoff, BLEND with probability 1 - alpha (stochastic transparency: an unbiased
// estimate of the "over" operator). Which BLEND surfaces a ray passes is a pure function of the
// ray's query key, its sample index (RayPacket::id) and the surface (instance and triangle):
// a surface stops the ray iff hash(query, sample, instance, triangle) < alpha, so that a
// packet lane and the same ray alone, and every traversal order, find the same surfaces.
// Queries in a render use ray_query(seed, pixel, bounce, kind); tests and the benchmark may
// use any key (0 by default).
enum class RayKind : uint32_t { Path = 0, Shadow = 1 };
uint64_t ray_query(uint64_t seed, uint64_t pixel, uint32_t bounce, RayKind kind);

class Scene;

// The deformed (skinned or morphed) meshes of one pose of an animated scene with their Embree
// BVHs, for the posing Scene constructor below: a pose given a set that already holds the same
// meshes (the same triangles, only the vertices moved) rewrites their vertices in place and
// refits the BVHs (RTC_BUILD_QUALITY_REFIT) instead of building them. A set serves one Scene
// at a time: the Scene holds it while it lives, and it may be handed to the next pose after.
class DeformedMeshes {
 public:
  DeformedMeshes();
  ~DeformedMeshes();
  DeformedMeshes(const DeformedMeshes&) = delete;
  DeformedMeshes& operator=(const DeformedMeshes&) = delete;
  // Bytes of the meshes' arrays (their BVHs are counted by the posed Scene's estimate).
  size_t memory_bytes() const;
  // What the last pose did with the meshes: how many it refit and how many it built.
  uint32_t refits() const { return refits_; }
  uint32_t builds() const { return builds_; }

 private:
  friend class Scene;
  struct Part;
  std::shared_ptr<const Scene> base_;  // the device and materials its BVHs use
  std::vector<std::unique_ptr<Part>> parts_;  // per mesh index of the base (null: not deformed)
  uint32_t refits_ = 0, builds_ = 0;
};

class Scene {
 public:
  // Builds the BVH; throws SceneError if the description has no usable triangle.
  // Warnings (e.g. missing camera) are appended to *warnings if given.
  explicit Scene(SceneDescription desc, std::vector<std::string>* warnings = nullptr,
                 BvhLayout bvh = BvhLayout::Fast);
  // The static part of an animated scene (AnimatedScene, animated_scene.h), which its poses
  // share: like the constructor above, but desc's instances must be empty (each pose places
  // the meshes itself), and it may hold no triangle at all (everything moves). Its own BVH
  // holds the world triangles only, and the poses place it as one instance.
  struct StaticPart {};
  Scene(StaticPart, SceneDescription desc, std::vector<std::string>* warnings, BvhLayout bvh);
  // A pose of an animated scene: base (a StaticPart scene) gives the static world triangles,
  // the meshes with their BVHs, built once and shared by every pose (never copied), materials
  // and textures; pose gives the camera, punctual lights and instances at this pose's time.
  // pose.meshes has one entry per base mesh: empty where the base mesh is used, else a
  // deformed mesh of this pose (in world space, placed at the identity), which goes into
  // *deformed (rewritten in place and refit if the set holds that mesh already). The scene
  // is what the first constructor builds from the same triangles up to the BVH's shape: rays
  // find the same hits (see docs/scenes.md, "Animated farm tasks").
  //
  // Motion blur: with several poses (the same scene at times evenly spaced over a shutter
  // interval, steps[0] at its opening), the scene moves during the shutter: Embree's motion
  // blur with one time step per pose (instances with a transform per step, deformed meshes
  // with vertices per step; the BVHs are built, never refit), the camera interpolated between
  // its poses, and each ray sees the scene at its RTCRay time in [0, 1] (0: steps[0], 1: the
  // last). Light sampling uses the emitters of steps[0]; a ray finds them where they are at its
  // own time.
  Scene(std::shared_ptr<const Scene> base, std::vector<SceneDescription> steps,
        std::shared_ptr<DeformedMeshes> deformed, std::vector<std::string>* warnings);
  ~Scene();
  Scene(const Scene&) = delete;
  Scene& operator=(const Scene&) = delete;

  // Closest hit along o + t d for t in (tmin, tmax); d need not be unit (t is then in units of
  // d). query and sample: the ray's transparency key (see ray_query). time: where in the
  // shutter the ray is, in [0, 1] (RayPacket::time likewise; only a scene with motion reads
  // it).
  bool intersect(Vec3 o, Vec3 d, float tmax, Hit* hit, uint64_t query = 0, uint32_t sample = 0,
                 float tmin = 0.f, float time = 0.f) const;
  // Closest hit distance only (no hit record); the benchmark's raw Embree rate uses it.
  bool intersect_t(Vec3 o, Vec3 d, float tmax, float* t) const;
  // True if anything blocks o + t d for t in (0, tmax).
  bool occluded(Vec3 o, Vec3 d, float tmax, uint64_t query = 0, uint32_t sample = 0,
                float time = 0.f) const;
  // intersect / occluded for the active lanes of a packet. found[i] is written for every lane
  // (false for inactive ones), hits[i] for the lanes found; blocked[i] is meaningful for
  // active lanes only.
  // coherent: the rays are alike (a pixel's camera rays, which leave one point in nearly one
  // direction): Embree traverses such a packet as one frustum (RTC_INTERSECT_CONTEXT_FLAG_
  // COHERENT), faster for them and far slower for scattered rays; the hits are the same. The
  // occlusion query has no coherent mode: Embree 3.13's coherent occlusion traversal never
  // returned for one of Scene/PacketQueries' scattered rays when we tried it.
  // query: the packet's transparency key (its lanes' sample indices are their ids).
  void intersect(const RayPacket& rays, Hit* hits, bool* found, bool coherent = false,
                 uint64_t query = 0) const;
  void occluded(const RayPacket& rays, bool* blocked, uint64_t query = 0) const;
  // True if some material of the scene's triangles is not opaque (MASK or BLEND): only then do
  // ray queries run the transparency test, and only on those materials' triangles, which are
  // Embree geometries of their own.
  bool has_transparency() const { return has_transparency_; }
  // How the packet queries reach Embree: 16 when one native 16-wide query serves a packet
  // (the default where Embree reports native 16-wide support), 8 for two 8-wide queries. The
  // results are the same either way; tests set both.
  int packet_query_width() const { return packet_query_width_; }
  void set_packet_query_width(int width) { packet_query_width_ = width == 16 ? 16 : 8; }

  const std::string& source() const { return desc_.source; }
  // The world triangles (meshes used by one node, in world space; a pose's are its base's).
  const TriangleMesh& world() const { return *slot_mesh_[kWorldSlot]; }
  // Material of world triangle prim.
  const Material& material(uint32_t prim) const {
    return desc_.materials[world().material[prim]];
  }
  // The material of triangle prim of slot's mesh.
  const Material& material(uint32_t slot, uint32_t prim) const;
  // The glTF node of triangle prim of slot (its index in the file's "nodes"), kNoNode where the
  // description gives none: the slot mesh's per-triangle node if it has them (the world, the
  // points and lines of a pose), else the slot's Instance's. Read for a camera ray's first hit
  // (the Instance row), not while tracing.
  uint32_t node(uint32_t slot, uint32_t prim) const {
    const TriangleMesh& mesh = *slot_mesh_[slot];
    if (!mesh.node.empty()) return mesh.node[prim];
    return slot == kWorldSlot ? kNoNode : desc_.instances[slot - 1].node;
  }
  // The world position of the point at barycentrics (b1, b2) of triangle prim of slot (a
  // Hit's slot, prim, b1, b2), where complete_hit puts a hit there: the world triangle's, or
  // the instance's mesh's placed by its transform, or the pose's deformed vertices; with
  // motion blur at shutter time `time` in [0, 1] (as a ray of that time sees it). The poses of
  // one AnimatedScene number their meshes' triangles alike, but not always their slots (a node
  // hidden by KHR_node_visibility has no instance in a pose): the Motion row maps a slot and
  // triangle to another pose's first (MotionPoses). False where the scene has no such slot or
  // triangle.
  bool surface_point(uint32_t slot, uint32_t prim, float b1, float b2, float time,
                     Vec3* p) const;
  const std::vector<Material>& materials() const { return desc_.materials; }
  const TextureSet& textures() const { return *textures_; }
  // The triangles of a geometry slot (the world, or instance slot - 1's mesh), in that slot's
  // space.
  const TriangleMesh& slot_mesh(uint32_t slot) const { return *slot_mesh_[slot]; }
  // Emitted radiance of the front face of triangle prim of slot at barycentrics (b1, b2),
  // including the emissive texture, towards a viewer at cosine cos_view with the emitter's
  // normal: under a clear coat (KHR_materials_clearcoat) emission is dimmed by 1 - c F_c, F_c
  // the coat's Fresnel at cos_view (read only for a coated material).
  Vec3 emission(uint32_t slot, uint32_t prim, float b1, float b2, float cos_view) const;
  // The same times the point's coverage (1 for opaque materials; MASK: 0 or 1 by the cutoff;
  // BLEND: alpha): what light sampling sees of an emitter, which a ray would find with
  // probability coverage (and then see its full emission).
  Vec3 covered_emission(uint32_t slot, uint32_t prim, float b1, float b2, float cos_view) const {
    if (!has_transparency_) return emission(slot, prim, b1, b2, cos_view);
    return emission(slot, prim, b1, b2, cos_view) * coverage(slot, prim, b1, b2);
  }
  // Coverage of the point, as above.
  float coverage(uint32_t slot, uint32_t prim, float b1, float b2) const;
  // Texture coordinates set (TextureRef::texcoord) interpolated at the hit ((0, 0) where the
  // mesh has none).
  Point2 texcoord(const Hit& hit, uint32_t set) const;
  // COLOR_0 interpolated at the hit into *rgb (linear); false (and *rgb untouched) where the
  // mesh has no vertex colours.
  bool vertex_color(const Hit& hit, Vec3* rgb) const;
  size_t instance_count() const { return desc_.instances.size(); }
  // Instance i (geometry slot 1 + i): its mesh slot, glTF node and transform.
  const Instance& instance(size_t i) const { return desc_.instances[i]; }
  // The mesh slot of an animated scene's points and lines (SceneDescription::thin_mesh), -1
  // for none.
  int thin_mesh() const { return desc_.thin_mesh; }
  size_t mesh_count() const { return base_ ? base_->mesh_count() : desc_.meshes.size(); }
  // Triangles in the world after instancing (world triangles + sum over instances).
  uint64_t world_triangle_count() const;
  // Bytes the scene holds: its triangle meshes and light tables, and everything Embree
  // allocated for it (BVHs, instance data). Textures are not included: their texels are read
  // at the first lookup, within a budget of their own (TextureSet::set_texel_budget). A pose
  // counts only what is its own (light tables, deformed meshes, and an estimate of its
  // top-level and deformed BVHs), not its base, which the poses share; a StaticPart scene
  // counts its Embree allocations up to the end of its construction.
  size_t memory_bytes() const;
  const SceneStats& stats() const { return desc_.stats; }
  // A pose's deformed meshes (null for other scenes).
  const DeformedMeshes* deformed_meshes() const { return deformed_.get(); }
  const Camera& camera() const { return camera_; }
  // The image height the scene's points and lines are one pixel wide at; 0 if it has none (it
  // renders the same at any height).
  uint32_t thin_height() const { return thin_height_; }
  // Motion blur (the posing constructor with several steps): whether anything moves during
  // the shutter, so that rays need a time; whether the camera does; the camera at time t in
  // [0, 1] (positions and every other parameter interpolated linearly between the steps, the
  // axes then made orthonormal again; camera() is the one at 0).
  bool has_motion() const { return motion_steps_ > 1; }
  bool camera_moves() const { return !camera_steps_.empty(); }
  Camera camera_at(float t) const;
  bool has_file_camera() const { return desc_.camera.has_value(); }
  const LightSet& lights() const { return lights_; }
  // The glTF nodes whose light can reach the image: the node of every triangle whose material
  // emits or is unlit, and of every punctual light of lights(); sorted, each once (kNoNode,
  // last, if such a triangle or light has no node). The light groups must hold each of them
  // (render/light_groups.h). Found with the lights, when the scene is built.
  const std::vector<uint32_t>& emitting_nodes() const { return emitting_nodes_; }
  // A node's "name" in the glTF file, for messages: known for the nodes that may emit light
  // (SceneDescription::node_names), "" for the others and for nodes without one.
  const std::string& node_name(uint32_t node) const;
  Vec3 bounds_min() const { return bmin_; }
  Vec3 bounds_max() const { return bmax_; }
  float diagonal() const { return length(bmax_ - bmin_); }

 private:
  SceneDescription desc_;
  Camera camera_;
  LightSet lights_;
  Vec3 bmin_, bmax_;
  std::shared_ptr<TextureSet> textures_;  // shared by a StaticPart scene with its poses
  std::shared_ptr<const Scene> base_;     // a pose's StaticPart scene, else null
  std::shared_ptr<DeformedMeshes> deformed_;  // a pose's deformed meshes, else null
  std::vector<std::pair<Vec3, Vec3>> mesh_bounds_;  // StaticPart: per mesh, its bounds
  size_t static_embree_bytes_ = 0;  // StaticPart: Embree's bytes once it was built
  size_t pose_bvh_bytes_ = 0;       // a pose: the estimate of its own BVHs
  bool static_part_ = false;
  uint32_t thin_height_ = 0;
  // The lights, the camera (framing the bounds if the description has none) and their
  // warnings: the end of every constructor.
  void finish_lights_and_camera(std::vector<std::string>* warnings);
  // material_hit_flags_ of the final materials (the base's, or a pose's with its animated
  // values).
  void find_material_hit_flags();
  void build(std::vector<std::string>* warnings, BvhLayout bvh);  // the first two constructors
  // Motion blur: the number of time steps (1: none), per instance its transform at each step
  // (empty: it does not move), per slot the deformed mesh whose vertices move (null: none), and
  // the camera at each step (empty: it does not move).
  uint32_t motion_steps_ = 1;
  std::vector<std::vector<Mat4>> instance_motion_;
  std::vector<const DeformedMeshes::Part*> slot_motion_;
  std::vector<Camera> camera_steps_;
  friend class DeformedMeshes;
  std::vector<Affine3f> instance_xf_;  // desc_.instances[k].to_world, for hits in slot k + 1
  std::vector<const TriangleMesh*> slot_mesh_;  // per slot: &desc_.world, then the meshes
  // Per slot: the number of its mesh's opaque triangles. The Scene puts them first; the others
  // are an Embree geometry of their own, whose triangle i is the mesh's triangle (this + i).
  std::vector<uint32_t> slot_first_transparent_;
  bool has_transparency_ = false;
  bool has_vertex_colors_ = false;  // some mesh has COLOR_0
  // Coverage of triangle prim of mesh at (b1, b2), and whether the ray of (query, sample) stops
  // there (the transparency test of the Embree filter functions).
  float coverage(const TriangleMesh& mesh, uint32_t prim, float b1, float b2) const;
  bool stops(const TriangleMesh& mesh, uint32_t prim, float b1, float b2, uint64_t query,
             uint32_t sample, uint32_t instance) const;
  friend struct TransparencyFilter;
  // Whether triangle prim of mesh has texture coordinates set (TextureRef::texcoord), and the
  // set interpolated at (b1, b2) ((0, 0) if not).
  static bool has_uv(const TriangleMesh& mesh, uint32_t prim, uint32_t set);
  static Point2 interpolate_uv(const TriangleMesh& mesh, uint32_t prim, float b1, float b2,
                               uint32_t set);
  // The hit record of Embree's closest hit (geometry geom, inside instance inst or none,
  // triangle prim, barycentrics (u, v), distance t).
  // One Embree packet query of width N over lanes [first, first + N) of a packet.
  template <int N, typename RayHitN>
  void intersect_lanes(const RayPacket& rays, int first, Hit* hits, bool* found,
                       bool coherent, uint64_t query) const;
  template <int N, typename RayN>
  void occluded_lanes(const RayPacket& rays, int first, bool* blocked, uint64_t query) const;
  void complete_hit(unsigned geom, unsigned inst, unsigned prim, float u, float v, float t,
                    Hit* hit, float time = 0.f) const;
  template <bool kMotion>
  void complete_hit_at(unsigned geom, unsigned inst, unsigned prim, float u, float v, float t,
                       Hit* hit, float time) const;
  struct Embree;
  std::unique_ptr<Embree> embree_;
  int packet_query_width_ = 8;
  // Per material (by index): what completing a hit on it reads, Material::reads_uv and
  // needs_tangent (kHitReadsUv, kHitNeedsTangent), found once the materials are final
  // (find_material_hit_flags) rather than from the material's texture slots at every hit.
  static constexpr uint8_t kHitReadsUv = 1, kHitNeedsTangent = 2;
  std::vector<uint8_t> material_hit_flags_;
  // emitting_nodes(); last, as it is read only when a task is checked.
  std::vector<uint32_t> emitting_nodes_;
};

// "812.5 kB", "12.3 MB" or "1.23 GB" (powers of 10), for messages about memory_bytes.
std::string format_bytes(size_t bytes);

// Benchmark hook: while a thread has a RayLog installed, every ray it traces through
// Scene::intersect/occluded (single rays and packet lanes) is appended to it, so the benchmark
// can replay the path tracer's exact rays through bare rtcIntersect1/rtcOccluded1. One
// thread-local pointer test per query when unused.
struct LoggedRay {
  Vec3 o, d;
  float tmax;
  bool shadow;
};
using RayLog = std::vector<LoggedRay>;
void set_thread_ray_log(RayLog* log);

// Loads a .gltf (embedded data: URIs or files next to it) or .glb. Throws SceneError naming
// the file and the offending node/mesh/accessor/field. Warnings go to *warnings.
// Scenes over options.limits are refused before their geometry is allocated.
SceneDescription load_gltf(const std::string& path, std::vector<std::string>* warnings,
                           const LoadOptions& options = {});
// Same, from the text of a .gltf; external URIs are resolved against base_dir.
SceneDescription load_gltf_from_string(const std::string& json, const std::string& base_dir,
                                       const std::string& name,
                                       std::vector<std::string>* warnings,
                                       const LoadOptions& options = {});
// A glTF file parsed once (tinygltf's model, its compressed geometry decoded), from which
// describe_gltf builds scene descriptions, one per LoadOptions: the farm worker parses an
// animated job's scene once and poses it at each frame's time. load_gltf(path, w, o) is
// describe_gltf(*parse_gltf(path, w, o), w, o); parse_gltf uses o's allow_external_files,
// limits and display_name, describe_gltf the rest.
struct GltfDocument;
std::shared_ptr<const GltfDocument> parse_gltf(const std::string& path,
                                               std::vector<std::string>* warnings,
                                               const LoadOptions& options = {});
SceneDescription describe_gltf(const GltfDocument& document, std::vector<std::string>* warnings,
                               const LoadOptions& options = {});
// The "name" of each of the document's animations, by index ("" where it has none).
std::vector<std::string> gltf_animation_names(const GltfDocument& document);
// KHR_materials_variants: the names of the document's variants, in index order.
std::vector<std::string> gltf_variant_names(const GltfDocument& document);
// Bytes the document holds (its buffers and encoded images), for cache budgets.
size_t gltf_document_bytes(const GltfDocument& document);
// load_gltf + Scene construction (with options.bvh).
std::unique_ptr<Scene> load_scene(const std::string& path, std::vector<std::string>* warnings,
                                  const LoadOptions& options);
std::unique_ptr<Scene> load_scene(const std::string& path, std::vector<std::string>* warnings,
                                  BvhLayout bvh = BvhLayout::Fast);

}  // namespace rf
