#include "testing/test_scenes.h"

#include <OpenImageIO/imageio.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <mutex>
#include <fstream>
#include <iterator>
#include <stdexcept>
#include <vector>

namespace rf {
namespace testing {

void add_quad(SceneDescription* desc, Vec3 p0, Vec3 p1, Vec3 p2, Vec3 p3, uint32_t material) {
  Triangle a, b;
  a.p[0] = p0, a.p[1] = p1, a.p[2] = p2;
  b.p[0] = p0, b.p[1] = p2, b.p[2] = p3;
  a.material = b.material = material;
  desc->world.add(a);
  desc->world.add(b);
}

void add_sphere(SceneDescription* desc, Vec3 center, float radius, uint32_t material, int rings,
                int segments) {
  auto point = [&](int i, int j) {
    const float theta = kPi * float(i) / float(rings), phi = 2.f * kPi * float(j) / float(segments);
    return center + Vec3(std::sin(theta) * std::cos(phi), std::cos(theta),
                         -std::sin(theta) * std::sin(phi)) *
                        radius;
  };
  for (int i = 0; i < rings; ++i)
    for (int j = 0; j < segments; ++j) {
      // Counter-clockwise seen from outside.
      const Vec3 a = point(i, j), b = point(i + 1, j), c = point(i + 1, j + 1), d = point(i, j + 1);
      Triangle t0, t1;
      t0.p[0] = a, t0.p[1] = b, t0.p[2] = c;
      t1.p[0] = a, t1.p[1] = c, t1.p[2] = d;
      t0.material = t1.material = material;
      desc->world.add(t0);  // the pole's degenerate ones are dropped by Scene
      desc->world.add(t1);
    }
}

Camera look_at(Vec3 eye, Vec3 target, float yfov) {
  Camera cam;
  cam.position = eye;
  cam.forward = normalize(target - eye);
  const Vec3 up_hint = std::fabs(cam.forward.y) > 0.99f ? Vec3(0, 0, 1) : Vec3(0, 1, 0);
  cam.right = normalize(cross(cam.forward, up_hint));
  cam.up = cross(cam.right, cam.forward);
  cam.yfov = yfov;
  return cam;
}

SceneDescription plane_under_emitter(float rho, float L, float a, float b, float c, Vec3 eye,
                                     float yfov) {
  SceneDescription desc;
  desc.source = "plane-under-emitter";
  desc.materials.push_back(Material{"plane", {rho, rho, rho}, {0, 0, 0}});
  desc.materials.push_back(Material{"emitter", {0, 0, 0}, {L, L, L}});
  add_quad(&desc, {-2, -2, 0}, {2, -2, 0}, {2, 2, 0}, {-2, 2, 0}, 0);  // faces +z
  const float ha = 0.5f * a, hb = 0.5f * b;
  // Clockwise seen from above = counter-clockwise seen from below: faces -z.
  add_quad(&desc, {-ha, -hb, c}, {-ha, hb, c}, {ha, hb, c}, {ha, -hb, c}, 1);
  desc.camera = look_at(eye, {0, 0, 0}, yfov);
  return desc;
}

namespace {

std::string base64(const std::vector<unsigned char>& data) {
  static const char* table =
      "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
  std::string out;
  for (size_t i = 0; i < data.size(); i += 3) {
    uint32_t v = uint32_t(data[i]) << 16;
    if (i + 1 < data.size()) v |= uint32_t(data[i + 1]) << 8;
    if (i + 2 < data.size()) v |= data[i + 2];
    out += table[(v >> 18) & 63];
    out += table[(v >> 12) & 63];
    out += i + 1 < data.size() ? table[(v >> 6) & 63] : '=';
    out += i + 2 < data.size() ? table[v & 63] : '=';
  }
  return out;
}

void put_floats(std::vector<unsigned char>* buf, std::initializer_list<float> values) {
  for (float f : values) {
    unsigned char b[4];
    std::memcpy(b, &f, 4);
    buf->insert(buf->end(), b, b + 4);
  }
}

}  // namespace

namespace {

std::string small_gltf(bool animated) {
  std::vector<unsigned char> buf;
  // [0, 48): floor positions, 4 x VEC3, y = 0 plane facing +y (CCW seen from above).
  put_floats(&buf, {-1, 0, 1, 1, 0, 1, 1, 0, -1, -1, 0, -1});
  // [48, 60): floor indices uint16 0 1 2 0 2 3.
  for (uint16_t i : {0, 1, 2, 0, 2, 3}) {
    buf.push_back(uint8_t(i & 0xff));
    buf.push_back(uint8_t(i >> 8));
  }
  // [60, 132): emitter positions, 6 x VEC3, unit square in y = 0 facing -y (local frame).
  put_floats(&buf, {-0.5f, 0, -0.5f, 0.5f, 0, -0.5f, 0.5f, 0, 0.5f,  //
                    -0.5f, 0, -0.5f, 0.5f, 0, 0.5f, -0.5f, 0, 0.5f});
  std::string animation_json;
  if (animated) {
    put_floats(&buf, {0, 2});                    // [132, 140): keyframe times
    put_floats(&buf, {0, 2, 0, 1.5f, 2, 0});     // [140, 164): light-parent translations
    put_floats(&buf, {1, 1, 1, 0.5f, 1, 0.5f});  // [164, 188): floor scales
    animation_json = R"(,
  "animations": [
    {"name": "slide", "channels": [{"sampler": 0, "target": {"node": 1, "path": "translation"}}],
     "samplers": [{"input": 3, "output": 4}]},
    {"name": "shrink", "channels": [{"sampler": 0, "target": {"node": 0, "path": "scale"}}],
     "samplers": [{"input": 3, "output": 5}]}
  ])";
  }
  const std::string uri = "data:application/octet-stream;base64," + base64(buf);
  return R"({
  "asset": {"version": "2.0"},
  "extensionsUsed": ["KHR_materials_emissive_strength", "EXT_made_up"],
  "scene": 0,
  "scenes": [{"nodes": [0, 1, 3]}],
  "nodes": [
    {"name": "floor", "mesh": 0},
    {"name": "light-parent", "translation": [0, 2, 0], "scale": [2, 1, 2], "children": [2]},
    {"name": "light", "mesh": 1},
    {"name": "camera", "camera": 0, "translation": [0, 1, 5],
     "rotation": [-0.0998334, 0, 0, 0.9950042]}
  ],
  "cameras": [{"type": "perspective", "perspective": {"yfov": 0.7, "znear": 0.01}}],
  "materials": [
    {"name": "grey", "pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.6, 0.7, 1]}},
    {"name": "lamp", "emissiveFactor": [1, 0.5, 0.25],
     "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 4}}}
  ],
  "meshes": [
    {"name": "floor", "primitives": [
      {"attributes": {"POSITION": 0}, "indices": 1, "material": 0},
      {"attributes": {"POSITION": 0}, "mode": 1}
    ]},
    {"name": "lamp", "primitives": [{"attributes": {"POSITION": 2}, "material": 1}]}
  ],
  "accessors": [
    {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
     "min": [-1, 0, -1], "max": [1, 0, 1]},
    {"bufferView": 1, "componentType": 5123, "count": 6, "type": "SCALAR"},
    {"bufferView": 2, "componentType": 5126, "count": 6, "type": "VEC3",
     "min": [-0.5, 0, -0.5], "max": [0.5, 0, 0.5]})" +
         std::string(animated ? R"(,
    {"bufferView": 3, "componentType": 5126, "count": 2, "type": "SCALAR", "min": [0],
     "max": [2]},
    {"bufferView": 4, "componentType": 5126, "count": 2, "type": "VEC3"},
    {"bufferView": 5, "componentType": 5126, "count": 2, "type": "VEC3"})"
                             : "") +
         R"(
  ],
  "bufferViews": [
    {"buffer": 0, "byteOffset": 0, "byteLength": 48},
    {"buffer": 0, "byteOffset": 48, "byteLength": 12},
    {"buffer": 0, "byteOffset": 60, "byteLength": 72})" +
         std::string(animated ? R"(,
    {"buffer": 0, "byteOffset": 132, "byteLength": 8},
    {"buffer": 0, "byteOffset": 140, "byteLength": 24},
    {"buffer": 0, "byteOffset": 164, "byteLength": 24})"
                             : "") +
         R"(
  ],
  "buffers": [{"byteLength": )" +
         std::to_string(buf.size()) + R"(, "uri": ")" + uri + R"("}])" + animation_json + R"(
})";
}

}  // namespace

