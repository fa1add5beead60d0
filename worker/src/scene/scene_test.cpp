#include "scene/scene.h"

#include <gtest/gtest.h>

#include <cstring>
#include <fstream>
#include <random>
#include <utility>

#include "bench/bench.h"
#include "render/integrators.h"
#include "testing/test_scenes.h"

namespace rf {
namespace {

uint32_t bits_of(float f) {
  uint32_t b;
  std::memcpy(&b, &f, sizeof b);
  return b;
}

bool any_contains(const std::vector<std::string>& lines, const std::string& needle) {
  for (const auto& l : lines)
    if (l.find(needle) != std::string::npos) return true;
  return false;
}

TEST(GltfLoader, SmallSceneHierarchyMaterialsAndCamera) {
  std::vector<std::string> warnings;
  SceneDescription desc = load_gltf_from_string(testing::small_gltf_json(), ".", "small.gltf",
                                                &warnings);
  EXPECT_TRUE(any_contains(warnings, "EXT_made_up")) << "unsupported extension used";
  EXPECT_FALSE(any_contains(warnings, "primitives[1]")) << "LINES are rendered";
  ASSERT_EQ(desc.world.size(), 4u);
  // The floor's LINES primitive (its four corners, no indices): two segments, unlit (no
  // NORMAL), which the Scene makes two ribbons of two triangles.
  ASSERT_EQ(desc.thin.elements.size(), 2u);
  EXPECT_TRUE(desc.materials[desc.thin.elements[0].material].unlit);
  ASSERT_TRUE(desc.camera.has_value());
  Scene scene(std::move(desc), &warnings);
  EXPECT_EQ(scene.world().size(), 8u);
  // Its lines are sized for an image height: the default one here, the load's otherwise; a
  // scene without points and lines is the same at any height (the farm worker shares it).
  EXPECT_EQ(scene.thin_height(), kDefaultThinHeight);
  LoadOptions at_48;
  at_48.image_height = 48;
  EXPECT_EQ(Scene(load_gltf_from_string(testing::small_gltf_json(), ".", "small.gltf", nullptr,
                                        at_48))
                .thin_height(),
            48u);
  EXPECT_EQ(Scene(testing::plane_under_emitter(0.5f, 1.f, 1.f, 1.f, 1.f, Vec3(0.f, 0.f, 3.f), 0.8f))
                .thin_height(),
            0u);
  ASSERT_EQ(scene.lights().size(), 2u);
  // Lamp: local unit square in y = 0 facing -y, under translation (0,2,0) and scale (2,1,2).
  float lamp_area = 0.f;
  for (uint32_t i = 0; i < scene.world().size(); ++i) {
    const Triangle t = scene.world().triangle(i);
    const Material& m = scene.material(i);
    if (m.unlit) continue;  // the lines' ribbons
    if (!m.is_emissive()) {
      EXPECT_NEAR(t.ng.y, 1.f, 1e-6f);
      EXPECT_NEAR(m.albedo.y, 0.6f, 1e-6f);
      continue;
    }
    lamp_area += t.area;
    EXPECT_NEAR(t.ng.y, -1.f, 1e-6f);
    for (const Vec3& p : t.p) EXPECT_NEAR(p.y, 2.f, 1e-6f);
    EXPECT_NEAR(m.emission.x, 4.f, 1e-6f);  // emissiveFactor x emissiveStrength
    EXPECT_NEAR(m.emission.y, 2.f, 1e-6f);
    EXPECT_NEAR(m.emission.z, 1.f, 1e-6f);
  }
  EXPECT_NEAR(lamp_area, 4.f, 1e-5f);
  // Camera at (0,1,5) rotated by -0.2 rad about X: looks down -Z and slightly down.
  const Camera& cam = scene.camera();
  EXPECT_NEAR(cam.position.z, 5.f, 1e-5f);
  EXPECT_NEAR(cam.forward.y, -std::sin(0.2f), 1e-4f);
  EXPECT_NEAR(cam.forward.z, -std::cos(0.2f), 1e-4f);
  EXPECT_NEAR(cam.yfov, 0.7f, 1e-6f);
  // A ray straight down from above hits the lamp (its back face) first, at y = 2.
  Hit hit;
  ASSERT_TRUE(scene.intersect({0.1f, 5.f, 0.2f}, {0.f, -1.f, 0.f}, 1e30f, &hit));
  EXPECT_NEAR(hit.t, 3.f, 1e-5f);
  EXPECT_TRUE(scene.material(hit.prim).is_emissive());
  EXPECT_TRUE(scene.occluded({0.1f, 5.f, 0.2f}, {0.f, -1.f, 0.f}, 10.f));
  EXPECT_FALSE(scene.occluded({0.1f, 5.f, 0.2f}, {0.f, -1.f, 0.f}, 2.9f));
  // Below the lamp, the floor.
  ASSERT_TRUE(scene.intersect({0.f, 1.f, 3.f}, {0.f, -1.f, -2.5f}, 1e30f, &hit));
  EXPECT_NEAR(hit.p.z, 0.5f, 1e-5f);
  EXPECT_FALSE(scene.material(hit.prim).is_emissive());
}

TEST(GltfLoader, ErrorsNameTheProblem) {
  std::vector<std::string> warnings;
  try {
    load_gltf("/nonexistent/scene.gltf", &warnings);
    FAIL() << "expected SceneError";
  } catch (const SceneError& e) {
    EXPECT_NE(std::string(e.what()).find("/nonexistent/scene.gltf"), std::string::npos);
  }
  EXPECT_THROW(load_gltf_from_string("{ not json", ".", "broken.gltf", &warnings), SceneError);
  std::string json = testing::small_gltf_json();
  const std::string good = "\"indices\": 1";
  json.replace(json.find(good), good.size(), "\"indices\": 7");
  try {
    load_gltf_from_string(json, ".", "bad-index.gltf", &warnings);
    FAIL() << "expected SceneError";
  } catch (const SceneError& e) {
    const std::string what = e.what();
    EXPECT_NE(what.find("bad-index.gltf"), std::string::npos) << what;
    EXPECT_NE(what.find("indices"), std::string::npos) << what;
  }
}

// The small scene with `from` replaced by `to` once, loaded as an upload: the SceneError's
// path (the field the server reports), or "" if it loads.
std::string refusal_path(const std::string& from, const std::string& to,
                         const SceneLimits& limits = {}, std::string* message = nullptr) {
  std::string json = testing::small_gltf_json();
  const size_t at = json.find(from);
  EXPECT_NE(at, std::string::npos) << from;
  json.replace(at, from.size(), to);
  LoadOptions options;
  options.allow_external_files = false;
  options.limits = limits;
  try {
    load_gltf_from_string(json, ".", "upload.gltf", nullptr, options);
  } catch (const SceneError& e) {
    if (message) *message = e.what();
    return e.path();
  }
  return "";
}

// glTF 2.0, 3.5.3: the node hierarchy is a set of disjoint strict trees.
TEST(GltfLoader, NodeGraphsThatAreNotTreesAreRefusedNamingTheNode) {
  const std::string nodes = R"("children": [2]},)";
  std::string message;
  // Node 1 lists node 2 twice: two parents' worth of references to one child.
  EXPECT_EQ(refusal_path(nodes, R"("children": [2, 2]},)", {}, &message),
            "nodes[1].children[1]");
  EXPECT_NE(message.find("already a child of node 1"), std::string::npos) << message;
  EXPECT_EQ(message.find("upload.gltf: nodes[1]"), 0u) << message;
  // Node 2 (the light) made its own parent's parent: a cycle 1 -> 2 -> 1, and node 1 is still
  // a root, so it is a child and a root at once.
  EXPECT_EQ(refusal_path(R"({"name": "light", "mesh": 1})",
                         R"({"name": "light", "mesh": 1, "children": [1]})"),
            "nodes[2].children");
  // The floor listed as a child of the camera while also a root.
  EXPECT_EQ(refusal_path(R"("camera": 0, "translation")",
                         R"("camera": 0, "children": [0], "translation")"),
            "scenes[0].nodes[0]");
  EXPECT_EQ(refusal_path(nodes, R"("children": [9]},)"), "nodes[1].children[0]");
  EXPECT_EQ(refusal_path(nodes, R"("children": [1]},)"), "nodes[1].children[0]");
  EXPECT_EQ(refusal_path(R"("nodes": [0, 1, 3])", R"("nodes": [0, 1, 3, 3])"),
            "scenes[0].nodes[3]");
}

TEST(GltfLoader, RequiredExtensionsTheRendererLacksAreRefused) {
  std::string message;
  EXPECT_EQ(refusal_path(R"("scene": 0,)",
                         R"("extensionsRequired": ["KHR_materials_ior", "EXT_made_up"], "scene": 0,)",
                         {}, &message),
            "extensionsRequired[1]");
  EXPECT_NE(message.find("EXT_made_up"), std::string::npos) << message;
  // Used but not required: a warning, and the scene loads.
  EXPECT_EQ(refusal_path(R"("scene": 0,)",
                         R"("extensionsRequired": ["KHR_materials_ior"], "scene": 0,)"),
            "");
}

TEST(GltfLoader, LimitsAreCheckedBeforeTheGeometryIsAllocated) {
  // The small scene: 4 nodes, depth 2 (light-parent -> light), 4 triangles over its meshes.
  SceneLimits limits;
  EXPECT_EQ(refusal_path("\"scene\": 0,", "\"scene\": 0,", limits), "");
  limits.max_nodes = 3;
  EXPECT_EQ(refusal_path("\"scene\": 0,", "\"scene\": 0,", limits), "nodes");
  limits = {};
  limits.max_depth = 1;
  EXPECT_EQ(refusal_path("\"scene\": 0,", "\"scene\": 0,", limits), "nodes[2]");
  limits = {};
  limits.max_instanced_triangles = 3;
  EXPECT_EQ(refusal_path("\"scene\": 0,", "\"scene\": 0,", limits).rfind("nodes[", 0), 0u);
  limits = {};
  limits.max_memory_bytes = 100;  // the data URI's buffer alone is 132 bytes
  std::string message;
  EXPECT_EQ(refusal_path("\"scene\": 0,", "\"scene\": 0,", limits, &message), "meshes");
  EXPECT_NE(message.find("over the limit"), std::string::npos) << message;
}

TEST(GltfLoader, DeclaredCountsWithoutDataSizeNothing) {
  // Accessor 0 (the floor's positions) claims 4e9 vertices: refused as data beyond its view,
  // never reserved (which would be 48 GB).
  EXPECT_EQ(refusal_path(R"("count": 4, "type": "VEC3")",
                         R"("count": 4000000000, "type": "VEC3")"),
            "accessors[0]");
}

TEST(GltfLoader, UploadsReadNoFileButTheirOwn) {
  // A buffer URI naming a file: refused for an upload, whatever the file.
  std::string message;
  const std::string path =
      refusal_path("data:application/octet-stream;base64,", "/etc/hostname?", {}, &message);
  EXPECT_NE(message.find("self-contained"), std::string::npos) << "[" << message << "]";
  EXPECT_EQ(path, "");
}

TEST(GltfLoader, MissingMaterialIsNamed) {
  std::string json = testing::small_gltf_json();
  const std::string good = "\"material\": 1}";
  json.replace(json.find(good), good.size(), "\"material\": 5}");
  try {
    load_gltf_from_string(json, ".", "bad-material.gltf", nullptr);
    FAIL() << "expected SceneError";
  } catch (const SceneError& e) {
    const std::string what = e.what();
    EXPECT_NE(what.find("bad-material.gltf"), std::string::npos) << what;
    EXPECT_NE(what.find("material"), std::string::npos) << what;
  }
}

// The pinhole model stated independently: the image centre looks along forward, the image
// corners lie on the frustum of yfov and aspect = width / height, and the angle between the
// top and bottom edge centres is yfov.
TEST(Camera, RasterDirectionsFollowThePinholeModel) {
  Camera cam;
  cam.position = Vec3(1.f, 2.f, 3.f);
  cam.forward = normalize(Vec3(0.3f, -0.2f, -1.f));
  cam.right = normalize(cross(cam.forward, Vec3(0.f, 1.f, 0.f)));
  cam.up = cross(cam.right, cam.forward);
  cam.yfov = 0.9f;
  const float t = std::tan(0.45f);
  auto near = [](Vec3 a, Vec3 b) {
    EXPECT_NEAR(a.x, b.x, 2e-6f);
    EXPECT_NEAR(a.y, b.y, 2e-6f);
    EXPECT_NEAR(a.z, b.z, 2e-6f);
  };
  for (auto [w, h] : {std::pair<uint32_t, uint32_t>{640, 480}, {17, 301}, {1, 1}}) {
    const Camera::Raster r = cam.raster(w, h);
    const float fw = float(w), fh = float(h), aspect = fw / fh;
    near(r.direction(0.5f * fw, 0.5f * fh), cam.forward);
    near(r.direction(0.f, 0.f), normalize(cam.forward - cam.right * (aspect * t) + cam.up * t));
    near(r.direction(fw, fh), normalize(cam.forward + cam.right * (aspect * t) - cam.up * t));
    const Vec3 top = r.direction(0.5f * fw, 0.f), bottom = r.direction(0.5f * fw, fh);
    EXPECT_NEAR(std::acos(dot(top, bottom)), cam.yfov, 1e-5f);
    near(cam.ray_direction(0.25f * fw, 0.75f * fh, w, h), r.direction(0.25f * fw, 0.75f * fh));
  }
}

// TriangleMesh::add keeps every attribute array as long as positions once any triangle has
// that attribute (zeros for the vertices before), whichever triangle comes first, and
// triangle() gathers back what was added, with the analytic normal and area.
TEST(TriangleMesh, AddKeepsAttributeArraysAlignedAndGathersBack) {
  Triangle plain, with_normals, with_uv1;
  plain.p[0] = {0, 0, 0}, plain.p[1] = {2, 0, 0}, plain.p[2] = {0, 3, 0};
  with_normals = plain;
  with_normals.has_normals = true;
  with_normals.n[0] = {0, 0, 1}, with_normals.n[1] = {0, 0.6f, 0.8f};
  with_normals.n[2] = {1, 0, 0};
  with_normals.material = 1;
  with_uv1 = plain;
  with_uv1.has_uv[1] = true;
  with_uv1.uv[1][0] = {0.1f, 0.2f}, with_uv1.uv[1][1] = {0.3f, 0.4f};
  with_uv1.uv[1][2] = {0.5f, 0.6f};
  with_uv1.material = 2;

  TriangleMesh mesh;
  for (const Triangle& t : {plain, with_normals, with_uv1}) mesh.add(t);
  ASSERT_EQ(mesh.size(), 3u);
  EXPECT_EQ(mesh.positions.size(), 9u);
  EXPECT_EQ(mesh.normals.size(), 9u);
  EXPECT_TRUE(mesh.uv[0].empty());
  EXPECT_EQ(mesh.uv[1].size(), 9u);
  const Triangle a = mesh.triangle(0), b = mesh.triangle(1), c = mesh.triangle(2);
  EXPECT_FALSE(a.has_normals || a.has_uv[0] || a.has_uv[1]);
  EXPECT_TRUE(b.has_normals && !b.has_uv[1]);
  EXPECT_TRUE(c.has_uv[1] && !c.has_normals);
  EXPECT_EQ(b.material, 1u);
  EXPECT_EQ(c.material, 2u);
  for (int k = 0; k < 3; ++k) {
    EXPECT_EQ(b.n[k].y, with_normals.n[k].y);
    EXPECT_EQ(b.n[k].z, with_normals.n[k].z);
    EXPECT_EQ(c.uv[1][k].x, with_uv1.uv[1][k].x);
    EXPECT_EQ(c.uv[1][k].y, with_uv1.uv[1][k].y);
  }
  // Legs 2 and 3 in the z = 0 plane, counter-clockwise seen from +z.
  EXPECT_FLOAT_EQ(b.area, 3.f);
  EXPECT_FLOAT_EQ(b.ng.z, 1.f);

  // The first triangle has normals: the array starts with it.
  TriangleMesh first;
  first.add(with_normals);
  first.add(plain);
  EXPECT_EQ(first.normals.size(), 6u);
  EXPECT_EQ(first.triangle(0).n[1].y, 0.6f);
  EXPECT_FALSE(first.triangle(1).has_normals);
}

// Scene drops a degenerate triangle from the middle of a mesh and the triangles after it keep
// their own material, normals and face normal; an inconsistent mesh is refused.
TEST(Scene, DropsDegenerateTrianglesAndRefusesInconsistentMeshes) {
  SceneDescription desc;
  desc.source = "compaction";
  desc.materials = {Material{}, Material{}};
  Triangle good, degenerate, second;
  good.p[0] = {-1, -1, 0}, good.p[1] = {1, -1, 0}, good.p[2] = {1, 1, 0};
  degenerate.p[0] = degenerate.p[1] = degenerate.p[2] = Vec3(0, 0, 5);
  second.p[0] = {-1, -1, 0}, second.p[1] = {-1, 1, 0}, second.p[2] = {1, 1, 0};  // faces -z
  second.material = 1;
  second.has_normals = true;
  for (int k = 0; k < 3; ++k) second.n[k] = Vec3(0, 0, -1);
  desc.world.add(good);
  desc.world.add(degenerate);
  desc.world.add(second);
  const SceneDescription copy = desc;
  std::vector<std::string> warnings;
  {
    Scene scene(std::move(desc), &warnings);
    ASSERT_EQ(scene.world().size(), 2u);
    EXPECT_TRUE(any_contains(warnings, "skipped 1 degenerate"));
    EXPECT_EQ(scene.world().material[1], 1u);
    EXPECT_TRUE(scene.world().flags[1] & TriangleMesh::kHasNormals);
    EXPECT_FLOAT_EQ(scene.world().face_normals[0].z, 1.f);
    EXPECT_FLOAT_EQ(scene.world().face_normals[1].z, -1.f);
    // A ray from below meets the second triangle's front face; the hit carries its data.
    Hit hit;
    ASSERT_TRUE(scene.intersect({-0.5f, 0.5f, -2.f}, {0.f, 0.f, 1.f}, 10.f, &hit));
    EXPECT_EQ(hit.prim, 1u);
    EXPECT_EQ(hit.material, 1u);
    EXPECT_FLOAT_EQ(hit.ng.z, -1.f);
    EXPECT_FLOAT_EQ(hit.ns.z, -1.f);
    EXPECT_NEAR(hit.t, 2.f, 1e-5f);
  }
  SceneDescription bad_index = copy;
  bad_index.world.indices[4] = 99;
  EXPECT_THROW(Scene scene(std::move(bad_index)), SceneError);
  SceneDescription short_normals = copy;
  short_normals.world.normals.pop_back();
  EXPECT_THROW(Scene scene(std::move(short_normals)), SceneError);
  SceneDescription missing_flags = copy;
  missing_flags.world.flags.pop_back();
  EXPECT_THROW(Scene scene(std::move(missing_flags)), SceneError);
}

// memory_bytes counts the geometry arrays and what Embree allocated (the BVH, which the
// device's memory monitor reports). For an indexed mesh of 200K triangles that is, per
// triangle, about 45 bytes of geometry (12 of indices, 4 material, 1 flags, 12 face normal,
// about half a vertex of 12) and about 65 of BVH; 144 bytes per triangle would mean the
// geometry is stored per triangle again.
TEST(Scene, MemoryBytesCountsGeometryAndBvh) {
  const Scene scene(generate_bench_scene(200000));
  const double n = double(scene.world_triangle_count());
  const double geometry = double(scene.world().memory_bytes());
  const double total = double(scene.memory_bytes());
  EXPECT_GT(geometry / n, 29.0);  // indices, material, flags, face normal at least
  EXPECT_LT(geometry / n, 50.0);
  EXPECT_GT(total - geometry, 20.0 * n) << "Embree's BVH is not counted";
  EXPECT_LT(total / n, 144.0);
}

// --bvh compact builds Embree's compact layout: the same closest hits (a ray through an edge
// may name either triangle that shares it) in less memory.
TEST(Scene, CompactBvhGivesTheSameHitsInLessMemory) {
  const Scene fast(generate_bench_scene(50000), nullptr, BvhLayout::Fast);
  const Scene compact(generate_bench_scene(50000), nullptr, BvhLayout::Compact);
  EXPECT_LT(double(compact.memory_bytes()), 0.85 * double(fast.memory_bytes()));
  std::mt19937 rng(7);
  std::uniform_real_distribution<float> uni(-1.f, 1.f);
  int hits = 0, same_prim = 0;
  const int n = 20000;
  for (int i = 0; i < n; ++i) {
    // From around the sphere towards its centre region, so that most rays hit it.
    const Vec3 o(3.f * uni(rng), 1.05f + 3.f * uni(rng), 3.f * uni(rng));
    const Vec3 d = normalize(Vec3(0.5f * uni(rng), 1.05f + 0.5f * uni(rng), 0.5f * uni(rng)) - o);
    Hit a, b;
    const bool ha = fast.intersect(o, d, 1e30f, &a), hb = compact.intersect(o, d, 1e30f, &b);
    ASSERT_EQ(ha, hb) << i;
    if (!ha) continue;
    ++hits;
    EXPECT_NEAR(a.t, b.t, 1e-5f * a.t) << i;
    same_prim += a.prim == b.prim && a.slot == b.slot;
  }
  EXPECT_GT(hits, n / 2);
  EXPECT_GE(same_prim, hits - hits / 1000);
  BvhLayout parsed = BvhLayout::Fast;
  EXPECT_TRUE(parse_bvh_layout("compact", &parsed));
  EXPECT_EQ(parsed, BvhLayout::Compact);
  EXPECT_FALSE(parse_bvh_layout("small", &parsed));
}

// The loader keeps glTF's indexing (a quad's 4 vertices are stored once, not per triangle),
// writes each attribute for every vertex of a mesh once any primitive has it, with per-
// triangle flags for the primitives that do, and flips the winding under a mirroring node so
// that the front face stays the one the normals point to.
TEST(GltfLoader, IndexedPrimitivesShareVerticesUnderAMirror) {
  const std::string json = R"({"asset": {"version": "2.0"},
  "scene": 0, "scenes": [{"nodes": [0]}],
  "nodes": [{"mesh": 0, "scale": [-1, 1, 1], "translation": [0, 0, 2]}],
  "meshes": [{"primitives": [
    {"attributes": {"POSITION": 0, "NORMAL": 1}, "indices": 3},
    {"attributes": {"POSITION": 0, "TEXCOORD_0": 2}, "indices": 3}
  ]}],
  )" + testing::quad_gltf_buffers_json() + "}";
  std::vector<std::string> warnings;
  const SceneDescription desc = load_gltf_from_string(json, "", "mirror.gltf", &warnings);
  const TriangleMesh& w = desc.world;
  ASSERT_EQ(w.size(), 4u);
  EXPECT_EQ(w.positions.size(), 8u);  // 4 + 4, not 3 per triangle
  EXPECT_EQ(w.normals.size(), 8u);
  EXPECT_EQ(w.uv[0].size(), 8u);
  EXPECT_TRUE(w.uv[1].empty());
  for (size_t i = 0; i < 4; ++i) {
    const Triangle t = w.triangle(i);
    EXPECT_EQ(t.has_normals, i < 2) << i;
    EXPECT_EQ(t.has_uv[0], i >= 2) << i;
    // The quad faces +z and the mirror is in x: the front face still faces +z.
    EXPECT_FLOAT_EQ(t.ng.z, 1.f) << i;
    for (int k = 0; k < 3; ++k) {
      EXPECT_FLOAT_EQ(t.p[k].z, 2.f);
      if (t.has_normals) {
        EXPECT_FLOAT_EQ(t.n[k].z, 1.f);
      }
    }
  }
  // Vertex 1 of the quad, (1, -1, 0), lands at (-1, -1, 2); its uv is (1, 1).
  EXPECT_FLOAT_EQ(w.positions[1].x, -1.f);
  EXPECT_FLOAT_EQ(w.uv[0][5].x, 1.f);
  EXPECT_FLOAT_EQ(w.uv[0][5].y, 1.f);
}

