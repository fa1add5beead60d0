// Compressed meshes through the loader: EXT_meshopt_compression buffer views (vertex and index
// codecs, the octahedral filter, a fallback buffer without data) and KHR_draco_mesh_compression
// primitives. Each compressed scene is written here with the libraries' own encoders from a
// known mesh, and the loaded geometry is compared with that mesh (exactly where the codec is
// lossless) or with the same scene written uncompressed. Malformed compressed data is refused
// with the glTF path of the bad part.
#include <draco/compression/encode.h>
#include <draco/mesh/triangle_soup_mesh_builder.h>
#include <gtest/gtest.h>
#include <meshoptimizer.h>

#include <nlohmann/json.hpp>

#include <algorithm>
#include <array>
#include <cmath>
#include <string>
#include <vector>

#include "scene/scene.h"
#include "testing/test_scenes.h"

namespace rf {
namespace {

// A 6x5 grid of vertices on a bumpy surface (positions are not round numbers, so a lossy codec
// could not pass for lossless), unit normals, texture coordinates, two triangles a cell.
struct Grid {
  static constexpr int kX = 6, kY = 5;
  std::vector<float> positions, normals, uv;
  std::vector<uint32_t> indices;
  Grid() {
    for (int y = 0; y < kY; ++y)
      for (int x = 0; x < kX; ++x) {
        const float px = -1.f + 2.f * float(x) / (kX - 1) + 0.0123f * float(y);
        const float py = -1.f + 2.f * float(y) / (kY - 1);
        const float pz = 0.1f * std::sin(3.1f * px) * std::cos(2.3f * py);
        positions.insert(positions.end(), {px, py, pz});
        float n[3] = {-0.31f * std::cos(3.1f * px) * std::cos(2.3f * py),
                      0.23f * std::sin(3.1f * px) * std::sin(2.3f * py), 1.f};
        const float len = std::sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
        normals.insert(normals.end(), {n[0] / len, n[1] / len, n[2] / len});
        uv.insert(uv.end(), {float(x) / (kX - 1), 1.f - float(y) / (kY - 1)});
      }
    for (int y = 0; y + 1 < kY; ++y)
      for (int x = 0; x + 1 < kX; ++x) {
        const uint32_t a = uint32_t(y * kX + x), b = a + 1, c = a + kX, d = c + 1;
        indices.insert(indices.end(), {a, b, d, a, d, c});
      }
  }
  size_t vertices() const { return positions.size() / 3; }
};

template <typename T>
void append(std::vector<unsigned char>* bytes, const std::vector<T>& values) {
  while (bytes->size() % 4) bytes->push_back(0);
  const auto* p = reinterpret_cast<const unsigned char*>(values.data());
  bytes->insert(bytes->end(), p, p + values.size() * sizeof(T));
}

std::string base64_buffer(const std::vector<unsigned char>& bytes) {
  return R"({"byteLength": )" + std::to_string(bytes.size()) + R"(, "uri": ")" +
         testing::data_uri("application/octet-stream", bytes) + R"("})";
}

