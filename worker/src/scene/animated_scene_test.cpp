// AnimatedScene (animated_scene.h): a scene split once into its static part and what moves,
// posed at a time by instances and refit deformed meshes. A pose made from another pose's
// leftovers renders the image a fresh pose renders, bit for bit; against the loader's
// flattened scene (everything baked into world-space vertices) the hits agree to float
// rounding.
#include "scene/animated_scene.h"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <fstream>
#include <string>
#include <thread>
#include <vector>

#include "render/integrators.h"
#include "render/render.h"
#include "scene/animation.h"
#include "testing/test_scenes.h"

namespace rf {
namespace {

struct Buffer {
  std::vector<unsigned char> bytes;
  std::vector<std::string> views;
  std::vector<std::string> accessors;
  // Appends values as a buffer view and an accessor of count elements of `type`; returns the
  // accessor's index.
  template <typename T>
  int add(const std::vector<T>& values, int component_type, size_t count, const std::string& type) {
    while (bytes.size() % 4) bytes.push_back(0);
    const size_t offset = bytes.size();
    const auto* p = reinterpret_cast<const unsigned char*>(values.data());
    bytes.insert(bytes.end(), p, p + values.size() * sizeof(T));
    views.push_back(R"({"buffer": 0, "byteOffset": )" + std::to_string(offset) +
                    R"(, "byteLength": )" + std::to_string(values.size() * sizeof(T)) + "}");
    accessors.push_back(R"({"bufferView": )" + std::to_string(views.size() - 1) +
                        R"(, "componentType": )" + std::to_string(component_type) +
                        R"(, "count": )" + std::to_string(count) + R"(, "type": ")" + type +
                        "\"}");
    return int(accessors.size() - 1);
  }
  std::string json() const {
    auto join = [](const std::vector<std::string>& items) {
      std::string list;
      for (const std::string& v : items) list += (list.empty() ? "" : ", ") + v;
      return list;
    };
    return R"("accessors": [)" + join(accessors) + R"(], "bufferViews": [)" + join(views) +
           R"(], "buffers": [{"byteLength": )" + std::to_string(bytes.size()) + R"(, "uri": ")" +
           testing::data_uri("application/octet-stream", bytes) + R"("}])";
  }
};