// Primitives of one mesh that use the same attribute accessors (one per material, as
// exporters often write them) share their vertices: stored once, not once per primitive.
TEST(GltfLoader, PrimitivesWithTheSameAccessorsShareTheirVertices) {
  const std::string json = R"({"asset": {"version": "2.0"},
  "scene": 0, "scenes": [{"nodes": [0]}],
  "nodes": [{"mesh": 0}],
  "materials": [{}, {"emissiveFactor": [1, 1, 1]}],
  "meshes": [{"primitives": [
    {"attributes": {"POSITION": 0, "NORMAL": 1}, "indices": 3, "material": 0},
    {"attributes": {"POSITION": 0, "NORMAL": 1}, "indices": 3, "material": 1},
    {"attributes": {"POSITION": 0}, "indices": 3, "material": 1}
  ]}],
  )" + testing::quad_gltf_buffers_json() + "}";
  std::vector<std::string> warnings;
  const SceneDescription desc = load_gltf_from_string(json, "", "shared.gltf", &warnings);
  const TriangleMesh& w = desc.world;
  ASSERT_EQ(w.size(), 6u);
  EXPECT_EQ(w.positions.size(), 8u);  // 4 shared by the first two primitives, 4 for the third
  for (size_t k = 0; k < 6; ++k) EXPECT_EQ(w.indices[6 + k], w.indices[k]);
  EXPECT_GE(w.indices[12], 4u);
  EXPECT_EQ(w.material[0], 0u);
  EXPECT_EQ(w.material[2], 1u);
  EXPECT_TRUE(w.flags[2] & TriangleMesh::kHasNormals);
  EXPECT_FALSE(w.flags[4] & TriangleMesh::kHasNormals);
}