// The scene around one primitive: a node with the mesh, a default material.
std::string scene_json(const std::string& attributes, int indices, const std::string& rest,
                       const std::string& prim_ext = "", const std::string& used = "") {
  return R"({"asset": {"version": "2.0"}, )" + used +
         R"("scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
    "meshes": [{"primitives": [{"attributes": )" +
         attributes + (indices >= 0 ? R"(, "indices": )" + std::to_string(indices) : "") +
         prim_ext + R"(}]}], )" +
         rest + "}";
}

std::string accessors_json(size_t vertices, size_t indices, int index_type = 5125,
                           bool views = true) {
  auto view = [&](int v) { return views ? R"("bufferView": )" + std::to_string(v) + ", " : ""; };
  return R"("accessors": [
    {)" + view(0) + R"("componentType": 5126, "count": )" +
         std::to_string(vertices) + R"(, "type": "VEC3", "min": [-2, -2, -1], "max": [2, 2, 1]},
    {)" + view(1) + R"("componentType": 5126, "count": )" +
         std::to_string(vertices) + R"(, "type": "VEC3"},
    {)" + view(2) + R"("componentType": 5126, "count": )" +
         std::to_string(vertices) + R"(, "type": "VEC2"},
    {)" + view(3) + R"("componentType": )" + std::to_string(index_type) +
         R"(, "count": )" + std::to_string(indices) + R"(, "type": "SCALAR"}])";
}

const std::string kAttributes = R"({"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2})";

// The grid written plainly: the reference every decoded scene must match.
std::string plain_json(const Grid& g) {
  std::vector<unsigned char> bytes;
  std::vector<size_t> offsets;
  for (const std::vector<float>* a : {&g.positions, &g.normals, &g.uv}) {
    while (bytes.size() % 4) bytes.push_back(0);
    offsets.push_back(bytes.size());
    append(&bytes, *a);
  }
  offsets.push_back(bytes.size());
  append(&bytes, g.indices);
  const size_t lengths[4] = {g.positions.size() * 4, g.normals.size() * 4, g.uv.size() * 4,
                             g.indices.size() * 4};
  std::string views;
  for (int i = 0; i < 4; ++i)
    views += std::string(i ? ", " : "") + R"({"buffer": 0, "byteOffset": )" +
             std::to_string(offsets[size_t(i)]) + R"(, "byteLength": )" +
             std::to_string(lengths[i]) + "}";
  return scene_json(kAttributes, 3,
                    accessors_json(g.vertices(), g.indices.size()) + R"(, "bufferViews": [)" +
                        views + R"(], "buffers": [)" + base64_buffer(bytes) + "]");
}

// The grid with every buffer view meshopt-compressed into buffer 0, decoded into buffer 1 (a
// fallback without data, as gltfpack writes it). `index_mode` TRIANGLES or INDICES;
// `octahedral`: normals as 8-bit octahedral (the OCTAHEDRAL filter, 4-byte elements) instead
// of floats.
std::string meshopt_json(const Grid& g, const std::string& index_mode, bool octahedral,
                         std::string* compressed_view_json = nullptr) {
  std::vector<unsigned char> packed;
  std::string views;
  size_t target = 0;
  auto add = [&](const void* data, size_t count, size_t stride, const std::string& mode,
                 const std::string& filter) {
    std::vector<unsigned char> out;
    size_t size = 0;
    if (mode == "ATTRIBUTES") {
      out.resize(meshopt_encodeVertexBufferBound(count, stride));
      size = meshopt_encodeVertexBuffer(out.data(), out.size(), data, count, stride);
    } else {
      const auto* idx = static_cast<const unsigned int*>(data);
      if (mode == "TRIANGLES") {
        out.resize(meshopt_encodeIndexBufferBound(count, g.vertices()));
        size = meshopt_encodeIndexBuffer(out.data(), out.size(), idx, count);
      } else {
        out.resize(meshopt_encodeIndexSequenceBound(count, g.vertices()));
        size = meshopt_encodeIndexSequence(out.data(), out.size(), idx, count);
      }
    }
    EXPECT_GT(size, 0u);
    out.resize(size);
    while (packed.size() % 4) packed.push_back(0);
    const size_t offset = packed.size();
    packed.insert(packed.end(), out.begin(), out.end());
    while (target % 4) ++target;
    const std::string ext = R"({"buffer": 0, "byteOffset": )" + std::to_string(offset) +
                            R"(, "byteLength": )" + std::to_string(size) +
                            R"(, "byteStride": )" + std::to_string(stride) + R"(, "count": )" +
                            std::to_string(count) + R"(, "mode": ")" + mode + "\"" +
                            (filter.empty() ? "" : R"(, "filter": ")" + filter + "\"") + "}";
    if (compressed_view_json && compressed_view_json->empty()) *compressed_view_json = ext;
    views += std::string(views.empty() ? "" : ", ") + R"({"buffer": 1, "byteOffset": )" +
             std::to_string(target) + R"(, "byteLength": )" + std::to_string(count * stride) +
             (mode == "ATTRIBUTES" ? R"(, "byteStride": )" + std::to_string(stride) : "") +
             R"(, "extensions": {"EXT_meshopt_compression": )" + ext + "}}";
    target += count * stride;
  };
  add(g.positions.data(), g.vertices(), 12, "ATTRIBUTES", "");
  std::vector<int8_t> oct(g.vertices() * 4);
  if (octahedral) {  // the encoder reads 4 floats a vector (W is kept)
    std::vector<float> n4;
    for (size_t i = 0; i < g.vertices(); ++i)
      n4.insert(n4.end(), {g.normals[3 * i], g.normals[3 * i + 1], g.normals[3 * i + 2], 0.f});
    meshopt_encodeFilterOct(oct.data(), g.vertices(), 4, 8, n4.data());
    add(oct.data(), g.vertices(), 4, "ATTRIBUTES", "OCTAHEDRAL");
  } else {
    add(g.normals.data(), g.vertices(), 12, "ATTRIBUTES", "");
  }
  add(g.uv.data(), g.vertices(), 8, "ATTRIBUTES", "");
  add(g.indices.data(), g.indices.size(), 4, index_mode, "");
  std::string accessors = accessors_json(g.vertices(), g.indices.size());
  if (octahedral) {  // normals: normalized signed bytes (KHR_mesh_quantization)
    const std::string from = R"("componentType": 5126, "count": )" +
                             std::to_string(g.vertices()) + R"(, "type": "VEC3"})";
    const size_t at = accessors.find(from, accessors.find("\"bufferView\": 1"));
    accessors.replace(at, from.size(),
                      R"("componentType": 5120, "normalized": true, "count": )" +
                          std::to_string(g.vertices()) + R"(, "type": "VEC3"})");
  }
  const std::string used =
      std::string(R"("extensionsUsed": ["EXT_meshopt_compression")") +
      (octahedral ? R"(, "KHR_mesh_quantization")" : "") +
      R"(], "extensionsRequired": ["EXT_meshopt_compression")" +
      (octahedral ? R"(, "KHR_mesh_quantization")" : "") + "], ";
  return scene_json(kAttributes, 3,
                    accessors + R"(, "bufferViews": [)" + views + R"(], "buffers": [)" +
                        base64_buffer(packed) + R"(, {"byteLength": )" + std::to_string(target) +
                        R"(, "extensions": {"EXT_meshopt_compression": {"fallback": true}}}])",
                    "", used);
}

