// glTF 2.0 core features through the loader and the renderer: sparse accessors, quantized and
// normalized attributes (KHR_mesh_quantization), vertex colours, texture coordinate sets above
// 1, triangle strips and fans, orthographic cameras and clipping planes, and alphaMode MASK and
// BLEND on camera and shadow rays. Expected values come from the specification's formulas,
// computed here.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <cstring>
#include <memory>
#include <string>
#include <vector>

#include "render/integrators.h"
#include "testing/test_scenes.h"

namespace rf {
namespace {

// A glTF buffer built by a test: buffer views appended one after another (4-byte aligned),
// and the JSON members "bufferViews" and "buffers" that describe them.
struct GltfBuffer {
  std::vector<unsigned char> bytes;
  std::vector<std::string> views;
  template <typename T>
  int add(const std::vector<T>& values, size_t stride = 0) {
    while (bytes.size() % 4) bytes.push_back(0);
    const size_t offset = bytes.size();
    const auto* p = reinterpret_cast<const unsigned char*>(values.data());
    bytes.insert(bytes.end(), p, p + values.size() * sizeof(T));
    views.push_back(R"({"buffer": 0, "byteOffset": )" + std::to_string(offset) +
                    R"(, "byteLength": )" + std::to_string(values.size() * sizeof(T)) +
                    (stride ? R"(, "byteStride": )" + std::to_string(stride) : "") + "}");
    return int(views.size() - 1);
  }
  std::string json() const {
    std::string list;
    for (const std::string& v : views) list += (list.empty() ? "" : ", ") + v;
    return R"("bufferViews": [)" + list + R"(], "buffers": [{"byteLength": )" +
           std::to_string(bytes.size()) + R"(, "uri": ")" +
           testing::data_uri("application/octet-stream", bytes) + R"("}])";
  }
};

// The unit quad of quad_gltf_buffers_json: z = 0, x and y in [-1, 1], counter-clockwise seen
// from +z, with TEXCOORD_0 = ((x + 1) / 2, (1 - y) / 2).
const std::vector<float> kQuadPositions = {-1, -1, 0, 1, -1, 0, 1, 1, 0, -1, 1, 0};
const std::vector<float> kQuadUv = {0, 1, 1, 1, 1, 0, 0, 0};
const std::vector<uint16_t> kQuadIndices = {0, 1, 2, 0, 2, 3};

std::string str(double v) {
  char text[32];
  std::snprintf(text, sizeof text, "%.17g", v);
  return text;
}

// The path of the SceneError loading json throws ("" if it loads), and its message.
std::string refusal(const std::string& json, std::string* message = nullptr) {
  try {
    load_gltf_from_string(json, "", "core.gltf", nullptr);
  } catch (const SceneError& e) {
    if (message) *message = e.what();
    return e.path();
  }
  return "";
}

// ---- Sparse accessors (glTF 2.0, 3.6.2.3).

// A quad whose POSITION accessor moves vertex 2 by a sparse substitution, whose indices get
// their last element from a sparse one (the base has the degenerate triangle 0 2 2), and whose
// TEXCOORD_0 has no buffer view: zeros but for the two elements its sparse values give.
// `sparse_uv_indices` are those two elements.
std::string sparse_quad_json(std::vector<uint8_t> sparse_uv_indices = {1, 3}) {
  GltfBuffer b;
  const int positions = b.add(kQuadPositions);
  const int indices = b.add(std::vector<uint16_t>{0, 1, 2, 0, 2, 2});
  const int moved_index = b.add(std::vector<uint8_t>{2});
  const int moved_value = b.add(std::vector<float>{2.f, 1.5f, 0.f});
  const int index_index = b.add(std::vector<uint16_t>{5});
  const int index_value = b.add(std::vector<uint16_t>{3});
  const int uv_index = b.add(sparse_uv_indices);
  const int uv_value = b.add(std::vector<float>{0.5f, 0.25f, 0.75f, 1.f});
  auto sparse = [](int count, int index_view, int index_type, int value_view) {
    return R"("sparse": {"count": )" + std::to_string(count) +
           R"(, "indices": {"bufferView": )" + std::to_string(index_view) +
           R"(, "componentType": )" + std::to_string(index_type) +
           R"(}, "values": {"bufferView": )" + std::to_string(value_view) + "}}";
  };
  return R"({"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
  "nodes": [{"mesh": 0}],
  "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 2}, "indices": 1}]}],
  "accessors": [
    {"bufferView": )" + std::to_string(positions) +
         R"(, "componentType": 5126, "count": 4, "type": "VEC3", )" +
         sparse(1, moved_index, 5121, moved_value) + R"(},
    {"bufferView": )" + std::to_string(indices) +
         R"(, "componentType": 5123, "count": 6, "type": "SCALAR", )" +
         sparse(1, index_index, 5123, index_value) + R"(},
    {"componentType": 5126, "count": 4, "type": "VEC2", )" +
         sparse(2, uv_index, 5121, uv_value) + R"(}
  ],
  )" + b.json() + "}";
}

TEST(GltfCore, SparseAccessorsReplaceTheElementsTheyName) {
  std::vector<std::string> warnings;
  const SceneDescription desc =
      load_gltf_from_string(sparse_quad_json(), "", "sparse.gltf", &warnings);
  const TriangleMesh& w = desc.world;
  ASSERT_EQ(w.positions.size(), 4u);
  // Vertex 2 moved to (2, 1.5, 0); the others are the base's.
  const float want[4][3] = {{-1, -1, 0}, {1, -1, 0}, {2, 1.5f, 0}, {-1, 1, 0}};
  for (int v = 0; v < 4; ++v)
    for (int c = 0; c < 3; ++c) EXPECT_EQ(w.positions[size_t(v)][c], want[v][c]) << v << "," << c;
  // Index 5 is 3: the second triangle is 0 2 3 rather than the degenerate 0 2 2.
  ASSERT_EQ(w.indices.size(), 6u);
  const uint32_t want_indices[6] = {0, 1, 2, 0, 2, 3};
  for (int i = 0; i < 6; ++i) EXPECT_EQ(w.indices[size_t(i)], want_indices[i]) << i;
  // TEXCOORD_0: zeros, with elements 1 and 3 from the sparse values.
  ASSERT_EQ(w.uv[0].size(), 4u);
  const float want_uv[4][2] = {{0, 0}, {0.5f, 0.25f}, {0, 0}, {0.75f, 1}};
  for (int v = 0; v < 4; ++v) {
    EXPECT_EQ(w.uv[0][size_t(v)].x, want_uv[v][0]) << v;
    EXPECT_EQ(w.uv[0][size_t(v)].y, want_uv[v][1]) << v;
  }
  // Sparse indices must strictly increase and stay below the accessor's count.
  std::string message;
  EXPECT_EQ(refusal(sparse_quad_json({3, 1}), &message), "accessors[2].sparse.indices");
  EXPECT_NE(message.find("strictly increase"), std::string::npos) << message;
  EXPECT_EQ(refusal(sparse_quad_json({1, 4}), &message), "accessors[2].sparse.indices");
  EXPECT_NE(message.find("out of range"), std::string::npos) << message;
}

// ---- Normalized and quantized attributes (glTF 2.0, 3.7.2.1 and 3.11; KHR_mesh_quantization).

// The quad with its POSITION accessor `position` (JSON of the accessor), whose data is view 0
// of `b`, under a node with `transform` (JSON members, may be empty).
std::string quantized_quad_json(GltfBuffer b, const std::string& position,
                                const std::string& transform, const std::string& extensions) {
  const int indices = b.add(kQuadIndices);
  return R"({"asset": {"version": "2.0"}, )" + extensions + R"(
  "scene": 0, "scenes": [{"nodes": [0]}],
  "nodes": [{"mesh": 0)" + (transform.empty() ? "" : ", " + transform) + R"(}],
  "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
  "accessors": [)" + position + R"(,
    {"bufferView": )" + std::to_string(indices) +
         R"(, "componentType": 5123, "count": 6, "type": "SCALAR"}],
  )" + b.json() + "}";
}