TEST(Scene, NoCameraFramesBoundsFromPlusZ) {
  SceneDescription desc;
  desc.source = "no-camera";
  desc.materials.push_back(Material{});
  testing::add_quad(&desc, {-1, -1, 0}, {1, -1, 0}, {1, 1, 0}, {-1, 1, 0}, 0);
  Triangle degenerate;
  degenerate.p[0] = degenerate.p[1] = degenerate.p[2] = Vec3(1, 2, 3);
  desc.world.add(degenerate);
  std::vector<std::string> warnings;
  Scene scene(std::move(desc), &warnings);
  EXPECT_EQ(scene.world().size(), 2u);
  EXPECT_TRUE(any_contains(warnings, "no camera"));
  EXPECT_TRUE(any_contains(warnings, "degenerate"));
  EXPECT_GT(scene.camera().position.z, 1.f);
  EXPECT_NEAR(scene.camera().forward.z, -1.f, 1e-6f);
  // The image center sees the quad.
  Hit hit;
  EXPECT_TRUE(scene.intersect(scene.camera().position,
                              scene.camera().ray_direction(32.f, 32.f, 64, 64), 1e30f, &hit));
}

TEST(Scene, EmptySceneIsAnError) {
  SceneDescription desc;
  desc.source = "empty";
  EXPECT_THROW(Scene scene(std::move(desc)), SceneError);
}