SceneDescription load(const std::string& json, const LoadOptions& options = {}) {
  return load_gltf_from_string(json, "", "compressed.gltf", nullptr, options);
}

std::string refusal(const std::string& json, std::string* message = nullptr,
                    const LoadOptions& options = {}) {
  try {
    load(json, options);
  } catch (const SceneError& e) {
    if (message) *message = e.what();
    return e.path();
  }
  return "";
}

void expect_same_geometry(const SceneDescription& got, const SceneDescription& want) {
  ASSERT_EQ(got.world.positions.size(), want.world.positions.size());
  for (size_t i = 0; i < want.world.positions.size(); ++i)
    for (int c = 0; c < 3; ++c) {
      EXPECT_EQ(got.world.positions[i][c], want.world.positions[i][c]) << i;
      EXPECT_EQ(got.world.normals[i][c], want.world.normals[i][c]) << i;
    }
  ASSERT_EQ(got.world.uv[0].size(), want.world.uv[0].size());
  for (size_t i = 0; i < want.world.uv[0].size(); ++i) {
    EXPECT_EQ(got.world.uv[0][i].x, want.world.uv[0][i].x);
    EXPECT_EQ(got.world.uv[0][i].y, want.world.uv[0][i].y);
  }
  // meshopt's index codec may rotate a triangle's corners (keeping its winding).
  ASSERT_EQ(got.world.indices.size(), want.world.indices.size());
  for (size_t t = 0; t < want.world.indices.size(); t += 3) {
    const uint32_t* a = &got.world.indices[t];
    const uint32_t* b = &want.world.indices[t];
    bool rotation = false;
    for (int r = 0; r < 3; ++r)
      rotation = rotation || (a[0] == b[r] && a[1] == b[(r + 1) % 3] && a[2] == b[(r + 2) % 3]);
    EXPECT_TRUE(rotation) << "triangle " << t / 3;
  }
}