TEST(GltfCore, QuantizedPositionsUnderTheirNodeTransformGiveTheFloatTriangles) {
  const std::string required = R"("extensionsUsed": ["KHR_mesh_quantization"],
                                  "extensionsRequired": ["KHR_mesh_quantization"],)";
  GltfBuffer floats;
  floats.add(kQuadPositions);
  const SceneDescription reference = load_gltf_from_string(
      quantized_quad_json(floats,
                          R"({"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3"})",
                          "", ""),
      "", "float.gltf", nullptr);
  struct Variant {
    const char* name;
    GltfBuffer buffer;
    std::string accessor, transform;
  };
  std::vector<Variant> variants;
  {
    // SHORT, not normalized: +-16384 with the node scale 2^-14 (exact in float).
    Variant v{"short", {}, "", R"("scale": [6.103515625e-05, 6.103515625e-05, 1])"};
    std::vector<int16_t> p;
    for (size_t i = 0; i < 4; ++i) {
      for (int c = 0; c < 3; ++c) p.push_back(int16_t(16384 * kQuadPositions[3 * i + size_t(c)]));
      p.push_back(0);  // vertex attributes are 4-byte aligned: a stride of 8
    }
    v.buffer.add(p, 8);
    v.accessor = R"({"bufferView": 0, "componentType": 5122, "count": 4, "type": "VEC3"})";
    variants.push_back(std::move(v));
  }
  {
    // UNSIGNED_SHORT normalized: -1 -> 0 and +1 -> 65535, c / 65535 in [0, 1], then the node
    // maps [0, 1] to [-1, 1] (scale 2, translation -1).
    Variant v{"unsigned short normalized", {}, "",
              R"("translation": [-1, -1, 0], "scale": [2, 2, 1])"};
    std::vector<uint16_t> p;
    for (size_t i = 0; i < 4; ++i) {
      for (int c = 0; c < 2; ++c) p.push_back(kQuadPositions[3 * i + size_t(c)] > 0 ? 65535 : 0);
      p.push_back(0);
      p.push_back(0);
    }
    v.buffer.add(p, 8);
    v.accessor = R"({"bufferView": 0, "componentType": 5123, "normalized": true, "count": 4,
                     "type": "VEC3"})";
    variants.push_back(std::move(v));
  }
  {
    // BYTE normalized: max(c / 127, -1), so both -127 and -128 are -1.
    Variant v{"byte normalized", {}, "", ""};
    std::vector<int8_t> p;
    for (size_t i = 0; i < 4; ++i) {
      for (int c = 0; c < 3; ++c) {
        const float x = kQuadPositions[3 * i + size_t(c)];
        p.push_back(int8_t(x > 0 ? 127 : x < 0 ? (i % 2 ? -127 : -128) : 0));
      }
      p.push_back(0);
    }
    v.buffer.add(p, 4);
    v.accessor = R"({"bufferView": 0, "componentType": 5120, "normalized": true, "count": 4,
                     "type": "VEC3"})";
    variants.push_back(std::move(v));
  }
  for (const Variant& v : variants) {
    const std::string json = quantized_quad_json(v.buffer, v.accessor, v.transform, required);
    std::vector<std::string> warnings;
    const SceneDescription desc = load_gltf_from_string(json, "", "quantized.gltf", &warnings);
    EXPECT_TRUE(warnings.empty()) << v.name << ": " << warnings.front();
    ASSERT_EQ(desc.world.positions.size(), reference.world.positions.size()) << v.name;
    for (size_t i = 0; i < desc.world.positions.size(); ++i)
      for (int c = 0; c < 3; ++c)
        EXPECT_EQ(desc.world.positions[i][c], reference.world.positions[i][c])
            << v.name << " vertex " << i << " component " << c;
    EXPECT_EQ(desc.world.indices, reference.world.indices) << v.name;
    // Without the extension, integer positions are not glTF 2.0: refused, naming the
    // accessor and the extension.
    std::string message;
    EXPECT_EQ(refusal(quantized_quad_json(v.buffer, v.accessor, v.transform, ""), &message),
              "accessors[0]")
        << v.name;
    EXPECT_NE(message.find("KHR_mesh_quantization"), std::string::npos) << message;
  }
}

// Normals as normalized bytes and texture coordinates as integers (KHR_mesh_quantization), and
// the core's normalized unsigned texture coordinates.
TEST(GltfCore, QuantizedNormalsAndTextureCoordinates) {
  GltfBuffer b;
  const int positions = b.add(kQuadPositions);
  // Normals (0, 0, 127) and (0, 0, -128): +z and -z after normalization.
  // Elements of 3 bytes, 4-byte aligned: a stride of 4.
  const int normals = b.add(std::vector<int8_t>{0, 0, 127, 0, 0, 0, -128, 0,  //
                                                0, 0, 127, 0, 0, 0, 127, 0},
                            4);
  // TEXCOORD_0 as unsigned shorts, not normalized: the integers themselves (a texture
  // transform would dequantize them); TEXCOORD_1 as normalized unsigned bytes: c / 255.
  const int uv0 = b.add(std::vector<uint16_t>{0, 1000, 1000, 1000, 1000, 0, 0, 0});
  const int uv1 = b.add(std::vector<uint8_t>{0, 255, 255, 255, 255, 51, 0, 0});
  const int indices = b.add(kQuadIndices);
  auto json = [&](bool declared) {
    return std::string(R"({"asset": {"version": "2.0"}, )") +
           (declared ? R"("extensionsUsed": ["KHR_mesh_quantization"],
                           "extensionsRequired": ["KHR_mesh_quantization"],)"
                     : "") +
           R"("scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
    "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2,
                                               "TEXCOORD_1": 3}, "indices": 4}]}],
    "accessors": [
      {"bufferView": )" + std::to_string(positions) +
           R"(, "componentType": 5126, "count": 4, "type": "VEC3"},
      {"bufferView": )" + std::to_string(normals) +
           R"(, "byteOffset": 0, "componentType": 5120, "normalized": true, "count": 4,
       "type": "VEC3"},
      {"bufferView": )" + std::to_string(uv0) +
           R"(, "componentType": 5123, "count": 4, "type": "VEC2"},
      {"bufferView": )" + std::to_string(uv1) +
           R"(, "componentType": 5121, "normalized": true, "count": 4, "type": "VEC2"},
      {"bufferView": )" + std::to_string(indices) +
           R"(, "componentType": 5123, "count": 6, "type": "SCALAR"}],
    )" + b.json() + "}";
  };
  const SceneDescription desc = load_gltf_from_string(json(true), "", "quantized.gltf", nullptr);
  const TriangleMesh& w = desc.world;
  ASSERT_EQ(w.normals.size(), 4u);
  const float nz[4] = {1, -1, 1, 1};
  for (size_t v = 0; v < 4; ++v) {
    EXPECT_EQ(w.normals[v].x, 0.f);
    EXPECT_EQ(w.normals[v].z, nz[v]) << v;
  }
  const float u0[4][2] = {{0, 1000}, {1000, 1000}, {1000, 0}, {0, 0}};
  const float u1[4][2] = {{0, 1}, {1, 1}, {1, float(51.0 / 255.0)}, {0, 0}};
  for (size_t v = 0; v < 4; ++v) {
    EXPECT_EQ(w.uv[0][v].x, u0[v][0]);
    EXPECT_EQ(w.uv[0][v].y, u0[v][1]);
    EXPECT_EQ(w.uv[1][v].x, u1[v][0]);
    EXPECT_EQ(w.uv[1][v].y, u1[v][1]);
  }
  // The core allows only normalized unsigned texture coordinates and float normals.
  std::string message;
  EXPECT_EQ(refusal(json(false), &message), "accessors[1]");
  EXPECT_NE(message.find("KHR_mesh_quantization"), std::string::npos) << message;
}

// ---- Triangle strips and fans (glTF 2.0, 3.7.2.1 "Topology types").

TEST(GltfCore, TriangleStripsAndFansFollowTheSpecificationsVertexOrder) {
  GltfBuffer b;
  // Four vertices of the unit square in z = 0: (0,0) (1,0) (0,1) (1,1).
  const int strip_view = b.add(std::vector<float>{0, 0, 0, 1, 0, 0, 0, 1, 0, 1, 1, 0});
  // A fan around (0,0): (0,0) (1,0) (1,1) (0,1).
  const int fan_view = b.add(std::vector<float>{0, 0, 0, 1, 0, 0, 1, 1, 0, 0, 1, 0});
  const std::string json = R"({"asset": {"version": "2.0"}, "scene": 0,
  "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
  "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "mode": 5},
                             {"attributes": {"POSITION": 1}, "mode": 6}]}],
  "accessors": [
    {"bufferView": )" + std::to_string(strip_view) +
                           R"(, "componentType": 5126, "count": 4, "type": "VEC3"},
    {"bufferView": )" + std::to_string(fan_view) +
                           R"(, "componentType": 5126, "count": 4, "type": "VEC3"}],
  )" + b.json() + "}";
  std::vector<std::string> warnings;
  const SceneDescription desc = load_gltf_from_string(json, "", "strips.gltf", &warnings);
  EXPECT_TRUE(warnings.empty()) << warnings.front();
  ASSERT_EQ(desc.world.size(), 4u);
  // Strip: triangle i is (v_i, v_{i + 1 + i % 2}, v_{i + 2 - i % 2}); fan: (v_{i+1}, v_{i+2}, v_0).
  const float s[4][2] = {{0, 0}, {1, 0}, {0, 1}, {1, 1}};
  const float f[4][2] = {{0, 0}, {1, 0}, {1, 1}, {0, 1}};
  const float want[4][3][2] = {{{s[0][0], s[0][1]}, {s[1][0], s[1][1]}, {s[2][0], s[2][1]}},
                               {{s[1][0], s[1][1]}, {s[3][0], s[3][1]}, {s[2][0], s[2][1]}},
                               {{f[1][0], f[1][1]}, {f[2][0], f[2][1]}, {f[0][0], f[0][1]}},
                               {{f[2][0], f[2][1]}, {f[3][0], f[3][1]}, {f[0][0], f[0][1]}}};
  for (size_t t = 0; t < 4; ++t) {
    const Triangle tri = desc.world.triangle(t);
    for (int k = 0; k < 3; ++k) {
      EXPECT_EQ(tri.p[k].x, want[t][k][0]) << "triangle " << t << " corner " << k;
      EXPECT_EQ(tri.p[k].y, want[t][k][1]) << "triangle " << t << " corner " << k;
    }
    EXPECT_FLOAT_EQ(tri.ng.z, 1.f) << "every triangle keeps the front face +z";
  }
}