TEST(Scene, CornellBoxExample) {
  const std::string path = std::string(RENDERFARM_EXAMPLES_DIR) + "/cornell-box.gltf";
  std::vector<std::string> warnings;
  auto scene = load_scene(path, &warnings);
  EXPECT_GT(scene->world().size(), 30u);
  EXPECT_FALSE(scene->lights().empty());
  EXPECT_TRUE(scene->has_file_camera());
  bool red = false, green = false;
  for (uint32_t i = 0; i < scene->world().size(); ++i) {
    const Vec3 a = scene->material(i).albedo;
    red = red || (a.x > 0.5f && a.y < 0.2f);
    green = green || (a.y > 0.3f && a.x < 0.2f);
  }
  EXPECT_TRUE(red);
  EXPECT_TRUE(green);
}

}  // namespace
}  // namespace rf

namespace rf {
namespace {

// A mesh used by two nodes is built once (one Embree scene, two instances), its emissive
// triangles become lights with the instance transforms, and the floor between two instanced
// emitters receives the closed-form irradiance of both (form factors by the corner formula).
TEST(Instancing, SharedMeshIsBuiltOnceAndLightsTheFloorCorrectly) {
  const std::string json = R"({"asset": {"version": "2.0"},
  "extensionsUsed": ["KHR_materials_specular"],
  "scene": 0, "scenes": [{"nodes": [0, 1, 2]}],
  "nodes": [
    {"mesh": 0, "scale": [10, 10, 1]},
    {"mesh": 1, "translation": [0.6, 0, 1], "rotation": [1, 0, 0, 0], "scale": [0.25, 0.25, 1]},
    {"mesh": 1, "translation": [-0.6, 0, 1], "rotation": [1, 0, 0, 0], "scale": [0.25, 0.25, 1]}
  ],
  "meshes": [
    {"name": "floor", "primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1},
                                       "indices": 3, "material": 0}]},
    {"name": "lamp", "primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1},
                                      "indices": 3, "material": 1}]}
  ],
  "materials": [
    {"pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.5, 0.5, 1], "metallicFactor": 0},
     "extensions": {"KHR_materials_specular": {"specularFactor": 0}}},
    {"pbrMetallicRoughness": {"baseColorFactor": [0, 0, 0, 1], "metallicFactor": 0},
     "emissiveFactor": [1, 1, 1]}
  ],
  )" + testing::quad_gltf_buffers_json() + "}";
  std::vector<std::string> warnings;
  SceneDescription desc = load_gltf_from_string(json, "", "instances.gltf", &warnings);
  EXPECT_EQ(desc.meshes.size(), 1u);
  EXPECT_EQ(desc.instances.size(), 2u);
  EXPECT_EQ(desc.world.size(), 2u);  // the floor, used once, is flattened
  desc.camera = testing::look_at({0.f, 0.f, 3.f}, {0.f, 0.f, 0.f}, 1e-4f);
  Scene scene(std::move(desc), &warnings);
  EXPECT_EQ(scene.mesh_count(), 1u);
  EXPECT_EQ(scene.instance_count(), 2u);
  EXPECT_EQ(scene.world_triangle_count(), 6u);
  EXPECT_EQ(scene.lights().emitter_count(), 4u);
  // The instanced emitters face down (rotated 180 degrees about X).
  Hit hit;
  ASSERT_TRUE(scene.intersect({0.6f, 0.f, 0.5f}, {0.f, 0.f, 1.f}, 10.f, &hit));
  EXPECT_NE(hit.slot, kWorldSlot);
  EXPECT_NEAR(hit.t, 0.5f, 1e-5f);
  EXPECT_NEAR(hit.ng.z, -1.f, 1e-5f);
  EXPECT_NEAR(hit.p.x, 0.6f, 1e-5f);
  auto corner = [](double a, double b, double c) {
    const double X = a / c, Y = b / c;
    const double sx = std::sqrt(1 + X * X), sy = std::sqrt(1 + Y * Y);
    return (X / sx * std::atan(Y / sx) + Y / sy * std::atan(X / sy)) / (2 * M_PI);
  };
  // Each emitter spans x in [0.35, 0.85] (mirrored for the other), y in [-0.25, 0.25]: two
  // corner rectangles of the [0, 0.85] strip minus those of [0, 0.35].
  const double F_one = 2 * (corner(0.85, 0.25, 1) - corner(0.35, 0.25, 1));
  const double expected = 0.5 * 1.0 * 2 * F_one;
  RenderSettings settings;
  settings.width = settings.height = 1;
  settings.seed = 4;
  settings.sampler = SamplerType::Independent;
  TileBuffer tile;
  ASSERT_TRUE(render_rect(scene, settings, {0, 0, 1, 1}, 0, 4096, &tile));
  const double mean = tile.rgb_sum[0] / 4096;
  const double se = std::sqrt(tile.luminance_m2[0] / 4095 / 4096);
  EXPECT_LT(se, 0.02 * expected);
  EXPECT_NEAR(mean, expected, 4 * se);
}