// A static floor under a static lamp, a door (a quad on a hinge whose rotation is animated),
// a strip skinned to two joints (one translated over time), a quad with a morph target whose
// weight is animated, and a camera sliding sideways. Times 0 to 1.
std::string moving_scene_json() {
  Buffer b;
  constexpr int kFloat = 5126, kUShort = 5123, kUByte = 5121;
  // A unit quad in the xz plane facing +y.
  const int quad_p = b.add(std::vector<float>{-1, 0, -1, -1, 0, 1, 1, 0, 1, 1, 0, -1}, kFloat, 4,
                           "VEC3");
  const int quad_n = b.add(std::vector<float>{0, 1, 0, 0, 1, 0, 0, 1, 0, 0, 1, 0}, kFloat, 4,
                           "VEC3");
  const int quad_i = b.add(std::vector<uint16_t>{0, 1, 2, 0, 2, 3}, kUShort, 6, "SCALAR");
  // The strip: x in {-1, 0, 1}, y in {0.5, 1.5}, facing +z.
  const int strip_p = b.add(std::vector<float>{-1, 0.5f, 0, 0, 0.5f, 0, 1, 0.5f, 0,
                                               -1, 1.5f, 0, 0, 1.5f, 0, 1, 1.5f, 0},
                            kFloat, 6, "VEC3");
  const int strip_n = b.add(std::vector<float>{0, 0, 1, 0, 0, 1, 0, 0, 1, 0, 0, 1, 0, 0, 1,
                                               0, 0, 1},
                            kFloat, 6, "VEC3");
  const int strip_i =
      b.add(std::vector<uint16_t>{0, 1, 4, 0, 4, 3, 1, 2, 5, 1, 5, 4}, kUShort, 12, "SCALAR");
  const int strip_j = b.add(std::vector<uint8_t>{0, 1, 0, 0, 0, 1, 0, 0, 1, 0, 0, 0,
                                                 0, 1, 0, 0, 0, 1, 0, 0, 1, 0, 0, 0},
                            kUByte, 6, "VEC4");
  const int strip_w = b.add(std::vector<float>{1, 0, 0, 0, 0.5f, 0.5f, 0, 0, 0, 1, 0, 0,
                                               1, 0, 0, 0, 0.5f, 0.5f, 0, 0, 0, 1, 0, 0},
                            kFloat, 6, "VEC4");
  const int morph_t = b.add(std::vector<float>{0, 0, 0, 0, 0, 0, 0, 0.8f, 0, 0, 0, 0}, kFloat, 4,
                            "VEC3");
  const int times = b.add(std::vector<float>{0, 1}, kFloat, 2, "SCALAR");
  const int camera_moves = b.add(std::vector<float>{0, 1.6f, 5, 0.8f, 1.8f, 5}, kFloat, 2, "VEC3");
  const float s = std::sqrt(0.5f);
  const int hinge_turns = b.add(std::vector<float>{0, 0, 0, 1, 0, s, 0, s}, kFloat, 2, "VEC4");
  const int joint_moves = b.add(std::vector<float>{0, 0, 0, 0.3f, 0.4f, 0.6f}, kFloat, 2, "VEC3");
  const int weights = b.add(std::vector<float>{0, 1}, kFloat, 2, "SCALAR");
  const std::string quad = R"({"attributes": {"POSITION": )" + std::to_string(quad_p) +
                           R"(, "NORMAL": )" + std::to_string(quad_n) + R"(}, "indices": )" +
                           std::to_string(quad_i);
  return R"({"asset": {"version": "2.0"}, "scene": 0,
  "scenes": [{"nodes": [0, 1, 2, 3, 5, 6, 8]}],
  "cameras": [{"type": "perspective", "perspective": {"yfov": 0.9, "znear": 0.01}}],
  "materials": [{"pbrMetallicRoughness": {"baseColorFactor": [0.8, 0.8, 0.8, 1],
                                          "metallicFactor": 0}, "doubleSided": true},
                {"emissiveFactor": [1, 1, 1],
                 "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 6}},
                 "pbrMetallicRoughness": {"baseColorFactor": [0, 0, 0, 1]}},
                {"pbrMetallicRoughness": {"baseColorFactor": [0.9, 0.3, 0.2, 1],
                                          "metallicFactor": 0}, "doubleSided": true}],
  "meshes": [{"primitives": [)" + quad + R"(, "material": 0}]},
             {"primitives": [)" + quad + R"(, "material": 1}]},
             {"primitives": [{"attributes": {"POSITION": )" + std::to_string(strip_p) +
         R"(, "NORMAL": )" + std::to_string(strip_n) + R"(, "JOINTS_0": )" +
         std::to_string(strip_j) + R"(, "WEIGHTS_0": )" + std::to_string(strip_w) +
         R"(}, "indices": )" + std::to_string(strip_i) + R"(, "material": 2}]},
             {"primitives": [)" + quad + R"(, "material": 2, "targets": [{"POSITION": )" +
         std::to_string(morph_t) + R"(}]}], "weights": [0]}],
  "nodes": [{"camera": 0, "translation": [0, 1.6, 5], "rotation": [-0.0998, 0, 0, 0.995]},
            {"mesh": 0, "scale": [4, 1, 4]},
            {"mesh": 1, "translation": [0, 3, 0], "rotation": [1, 0, 0, 0]},
            {"translation": [-1.5, 0, 0], "children": [4]},
            {"mesh": 0, "translation": [0.5, 1, 0], "rotation": [0.7071068, 0, 0, 0.7071068],
             "scale": [0.5, 1, 0.8]},
            {"mesh": 2, "skin": 0},
            {"translation": [0, 0, -1], "children": [7]},
            {},
            {"mesh": 3, "translation": [1.8, 0.6, 0.5], "scale": [0.6, 1, 0.6],
             "rotation": [0.5, 0, 0, 0.8660254]}],
  "skins": [{"joints": [6, 7]}],
  "animations": [{"channels": [{"sampler": 0, "target": {"node": 0, "path": "translation"}},
                               {"sampler": 1, "target": {"node": 3, "path": "rotation"}},
                               {"sampler": 2, "target": {"node": 7, "path": "translation"}},
                               {"sampler": 3, "target": {"node": 8, "path": "weights"}}],
                  "samplers": [{"input": )" + std::to_string(times) + R"(, "output": )" +
         std::to_string(camera_moves) + R"(},
                               {"input": )" + std::to_string(times) + R"(, "output": )" +
         std::to_string(hinge_turns) + R"(},
                               {"input": )" + std::to_string(times) + R"(, "output": )" +
         std::to_string(joint_moves) + R"(},
                               {"input": )" + std::to_string(times) + R"(, "output": )" +
         std::to_string(weights) + R"(}]}],
  )" + b.json() + "}";
}

class AnimatedSceneTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    path_ = testing::test_path("animated_scene_test.gltf");
    std::ofstream out(path_);
    out << moving_scene_json();
  }
  static std::shared_ptr<const GltfDocument> document() { return parse_gltf(path_, nullptr); }
  static std::string path_;
};
std::string AnimatedSceneTest::path_;

Image render(const Scene& scene, uint64_t seed = 5) {
  RenderSettings settings;
  settings.width = 40;
  settings.height = 30;
  settings.seed = seed;
  settings.max_depth = 3;
  RenderStats stats;
  return render_image(scene, settings, 8, 1, &stats);
}

TEST_F(AnimatedSceneTest, SplitsTheStaticPartFromWhatMoves) {
  std::vector<std::string> warnings;
  const AnimatedScene animated(document(), LoadOptions{}, &warnings);
  for (const std::string& w : warnings) ADD_FAILURE() << "unexpected warning: " << w;
  // The floor and the lamp are static world triangles; the door moves with its hinge; the
  // skinned strip (a moving joint) and the morphed quad (a weights channel) deform.
  EXPECT_EQ(animated.static_part().world().size(), 4u);
  EXPECT_EQ(animated.moving_nodes(), 1u);
  EXPECT_EQ(animated.deformed_nodes(), 2u);
  const auto pose = animated.pose(0.5);
  EXPECT_EQ(pose->world_triangle_count(), 4u + 2u + 4u + 2u);
  EXPECT_EQ(&pose->world(), &animated.static_part().world());  // shared, not copied
  ASSERT_NE(pose->deformed_meshes(), nullptr);
  EXPECT_EQ(pose->deformed_meshes()->builds(), 2u);
}

TEST_F(AnimatedSceneTest, APoseRefitFromAnotherTimeRendersLikeAFreshOne) {
  const AnimatedScene reused(document(), LoadOptions{});
  Image first = render(*reused.pose(0.2));  // its deformed meshes go back to the pool
  const auto refit = reused.pose(0.7);
  ASSERT_NE(refit->deformed_meshes(), nullptr);
  EXPECT_EQ(refit->deformed_meshes()->refits(), 2u);
  EXPECT_EQ(refit->deformed_meshes()->builds(), 0u);
  const AnimatedScene fresh_scene(document(), LoadOptions{});
  const auto fresh = fresh_scene.pose(0.7);
  EXPECT_EQ(fresh->deformed_meshes()->builds(), 2u);
  const Image a = render(*refit), b = render(*fresh);
  EXPECT_EQ(a.rgb, b.rgb);
  EXPECT_EQ(a.normal, b.normal);
  EXPECT_EQ(a.depth, b.depth);
  EXPECT_NE(a.rgb, first.rgb);  // the pose did change
  double sum = 0.0;
  for (float v : a.rgb) sum += v;
  EXPECT_GT(sum, 0.0);
  // Back to the first time through the refit set: the first image again.
  const auto back = reused.pose(0.2);
  EXPECT_EQ(render(*back).rgb, first.rgb);
}

TEST_F(AnimatedSceneTest, PosesAliveTogetherHaveSetsOfTheirOwn) {
  const AnimatedScene animated(document(), LoadOptions{});
  const AnimatedScene fresh_scene(document(), LoadOptions{});
  const auto a = animated.pose(0.3);
  const auto b = animated.pose(0.9);  // a still holds its set: b builds one
  EXPECT_EQ(b->deformed_meshes()->builds(), 2u);
  EXPECT_NE(a->deformed_meshes(), b->deformed_meshes());
  // Rendered concurrently, each is its own time.
  Image ia(1, 1), ib(1, 1);
  std::thread ta([&] { ia = render(*a); });
  std::thread tb([&] { ib = render(*b); });
  ta.join();
  tb.join();
  EXPECT_EQ(ia.rgb, render(*fresh_scene.pose(0.3)).rgb);
  EXPECT_EQ(ib.rgb, render(*fresh_scene.pose(0.9)).rgb);
}

// Against the loader's flattened scene at the same time: the same surfaces, to float rounding
// (the door is transformed at ray time by its instance instead of in its vertices).
TEST_F(AnimatedSceneTest, HitsMatchTheFlattenedSceneToRounding) {
  const AnimatedScene animated(document(), LoadOptions{});
  for (double t : {0.0, 0.45, 1.0}) {
    const auto pose = animated.pose(t);
    LoadOptions load;
    load.time = t;
    const auto flat = load_scene(path_, nullptr, load);
    const Camera& cam = flat->camera();
    EXPECT_NEAR(length(pose->camera().position - cam.position), 0.f, 1e-6f);
    int hits = 0, differ = 0;
    const Camera::Raster raster = cam.raster(64, 48);
    for (int y = 0; y < 48; ++y)
      for (int x = 0; x < 64; ++x) {
        const Vec3 o = raster.origin(x + 0.5f, y + 0.5f), d = raster.direction(x + 0.5f, y + 0.5f);
        Hit h1, h2;
        const bool f1 = pose->intersect(o, d, 1e30f, &h1), f2 = flat->intersect(o, d, 1e30f, &h2);
        if (f1 != f2 || (f1 && (std::fabs(h1.t - h2.t) > 1e-4f * h2.t ||
                                length(h1.ng - h2.ng) > 1e-4f || h1.material != h2.material))) {
          ++differ;
          continue;
        }
        hits += f1;
      }
    EXPECT_GT(hits, 1500) << "t = " << t;
    EXPECT_LE(differ, 3) << "t = " << t << ": rays on an edge may part";
    EXPECT_NEAR(length(pose->bounds_max() - flat->bounds_max()), 0.f, 1e-4f);
    EXPECT_EQ(pose->lights().size(), flat->lights().size());
  }
}

TEST_F(AnimatedSceneTest, LoadAnimatedSceneIsOnePose) {
  LoadOptions load;
  load.time = 0.6;
  const auto once = load_animated_scene(path_, nullptr, load);
  const AnimatedScene animated(document(), LoadOptions{});
  EXPECT_EQ(render(*once).rgb, render(*animated.pose(0.6)).rgb);
}

// ---- KHR_animation_pointer: a material's base colour and emissive strength, a light's
// intensity, the camera's field of view, a node's visibility and a node's translation, all
// animated by pointers over t in [0, 2] (LINEAR, the visibility STEP: hidden until t = 1),
// and a pointer to a property that is not animatable (ignored with a warning).
std::string pointer_scene_json(const std::string& extra_channel = "",
                               const std::string& visibility_interpolation = "STEP") {
  Buffer b;
  constexpr int kFloat = 5126, kUShort = 5123, kUByte = 5121;
  const int quad_p = b.add(std::vector<float>{-1, 0, -1, -1, 0, 1, 1, 0, 1, 1, 0, -1}, kFloat, 4,
                           "VEC3");
  const int quad_i = b.add(std::vector<uint16_t>{0, 1, 2, 0, 2, 3}, kUShort, 6, "SCALAR");
  const int times = b.add(std::vector<float>{0, 2}, kFloat, 2, "SCALAR");
  const int colour = b.add(std::vector<float>{1, 0, 0, 1, 0, 0, 1, 1}, kFloat, 2, "VEC4");
  const int strength = b.add(std::vector<float>{1, 5}, kFloat, 2, "SCALAR");
  const int intensity = b.add(std::vector<float>{2, 6}, kFloat, 2, "SCALAR");
  const int yfov = b.add(std::vector<float>{0.6f, 1.0f}, kFloat, 2, "SCALAR");
  const int switch_times = b.add(std::vector<float>{0, 1}, kFloat, 2, "SCALAR");
  const int visible = b.add(std::vector<uint8_t>{0, 1}, kUByte, 2, "SCALAR");
  const int slide = b.add(std::vector<float>{-2, 0.25f, 0, 2, 0.25f, 0}, kFloat, 2, "VEC3");
  auto pointer = [](int sampler, const std::string& p) {
    return R"({"sampler": )" + std::to_string(sampler) +
           R"(, "target": {"path": "pointer", "extensions": {"KHR_animation_pointer": )"
           R"({"pointer": ")" + p + "\"}}}}";
  };
  auto sampler = [](int input, int output, const std::string& interpolation = "LINEAR") {
    return R"({"input": )" + std::to_string(input) + R"(, "output": )" + std::to_string(output) +
           R"(, "interpolation": ")" + interpolation + "\"}";
  };
  const std::string mesh = R"({"primitives": [{"attributes": {"POSITION": )" +
                           std::to_string(quad_p) + R"(}, "indices": )" +
                           std::to_string(quad_i) + R"(, "material": )";
  return R"({"asset": {"version": "2.0"},
  "extensionsUsed": ["KHR_animation_pointer", "KHR_node_visibility", "KHR_lights_punctual",
                     "KHR_materials_emissive_strength"],
  "scene": 0, "scenes": [{"nodes": [0, 1, 2, 3, 4]}],
  "nodes": [{"mesh": 0, "scale": [3, 1, 3]},
            {"mesh": 1, "translation": [0, 0.5, 0], "scale": [0.5, 1, 0.5],
             "extensions": {"KHR_node_visibility": {"visible": true}}},
            {"camera": 0, "translation": [0, 4, 0], "rotation": [-0.7071068, 0, 0, 0.7071068]},
            {"translation": [0, 2, 0], "extensions": {"KHR_lights_punctual": {"light": 0}}},
            {"mesh": 1, "translation": [-2, 0.25, 0], "scale": [0.25, 1, 0.25]}],
  "meshes": [)" + mesh + R"(0}]}, )" + mesh + R"(1}]}],
  "materials": [{"pbrMetallicRoughness": {"baseColorFactor": [1, 0, 0, 1]},
                 "emissiveFactor": [1, 1, 1],
                 "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 1}}},
                {"pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.5, 0.5, 1]}}],
  "cameras": [{"type": "perspective", "perspective": {"yfov": 0.6, "znear": 0.01}}],
  "extensions": {"KHR_lights_punctual": {"lights": [{"type": "point", "intensity": 2}]}},
  "animations": [{"channels": [)" +
         pointer(0, "/materials/0/pbrMetallicRoughness/baseColorFactor") + ", " +
         pointer(1, "/materials/0/extensions/KHR_materials_emissive_strength/emissiveStrength") +
         ", " + pointer(2, "/extensions/KHR_lights_punctual/lights/0/intensity") + ", " +
         pointer(3, "/cameras/0/perspective/yfov") + ", " +
         pointer(4, "/nodes/1/extensions/KHR_node_visibility/visible") + ", " +
         pointer(5, "/nodes/4/translation") + ", " + pointer(1, "/materials/0/doubleSided") +
         extra_channel + R"(],
                  "samplers": [)" +
         sampler(times, colour) + ", " + sampler(times, strength) + ", " +
         sampler(times, intensity) + ", " + sampler(times, yfov) + ", " +
         sampler(switch_times, visible, visibility_interpolation) + ", " +
         sampler(times, slide) + R"(]}],
  )" + b.json() + "}";
}

std::string write_scene(const std::string& name, const std::string& json) {
  const std::string path = testing::test_path(name);
  std::ofstream(path) << json;
  return path;
}

// The material the ray from (x, 10, z) straight down meets first, or -1.
int material_below(const Scene& scene, float x, float z) {
  Hit hit;
  if (!scene.intersect({x, 10.f, z}, {0.f, -1.f, 0.f}, 100.f, &hit)) return -1;
  return int(hit.material);
}

// Each animated value is the glTF spec's interpolation of its keyframes at the pose's time,
// in a pose of the animated scene and in the loader's flattened scene alike.
TEST(AnimationPointerScene, MaterialsLightsCamerasVisibilityAndNodesFollowTheirPointers) {
  const std::string path = write_scene("pointer.gltf", pointer_scene_json());
  std::vector<std::string> warnings;
  const AnimatedScene animated(parse_gltf(path, &warnings), LoadOptions{}, &warnings);
  bool ignored = false;
  for (const std::string& w : warnings) {
    if (w.find("/materials/0/doubleSided") != std::string::npos &&
        w.find("channel ignored") != std::string::npos)
      ignored = true;
    else
      ADD_FAILURE() << "unexpected warning: " << w;
  }
  EXPECT_TRUE(ignored);
  for (double t : {0.5, 1.5}) {
    const double s = t / 2.0;  // LINEAR from 0 to 2
    const auto pose = animated.pose(t);
    const Material& m = pose->materials()[0];
    EXPECT_NEAR(m.albedo.x, 1.0 - s, 1e-6) << t;
    EXPECT_NEAR(m.albedo.z, s, 1e-6) << t;
    EXPECT_NEAR(m.emission.y, 1.0 + 4.0 * s, 1e-5) << t;  // emissiveFactor x strength
    ASSERT_EQ(pose->lights().punctual().size(), 1u);
    EXPECT_NEAR(pose->lights().punctual()[0].intensity.x, 2.0 + 4.0 * s, 1e-5) << t;
    EXPECT_NEAR(pose->camera().yfov, 0.6 + 0.4 * s, 1e-6) << t;
    // Hidden (STEP 0) before t = 1, shown after: the panel over the floor's centre.
    EXPECT_EQ(material_below(*pose, 0.f, 0.f), t < 1.0 ? 0 : 1) << t;
    // The slid node: from x = -2 to x = 2.
    const float x = float(-2.0 + 4.0 * s);
    EXPECT_EQ(material_below(*pose, x, 0.f), 1) << t;
    EXPECT_EQ(material_below(*pose, x + 0.5f, 0.f), 0) << t;
    // The loader's flattened scene at the same time.
    LoadOptions at;
    at.time = t;
    const Scene flat(load_gltf(path, nullptr, at));
    EXPECT_NEAR(flat.materials()[0].albedo.z, s, 1e-6) << t;
    EXPECT_NEAR(flat.camera().yfov, 0.6 + 0.4 * s, 1e-6) << t;
    EXPECT_EQ(material_below(flat, 0.f, 0.f), t < 1.0 ? 0 : 1) << t;
  }
}

// A pose finds what its hits read of each material from the pose's own values: a quad with
// texture coordinates whose KHR_materials_anisotropy strength a pointer animates from 0 at t = 0
// to 1 at t = 2 has no tangent at t = 0 (nothing needs one) and the tangent its uv layout gives
// (along +x, u running from x = -1 to x = 1 over the node's scale of 3) once the strength is
// above 0, though the file's own strength is 0.
TEST(AnimationPointerScene, APosesHitsReadWhatItsAnimatedMaterialsNeed) {
  Buffer b;
  constexpr int kFloat = 5126, kUShort = 5123;
  const int quad_p = b.add(std::vector<float>{-1, 0, -1, -1, 0, 1, 1, 0, 1, 1, 0, -1}, kFloat, 4,
                           "VEC3");
  const int quad_uv = b.add(std::vector<float>{0, 0, 0, 1, 1, 1, 1, 0}, kFloat, 4, "VEC2");
  const int quad_i = b.add(std::vector<uint16_t>{0, 1, 2, 0, 2, 3}, kUShort, 6, "SCALAR");
  const int times = b.add(std::vector<float>{0, 2}, kFloat, 2, "SCALAR");
  const int strength = b.add(std::vector<float>{0, 1}, kFloat, 2, "SCALAR");
  const std::string json = R"({"asset": {"version": "2.0"},
  "extensionsUsed": ["KHR_animation_pointer", "KHR_materials_anisotropy"],
  "scene": 0, "scenes": [{"nodes": [0]}],
  "nodes": [{"mesh": 0, "scale": [3, 1, 3]}],
  "meshes": [{"primitives": [{"attributes": {"POSITION": )" + std::to_string(quad_p) +
                           R"(, "TEXCOORD_0": )" + std::to_string(quad_uv) +
                           R"(}, "indices": )" + std::to_string(quad_i) + R"(, "material": 0}]}],
  "materials": [{"pbrMetallicRoughness": {"metallicFactor": 1, "roughnessFactor": 0.5},
                 "extensions": {"KHR_materials_anisotropy": {"anisotropyStrength": 0}}}],
  "animations": [{"channels": [{"sampler": 0, "target": {"path": "pointer", "extensions":
      {"KHR_animation_pointer": {"pointer":
       "/materials/0/extensions/KHR_materials_anisotropy/anisotropyStrength"}}}}],
    "samplers": [{"input": )" + std::to_string(times) + R"(, "output": )" +
                           std::to_string(strength) + R"(, "interpolation": "LINEAR"}]}],
  )" + b.json() + "}";
  const std::string path = write_scene("anisotropy_pointer.gltf", json);
  std::vector<std::string> warnings;
  const AnimatedScene animated(parse_gltf(path, &warnings), LoadOptions{}, &warnings);
  for (const std::string& w : warnings) ADD_FAILURE() << "unexpected warning: " << w;
  for (double t : {0.0, 0.5, 1.5}) {
    const auto pose = animated.pose(t);
    ASSERT_NEAR(pose->materials()[0].anisotropy, t / 2.0, 1e-6) << t;
    Hit hit;
    ASSERT_TRUE(pose->intersect({0.3f, 10.f, 0.2f}, {0.f, -1.f, 0.f}, 100.f, &hit)) << t;
    if (t == 0.0) {
      EXPECT_EQ(length(hit.dpdu), 0.f) << "no tangent where nothing needs one";
    } else {
      // dp/du: x runs over 2 x 3 world units while u runs over 1.
      EXPECT_NEAR(hit.dpdu.x, 6.f, 1e-4) << t;
      EXPECT_NEAR(hit.dpdu.y, 0.f, 1e-4) << t;
      EXPECT_NEAR(hit.dpdu.z, 0.f, 1e-4) << t;
    }
  }
}

// A pointer to what the file does not have, and a bool animated by anything but STEP, make
// the file invalid: refused naming the channel or sampler.
TEST(AnimationPointerScene, InvalidPointersAreRefusedByPath) {
  struct Case {
    std::string json, path;
  };
  const std::string missing = R"(, {"sampler": 1, "target": {"path": "pointer", "extensions":
      {"KHR_animation_pointer": {"pointer": "/materials/7/emissiveFactor"}}}})";
  const std::string no_pointer = R"(, {"sampler": 1, "target": {"path": "pointer"}})";
  const Case cases[] = {
      {pointer_scene_json(missing),
       "animations[0].channels[7].target.extensions.KHR_animation_pointer.pointer"},
      {pointer_scene_json(no_pointer),
       "animations[0].channels[7].target.extensions.KHR_animation_pointer.pointer"},
      {pointer_scene_json("", "LINEAR"), "animations[0].samplers[4].interpolation"},
  };
  for (const Case& c : cases) {
    const std::string path = write_scene("invalid.gltf", c.json);
    LoadOptions at;
    at.time = 0.5;
    try {
      load_gltf(path, nullptr, at);
      ADD_FAILURE() << "accepted: " << c.path;
    } catch (const SceneError& e) {
      EXPECT_EQ(e.path(), c.path) << e.what();
    }
  }
}

// ---- Motion blur: a white (emissive) half-plane whose edge moves at constant speed across
// the image during the shutter, seen by an orthographic camera. A pixel column [x, x + w) of
// the image is covered for the part of the shutter the edge e(s) = e0 + (e1 - e0) s spends
// beyond it, fractionally while it crosses it: its value is
// (1 / (e1 - e0)) integral over e in [e0, e1] of clamp((e - x) / w, 0, 1) de,
// (e1 - x - w / 2) / (e1 - e0) for a column inside the sweep: a linear ramp.
// What moves the edge: its node (an instance), the camera the other way, or a morph target
// whose weight goes from 0 to 1 (a deformed mesh, its vertices per time step).
enum class Mover { Node, Camera, Morph };

std::string edge_scene_json(Mover mover) {
  Buffer b;
  constexpr int kFloat = 5126, kUShort = 5123;
  const int pos = b.add(std::vector<float>{-10, -5, 0, 0, -5, 0, 0, 5, 0, -10, 5, 0}, kFloat, 4,
                        "VEC3");
  const int idx = b.add(std::vector<uint16_t>{0, 1, 2, 0, 2, 3}, kUShort, 6, "SCALAR");
  const int times = b.add(std::vector<float>{0, 1}, kFloat, 2, "SCALAR");
  // The edge goes from x = 0 to x = 4 in one second (or the camera from 0 to -4).
  const int moves =
      mover == Mover::Camera ? b.add(std::vector<float>{0, 0, 5, -4, 0, 5}, kFloat, 2, "VEC3")
      : mover == Mover::Node ? b.add(std::vector<float>{0, 0, 0, 4, 0, 0}, kFloat, 2, "VEC3")
                             : b.add(std::vector<float>{0, 1}, kFloat, 2, "SCALAR");
  // The morph target moves the edge's vertices (1 and 2) by 4 along x.
  const int target = b.add(std::vector<float>{0, 0, 0, 4, 0, 0, 4, 0, 0, 0, 0, 0}, kFloat, 4,
                           "VEC3");
  const std::string targets = mover == Mover::Morph
                                  ? R"(, "targets": [{"POSITION": )" + std::to_string(target) +
                                        "}]"
                                  : std::string();
  const std::string animated = mover == Mover::Camera ? "1" : "0";
  const std::string path = mover == Mover::Morph ? "weights" : "translation";
  return R"({"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0, 1]}],
  "cameras": [{"type": "orthographic",
               "orthographic": {"xmag": 4, "ymag": 1, "znear": 0.01, "zfar": 100}}],
  "materials": [{"emissiveFactor": [1, 1, 1],
                 "pbrMetallicRoughness": {"baseColorFactor": [0, 0, 0, 1]}}],
  "meshes": [{"primitives": [{"attributes": {"POSITION": )" + std::to_string(pos) +
         R"(}, "indices": )" + std::to_string(idx) + R"(, "material": 0)" + targets + R"(}]}],
  "nodes": [{"mesh": 0}, {"camera": 0, "translation": [0, 0, 5]}],
  "animations": [{"channels": [{"sampler": 0, "target": {"node": )" + animated +
         R"(, "path": ")" + path + R"("}}],
                  "samplers": [{"input": )" + std::to_string(times) + R"(, "output": )" +
         std::to_string(moves) + R"(}]}],
  )" + b.json() + "}";
}

// Each column's mean over the image's rows.
std::vector<double> column_means(const Image& image) {
  std::vector<double> out(image.width, 0.0);
  for (uint32_t y = 0; y < image.height; ++y)
    for (uint32_t x = 0; x < image.width; ++x)
      out[x] += image.rgb[3 * (size_t(y) * image.width + x)] / double(image.height);
  return out;
}

class MotionBlur : public ::testing::TestWithParam<Mover> {};

TEST_P(MotionBlur, AMovingEdgeCoversPixelsAsItsSweepSays) {
  const std::string path = testing::test_path("motion_edge.gltf");
  {
    std::ofstream out(path);
    out << edge_scene_json(GetParam());
  }
  const AnimatedScene animated(parse_gltf(path, nullptr), LoadOptions{});
  Shutter shutter;
  std::string err;
  ASSERT_TRUE(parse_shutter("0,1", 1.0, &shutter, &err)) << err;  // one frame of 1 s
  const auto blurred = animated.pose(0.0, nullptr, shutter);
  EXPECT_TRUE(blurred->has_motion());
  EXPECT_EQ(blurred->camera_moves(), GetParam() == Mover::Camera);
  EXPECT_EQ(animated.deformed_nodes(), GetParam() == Mover::Morph ? 1u : 0u);
  RenderSettings settings;
  settings.width = 64;  // the image spans x in [-4, 4]: pixels 0.125 wide
  settings.height = 16;
  settings.max_depth = 1;
  settings.seed = 11;
  RenderStats stats;
  const Image image = render_image(*blurred, settings, 1024, 2, &stats);
  const std::vector<double> got = column_means(image);
  const double w = 0.125, e0 = 0.0, e1 = 4.0;
  for (uint32_t c = 0; c < settings.width; ++c) {
    const double x = -4.0 + w * c;
    double want;
    if (x + w <= e0) {
      want = 1.0;
    } else if (x >= e1) {
      want = 0.0;
    } else {
      want = (e1 - x - w / 2) / (e1 - e0);
    }
    // 16 x 1024 samples of a value in [0, 1] per column: a standard error below 0.004.
    EXPECT_NEAR(got[c], want, 0.02) << "column " << c << " (x = " << x << ")";
  }
  // Rendered again: the same image (every sample's time is a sampler dimension).
  EXPECT_EQ(render_image(*blurred, settings, 1024, 1, &stats).rgb, image.rgb);
  // A closed shutter: the sharp edge at the frame's time (x = 2 at t = 0.5).
  const auto sharp = animated.pose(0.5);
  EXPECT_FALSE(sharp->has_motion());
  const std::vector<double> edge = column_means(render_image(*sharp, settings, 16, 1, &stats));
  for (uint32_t c = 0; c < settings.width; ++c)
    EXPECT_NEAR(edge[c], -4.0 + w * (c + 1) <= 2.0 ? 1.0 : 0.0, 1e-6) << "column " << c;
  std::remove(path.c_str());
}

INSTANTIATE_TEST_SUITE_P(NodeCameraOrMorph, MotionBlur,
                         ::testing::Values(Mover::Node, Mover::Camera, Mover::Morph));

TEST(MotionBlurShutter, ParsesFractionsOfAFrame) {
  Shutter s;
  std::string err;
  ASSERT_TRUE(parse_shutter("", 24.0, &s, &err));
  EXPECT_FALSE(s.is_open());
  ASSERT_TRUE(parse_shutter("-0.25, 0.5", 25.0, &s, &err)) << err;
  EXPECT_DOUBLE_EQ(s.open_s, -0.01);
  EXPECT_DOUBLE_EQ(s.close_s, 0.02);
  for (const char* bad : {"0.5", "0.5,0.5", "0,2", "-0.75,0.5", "a,b", "0,1,2", "nan,1"}) {
    EXPECT_FALSE(parse_shutter(bad, 24.0, &s, &err)) << bad;
    EXPECT_NE(err.find("settings.shutter"), std::string::npos) << err;
  }
}

}  // namespace
}  // namespace rf