// Skins and morph targets apply (animation_test.cpp); a skinned node whose primitive has no
// JOINTS_0 / WEIGHTS_0 is placed by its node, and the TANGENT attribute of a skinned mesh,
// whose tangents normal maps do not use (a rigid mesh's are used: textures_test.cpp): each
// said by name, once per scene. Skinned and morphed nodes have vertices
// of their own (no instances).
TEST(GltfCore, UnskinnedSkinsAndTangentsWarnOncePerScene) {
  const std::string json = R"({"asset": {"version": "2.0"}, "scene": 0,
  "scenes": [{"nodes": [0, 1, 2, 3]}],
  "nodes": [{"mesh": 0, "skin": 0}, {"mesh": 0, "skin": 0}, {"mesh": 1}, {"mesh": 1}],
  "skins": [{"joints": [2]}],
  "textures": [{"source": 0}], "images": [{"uri": ")" +
                           testing::png_data_uri(1, 1, 3, {128, 128, 255}) + R"("}],
  "materials": [{"normalTexture": {"index": 0}}],
  "meshes": [
    {"primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2, "TANGENT": 4},
                     "indices": 3, "material": 0},
                    {"attributes": {"POSITION": 0, "TANGENT": 4}, "indices": 3,
                     "material": 0}]},
    {"primitives": [{"attributes": {"POSITION": 0}, "indices": 3,
                     "targets": [{"POSITION": 1}]}], "weights": [0.5]}],
  )" + testing::quad_gltf_buffers_json() + "}";
  // A TANGENT accessor (VEC4) on the normals' view: accessor 4.
  std::string text = json;
  const std::string last =
      R"({"bufferView": 3, "componentType": 5123, "count": 6, "type": "SCALAR"})";
  text.replace(text.find(last), last.size(),
               last + R"(, {"bufferView": 1, "componentType": 5126, "count": 3, "type": "VEC4"})");
  std::vector<std::string> warnings;
  const SceneDescription desc = load_gltf_from_string(text, "", "rigged.gltf", &warnings);
  int unskinned = 0, unsupported = 0, tangents = 0;
  for (const std::string& w : warnings) {
    unskinned += w.find("no JOINTS_0 and WEIGHTS_0") != std::string::npos;
    unsupported += w.find("not supported") != std::string::npos;
    tangents += w.find("TANGENT of a skinned or morphed mesh is not used") != std::string::npos;
  }
  EXPECT_EQ(unskinned, 1);
  EXPECT_EQ(unsupported, 0);
  EXPECT_EQ(tangents, 1);
  EXPECT_TRUE(desc.instances.empty());
}

// ---- Vertex colours and texture coordinate sets (glTF 2.0, 3.7.2.1, 3.9.2).

// First-hit albedo (base colour) at (x, y) of the z = 0 plane, seen from +z.
Vec3 albedo_at(const std::string& json, float x, float y) {
  std::vector<std::string> warnings;
  SceneDescription desc = load_gltf_from_string(json, "", "quad.gltf", &warnings);
  for (const auto& w : warnings) ADD_FAILURE() << "unexpected warning: " << w;
  desc.camera = testing::look_at({x, y, 2.f}, {x, y, 0.f}, 1e-4f);
  Scene scene(std::move(desc));
  RenderSettings settings;
  settings.width = settings.height = 1;
  settings.integrator = IntegratorType::AmbientOcclusion;
  TileBuffer tile;
  EXPECT_TRUE(render_rect(scene, settings, {0, 0, 1, 1}, 0, 4, &tile));
  const std::vector<float>& albedo = tile.sum(channels::Id::Albedo);
  return Vec3(albedo[0], albedo[1], albedo[2]) / 4.f;
}

void expect_near(Vec3 got, Vec3 want, float tolerance, const std::string& what) {
  for (int c = 0; c < 3; ++c) EXPECT_NEAR(got[c], want[c], tolerance) << what << " channel " << c;
}

// COLOR_0 multiplies baseColorFactor (and the texture): a colour linear in x is interpolated
// exactly by any triangulation, so the albedo at (x, y) is the factor times that function.
TEST(GltfCore, VertexColorsMultiplyTheBaseColor) {
  GltfBuffer b;
  const int positions = b.add(kQuadPositions);
  const int indices = b.add(kQuadIndices);
  // Normalized unsigned bytes RGBA: red (x + 1) / 2, green (1 - x) / 2, blue 51 / 255.
  std::vector<uint8_t> rgba;
  std::vector<float> rgb;
  for (size_t v = 0; v < 4; ++v) {
    const bool right = kQuadPositions[3 * v] > 0;
    rgba.insert(rgba.end(), {uint8_t(right ? 255 : 0), uint8_t(right ? 0 : 255), 51, 255});
    rgb.insert(rgb.end(), {right ? 1.f : 0.f, right ? 0.f : 1.f, 0.2f});
  }
  const int colors_u8 = b.add(rgba);
  const int colors_f = b.add(rgb);
  auto json = [&](int color_accessor) {
    return R"({"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
    "nodes": [{"mesh": 0}],
    "materials": [{"pbrMetallicRoughness": {"baseColorFactor": [0.5, 1, 0.8, 1],
                                            "metallicFactor": 0}}],
    "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "COLOR_0": )" +
           std::to_string(color_accessor) + R"(}, "indices": 1, "material": 0}]}],
    "accessors": [
      {"bufferView": )" + std::to_string(positions) +
           R"(, "componentType": 5126, "count": 4, "type": "VEC3"},
      {"bufferView": )" + std::to_string(indices) +
           R"(, "componentType": 5123, "count": 6, "type": "SCALAR"},
      {"bufferView": )" + std::to_string(colors_u8) +
           R"(, "componentType": 5121, "normalized": true, "count": 4, "type": "VEC4"},
      {"bufferView": )" + std::to_string(colors_f) +
           R"(, "componentType": 5126, "count": 4, "type": "VEC3"}],
    )" + b.json() + "}";
  };
  for (const auto& [x, y] : {std::pair<float, float>{0.5f, 0.2f}, {-0.6f, -0.7f}, {0.f, 0.9f}}) {
    const float red = 0.5f * (x + 1.f) / 2.f, green = 1.f * (1.f - x) / 2.f;
    expect_near(albedo_at(json(2), x, y), {red, green, 0.8f * 51.f / 255.f}, 1e-5f, "VEC4 u8");
    expect_near(albedo_at(json(3), x, y), {red, green, 0.8f * 0.2f}, 1e-5f, "VEC3 float");
  }
}

// A 2 x 1 texture, red on the left and green on the right, read through TEXCOORD_2 (TEXCOORD_0
// points at the red texel everywhere): by baseColorTexture.texCoord and by
// KHR_texture_transform's texCoord override; and through TEXCOORD_7.
TEST(GltfCore, TextureCoordinateSetsAboveOneAreSampled) {
  GltfBuffer b;
  const int positions = b.add(kQuadPositions);
  const int indices = b.add(kQuadIndices);
  const int uv0 = b.add(std::vector<float>{0.25f, 0.5f, 0.25f, 0.5f, 0.25f, 0.5f, 0.25f, 0.5f});
  const int uv2 = b.add(kQuadUv);
  const std::string image = testing::png_data_uri(2, 1, 3, {255, 0, 0, 0, 255, 0});
  auto json = [&](const std::string& texture_info, const std::string& extensions,
                  const std::string& set = "TEXCOORD_2") {
    return R"({"asset": {"version": "2.0"}, )" + extensions + R"(
    "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
    "materials": [{"pbrMetallicRoughness": {"baseColorTexture": )" + texture_info + R"(,
                                            "metallicFactor": 0}}],
    "textures": [{"source": 0}], "images": [{"uri": ")" + image + R"("}],
    "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 2, "TEXCOORD_1": 2,
                                               ")" + set + R"(": 3}, "indices": 1,
                                "material": 0}]}],
    "accessors": [
      {"bufferView": )" + std::to_string(positions) +
           R"(, "componentType": 5126, "count": 4, "type": "VEC3"},
      {"bufferView": )" + std::to_string(indices) +
           R"(, "componentType": 5123, "count": 6, "type": "SCALAR"},
      {"bufferView": )" + std::to_string(uv0) +
           R"(, "componentType": 5126, "count": 4, "type": "VEC2"},
      {"bufferView": )" + std::to_string(uv2) +
           R"(, "componentType": 5126, "count": 4, "type": "VEC2"}],
    )" + b.json() + "}";
  };
  const std::string by_texcoord = json(R"({"index": 0, "texCoord": 2})", "");
  const std::string by_transform =
      json(R"({"index": 0, "texCoord": 0, "extensions": {"KHR_texture_transform":
                 {"texCoord": 2}}})",
           R"("extensionsUsed": ["KHR_texture_transform"],)");
  const std::string seventh = json(R"({"index": 0, "texCoord": 7})", "", "TEXCOORD_7");
  for (const std::string& scene : {by_texcoord, by_transform, seventh}) {
    // Texel centres: u = 0.25 at x = -0.5 and u = 0.75 at x = 0.5.
    expect_near(albedo_at(scene, -0.5f, 0.f), {1, 0, 0}, 2e-3f, "left texel");
    expect_near(albedo_at(scene, 0.5f, 0.f), {0, 1, 0}, 2e-3f, "right texel");
  }
  // A set above 1 is stored because a material reads it, in the next free array.
  for (const std::string& scene : {by_texcoord, seventh}) {
    const SceneDescription desc = load_gltf_from_string(scene, "", "uv.gltf", nullptr);
    ASSERT_EQ(desc.world.uv.size(), 3u);
    EXPECT_EQ(desc.world.uv[2].size(), 4u);
  }
}

// ---- Cameras (glTF 2.0, 3.10).

// An emissive square (radiance 2, x and y in [-1, 1] at z = 0, facing +z), a black square of
// the same size at z = 3 in front of it, and a camera at z = 5 looking down -z.
std::string camera_scene(const std::string& camera) {
  GltfBuffer b;
  const int positions = b.add(kQuadPositions);
  const int indices = b.add(kQuadIndices);
  return R"({"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0, 1, 2]}],
  "nodes": [{"mesh": 0}, {"mesh": 1, "translation": [0, 0, 3]},
            {"camera": 0, "translation": [0, 0, 5]}],
  "cameras": [)" + camera + R"(],
  "materials": [
    {"pbrMetallicRoughness": {"baseColorFactor": [0, 0, 0, 1], "metallicFactor": 0},
     "emissiveFactor": [1, 1, 1],
     "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 2}}},
    {"pbrMetallicRoughness": {"baseColorFactor": [0, 0, 0, 1], "metallicFactor": 0},
     "extensions": {"KHR_materials_specular": {"specularFactor": 0}}}],
  "extensionsUsed": ["KHR_materials_emissive_strength", "KHR_materials_specular"],
  "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "material": 0}]},
             {"primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "material": 1}]}],
  "accessors": [
    {"bufferView": )" + std::to_string(positions) +
         R"(, "componentType": 5126, "count": 4, "type": "VEC3"},
    {"bufferView": )" + std::to_string(indices) +
         R"(, "componentType": 5123, "count": 6, "type": "SCALAR"}],
  )" + b.json() + "}";
}