TEST(MeshoptCompression, DecodesToTheUncompressedSceneExactly) {
  const Grid g;
  const SceneDescription want = load(plain_json(g));
  ASSERT_EQ(want.world.size(), g.indices.size() / 3);
  for (const char* mode : {"TRIANGLES", "INDICES"}) {
    SCOPED_TRACE(mode);
    expect_same_geometry(load(meshopt_json(g, mode, false)), want);
  }
}

TEST(MeshoptCompression, OctahedralNormalsDecodeWithinTheirQuantization) {
  const Grid g;
  const SceneDescription desc = load(meshopt_json(g, "TRIANGLES", true));
  ASSERT_EQ(desc.world.normals.size(), g.vertices());
  for (size_t i = 0; i < g.vertices(); ++i) {
    const Vec3 n = desc.world.normals[i];
    const double dot = double(n.x) * g.normals[3 * i] + double(n.y) * g.normals[3 * i + 1] +
                       double(n.z) * g.normals[3 * i + 2];
    // 8-bit octahedral coordinates: a step of 2/127 on the octahedron, under 2 degrees.
    EXPECT_GT(dot, std::cos(2.0 * M_PI / 180.0)) << i;
  }
}

TEST(MeshoptCompression, MalformedViewsAreRefusedByPath) {
  const Grid g;
  const std::string good = meshopt_json(g, "TRIANGLES", false);
  const std::string path = "bufferViews[0].extensions.EXT_meshopt_compression";
  std::string message;
  {  // the compressed bytes of the positions overwritten (a data URI cannot be edited: change
     // the declared count instead, which no longer matches the stream)
    std::string bad = good;
    const std::string from = R"("count": )" + std::to_string(g.vertices()) + R"(, "mode")";
    bad.replace(bad.find(from), from.size(), R"("count": 1, "mode")");
    EXPECT_EQ(refusal(bad, &message), path) << message;
    EXPECT_NE(message.find("differs from the buffer view's byteLength"), std::string::npos)
        << message;
  }
  {
    std::string bad = good;
    const std::string from = R"("mode": "ATTRIBUTES")";
    bad.replace(bad.find(from), from.size(), R"("mode": "VERTICES")");
    EXPECT_EQ(refusal(bad, &message), path) << message;
    EXPECT_NE(message.find("'mode' must be ATTRIBUTES, TRIANGLES or INDICES"), std::string::npos);
  }
  {  // a compressed range past the end of its buffer
    std::string bad = good;
    const std::string from = R"({"buffer": 0, "byteOffset": 0, "byteLength": )";
    const size_t at = bad.find(from);
    const size_t end = bad.find(',', at + from.size());
    bad.replace(at + from.size(), end - at - from.size(), "100000");
    EXPECT_EQ(refusal(bad, &message), path) << message;
    EXPECT_NE(message.find("exceeds its buffer"), std::string::npos) << message;
  }
}

TEST(MeshoptCompression, CorruptStreamsAreRefused) {
  // Valid JSON around bytes that are no meshopt stream.
  const std::vector<unsigned char> junk(64, 0x5a);
  const std::string json = scene_json(
      R"({"POSITION": 0})", -1,
      R"("accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
          "min": [0, 0, 0], "max": [1, 1, 1]}],
        "bufferViews": [{"buffer": 1, "byteLength": 36, "byteStride": 12,
          "extensions": {"EXT_meshopt_compression": {"buffer": 0, "byteLength": 64,
          "byteStride": 12, "count": 3, "mode": "ATTRIBUTES"}}}],
        "buffers": [)" + base64_buffer(junk) +
          R"(, {"byteLength": 36, "extensions": {"EXT_meshopt_compression": {"fallback": true}}}])");
  std::string message;
  EXPECT_EQ(refusal(json, &message), "bufferViews[0].extensions.EXT_meshopt_compression")
      << message;
  EXPECT_NE(message.find("does not decode"), std::string::npos) << message;
}