// The float transform a hit in an instance uses equals the double Mat4 arithmetic it
// replaces: points, vectors, normals (after normalizing: the normal matrix is only defined up
// to a positive factor) and handedness, for rotations, non-uniform and mirroring scales and
// translations.
TEST(Instancing, FloatTransformEqualsDoubleMatrix) {
  std::mt19937 rng(11);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  int mirrored = 0;
  for (int trial = 0; trial < 200; ++trial) {
    // M = R S with R a random rotation (normalized quaternion) and S a random diagonal.
    double q[4];
    double qn = 0.0;
    for (double& c : q) {
      c = u(rng);
      qn += c * c;
    }
    for (double& c : q) c /= std::sqrt(qn);
    const double w = q[0], x = q[1], y = q[2], z = q[3];
    const double R[3][3] = {{1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)},
                            {2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)},
                            {2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)}};
    double S[3];
    for (double& s : S) s = (0.2 + 2.0 * std::fabs(u(rng))) * (u(rng) < -0.6 ? -1.0 : 1.0);
    Mat4 m = Mat4::identity();
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) m.m[size_t(c)][size_t(r)] = R[r][c] * S[c];
      m.m[3][size_t(r)] = 20.0 * u(rng);
    }
    const Affine3f a = Affine3f::from(m);
    const bool flips = S[0] * S[1] * S[2] < 0.0;
    EXPECT_EQ(a.mirror, flips);
    mirrored += flips;
    for (int k = 0; k < 5; ++k) {
      const Vec3 v(float(u(rng)), float(u(rng)), float(u(rng)));
      const Vec3 p = v * 5.f;
      const Vec3 want_p = m.transform_point(p), got_p = a.point(p);
      const Vec3 want_v = m.transform_vector(v), got_v = a.vector(v);
      const Vec3 want_n = normalize(m.transform_normal(v)), got_n = normalize(a.normal(v));
      for (int c = 0; c < 3; ++c) {
        EXPECT_NEAR(got_p[c], want_p[c], 1e-5f * (1.f + std::fabs(want_p[c])));
        EXPECT_NEAR(got_v[c], want_v[c], 1e-5f * (1.f + std::fabs(want_v[c])));
        EXPECT_NEAR(got_n[c], want_n[c], 1e-5f);
      }
    }
  }
  EXPECT_GT(mirrored, 20);
  EXPECT_LT(mirrored, 180);
  // Scales whose cofactors (scale^2) leave float's range still give unit normals.
  for (double s : {1e-25, 1e25}) {
    Mat4 m = Mat4::identity();
    m.m[0][0] = s;
    m.m[1][1] = 2.0 * s;
    m.m[2][2] = -s;
    const Affine3f a = Affine3f::from(m);
    EXPECT_TRUE(a.mirror);
    const Vec3 n = a.normal({0.f, 0.f, 1.f});
    ASSERT_GT(length(n), 0.f) << "scale " << s;
    EXPECT_NEAR(normalize(n).z, -1.f, 1e-6f) << "scale " << s;
  }
}

}  // namespace
}  // namespace rf