// The scene's 8 x 8 image, 4 samples per pixel: mean radiance per pixel.
std::vector<double> render_image(const Scene& scene, uint32_t spp = 4) {
  RenderSettings settings;
  settings.width = settings.height = 8;
  TileBuffer tile;
  EXPECT_TRUE(render_rect(scene, settings, {0, 0, 8, 8}, 0, spp, &tile));
  std::vector<double> out(64);
  for (size_t i = 0; i < 64; ++i) out[i] = tile.rgb_sum[3 * i] / spp;
  return out;
}

// An orthographic camera of xmag = ymag = 2 sees [-2, 2] x [-2, 2] through parallel rays, so the
// square of [-1, 1] covers exactly the middle 4 x 4 pixels of an 8 x 8 image; znear and zfar
// clip along the axis (the black square is 2 in front of the camera, the emitter 5).
TEST(GltfCore, OrthographicCamerasSeeTheirBoxAndClip) {
  auto ortho = [](double znear, double zfar) {
    return R"({"type": "orthographic", "orthographic": {"xmag": 2, "ymag": 2, "znear": )" +
           str(znear) + R"(, "zfar": )" + str(zfar) + "}}";
  };
  std::vector<std::string> warnings;
  {
    // Near plane past the black square: the emitter shows through it.
    Scene scene(load_gltf_from_string(camera_scene(ortho(2.5, 100)), "", "ortho.gltf", &warnings),
                &warnings);
    EXPECT_TRUE(warnings.empty()) << warnings.front();
    const std::vector<double> image = render_image(scene);
    for (int y = 0; y < 8; ++y)
      for (int x = 0; x < 8; ++x) {
        const bool inside = x >= 2 && x < 6 && y >= 2 && y < 6;
        EXPECT_EQ(image[size_t(y * 8 + x)], inside ? 2.0 : 0.0) << x << "," << y;
      }
  }
  {
    // Near plane before it: black. Far plane before the emitter, without the black square in
    // front (near plane past it): black as well.
    Scene near_scene(
        load_gltf_from_string(camera_scene(ortho(1, 100)), "", "ortho.gltf", nullptr));
    for (double v : render_image(near_scene)) EXPECT_EQ(v, 0.0);
    Scene far_scene(
        load_gltf_from_string(camera_scene(ortho(2.5, 4.5)), "", "ortho.gltf", nullptr));
    for (double v : render_image(far_scene)) EXPECT_EQ(v, 0.0);
  }
  // The perspective camera's znear clips the same way (yfov 0.38: the emitter fills the view).
  Scene persp(load_gltf_from_string(
      camera_scene(R"({"type": "perspective", "perspective": {"yfov": 0.38, "znear": 2.5}})"), "",
      "persp.gltf", nullptr));
  for (double v : render_image(persp)) EXPECT_EQ(v, 2.0);
  // Invalid orthographic cameras are refused, naming the field.
  EXPECT_EQ(refusal(camera_scene(R"({"type": "orthographic", "orthographic":
                                   {"xmag": 0, "ymag": 2, "znear": 0, "zfar": 10}})")),
            "cameras[0].orthographic.xmag");
  EXPECT_EQ(refusal(camera_scene(R"({"type": "orthographic", "orthographic":
                                   {"xmag": 1, "ymag": 2, "znear": 3, "zfar": 2}})")),
            "cameras[0].orthographic.zfar");
}

// Orthographic ray origins and directions, from glTF's projection: pixel (px, py) of a W x H
// image is the camera-space point ((2 px / W - 1) xmag, (1 - 2 py / H) ymag) on the plane
// through the camera, and every ray goes along the camera's -Z.
TEST(GltfCore, OrthographicRayOriginsAndDirections) {
  GltfBuffer b;
  const int positions = b.add(kQuadPositions);
  // The camera at (1, 2, 3), turned 90 degrees about +Y: it looks along -X, its right is -Z.
  const double h = std::sqrt(0.5);
  const std::string json = R"({"asset": {"version": "2.0"}, "scene": 0,
  "scenes": [{"nodes": [0, 1]}],
  "nodes": [{"mesh": 0}, {"camera": 0, "translation": [1, 2, 3], "rotation": [0, )" + str(h) +
                           R"(, 0, )" + str(h) + R"(]}],
  "cameras": [{"type": "orthographic",
               "orthographic": {"xmag": 1.5, "ymag": 0.5, "znear": 0.25, "zfar": 40}}],
  "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
  "accessors": [{"bufferView": )" + std::to_string(positions) +
                           R"(, "componentType": 5126, "count": 3, "type": "VEC3"}],
  )" + b.json() + "}";
  Scene scene(load_gltf_from_string(json, "", "ortho.gltf", nullptr));
  const Camera& cam = scene.camera();
  ASSERT_TRUE(cam.orthographic);
  EXPECT_EQ(cam.znear, 0.25f);
  EXPECT_EQ(cam.zfar, 40.f);
  const Camera::Raster r = cam.raster(64, 16);
  for (const auto& [px, py] : {std::pair<float, float>{0.f, 0.f}, {64.f, 16.f}, {10.5f, 3.25f}}) {
    const double sx = (2.0 * px / 64 - 1) * 1.5, sy = (1 - 2.0 * py / 16) * 0.5;
    // Camera right = -Z, up = +Y, forward = -X in world space.
    const double want[3] = {1.0, 2.0 + sy, 3.0 - sx};
    const Vec3 o = r.origin(px, py), d = r.direction(px, py);
    for (int c = 0; c < 3; ++c) EXPECT_NEAR(o[c], want[c], 1e-5) << px << "," << py << " " << c;
    EXPECT_NEAR(d.x, -1.f, 1e-6f);
    EXPECT_NEAR(d.y, 0.f, 1e-6f);
    EXPECT_NEAR(d.z, 0.f, 1e-6f);
  }
}

// ---- alphaMode MASK and BLEND (glTF 2.0, 3.9.4).

// An RGBA texture of 8 x 1 texels, white, alpha 0 on the left half and 255 on the right, with
// a clamping sampler: bilinear alpha is below 1/2 exactly for u < 1/2 (x < 0 on the quad).
const char* kHalfCutTexture = R"("textures": [{"source": 0, "sampler": 0}],
  "samplers": [{"wrapS": 33071, "wrapT": 33071}],)";
std::string half_cut_image() {
  std::vector<unsigned char> px;
  for (int i = 0; i < 8; ++i) px.insert(px.end(), {255, 255, 255, uint8_t(i < 4 ? 0 : 255)});
  return R"("images": [{"uri": ")" + testing::png_data_uri(8, 1, 4, px) + R"("}],)";
}

// A surface material: black and without specular reflection, so that it reflects nothing;
// `mode` holds its alpha members ("alphaMode": ..., with a trailing comma), `alpha` the
// alpha of its baseColorFactor, and it may have the texture.
std::string black_material(const std::string& mode, const std::string& alpha, bool textured) {
  return "{" + mode + R"("pbrMetallicRoughness": {"baseColorFactor": [0, 0, 0, )" + alpha +
         R"(], "metallicFactor": 0)" + (textured ? R"(, "baseColorTexture": {"index": 0})" : "") +
         R"(}, "extensions": {"KHR_materials_specular": {"specularFactor": 0}}})";
}
const char* kMask = R"("alphaMode": "MASK",)";

// Camera rays: a background emitter (radiance 2, facing +z at z = -1) seen through a quad at
// z = 0 of material `front` (materials[1]); the 8 x 8 image sees x, y in [-0.5, 0.5] of the
// quad's plane.
std::unique_ptr<Scene> window_scene(const std::string& front, const std::string& textures) {
  GltfBuffer b;
  const int positions = b.add(kQuadPositions);
  const int uv = b.add(kQuadUv);
  const int indices = b.add(kQuadIndices);
  const std::string json = R"({"asset": {"version": "2.0"},
  "extensionsUsed": ["KHR_materials_emissive_strength", "KHR_materials_specular"],
  "scene": 0, "scenes": [{"nodes": [0, 1]}],
  "nodes": [{"mesh": 0, "translation": [0, 0, -1], "scale": [3, 3, 1]}, {"mesh": 1}],
  "materials": [
    {"pbrMetallicRoughness": {"baseColorFactor": [0, 0, 0, 1], "metallicFactor": 0},
     "emissiveFactor": [1, 1, 1],
     "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 2}}},
    )" + front + R"(],
  )" + textures + R"(
  "meshes": [
    {"primitives": [{"attributes": {"POSITION": 0}, "indices": 2, "material": 0}]},
    {"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2,
                     "material": 1}]}],
  "accessors": [
    {"bufferView": )" + std::to_string(positions) +
                           R"(, "componentType": 5126, "count": 4, "type": "VEC3"},
    {"bufferView": )" + std::to_string(uv) +
                           R"(, "componentType": 5126, "count": 4, "type": "VEC2"},
    {"bufferView": )" + std::to_string(indices) +
                           R"(, "componentType": 5123, "count": 6, "type": "SCALAR"}],
  )" + b.json() + "}";
  std::vector<std::string> warnings;
  SceneDescription desc = load_gltf_from_string(json, "", "window.gltf", &warnings);
  for (const auto& w : warnings) ADD_FAILURE() << "unexpected warning: " << w;
  desc.camera = testing::look_at({0.f, 0.f, 3.f}, {0.f, 0.f, 0.f}, 2.f * std::atan(1.f / 6.f));
  return std::make_unique<Scene>(std::move(desc));
}