TEST(MeshoptCompression, AFallbackBufferOverTheMemoryLimitIsRefusedBeforeAllocating) {
  const Grid g;
  std::string json = meshopt_json(g, "TRIANGLES", false);
  // A fallback buffer declaring a terabyte: refused from its declared size alone.
  const std::string from = R"(, "extensions": {"EXT_meshopt_compression": {"fallback": true}})";
  const size_t at = json.rfind(R"({"byteLength": )", json.find(from));
  json.replace(at, json.find(from) - at, R"({"byteLength": 1000000000000)");
  LoadOptions options;
  options.limits.max_memory_bytes = 512ull << 20;
  std::string message;
  EXPECT_EQ(refusal(json, &message, options), "meshes") << message;
  EXPECT_NE(message.find("over the scene memory limit"), std::string::npos) << message;
}

// ---- KHR_draco_mesh_compression.

// The grid as a Draco mesh, encoded losslessly (no quantization) with the sequential
// connectivity coder, which keeps the face order; attribute ids in *ids (position, normal, uv).
std::vector<unsigned char> draco_bytes(const Grid& g, std::array<int, 3>* ids, size_t* points) {
  draco::TriangleSoupMeshBuilder builder;
  const int faces = int(g.indices.size() / 3);
  builder.Start(faces);
  const int pos = builder.AddAttribute(draco::GeometryAttribute::POSITION, 3, draco::DT_FLOAT32);
  const int nor = builder.AddAttribute(draco::GeometryAttribute::NORMAL, 3, draco::DT_FLOAT32);
  const int tex =
      builder.AddAttribute(draco::GeometryAttribute::TEX_COORD, 2, draco::DT_FLOAT32);
  for (int f = 0; f < faces; ++f) {
    const uint32_t* v = &g.indices[size_t(f) * 3];
    builder.SetAttributeValuesForFace(pos, draco::FaceIndex(uint32_t(f)), &g.positions[3 * v[0]],
                                      &g.positions[3 * v[1]], &g.positions[3 * v[2]]);
    builder.SetAttributeValuesForFace(nor, draco::FaceIndex(uint32_t(f)), &g.normals[3 * v[0]],
                                      &g.normals[3 * v[1]], &g.normals[3 * v[2]]);
    builder.SetAttributeValuesForFace(tex, draco::FaceIndex(uint32_t(f)), &g.uv[2 * v[0]],
                                      &g.uv[2 * v[1]], &g.uv[2 * v[2]]);
  }
  std::unique_ptr<draco::Mesh> mesh = builder.Finalize();
  EXPECT_TRUE(mesh != nullptr);
  *points = mesh->num_points();  // corners with equal attributes may have been merged
  *ids = {int(mesh->attribute(pos)->unique_id()), int(mesh->attribute(nor)->unique_id()),
          int(mesh->attribute(tex)->unique_id())};
  draco::Encoder encoder;
  encoder.SetEncodingMethod(draco::MESH_SEQUENTIAL_ENCODING);
  draco::EncoderBuffer out;
  EXPECT_TRUE(encoder.EncodeMeshToBuffer(*mesh, &out).ok());
  return std::vector<unsigned char>(out.data(), out.data() + out.size());
}

std::string draco_json(const Grid& g, size_t declared_points = 0) {
  std::array<int, 3> ids{};
  size_t decoded_points = 0;
  const std::vector<unsigned char> bytes = draco_bytes(g, &ids, &decoded_points);
  const size_t points = declared_points ? declared_points : decoded_points;
  const std::string ext = R"(, "extensions": {"KHR_draco_mesh_compression": {"bufferView": 0,
      "attributes": {"POSITION": )" + std::to_string(ids[0]) +
                          R"(, "NORMAL": )" + std::to_string(ids[1]) + R"(, "TEXCOORD_0": )" +
                          std::to_string(ids[2]) + "}}}";
  return scene_json(kAttributes, 3,
                    accessors_json(points, g.indices.size(), 5123, false) +
                        R"(, "bufferViews": [{"buffer": 0, "byteLength": )" +
                        std::to_string(bytes.size()) + R"(}], "buffers": [)" +
                        base64_buffer(bytes) + "]",
                    ext,
                    R"("extensionsUsed": ["KHR_draco_mesh_compression"],
                       "extensionsRequired": ["KHR_draco_mesh_compression"], )");
}