namespace rf {
namespace {

// The packet queries (one 16-wide Embree query, or two 8-wide ones) return, lane by lane, what
// the single-ray queries return: on world triangles and on instances (one mirrored), for rays
// that start inside, outside and on the far side of the geometry, with finite and infinite
// tmax, and with any set of active lanes (including a packet half with none). Inactive lanes'
// outputs are left as they were. The coherent intersection query (a pixel's camera rays) finds
// the incoherent one's hits to the last bit, on such rays and on scattered ones.
class PacketQueries : public ::testing::TestWithParam<int> {};

// The coherent packet query finds the hits of the incoherent one (hits, found), to the last
// bit.
void expect_coherent_hits_equal(const Scene& scene, const RayPacket& rays, const Hit* hits,
                                const bool* found) {
  Hit coherent[kPacketSize];
  bool coherent_found[kPacketSize];
  scene.intersect(rays, coherent, coherent_found, true);
  for (int i = 0; i < kPacketSize; ++i) {
    ASSERT_EQ(coherent_found[i], found[i]) << "lane " << i;
    if (!found[i]) continue;
    EXPECT_EQ(coherent[i].prim, hits[i].prim);
    EXPECT_EQ(coherent[i].slot, hits[i].slot);
    EXPECT_EQ(bits_of(coherent[i].t), bits_of(hits[i].t));
    EXPECT_EQ(bits_of(coherent[i].b1), bits_of(hits[i].b1));
    EXPECT_EQ(bits_of(coherent[i].b2), bits_of(hits[i].b2));
    for (int c = 0; c < 3; ++c) EXPECT_EQ(bits_of(coherent[i].p[c]), bits_of(hits[i].p[c]));
  }
}

TEST_P(PacketQueries, EqualSingleRayQueries) {
  SceneDescription desc;
  Material grey;
  grey.albedo = Vec3(0.5f, 0.5f, 0.5f);
  desc.materials = {grey};
  testing::add_sphere(&desc, {0.f, 0.f, 0.f}, 1.f, 0, 12, 24);
  testing::add_quad(&desc, {-3, -1, 3}, {3, -1, 3}, {3, -1, -3}, {-3, -1, -3}, 0);
  Mesh mesh;
  mesh.name = "small sphere";
  {
    SceneDescription part;
    testing::add_sphere(&part, {0.f, 0.f, 0.f}, 0.5f, 0, 8, 16);
    mesh.geometry = part.world;
  }
  desc.meshes = {mesh};
  for (float sx : {1.f, -1.f}) {
    Instance inst;
    inst.to_world = Mat4::identity();
    inst.to_world.m[0][0] = sx;  // the second instance is mirrored
    inst.to_world.m[3][0] = 2.0 * sx;  // m[col][row]: column 3 is the translation
    inst.to_world.m[3][1] = 0.5;
    desc.instances.push_back(inst);
  }
  Scene scene(std::move(desc));
  ASSERT_EQ(scene.instance_count(), 2u);
  scene.set_packet_query_width(GetParam());
  ASSERT_EQ(scene.packet_query_width(), GetParam());

  std::mt19937 rng(7);
  std::uniform_real_distribution<float> coord(-4.f, 4.f), unit(0.f, 1.f);
  int hits_found = 0, blocked_found = 0, compared = 0;
  int slot_hits[3] = {0, 0, 0};
  for (int packet = 0; packet < 400; ++packet) {
    RayPacket rays;
    // Every third packet is like a pixel's camera rays: one origin, nearly one direction.
    const bool alike = packet % 3 == 2;
    const Vec3 eye(coord(rng), coord(rng), coord(rng));
    const Vec3 aim(0.5f * coord(rng), 0.25f * coord(rng), 0.5f * coord(rng));
    for (int i = 0; i < kPacketSize; ++i) {
      const Vec3 o = alike ? eye : Vec3(coord(rng), coord(rng), coord(rng));
      // Aim near the origin so that most rays hit something.
      const Vec3 target = alike ? aim + Vec3(coord(rng), coord(rng), coord(rng)) * 0.01f
                                : Vec3(0.5f * coord(rng), 0.25f * coord(rng), 0.5f * coord(rng));
      rays.set(i, o, normalize(target - o),
               unit(rng) < 0.5f ? std::numeric_limits<float>::infinity() : 8.f * unit(rng));
      rays.active[i] = unit(rng) < 0.7f;
    }
    // Every fourth packet has an empty second half, every eighth an empty first half.
    if (packet % 4 == 1)
      for (int i = kPacketSize / 2; i < kPacketSize; ++i) rays.active[i] = false;
    if (packet % 8 == 3)
      for (int i = 0; i < kPacketSize / 2; ++i) rays.active[i] = false;
    Hit hits[kPacketSize];
    bool found[kPacketSize], blocked[kPacketSize];
    for (int i = 0; i < kPacketSize; ++i) {
      hits[i].prim = 12345;  // sentinels for inactive lanes
      found[i] = blocked[i] = true;
    }
    scene.intersect(rays, hits, found);
    scene.occluded(rays, blocked);
    expect_coherent_hits_equal(scene, rays, hits, found);
    for (int i = 0; i < kPacketSize; ++i) {
      if (!rays.active[i]) {
        // Inactive lanes: no hit record written, found false; blocked means nothing there.
        EXPECT_EQ(hits[i].prim, 12345u);
        EXPECT_FALSE(found[i]);
        continue;
      }
      ++compared;
      Hit single;
      const bool single_found = scene.intersect(rays.origin(i), rays.direction(i), rays.tfar[i], &single);
      ASSERT_EQ(found[i], single_found) << "packet " << packet << " lane " << i;
      EXPECT_EQ(blocked[i], scene.occluded(rays.origin(i), rays.direction(i), rays.tfar[i]));
      EXPECT_EQ(blocked[i], single_found);  // closest hit exists iff something blocks
      hits_found += single_found;
      blocked_found += blocked[i];
      if (!single_found) continue;
      ++slot_hits[std::min<uint32_t>(2u, single.slot)];
      EXPECT_EQ(hits[i].slot, single.slot);
      EXPECT_EQ(hits[i].prim, single.prim);
      EXPECT_EQ(hits[i].material, single.material);
      EXPECT_FLOAT_EQ(hits[i].t, single.t);
      EXPECT_FLOAT_EQ(hits[i].b1, single.b1);
      EXPECT_FLOAT_EQ(hits[i].b2, single.b2);
      for (int c = 0; c < 3; ++c) {
        EXPECT_FLOAT_EQ(hits[i].p[c], single.p[c]);
        EXPECT_FLOAT_EQ(hits[i].ng[c], single.ng[c]);
        EXPECT_FLOAT_EQ(hits[i].ns[c], single.ns[c]);
      }
    }
  }
  // Many more packets through both traversals: alike rays, scattered ones and single lanes.
  for (int packet = 0; packet < 20000; ++packet) {
    RayPacket rays;
    const int kind = packet % 3;
    const Vec3 eye(coord(rng), coord(rng), coord(rng));
    for (int i = 0; i < kPacketSize; ++i) {
      const Vec3 o = kind == 0 ? eye : Vec3(coord(rng), coord(rng), coord(rng));
      const Vec3 target = Vec3(coord(rng), coord(rng), coord(rng)) * (kind == 0 ? 0.05f : 0.5f);
      rays.set(i, o, normalize(target - o),
               unit(rng) < 0.5f ? std::numeric_limits<float>::infinity() : 8.f * unit(rng));
      rays.active[i] = kind == 2 ? i == packet % kPacketSize : unit(rng) < 0.7f;
    }
    Hit hits[kPacketSize];
    bool found[kPacketSize];
    scene.intersect(rays, hits, found);
    expect_coherent_hits_equal(scene, rays, hits, found);
    if (HasFailure()) break;
  }
  // The comparison covered hits on the world triangles, on both instances, and misses.
  EXPECT_GT(slot_hits[0], 100);
  EXPECT_GT(slot_hits[1], 20);
  EXPECT_GT(slot_hits[2], 20);
  EXPECT_GT(hits_found, compared / 4);
  EXPECT_LT(hits_found, compared);
  EXPECT_EQ(blocked_found, hits_found);
}

INSTANTIATE_TEST_SUITE_P(Scene, PacketQueries, ::testing::Values(8, 16));

}  // namespace
}  // namespace rf