TEST(AlphaMode, MaskCutsOutWhereAlphaIsBelowTheCutoff) {
  const auto scene =
      window_scene(black_material(kMask, "1", true), kHalfCutTexture + half_cut_image());
  EXPECT_TRUE(scene->has_transparency());
  const std::vector<double> image = render_image(*scene, 8);
  // Left half (x < 0): the texels of alpha 0 are cut out, the emitter shows. Right half:
  // alpha 1 >= 0.5, the black quad.
  for (int y = 0; y < 8; ++y)
    for (int x = 0; x < 8; ++x)
      EXPECT_EQ(image[size_t(y * 8 + x)], x < 4 ? 2.0 : 0.0) << x << "," << y;
  // alphaCutoff above the alpha: all cut out; alphaMode OPAQUE: no cut-out at all, whatever
  // the alpha.
  const auto all_cut = window_scene(
      R"({"alphaMode": "MASK", "alphaCutoff": 0.6,
          "pbrMetallicRoughness": {"baseColorFactor": [0, 0, 0, 0.55], "metallicFactor": 0}})",
      "");
  for (double v : render_image(*all_cut)) EXPECT_EQ(v, 2.0);
  const auto opaque =
      window_scene(black_material("", "0", true), kHalfCutTexture + half_cut_image());
  EXPECT_FALSE(opaque->has_transparency());
  for (double v : render_image(*opaque)) EXPECT_EQ(v, 0.0);
}

// BLEND: the "over" operator, stochastically. A quad of alpha 0.25 that emits 4 in front of the
// emitter of 2: each camera sample sees 4 with probability 0.25 and 2 otherwise, so the image
// mean is 2.5 and the fraction of samples that stop on the quad, (mean - 2) / 2, is a binomial
// proportion of 0.25.
TEST(AlphaMode, BlendStopsRaysWithProbabilityAlpha) {
  const std::string front = R"({"alphaMode": "BLEND",
    "pbrMetallicRoughness": {"baseColorFactor": [0, 0, 0, 0.25], "metallicFactor": 0},
    "emissiveFactor": [1, 1, 1],
    "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 4},
                   "KHR_materials_specular": {"specularFactor": 0}}})";
  const auto scene = window_scene(front, "");
  const uint32_t spp = 64;
  const std::vector<double> image = render_image(*scene, spp);
  double sum = 0.0;
  for (double v : image) sum += v;
  const double n = 64.0 * spp;
  const double fraction = (sum / 64.0 - 2.0) / 2.0;
  const double se = std::sqrt(0.25 * 0.75 / n);
  EXPECT_NEAR(fraction, 0.25, 4.0 * se) << "standard error " << se;
  // The same render again: the same image (the choices are a function of the sample).
  EXPECT_EQ(render_image(*scene, spp), image);
}

// Form factor from a point to a parallel a x b rectangle at height c with the point under a
// corner (the "corner formula").
double form_factor_corner(double a, double b, double c) {
  const double X = a / c, Y = b / c;
  const double sx = std::sqrt(1 + X * X), sy = std::sqrt(1 + Y * Y);
  return (X / sx * std::atan(Y / sx) + Y / sy * std::atan(X / sy)) / (2 * M_PI);
}

// Shadow rays: a Lambertian floor of albedo 1/2 under a 1 x 1 emitter of radiance 3 at height 1,
// with a black quad of material `occluder` at height 1/2 between them (x, y in [-1, 1]). The
// pixel sees the floor point under the emitter's centre, from below the occluder.
double shadowed_floor(const std::string& occluder, const std::string& textures,
                      double* standard_error) {
  GltfBuffer b;
  const int positions = b.add(kQuadPositions);
  const int uv = b.add(kQuadUv);
  const int indices = b.add(kQuadIndices);
  const std::string json = R"({"asset": {"version": "2.0"},
  "extensionsUsed": ["KHR_materials_emissive_strength", "KHR_materials_specular"],
  "scene": 0, "scenes": [{"nodes": [0, 1, 2]}],
  "nodes": [{"mesh": 0, "scale": [4, 4, 1]},
            {"mesh": 1, "translation": [0, 0, 1], "rotation": [1, 0, 0, 0],
             "scale": [0.5, 0.5, 1]},
            {"mesh": 2, "translation": [0, 0, 0.5]}],
  "materials": [
    {"pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.5, 0.5, 1], "metallicFactor": 0},
     "extensions": {"KHR_materials_specular": {"specularFactor": 0}}},
    {"pbrMetallicRoughness": {"baseColorFactor": [0, 0, 0, 1], "metallicFactor": 0},
     "emissiveFactor": [1, 1, 1],
     "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 3},
                    "KHR_materials_specular": {"specularFactor": 0}}},
    )" + occluder + R"(],
  )" + textures + R"(
  "meshes": [
    {"primitives": [{"attributes": {"POSITION": 0}, "indices": 2, "material": 0}]},
    {"primitives": [{"attributes": {"POSITION": 0}, "indices": 2, "material": 1}]},
    {"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2,
                     "material": 2}]}],
  "accessors": [
    {"bufferView": )" + std::to_string(positions) +
                           R"(, "componentType": 5126, "count": 4, "type": "VEC3"},
    {"bufferView": )" + std::to_string(uv) +
                           R"(, "componentType": 5126, "count": 4, "type": "VEC2"},
    {"bufferView": )" + std::to_string(indices) +
                           R"(, "componentType": 5123, "count": 6, "type": "SCALAR"}],
  )" + b.json() + "}";
  std::vector<std::string> warnings;
  SceneDescription desc = load_gltf_from_string(json, "", "shadow.gltf", &warnings);
  for (const auto& w : warnings) ADD_FAILURE() << "unexpected warning: " << w;
  desc.camera = testing::look_at({0.f, -2.f, 0.2f}, {0.f, 0.f, 0.f}, 1e-3f);
  Scene scene(std::move(desc));
  RenderSettings settings;
  settings.width = settings.height = 1;
  settings.seed = 5;
  const uint32_t spp = 8192;
  TileBuffer tile;
  EXPECT_TRUE(render_rect(scene, settings, {0, 0, 1, 1}, 0, spp, &tile));
  *standard_error = std::sqrt(tile.luminance_m2[0] / (spp - 1) / spp);
  return tile.rgb_sum[0] / spp;
}

TEST(AlphaMode, ShadowRaysPassCutOutTexelsAndBlendedSurfaces) {
  const double rho = 0.5, L = 3.0;
  const double quarter = form_factor_corner(0.5, 0.5, 1.0);  // a quarter of the emitter
  double se = 0.0;
  // MASK: the occluder is cut out for x < 0, and every line from the floor point to the
  // emitter's half x < 0 crosses it there (at x / 2): that half lights the point, the other is
  // blocked.
  const double mask =
      shadowed_floor(black_material(kMask, "1", true), kHalfCutTexture + half_cut_image(), &se);
  const double half = rho * L * 2.0 * quarter;
  EXPECT_LT(se, 0.02 * half) << "test would have no power";
  EXPECT_NEAR(mask, half, 4.0 * se + 1e-4 * half);
  // BLEND of alpha 0.25 over the whole emitter: 3/4 of the light gets through.
  const double blend = shadowed_floor(
      R"({"alphaMode": "BLEND", "pbrMetallicRoughness": {"baseColorFactor": [0, 0, 0, 0.25],
         "metallicFactor": 0}, "extensions": {"KHR_materials_specular": {"specularFactor": 0}}})",
      "", &se);
  const double three_quarters = 0.75 * rho * L * 4.0 * quarter;
  EXPECT_LT(se, 0.02 * three_quarters) << "test would have no power";
  EXPECT_NEAR(blend, three_quarters, 4.0 * se + 1e-4 * three_quarters);
}

// Coverage is baseColorFactor.a x baseColorTexture.a x COLOR_0.a; MASK compares it with the
// cutoff (>= is opaque); opaque materials cover fully whatever their alpha.
TEST(AlphaMode, CoverageMultipliesFactorTextureAndVertexAlpha) {
  GltfBuffer b;
  const int positions = b.add(kQuadPositions);
  const int uv = b.add(kQuadUv);
  const int indices = b.add(kQuadIndices);
  const int colors = b.add(std::vector<float>{1, 1, 1, 0.5f, 1, 1, 1, 0.5f,  //
                                              1, 1, 1, 0.5f, 1, 1, 1, 0.5f});
  // One texel of alpha 102 (0.4).
  const std::string image = testing::png_data_uri(1, 1, 4, {255, 255, 255, 102});
  auto scene_with = [&](const std::string& mode) {
    const std::string json = R"({"asset": {"version": "2.0"}, "scene": 0,
    "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
    "materials": [{)" + mode + R"("pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 0.8],
                   "baseColorTexture": {"index": 0}}}],
    "textures": [{"source": 0}], "images": [{"uri": ")" + image + R"("}],
    "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1, "COLOR_0": 3},
                                "indices": 2, "material": 0}]}],
    "accessors": [
      {"bufferView": )" + std::to_string(positions) +
                             R"(, "componentType": 5126, "count": 4, "type": "VEC3"},
      {"bufferView": )" + std::to_string(uv) +
                             R"(, "componentType": 5126, "count": 4, "type": "VEC2"},
      {"bufferView": )" + std::to_string(indices) +
                             R"(, "componentType": 5123, "count": 6, "type": "SCALAR"},
      {"bufferView": )" + std::to_string(colors) +
                             R"(, "componentType": 5126, "count": 4, "type": "VEC4"}],
    )" + b.json() + "}";
    return std::make_unique<Scene>(load_gltf_from_string(json, "", "coverage.gltf", nullptr));
  };
  const double alpha = 0.8 * (102.0 / 255.0) * 0.5;  // 0.16
  EXPECT_NEAR(scene_with(R"("alphaMode": "BLEND",)")->coverage(kWorldSlot, 0, 0.2f, 0.3f), alpha,
              1e-6);
  EXPECT_EQ(scene_with(R"("alphaMode": "MASK", "alphaCutoff": 0.15,)")
                ->coverage(kWorldSlot, 1, 0.2f, 0.3f),
            1.f);
  EXPECT_EQ(scene_with(R"("alphaMode": "MASK", "alphaCutoff": 0.17,)")
                ->coverage(kWorldSlot, 1, 0.2f, 0.3f),
            0.f);
  EXPECT_EQ(scene_with("")->coverage(kWorldSlot, 0, 0.2f, 0.3f), 1.f);
  // An alphaMode that glTF does not define is refused.
  EXPECT_THROW(scene_with(R"("alphaMode": "ADD",)"), SceneError);
}