TEST(DracoCompression, DecodesEveryTriangleWithItsAttributesExactly) {
  const Grid g;
  const SceneDescription desc = load(draco_json(g));
  ASSERT_EQ(desc.world.size(), g.indices.size() / 3);
  // Triangle t's corners are the grid's vertices of triangle t, in order (the sequential coder
  // keeps faces; corners may start at another vertex of the face, so match a rotation).
  for (size_t t = 0; t < desc.world.size(); ++t) {
    const Triangle tri = desc.world.triangle(t);
    const Vec3* p[3] = {&tri.p[0], &tri.p[1], &tri.p[2]};
    bool matched = false;
    for (int r = 0; r < 3 && !matched; ++r) {
      matched = true;
      for (int k = 0; k < 3; ++k) {
        const uint32_t v = g.indices[3 * t + size_t((k + r) % 3)];
        for (int c = 0; c < 3; ++c)
          matched = matched && (*p[k])[c] == g.positions[3 * v + size_t(c)];
      }
    }
    EXPECT_TRUE(matched) << "triangle " << t;
  }
  // Every decoded vertex carries the normal and uv of the grid vertex at its position.
  for (size_t i = 0; i < desc.world.positions.size(); ++i) {
    const Vec3 q = desc.world.positions[i];
    size_t v = 0;
    while (v < g.vertices() &&
           !(q.x == g.positions[3 * v] && q.y == g.positions[3 * v + 1] &&
             q.z == g.positions[3 * v + 2]))
      ++v;
    ASSERT_LT(v, g.vertices()) << i;
    EXPECT_NEAR(desc.world.normals[i].x, g.normals[3 * v], 1e-6f);
    EXPECT_NEAR(desc.world.normals[i].y, g.normals[3 * v + 1], 1e-6f);
    EXPECT_NEAR(desc.world.normals[i].z, g.normals[3 * v + 2], 1e-6f);
    EXPECT_EQ(desc.world.uv[0][i].x, g.uv[2 * v]);
    EXPECT_EQ(desc.world.uv[0][i].y, g.uv[2 * v + 1]);
  }
}

TEST(DracoCompression, MismatchesAndCorruptDataAreRefusedByPath) {
  const Grid g;
  const std::string path = "meshes[0].primitives[0].extensions.KHR_draco_mesh_compression";
  std::string message;
  EXPECT_EQ(refusal(draco_json(g, 7), &message), path + ".attributes") << message;
  EXPECT_NE(message.find("declares 7 elements; the Draco data decodes"), std::string::npos)
      << message;

  const std::string junk = scene_json(
      R"({"POSITION": 0})", 1,
      R"("accessors": [{"componentType": 5126, "count": 3, "type": "VEC3",
          "min": [0, 0, 0], "max": [1, 1, 1]}, {"componentType": 5125, "count": 3,
          "type": "SCALAR"}],
        "bufferViews": [{"buffer": 0, "byteLength": 64}],
        "buffers": [)" + base64_buffer(std::vector<unsigned char>(64, 0x33)) + "]",
      R"(, "extensions": {"KHR_draco_mesh_compression": {"bufferView": 0,
          "attributes": {"POSITION": 0}}})");
  EXPECT_EQ(refusal(junk, &message), path) << message;
  EXPECT_NE(message.find("not a Draco triangle mesh"), std::string::npos) << message;

  std::string missing = draco_json(g);
  const std::string from = R"("NORMAL": 1, )";
  missing.replace(missing.find(from), from.size(), "");  // the primitive's NORMAL attribute
  EXPECT_EQ(refusal(missing, &message), path + ".attributes.NORMAL") << message;
}