#include "bench/bench.h"

namespace rf {
namespace {

// The benchmark's instanced scene: every instance is the one mesh, turned, scaled and (every
// third) mirrored, standing on the floor. A ray straight down onto each instance's axis hits
// that instance's top with the normal facing up, towards the ray, mirrored or not.
TEST(Instancing, BenchSceneInstancesStandOnTheFloorFacingOut) {
  const uint32_t grid = 3;
  Scene scene(generate_instanced_bench_scene(256, grid));
  ASSERT_EQ(scene.instance_count(), size_t(grid * grid));
  ASSERT_EQ(scene.mesh_count(), 1u);
  const float spacing = 7.f / float(grid);
  for (uint32_t i = 0; i < grid; ++i)
    for (uint32_t j = 0; j < grid; ++j) {
      const float x = -3.5f + spacing * (float(j) + 0.5f), z = -3.5f + spacing * (float(i) + 0.5f);
      Hit hit;
      ASSERT_TRUE(scene.intersect({x, 3.f, z}, {0.f, -1.f, 0.f}, 10.f, &hit));
      EXPECT_EQ(hit.slot, 1 + i * grid + j);
      EXPECT_GT(hit.p.y, 0.05f);
      // The coarse mesh's polar triangles lean about 35 degrees: up, not exactly up.
      EXPECT_GT(hit.ng.y, 0.7f) << "instance " << i * grid + j;
      EXPECT_GT(hit.ns.y, 0.7f);
    }
}

}  // namespace
}  // namespace rf