// A gray-and-alpha image (two channels) gives its gray to red, green and blue and its second
// channel as alpha.
TEST(AlphaMode, GrayAndAlphaImagesGiveTheirSecondChannelAsAlpha) {
  GltfBuffer b;
  const int positions = b.add(kQuadPositions);
  const int uv = b.add(kQuadUv);
  const int indices = b.add(kQuadIndices);
  const std::string image = testing::png_data_uri(1, 1, 2, {188, 102});
  const std::string json = R"({"asset": {"version": "2.0"}, "scene": 0,
  "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
  "materials": [{"alphaMode": "BLEND", "pbrMetallicRoughness": {"baseColorTexture": {"index": 0},
                 "metallicFactor": 0}}],
  "textures": [{"source": 0}], "images": [{"uri": ")" + image + R"("}],
  "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2,
                              "material": 0}]}],
  "accessors": [
    {"bufferView": )" + std::to_string(positions) +
                           R"(, "componentType": 5126, "count": 4, "type": "VEC3"},
    {"bufferView": )" + std::to_string(uv) +
                           R"(, "componentType": 5126, "count": 4, "type": "VEC2"},
    {"bufferView": )" + std::to_string(indices) +
                           R"(, "componentType": 5123, "count": 6, "type": "SCALAR"}],
  )" + b.json() + "}";
  const Scene scene(load_gltf_from_string(json, "", "gray.gltf", nullptr));
  EXPECT_NEAR(scene.coverage(kWorldSlot, 0, 0.3f, 0.3f), 102.0 / 255.0, 1e-6);
  // sRGB 188 is linear ((188 / 255 + 0.055) / 1.055)^2.4 in every channel.
  const double gray = std::pow((188.0 / 255.0 + 0.055) / 1.055, 2.4);
  float c[4];
  ASSERT_TRUE(scene.textures().lookup(0, {0.5f, 0.5f}, 4, c));  // the base colour: linear
  for (int k = 0; k < 3; ++k) EXPECT_NEAR(c[k], gray, 1e-6) << k;
  EXPECT_NEAR(c[3], 102.0 / 255.0, 1e-6);
}

// A texture's colours are not premultiplied by its alpha: an opaque material (which ignores
// alpha) shows the texel's colour whatever its alpha.
TEST(AlphaMode, OpaqueMaterialsShowTexelColoursWhateverTheirAlpha) {
  const std::string image = testing::png_data_uri(1, 1, 4, {200, 100, 50, 51});
  const std::string json = R"({"asset": {"version": "2.0"}, "scene": 0,
  "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
  "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2},
                              "indices": 3, "material": 0}]}],
  "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0},
                 "metallicFactor": 0}}],
  "textures": [{"source": 0}], "images": [{"uri": ")" + image + R"("}],
  )" + testing::quad_gltf_buffers_json() + "}";
  auto linear = [](double c) { return std::pow((c / 255.0 + 0.055) / 1.055, 2.4); };
  expect_near(albedo_at(json, 0.2f, 0.3f),
              {float(linear(200)), float(linear(100)), float(linear(50))}, 1e-5f, "texel");
}

// ---- KHR_materials_volume.

// An orthographic camera looks down -z through a glass slab (a closed box, z in [-2 - L, -2],
// ior 1: no refraction, no Fresnel reflection) at an emitter of radiance 2. Every pixel is
// 2 T, with T the Beer-Lambert transmittance over the slab's thickness L: the extension's
// attenuationColor^(L / attenuationDistance) per channel.
std::string slab_scene(const std::string& volume) {
  const float L = 0.5f;
  const float z0 = -2.f, z1 = -2.f - L;
  GltfBuffer b;
  // The box's 8 corners; faces wound counter-clockwise seen from outside.
  const std::vector<float> corners = {-1, -1, z0, 1, -1, z0, 1, 1, z0, -1, 1, z0,
                                      -1, -1, z1, 1, -1, z1, 1, 1, z1, -1, 1, z1};
  const std::vector<uint16_t> box = {0, 1, 2, 0, 2, 3,  5, 4, 7, 5, 7, 6,  4, 0, 3, 4, 3, 7,
                                     1, 5, 6, 1, 6, 2,  3, 2, 6, 3, 6, 7,  4, 5, 1, 4, 1, 0};
  const std::vector<float> emitter = {-3, -3, -5, 3, -3, -5, 3, 3, -5, -3, 3, -5};
  const int corner_view = b.add(corners), box_view = b.add(box);
  const int emitter_view = b.add(emitter), quad_view = b.add(kQuadIndices);
  return R"({"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0, 1, 2]}],
  "nodes": [{"camera": 0}, {"mesh": 0}, {"mesh": 1}],
  "cameras": [{"type": "orthographic",
               "orthographic": {"xmag": 0.5, "ymag": 0.5, "znear": 0.01, "zfar": 100}}],
  "extensionsUsed": ["KHR_materials_transmission", "KHR_materials_ior",
                     "KHR_materials_volume", "KHR_materials_emissive_strength"],
  "materials": [
    {"pbrMetallicRoughness": {"metallicFactor": 0, "roughnessFactor": 0},
     "extensions": {"KHR_materials_transmission": {"transmissionFactor": 1},
                    "KHR_materials_ior": {"ior": 1.0}, "KHR_materials_volume": )" +
         volume + R"(}},
    {"pbrMetallicRoughness": {"baseColorFactor": [0, 0, 0, 1], "metallicFactor": 0},
     "emissiveFactor": [1, 1, 1],
     "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 2}}}],
  "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "material": 0}]},
             {"primitives": [{"attributes": {"POSITION": 2}, "indices": 3, "material": 1}]}],
  "accessors": [
    {"bufferView": )" + std::to_string(corner_view) +
         R"(, "componentType": 5126, "count": 8, "type": "VEC3"},
    {"bufferView": )" + std::to_string(box_view) +
         R"(, "componentType": 5123, "count": 36, "type": "SCALAR"},
    {"bufferView": )" + std::to_string(emitter_view) +
         R"(, "componentType": 5126, "count": 4, "type": "VEC3"},
    {"bufferView": )" + std::to_string(quad_view) +
         R"(, "componentType": 5123, "count": 6, "type": "SCALAR"}],
  )" + b.json() + "}";
}

// The scene's 8 x 8 image, 4 samples per pixel, as RGB means.
std::vector<Vec3> render_rgb(const Scene& scene) {
  RenderSettings settings;
  settings.width = settings.height = 8;
  TileBuffer tile;
  EXPECT_TRUE(render_rect(scene, settings, {0, 0, 8, 8}, 0, 4, &tile));
  std::vector<Vec3> out(64);
  for (size_t i = 0; i < 64; ++i)
    out[i] = Vec3(float(tile.rgb_sum[3 * i] / 4), float(tile.rgb_sum[3 * i + 1] / 4),
                  float(tile.rgb_sum[3 * i + 2] / 4));
  return out;
}

TEST(MaterialsVolume, ASlabAttenuatesByBeerLambertOverItsThickness) {
  const double color[3] = {0.5, 0.25, 0.8}, distance = 0.4, thickness = 0.5;
  std::vector<std::string> warnings;
  const Scene scene(load_gltf_from_string(slab_scene(R"({"thicknessFactor": 0.5,
      "attenuationDistance": 0.4, "attenuationColor": [0.5, 0.25, 0.8]})"),
                                          "", "slab.gltf", &warnings),
                    &warnings);
  EXPECT_TRUE(warnings.empty()) << warnings.front();
  // To 3e-4 relative: the ray inside starts a ray epsilon (about 1e-4) past the entry face, so
  // the length it measures is short by that much.
  for (const Vec3& c : render_rgb(scene))
    for (int k = 0; k < 3; ++k) {
      const double expected = 2.0 * std::pow(color[k], thickness / distance);
      EXPECT_NEAR(c[k], expected, 3e-4 * expected) << k;
    }
  // Thin-walled (thicknessFactor 0, the default) and without attenuationDistance (infinite:
  // clear): the emitter unattenuated.
  for (const char* clear : {R"({"attenuationDistance": 0.4, "attenuationColor": [0.5, 0.25, 0.8]})",
                            R"({"thicknessFactor": 0.5, "attenuationColor": [0.5, 0.25, 0.8]})"}) {
    const Scene thin(load_gltf_from_string(slab_scene(clear), "", "slab.gltf", nullptr));
    for (const Vec3& c : render_rgb(thin))
      for (int k = 0; k < 3; ++k) EXPECT_NEAR(c[k], 2.0, 2e-5) << clear;
  }
}