// Two primitives of one Draco mesh that differ only in material, decoding into the same
// accessors from the same compressed data (as some exporters write them): the data is decoded
// once and both primitives render its triangles, each with its material. Two primitives that
// fill one accessor from different data each get their own (the second a copy of the
// accessor), as viewers decode each primitive's Draco data on its own.
std::string two_primitive_draco_json(const Grid& g, bool swap_ids) {
  nlohmann::json doc = nlohmann::json::parse(draco_json(g));
  nlohmann::json& prims = doc["meshes"][0]["primitives"];
  nlohmann::json second = prims[0];
  prims[0]["material"] = 0;
  second["material"] = 1;
  if (swap_ids) {
    nlohmann::json& attrs = second["extensions"]["KHR_draco_mesh_compression"]["attributes"];
    std::swap(attrs["POSITION"], attrs["NORMAL"]);
  }
  prims.push_back(second);
  doc["materials"] = nlohmann::json::array({{{"name", "red"}}, {{"name", "blue"}}});
  return doc.dump();
}

TEST(DracoCompression, PrimitivesSharingTheirDecodedAccessorsDecodeOnce) {
  const Grid g;
  const SceneDescription one = load(draco_json(g));
  const SceneDescription two = load(two_primitive_draco_json(g, false));
  const size_t n = one.world.size();
  ASSERT_EQ(n, g.indices.size() / 3);
  ASSERT_EQ(two.world.size(), 2 * n);
  for (size_t t = 0; t < n; ++t) {
    const Triangle a = two.world.triangle(t), b = two.world.triangle(n + t), ref =
                                                                           one.world.triangle(t);
    for (int k = 0; k < 3; ++k)
      for (int c = 0; c < 3; ++c) {
        EXPECT_EQ(a.p[k][c], ref.p[k][c]) << "triangle " << t;
        EXPECT_EQ(b.p[k][c], ref.p[k][c]) << "triangle " << t;
      }
    EXPECT_EQ(two.materials[two.world.material[t]].name, "red");
    EXPECT_EQ(two.materials[two.world.material[n + t]].name, "blue");
  }
  // The second primitive's POSITION from the Draco normals: the first keeps the grid.
  const SceneDescription swapped = load(two_primitive_draco_json(g, true));
  ASSERT_GE(swapped.world.size(), n);
  for (size_t t = 0; t < n; ++t) {
    EXPECT_EQ(swapped.materials[swapped.world.material[t]].name, "red");
    const Triangle a = swapped.world.triangle(t), ref = one.world.triangle(t);
    for (int k = 0; k < 3; ++k)
      for (int c = 0; c < 3; ++c) EXPECT_EQ(a.p[k][c], ref.p[k][c]) << "triangle " << t;
  }
  size_t blue = 0;
  for (size_t t = 0; t < swapped.world.size(); ++t) {
    if (swapped.materials[swapped.world.material[t]].name != "blue") continue;
    ++blue;
    const Triangle b = swapped.world.triangle(t);
    for (int k = 0; k < 3; ++k) EXPECT_NEAR(length(b.p[k]), 1.f, 1e-5f) << t;  // unit normals
  }
  EXPECT_GT(blue, 0u);
}

// One primitive whose POSITION and NORMAL name the same accessor while its Draco extension
// decodes them from two attributes (as an exporter wrote a PlayCanvas demo's TEXCOORD_0..3):
// each attribute gets its own Draco data, exactly as with separate accessors.
TEST(DracoCompression, AttributesNamingOneAccessorGetTheirOwnData) {
  const Grid g;
  const SceneDescription separate = load(draco_json(g));
  nlohmann::json doc = nlohmann::json::parse(draco_json(g));
  doc["meshes"][0]["primitives"][0]["attributes"]["NORMAL"] = 0;  // POSITION's accessor
  const SceneDescription shared = load(doc.dump());
  ASSERT_EQ(shared.world.size(), separate.world.size());
  ASSERT_EQ(shared.world.positions.size(), separate.world.positions.size());
  for (size_t i = 0; i < shared.world.positions.size(); ++i)
    for (int c = 0; c < 3; ++c) {
      EXPECT_EQ(shared.world.positions[i][c], separate.world.positions[i][c]) << i;
      EXPECT_EQ(shared.world.normals[i][c], separate.world.normals[i][c]) << i;
    }
}

}  // namespace
}  // namespace rf