std::string small_gltf_json() { return small_gltf(false); }

std::string animated_gltf_json() { return small_gltf(true); }

std::string ids_gltf_json(bool animated) {
  std::vector<unsigned char> buf;
  put_floats(&buf, {-1, -1, 0, 1, -1, 0, 1, 1, 0, -1, 1, 0});  // [0, 48): the quad
  // [48, 144) and [144, 240): four segments each, along x at the heights of pixel rows 9 and
  // 10 (y in [-2.5, -1.5]) and a quarter of a pixel apart: their ribbons, one pixel wide, cover
  // y in [-2.625, -1.375]; x in [0.25, 1.75] and in [2.25, 3.75].
  for (float x0 : {0.25f, 2.25f})
    for (float y : {-1.625f, -1.875f, -2.125f, -2.375f})
      put_floats(&buf, {x0, y, 0, x0 + 1.5f, y, 0});
  put_floats(&buf, {-1, 0, 0, 1, 0, 0});                      // [240, 264): crowd's instances
  put_floats(&buf, {0, 0, 0.25f, 0, 0, 0.25f, 0, 0, 0.25f, 0, 0, 0.25f});  // [264, 312): target
  put_floats(&buf, {0, 1});                                   // [312, 320): keyframe times
  put_floats(&buf, {1, 2, 0, 1, 2, -0.5f});                   // [320, 344): node 2's slide
  put_floats(&buf, {0, 1});                                   // [344, 352): node 4's weight
  // [352, 364): the quad's indices; [364, 382): a degenerate triangle, then the quad's.
  for (uint16_t i : {0, 1, 2, 0, 2, 3, 0, 0, 1, 0, 1, 2, 0, 2, 3}) {
    buf.push_back(uint8_t(i & 0xff));
    buf.push_back(uint8_t(i >> 8));
  }
  buf.resize(384, 0);
  const std::string quad = R"("attributes": {"POSITION": 0}, "indices": 8)";
  const std::string variant = R"(, "extensions": {"KHR_materials_variants": {"mappings": [)";
  return R"({
  "asset": {"version": "2.0"},
  "extensionsUsed": ["EXT_mesh_gpu_instancing", "KHR_materials_variants"],
  "extensions": {"KHR_materials_variants": {"variants": [{"name": "v0"}]}},
  "scene": 0,
  "scenes": [{"nodes": [6, 8, 11, 3, 0, 1, 4, 7, 9, 10]}],
  "nodes": [
    {"name": "group", "children": [5, 2]},
    {"name": "camera", "camera": 0, "translation": [0, 0, 10]},
    {"name": "shared-2", "mesh": 1, "translation": [1, 2, 0]},
    {"name": "lines", "mesh": 7, "translation": [0, 0, 0.5]},
    {"name": "back", "mesh": 4, "translation": [-2, 0, 0], "scale": [2, 1, 1]},
    {"name": "shared-1", "mesh": 1, "translation": [-1, 2, 0]},
    {"name": "mask", "mesh": 3, "translation": [-3, 0, 1]},
    {"name": "single", "mesh": 2, "translation": [-3, 2, 0]},
    {"name": "glass", "mesh": 5, "translation": [-1, 0, 1]},
    {"name": "plain", "mesh": 0, "translation": [3, 2, 0]},
    {"name": "crowd", "mesh": 8, "translation": [-2, -2, 0],
     "extensions": {"EXT_mesh_gpu_instancing": {"attributes": {"TRANSLATION": 3}}}},
    {"name": "hole", "mesh": 6, "translation": [3, 0, 1]}
  ],
  "cameras": [{"type": "orthographic",
               "orthographic": {"xmag": 4, "ymag": 3, "znear": 0.01, "zfar": 100}}],
  "materials": [
    {"name": "red", "pbrMetallicRoughness": {"baseColorFactor": [0.8, 0.2, 0.2, 1]}},
    {"name": "green", "pbrMetallicRoughness": {"baseColorFactor": [0.2, 0.8, 0.2, 1]}},
    {"name": "blue", "pbrMetallicRoughness": {"baseColorFactor": [0.2, 0.2, 0.8, 1]}},
    {"name": "mask-solid", "alphaMode": "MASK", "alphaCutoff": 0.5,
     "pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 0.8]}},
    {"name": "glass", "alphaMode": "BLEND",
     "pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 0]}},
    {"name": "ink", "pbrMetallicRoughness": {"baseColorFactor": [0.1, 0.1, 0.1, 1]}},
    {"name": "mask-hole", "alphaMode": "MASK", "alphaCutoff": 0.5,
     "pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 0.2]}}
  ],
  "meshes": [
    {"name": "plain", "primitives": [{)" + quad + variant +
         R"({"material": 0, "variants": [0]}]}}}]},
    {"name": "shared", "primitives": [{)" + quad + R"(, "material": 1)" + variant +
         R"({"material": 2, "variants": [0]}]}}}]},
    {"name": "single", "primitives": [{"attributes": {"POSITION": 0}, "indices": 9,
                                       "material": 0}]},
    {"name": "mask", "primitives": [{)" + quad + R"(, "material": 3}]},
    {"name": "back", "primitives": [{)" + quad + R"(, "material": 2,
                                     "targets": [{"POSITION": 4}]}], "weights": [0.5]},
    {"name": "glass", "primitives": [{)" + quad + R"(, "material": 4}]},
    {"name": "hole", "primitives": [{)" + quad + R"(, "material": 6}]},
    {"name": "lines", "primitives": [{"attributes": {"POSITION": 1}, "mode": 1, "material": 5},
                                     {"attributes": {"POSITION": 2}, "mode": 1}]},
    {"name": "crowd", "primitives": [{)" + quad + R"(, "material": 1}]}
  ],
  "accessors": [
    {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
     "min": [-1, -1, 0], "max": [1, 1, 0]},
    {"bufferView": 1, "componentType": 5126, "count": 8, "type": "VEC3",
     "min": [0.25, -2.375, 0], "max": [1.75, -1.625, 0]},
    {"bufferView": 2, "componentType": 5126, "count": 8, "type": "VEC3",
     "min": [2.25, -2.375, 0], "max": [3.75, -1.625, 0]},
    {"bufferView": 3, "componentType": 5126, "count": 2, "type": "VEC3"},
    {"bufferView": 4, "componentType": 5126, "count": 4, "type": "VEC3",
     "min": [0, 0, 0.25], "max": [0, 0, 0.25]},
    {"bufferView": 5, "componentType": 5126, "count": 2, "type": "SCALAR", "min": [0],
     "max": [1]},
    {"bufferView": 6, "componentType": 5126, "count": 2, "type": "VEC3"},
    {"bufferView": 7, "componentType": 5126, "count": 2, "type": "SCALAR"},
    {"bufferView": 8, "componentType": 5123, "count": 6, "type": "SCALAR"},
    {"bufferView": 9, "componentType": 5123, "count": 9, "type": "SCALAR"}
  ],
  "bufferViews": [
    {"buffer": 0, "byteOffset": 0, "byteLength": 48},
    {"buffer": 0, "byteOffset": 48, "byteLength": 96},
    {"buffer": 0, "byteOffset": 144, "byteLength": 96},
    {"buffer": 0, "byteOffset": 240, "byteLength": 24},
    {"buffer": 0, "byteOffset": 264, "byteLength": 48},
    {"buffer": 0, "byteOffset": 312, "byteLength": 8},
    {"buffer": 0, "byteOffset": 320, "byteLength": 24},
    {"buffer": 0, "byteOffset": 344, "byteLength": 8},
    {"buffer": 0, "byteOffset": 352, "byteLength": 12},
    {"buffer": 0, "byteOffset": 364, "byteLength": 18}
  ],
  "buffers": [{"byteLength": 384, "uri": "data:application/octet-stream;base64,)" +
         base64(buf) + R"("}])" +
         std::string(animated ? R"(,
  "animations": [{"name": "move",
    "channels": [{"sampler": 0, "target": {"node": 2, "path": "translation"}},
                 {"sampler": 1, "target": {"node": 4, "path": "weights"}}],
    "samplers": [{"input": 5, "output": 6}, {"input": 5, "output": 7}]}])"
                             : "") +
         R"(
})";
}

const std::vector<IdCell>& ids_gltf_cells() {
  // Cell (column c, row r) is the quad centred at (2c - 3, 2 - 2r): pixels x in [4c, 4c + 4),
  // y in [4r, 4r + 4). Instance: node + 1; material: material + 1 (0: none).
  static const std::vector<IdCell> cells = {
      {0, 0, "nodes[7] 'single' (world, after a degenerate triangle), red", 8, 1, 1},
      {4, 0, "nodes[5] 'shared-1' (an instance), green (v0: blue)", 6, 2, 3},
      {8, 0, "nodes[2] 'shared-2' (an instance), green (v0: blue)", 3, 2, 3},
      {12, 0, "nodes[9] 'plain' without a material (v0: red)", 10, 0, 1},
      {0, 4, "nodes[6] 'mask' (MASK, alpha over the cutoff) in front of 'back'", 7, 4, 4},
      {4, 4, "nodes[4] 'back' (morphed) behind nodes[8] 'glass' (BLEND, alpha 0), blue", 5, 3,
       3},
      {8, 4, "nothing", 0, 0, 0},
      {12, 4, "nothing behind nodes[11] 'hole' (MASK, alpha under the cutoff)", 0, 0, 0},
      {0, 8, "nodes[10] 'crowd' (EXT_mesh_gpu_instancing's first), green", 11, 2, 2},
      {4, 8, "nodes[10] 'crowd' (EXT_mesh_gpu_instancing's second), green", 11, 2, 2},
      {8, 8, "nodes[3] 'lines' (rows 9 and 10), ink's points-and-lines variant", 4, 6, 6},
      {12, 8, "nodes[3] 'lines' (rows 9 and 10), without a material", 4, 0, 0},
  };
  return cells;
}

std::string quad_gltf_buffers_json() {
  std::vector<unsigned char> buf;
  put_floats(&buf, {-1, -1, 0, 1, -1, 0, 1, 1, 0, -1, 1, 0});       // [0, 48) positions
  put_floats(&buf, {0, 0, 1, 0, 0, 1, 0, 0, 1, 0, 0, 1});           // [48, 96) normals
  put_floats(&buf, {0, 1, 1, 1, 1, 0, 0, 0});                       // [96, 128) uv
  for (uint16_t i : {0, 1, 2, 0, 2, 3}) {                           // [128, 140) indices
    buf.push_back(uint8_t(i & 0xff));
    buf.push_back(uint8_t(i >> 8));
  }
  return R"("accessors": [
    {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
     "min": [-1, -1, 0], "max": [1, 1, 0]},
    {"bufferView": 1, "componentType": 5126, "count": 4, "type": "VEC3"},
    {"bufferView": 2, "componentType": 5126, "count": 4, "type": "VEC2"},
    {"bufferView": 3, "componentType": 5123, "count": 6, "type": "SCALAR"}
  ],
  "bufferViews": [
    {"buffer": 0, "byteOffset": 0, "byteLength": 48},
    {"buffer": 0, "byteOffset": 48, "byteLength": 48},
    {"buffer": 0, "byteOffset": 96, "byteLength": 32},
    {"buffer": 0, "byteOffset": 128, "byteLength": 12}
  ],
  "buffers": [{"byteLength": 140, "uri": "data:application/octet-stream;base64,)" +
         base64(buf) + R"("}])";
}

namespace {

// The folders test_path made in this process, removed at exit.
struct TestFolders {
  std::mutex mutex;
  std::vector<std::filesystem::path> made;
  ~TestFolders() {
    std::error_code ec;
    for (const auto& dir : made) std::filesystem::remove_all(dir, ec);
  }
};

TestFolders& test_folders() {
  static TestFolders folders;
  return folders;
}

}  // namespace

std::string test_path(const std::string& name) {
  const ::testing::TestInfo* info = ::testing::UnitTest::GetInstance()->current_test_info();
  std::string test = info ? std::string(info->test_suite_name()) + "." + info->name() : "none";
  for (char& ch : test)
    if (ch == '/') ch = '_';  // parameterized tests: Suite/Name.Case/0
  const std::filesystem::path dir = std::filesystem::path(::testing::TempDir()) /
                                    ("rf-" + std::to_string(::getpid()) + "-" + test);
  TestFolders& folders = test_folders();
  {
    std::lock_guard<std::mutex> lock(folders.mutex);
    if (std::find(folders.made.begin(), folders.made.end(), dir) == folders.made.end()) {
      std::filesystem::create_directories(dir);
      folders.made.push_back(dir);
    }
  }
  return (dir / name).string();
}

std::string data_uri(const std::string& mime_type, const std::vector<unsigned char>& bytes) {
  return "data:" + mime_type + ";base64," + base64(bytes);
}

std::string png_data_uri(int width, int height, int channels,
                         const std::vector<unsigned char>& pixels) {
  return image_data_uri("png", width, height, channels, pixels);
}

std::string image_data_uri(const std::string& format, int width, int height, int channels,
                           const std::vector<unsigned char>& pixels) {
  static std::atomic<int> counter{0};
  const std::string path = test_path("image_" + std::to_string(++counter) + "." + format);
  auto out = OIIO::ImageOutput::create(path);
  if (!out) throw std::runtime_error("cannot create PNG writer");
  OIIO::ImageSpec spec(width, height, channels, OIIO::TypeDesc::UINT8);
  // The pixels as given: colours not premultiplied by alpha (OpenImageIO would otherwise
  // divide them by it on writing).
  spec.attribute("oiio:UnassociatedAlpha", 1);
  spec.attribute("CompressionQuality", 100);  // the lossy formats (webp, avif) at their best
  if (!out->open(path, spec) || !out->write_image(OIIO::TypeDesc::UINT8, pixels.data()) ||
      !out->close())
    throw std::runtime_error("cannot write " + path);
  std::ifstream in(path, std::ios::binary);
  const std::vector<unsigned char> bytes((std::istreambuf_iterator<char>(in)),
                                         std::istreambuf_iterator<char>());
  std::remove(path.c_str());
  return "data:image/" + format + ";base64," + base64(bytes);
}

}  // namespace testing
}  // namespace rf