TEST(MaterialsVolume, InvalidParametersAreRefusedNamingTheField) {
  const std::string at = "materials[0].extensions.KHR_materials_volume";
  EXPECT_EQ(refusal(slab_scene(R"({"thicknessFactor": 1, "attenuationDistance": 0})")),
            at + ".attenuationDistance");
  EXPECT_EQ(refusal(slab_scene(R"({"thicknessFactor": -1})")), at + ".thicknessFactor");
  EXPECT_EQ(refusal(slab_scene(R"({"thicknessFactor": 1, "attenuationColor": [0.5, 2, 0.5]})")),
            at + ".attenuationColor");
  EXPECT_EQ(refusal(slab_scene(R"({"thicknessFactor": 1, "attenuationColor": [0.5]})")),
            at + ".attenuationColor");
}

// ---- Textures: a pixel converges to the integral of the (linear) texture over it.

// The first-hit albedo of an 8 x 8 image of the unit quad seen through an orthographic camera
// that frames it exactly, its base colour a 16 x 16 grey texture (sRGB-encoded bytes, as glTF
// base colour textures are): every pixel covers 2 x 2 texels.
std::vector<double> albedo_image(const std::vector<unsigned char>& texels, uint32_t spp,
                                 const std::string& sampler = "{}") {
  const std::string json = R"({"asset": {"version": "2.0"}, "scene": 0,
  "scenes": [{"nodes": [0, 1]}],
  "nodes": [{"mesh": 0}, {"camera": 0, "translation": [0, 0, 2]}],
  "cameras": [{"type": "orthographic",
               "orthographic": {"xmag": 1, "ymag": 1, "znear": 0.1, "zfar": 10}}],
  "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2},
                              "indices": 3, "material": 0}]}],
  "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0},
                 "metallicFactor": 0}}],
  "textures": [{"source": 0, "sampler": 0}], "samplers": [)" + sampler + R"(],
  "images": [{"uri": ")" + testing::png_data_uri(16, 16, 1, texels) + R"("}],
  )" + testing::quad_gltf_buffers_json() + "}";
  const Scene scene(load_gltf_from_string(json, "", "texels.gltf", nullptr));
  RenderSettings settings;
  settings.width = settings.height = 8;
  settings.integrator = IntegratorType::AmbientOcclusion;
  TileBuffer tile;
  EXPECT_TRUE(render_rect(scene, settings, {0, 0, 8, 8}, 0, spp, &tile));
  std::vector<double> out(64);
  for (size_t i = 0; i < 64; ++i) out[i] = double(tile.sum(channels::Id::Albedo)[3 * i]) / spp;
  return out;
}

// A black and white checker of single texels: each pixel holds two of each, so it converges
// to their mean in linear light, 0.5 (bilinear filtering moves 1/8 of a texel's weight across
// each pixel edge, in both directions alike). Decoding sRGB after filtering would give the
// decoded mean of the encoded values, srgb_to_linear(0.5) = 0.21.
TEST(Textures, ACheckerOfTexelsConvergesToItsLinearMean) {
  std::vector<unsigned char> checker(256);
  for (int y = 0; y < 16; ++y)
    for (int x = 0; x < 16; ++x) checker[size_t(y * 16 + x)] = (x + y) % 2 ? 255 : 0;
  for (double v : albedo_image(checker, 256)) EXPECT_NEAR(v, 0.5, 0.01);
}

// A white line one texel wide (column 5) on black: pixel column 2 covers texel columns 4 and
// 5. Bilinear reconstruction (the texture function the glTF LINEAR filter defines) spreads
// the texel as a tent of two texels; 7/8 of it lies in pixel column 2 and 1/8 in column 3, so
// the pixels converge to 7/16 and 1/16 (and 0 elsewhere): no wider blur than that.
TEST(Textures, AOneTexelLineConvergesToItsReconstructionsIntegral) {
  std::vector<unsigned char> line(256, 0);
  for (int y = 0; y < 16; ++y) line[size_t(y * 16 + 5)] = 255;
  const std::vector<double> image = albedo_image(line, 256);
  for (int y = 0; y < 8; ++y)
    for (int x = 0; x < 8; ++x) {
      const double expected = x == 2 ? 7.0 / 16.0 : x == 3 ? 1.0 / 16.0 : 0.0;
      EXPECT_NEAR(image[size_t(y * 8 + x)], expected, 0.01) << x << "," << y;
    }
  // A sampler with magFilter NEAREST (9728) makes the texture the texels themselves: the line
  // is half of pixel column 2 and nothing of the others.
  const std::vector<double> nearest = albedo_image(line, 256, R"({"magFilter": 9728})");
  for (int y = 0; y < 8; ++y)
    for (int x = 0; x < 8; ++x)
      EXPECT_NEAR(nearest[size_t(y * 8 + x)], x == 2 ? 0.5 : 0.0, 0.01) << x << "," << y;
}

// ---- doubleSided emitters (glTF 3.9.5: the back face is lit, and so emits, as the front).

// A white diffuse floor (z = 0, [-1, 1]^2, seen from above by an orthographic camera) under an
// emissive quad at z = 0.5 whose front face looks up, away from the floor: only a double-sided
// one lights the floor. The same quad wound the other way (its front face down) is the
// reference: the floor must be as bright, through light sampling and BSDF sampling alike.
std::string emitter_scene(bool front_down, bool double_sided) {
  GltfBuffer b;
  const std::vector<float> floor = {-1, -1, 0, 1, -1, 0, 1, 1, 0, -1, 1, 0};
  const std::vector<float> lamp = {-0.3f, -0.3f, 0.5f, 0.3f, -0.3f, 0.5f,
                                   0.3f,  0.3f,  0.5f, -0.3f, 0.3f, 0.5f};
  const std::vector<uint16_t> up = {0, 1, 2, 0, 2, 3}, down = {0, 2, 1, 0, 3, 2};
  const int floor_view = b.add(floor), lamp_view = b.add(lamp);
  const int up_view = b.add(up), lamp_index = b.add(front_down ? down : up);
  return R"({"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0, 1, 2]}],
  "nodes": [{"mesh": 0}, {"mesh": 1},
            {"camera": 0, "translation": [0, 0, 3]}],
  "cameras": [{"type": "orthographic",
               "orthographic": {"xmag": 1, "ymag": 1, "znear": 0.1, "zfar": 10}}],
  "materials": [
    {"pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 1], "metallicFactor": 0},
     "extensions": {"KHR_materials_specular": {"specularFactor": 0}}},
    {"pbrMetallicRoughness": {"baseColorFactor": [0, 0, 0, 1], "metallicFactor": 0},
     "emissiveFactor": [1, 1, 1], "doubleSided": )" +
         std::string(double_sided ? "true" : "false") + R"(,
     "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 3},
                    "KHR_materials_specular": {"specularFactor": 0}}}],
  "extensionsUsed": ["KHR_materials_emissive_strength", "KHR_materials_specular"],
  "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 2, "material": 0}]},
             {"primitives": [{"attributes": {"POSITION": 1}, "indices": 3, "material": 1}]}],
  "accessors": [
    {"bufferView": )" + std::to_string(floor_view) +
         R"(, "componentType": 5126, "count": 4, "type": "VEC3"},
    {"bufferView": )" + std::to_string(lamp_view) +
         R"(, "componentType": 5126, "count": 4, "type": "VEC3"},
    {"bufferView": )" + std::to_string(up_view) +
         R"(, "componentType": 5123, "count": 6, "type": "SCALAR"},
    {"bufferView": )" + std::to_string(lamp_index) +
         R"(, "componentType": 5123, "count": 6, "type": "SCALAR"}],
  )" + b.json() + "}";
}

double floor_mean(const std::string& json, IntegratorType integrator) {
  const Scene scene(load_gltf_from_string(json, "", "emitter.gltf", nullptr));
  RenderSettings settings;
  settings.width = settings.height = 8;
  settings.integrator = integrator;
  TileBuffer tile;
  EXPECT_TRUE(render_rect(scene, settings, {0, 0, 8, 8}, 0, 256, &tile));
  double sum = 0.0;
  for (int y = 0; y < 8; ++y)
    for (int x = 0; x < 8; ++x) {
      // Pixels not under the lamp (whose black back or front hides the floor there).
      if (x >= 2 && x < 6 && y >= 2 && y < 6) continue;
      sum += tile.rgb_sum[3 * size_t(y * 8 + x)];
    }
  return sum / (48.0 * 256.0);
}

TEST(DoubleSided, TheBackFaceOfADoubleSidedEmitterEmitsLikeItsFront) {
  for (IntegratorType integrator : {IntegratorType::Direct, IntegratorType::Path}) {
    const double reference = floor_mean(emitter_scene(true, false), integrator);
    EXPECT_GT(reference, 0.05);
    EXPECT_NEAR(floor_mean(emitter_scene(false, true), integrator), reference,
                0.02 * reference);
    // Single-sided and facing away: the floor gets nothing from it.
    EXPECT_EQ(floor_mean(emitter_scene(false, false), integrator), 0.0);
  }
  // Seen from behind by the camera, the double-sided lamp shows its radiance (3), the
  // single-sided one is black.
  auto centre = [](const std::string& json) {
    const Scene scene(load_gltf_from_string(json, "", "emitter.gltf", nullptr));
    RenderSettings settings;
    settings.width = settings.height = 8;
    TileBuffer tile;
    EXPECT_TRUE(render_rect(scene, settings, {3, 3, 1, 1}, 0, 4, &tile));
    return tile.rgb_sum[0] / 4.0;
  };
  EXPECT_NEAR(centre(emitter_scene(true, true)), 3.0, 1e-5);
  EXPECT_EQ(centre(emitter_scene(true, false)), 0.0);
}

// ---- KHR_node_visibility: a hidden node renders nothing below it, not even a descendant
// whose own `visible` is true; its light is off; a camera below it still frames the image.

std::string visibility_scene(const std::string& hidden) {
  return R"({"asset": {"version": "2.0"},
  "extensionsUsed": ["KHR_node_visibility", "KHR_lights_punctual"],
  "extensions": {"KHR_lights_punctual": {"lights": [{"type": "point", "intensity": 5}]}},
  "scene": 0, "scenes": [{"nodes": [0, 1]}],
  "nodes": [{"mesh": 0},
            {"children": [2, 3], "translation": [0, 0, 3], )" + hidden + R"(},
            {"mesh": 1, "extensions": {"KHR_node_visibility": {"visible": true}}},
            {"camera": 0, "extensions": {"KHR_lights_punctual": {"light": 0}}}],
  "cameras": [{"type": "perspective", "perspective": {"yfov": 0.5, "znear": 0.01}}],
  "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1}, "indices": 3}]},
             {"primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1}, "indices": 3}]}],
  )" + testing::quad_gltf_buffers_json() + "}";
}

TEST(NodeVisibility, AHiddenNodeHidesItsSubtreeButNotItsCamera) {
  std::vector<std::string> warnings;
  const SceneDescription shown = load_gltf_from_string(
      visibility_scene(R"("extensions": {"KHR_node_visibility": {"visible": true}})"), "",
      "visibility.gltf", &warnings);
  EXPECT_EQ(shown.world.size(), 4u);  // both quads
  EXPECT_EQ(shown.punctual_lights.size(), 1u);
  const SceneDescription hidden = load_gltf_from_string(
      visibility_scene(R"("extensions": {"KHR_node_visibility": {"visible": false}})"), "",
      "visibility.gltf", &warnings);
  EXPECT_EQ(hidden.world.size(), 2u);  // the root's quad only
  EXPECT_TRUE(hidden.instances.empty());
  EXPECT_TRUE(hidden.punctual_lights.empty());
  ASSERT_TRUE(hidden.camera.has_value());  // the camera below the hidden node
  EXPECT_NEAR(hidden.camera->position.z, 3.f, 1e-6f);
  for (const auto& w : warnings)
    EXPECT_EQ(w.find("KHR_node_visibility"), std::string::npos) << "supported: " << w;
  std::string message;
  EXPECT_EQ(refusal(visibility_scene(R"("extensions": {"KHR_node_visibility": {"visible": 0}})"),
                    &message),
            "nodes[1].extensions.KHR_node_visibility.visible")
      << message;
}

// ---- EXT_mesh_gpu_instancing: the node's mesh once, drawn at node x T R S of each instance.

// The unit quad under a node at (0, 0, -1) with three instances: (1) moved by (3, 0, 0);
// (2) turned a quarter about +z (ROTATION as normalized shorts when `short_rotation`);
// (3) scaled by 2 and moved by (0, 3, 0).
std::string gpu_instancing_scene(bool short_rotation, size_t scale_count = 3) {
  GltfBuffer b;
  const int positions = b.add(kQuadPositions);
  const int indices = b.add(kQuadIndices);
  const int translation = b.add(std::vector<float>{3, 0, 0, 0, 0, 0, 0, 3, 0});
  const float h = std::sqrt(0.5f);
  const int rotation =
      short_rotation
          ? b.add(std::vector<int16_t>{0, 0, 0, 32767, 0, 0, 23170, 23170, 0, 0, 0, 32767})
          : b.add(std::vector<float>{0, 0, 0, 1, 0, 0, h, h, 0, 0, 0, 1});
  std::vector<float> scales = {1, 1, 1, 1, 1, 1, 2, 2, 2, 1, 1, 1};
  scales.resize(3 * scale_count);
  const int scale = b.add(scales);
  return R"({"asset": {"version": "2.0"},
  "extensionsUsed": ["EXT_mesh_gpu_instancing"],
  "extensionsRequired": ["EXT_mesh_gpu_instancing"],
  "scene": 0, "scenes": [{"nodes": [0]}],
  "nodes": [{"mesh": 0, "translation": [0, 0, -1], "extensions": {"EXT_mesh_gpu_instancing":
      {"attributes": {"TRANSLATION": 2, "ROTATION": 3, "SCALE": 4}}}}],
  "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
  "accessors": [
    {"bufferView": )" + std::to_string(positions) + R"(, "componentType": 5126, "count": 4,
     "type": "VEC3", "min": [-1, -1, 0], "max": [1, 1, 0]},
    {"bufferView": )" + std::to_string(indices) + R"(, "componentType": 5123, "count": 6,
     "type": "SCALAR"},
    {"bufferView": )" + std::to_string(translation) + R"(, "componentType": 5126, "count": 3,
     "type": "VEC3"},
    {"bufferView": )" + std::to_string(rotation) + R"(, "componentType": )" +
         (short_rotation ? "5122, \"normalized\": true" : "5126") + R"(, "count": 3,
     "type": "VEC4"},
    {"bufferView": )" + std::to_string(scale) + R"(, "componentType": 5126, "count": )" +
         std::to_string(scale_count) + R"(, "type": "VEC3"}],
  )" + b.json() + "}";
}

TEST(GpuInstancing, EachInstanceDrawsTheMeshAtNodeTimesItsTrs) {
  for (bool short_rotation : {false, true}) {
    const SceneDescription desc =
        load_gltf_from_string(gpu_instancing_scene(short_rotation), "", "forest.gltf", nullptr);
    ASSERT_EQ(desc.meshes.size(), 1u);  // the mesh once
    EXPECT_EQ(desc.meshes[0].geometry.size(), 2u);
    EXPECT_TRUE(desc.world.empty());  // not also drawn at the node itself
    ASSERT_EQ(desc.instances.size(), 3u);
    EXPECT_EQ(desc.stats.instanced_triangles, 6u);
    // The quad's corner (1, 1, 0) in each instance, by hand: node (0, 0, -1) + T + R S p.
    const Vec3 want[3] = {{4, 1, -1}, {-1, 1, -1}, {2, 5, -1}};
    for (size_t i = 0; i < 3; ++i) {
      const Vec3 got = desc.instances[i].to_world.transform_point({1.f, 1.f, 0.f});
      // A normalized short quaternion holds 1/32767 of precision.
      const float tol = short_rotation ? 1e-4f : 1e-6f;
      for (int c = 0; c < 3; ++c)
        EXPECT_NEAR(got[c], want[i][c], tol) << "instance " << i << " short " << short_rotation;
    }
  }
}

TEST(GpuInstancing, AttributesOfDifferentCountsAreRefusedNamingThem) {
  std::string message;
  EXPECT_EQ(refusal(gpu_instancing_scene(false, 4), &message),
            "nodes[0].extensions.EXT_mesh_gpu_instancing.attributes.SCALE")
      << message;
}

// ---- KHR_materials_variants: a variant (by name or index) gives the primitives that map it
// their mapped material; the others, and a load without a variant, keep their own.

std::string variants_scene(const std::string& mappings = R"([{"material": 1, "variants": [0]},
                                                           {"material": 2, "variants": [1, 2]}])") {
  return R"({"asset": {"version": "2.0"},
  "extensionsUsed": ["KHR_materials_variants"],
  "extensions": {"KHR_materials_variants": {"variants": [{"name": "Blue"}, {"name": "Green"},
                                                        {"name": "Lime"}]}},
  "scene": 0, "scenes": [{"nodes": [0, 1]}],
  "nodes": [{"mesh": 0}, {"mesh": 1, "translation": [3, 0, 0]}],
  "materials": [{"name": "red"}, {"name": "blue"}, {"name": "green"}, {"name": "grey"}],
  "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 3, "material": 0,
                              "extensions": {"KHR_materials_variants": {"mappings": )" +
         mappings + R"(}}}]},
             {"primitives": [{"attributes": {"POSITION": 0}, "indices": 3, "material": 3}]}],
  )" + testing::quad_gltf_buffers_json() + "}";
}

TEST(MaterialVariants, AVariantGivesThePrimitivesThatMapItTheirMaterial) {
  auto materials = [](const std::string& variant) {
    LoadOptions options;
    options.variant = variant;
    const SceneDescription desc =
        load_gltf_from_string(variants_scene(), "", "variants.gltf", nullptr, options);
    std::vector<std::string> names;
    for (uint32_t m : desc.world.material) names.push_back(desc.materials[m].name);
    return names;
  };
  using V = std::vector<std::string>;
  EXPECT_EQ(materials(""), (V{"red", "red", "grey", "grey"}));  // the default materials
  EXPECT_EQ(materials("Blue"), (V{"blue", "blue", "grey", "grey"}));
  EXPECT_EQ(materials("1"), (V{"green", "green", "grey", "grey"}));  // by index
  EXPECT_EQ(materials("Lime"), (V{"green", "green", "grey", "grey"}));
  std::string message;
  try {
    materials("Purple");
    ADD_FAILURE() << "an unknown variant was accepted";
  } catch (const SceneError& e) {
    message = e.what();
    EXPECT_EQ(e.path(), "extensions.KHR_materials_variants");
  }
  EXPECT_NE(message.find("'Purple'"), std::string::npos) << message;
  EXPECT_NE(message.find("0 'Blue'"), std::string::npos) << message;
  // Malformed mappings are refused by path, whatever the variant.
  EXPECT_EQ(refusal(variants_scene(R"([{"material": 9, "variants": [0]}])"), &message),
            "meshes[0].primitives[0].extensions.KHR_materials_variants.mappings[0].material")
      << message;
  EXPECT_EQ(refusal(variants_scene(R"([{"material": 1, "variants": [5]}])"), &message),
            "meshes[0].primitives[0].extensions.KHR_materials_variants.mappings[0].variants[0]")
      << message;
}

}  // namespace
}  // namespace rf
