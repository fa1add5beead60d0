// The Motion row of the channel table (a window of one sample, 4 float32 components): the
// screen-space motion of each pixel's first sample's first hit from the previous frame and to
// the next, in pixels, y up (Blender's Vector pass: X, Y = prev - cur, Z, W = cur - next, the
// y components negated from the image's y down). Expected values come from the construction
// of the scene (quads translating at known speeds in front of a camera of known focal length,
// a morphed quad, a static wall, a moving camera), never from the renderer.
#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <memory>
#include <string>
#include <vector>

#include "render/channels.h"
#include "render/integrators.h"
#include "render/motion.h"
#include "scene/animated_scene.h"
#include "testing/test_scenes.h"

namespace rf {
namespace {

constexpr uint32_t kWidth = 48, kHeight = 36;
constexpr double kFps = 4.0;
constexpr double kTime = 1.0;  // frame 4: the previous frame is at 0.75 s, the next at 1.25 s
// The perspective camera: tan(yfov / 2) = 0.5, so its focal length is (36 / 2) / 0.5 = 36
// pixels. The orthographic one: ymag 6, xmag 8, 3 pixels per unit.
constexpr double kFocalPx = 36.0;
constexpr double kOrthoPxPerUnit = 3.0;

struct Buffer {
  std::vector<unsigned char> bytes;
  std::vector<std::string> views, accessors;
  int add(const std::vector<float>& values, size_t count, const std::string& type) {
    const size_t offset = bytes.size();
    const auto* p = reinterpret_cast<const unsigned char*>(values.data());
    bytes.insert(bytes.end(), p, p + values.size() * sizeof(float));
    return view(offset, values.size() * sizeof(float), 5126, count, type);
  }
  int add_indices(const std::vector<uint16_t>& values) {
    const size_t offset = bytes.size();
    const auto* p = reinterpret_cast<const unsigned char*>(values.data());
    bytes.insert(bytes.end(), p, p + values.size() * sizeof(uint16_t));
    while (bytes.size() % 4) bytes.push_back(0);
    return view(offset, values.size() * sizeof(uint16_t), 5123, values.size(), "SCALAR");
  }
  int view(size_t offset, size_t length, int component_type, size_t count,
           const std::string& type) {
    views.push_back(R"({"buffer": 0, "byteOffset": )" + std::to_string(offset) +
                    R"(, "byteLength": )" + std::to_string(length) + "}");
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

// A camera at (0, 0, 10) looking down -z (perspective or orthographic) and, over t in [0, 2]
// (LINEAR), in animation 0 "objects":
//   A (node 1): a 2 x 2 quad at z = 0 whose centre slides from (-3, 2) to (1, 2): +2 units/s
//     in x, (-1, 2) at t = 1;
//   B (node 2): a 2 x 2 quad at z = -2 whose centre slides from (2, 3) to (2, -1): -2 units/s
//     in y (down the image), (2, 1) at t = 1;
//   C (node 3): a 2 x 2 quad at z = 0 centred at (-2, -2) whose morph target shifts it by
//     (4, 0, 0) at weight 1, the weight going from 0 to 1: +2 units/s in x, centred at (0, -2)
//     at t = 1 (a deformed mesh);
// and a static wall (node 4, the world's triangles) x in [-10, -4], y in [-7, 7] at z = -5;
// in animation 1 "camera", the camera's node slides from (0, 0, 10) to (2, 0, 10): +1 unit/s
// in x. Nothing right of pixel column 36.
std::string motion_gltf_json(bool orthographic) {
  Buffer b;
  const int quad_p = b.add({-1, -1, 0, 1, -1, 0, 1, 1, 0, -1, 1, 0}, 4, "VEC3");
  const int quad_i = b.add_indices({0, 1, 2, 0, 2, 3});
  const int shift = b.add({4, 0, 0, 4, 0, 0, 4, 0, 0, 4, 0, 0}, 4, "VEC3");
  const int times = b.add({0, 2}, 2, "SCALAR");
  const int a_moves = b.add({-3, 2, 0, 1, 2, 0}, 2, "VEC3");
  const int b_moves = b.add({2, 3, -2, 2, -1, -2}, 2, "VEC3");
  const int weights = b.add({0, 1}, 2, "SCALAR");
  const int camera_moves = b.add({0, 0, 10, 2, 0, 10}, 2, "VEC3");
  const std::string quad = R"({"attributes": {"POSITION": )" + std::to_string(quad_p) +
                           R"(}, "indices": )" + std::to_string(quad_i) + R"(, "material": 0)";
  const std::string camera =
      orthographic
          ? R"({"type": "orthographic", "orthographic": {"xmag": 8, "ymag": 6, "znear": 0.01,
               "zfar": 100}})"
          : R"({"type": "perspective", "perspective": {"yfov": 0.9272952180016122,
               "znear": 0.01}})";
  auto sampler = [&](int output) {
    return R"({"input": )" + std::to_string(times) + R"(, "output": )" +
           std::to_string(output) + "}";
  };
  return R"({"asset": {"version": "2.0"}, "scene": 0,
  "scenes": [{"nodes": [0, 1, 2, 3, 4]}],
  "cameras": [)" + camera + R"(],
  "materials": [{"pbrMetallicRoughness": {"baseColorFactor": [0.8, 0.8, 0.8, 1]},
                 "emissiveFactor": [1, 1, 1]}],
  "meshes": [{"primitives": [)" + quad + R"(}]},
             {"primitives": [)" + quad + R"(}]},
             {"primitives": [)" + quad + R"(, "targets": [{"POSITION": )" +
         std::to_string(shift) + R"(}]}], "weights": [0]},
             {"primitives": [)" + quad + R"(}]}],
  "nodes": [{"name": "camera", "camera": 0, "translation": [0, 0, 10]},
            {"name": "A", "mesh": 0, "translation": [-1, 2, 0]},
            {"name": "B", "mesh": 1, "translation": [2, 1, -2]},
            {"name": "C", "mesh": 2, "translation": [-2, -2, 0]},
            {"name": "wall", "mesh": 3, "translation": [-7, 0, -5], "scale": [3, 7, 1]}],
  "animations": [
    {"name": "objects",
     "channels": [{"sampler": 0, "target": {"node": 1, "path": "translation"}},
                  {"sampler": 1, "target": {"node": 2, "path": "translation"}},
                  {"sampler": 2, "target": {"node": 3, "path": "weights"}}],
     "samplers": [)" + sampler(a_moves) + ", " + sampler(b_moves) + ", " + sampler(weights) +
         R"(]},
    {"name": "camera",
     "channels": [{"sampler": 0, "target": {"node": 0, "path": "translation"}}],
     "samplers": [)" + sampler(camera_moves) + R"(]}],
  )" + b.json() + "}";
}

// A rectangle of the scene at t = 1 (world x in [x0, x1], y in [y0, y1] at depth `depth` from
// the camera's plane) and its expected Motion row in pixels.
struct Region {
  const char* name;
  double x0, x1, y0, y1, depth;
  float motion[4];
};

// The pixel rectangle a region covers: the camera at (cam_x, 0, 10), image x right, y down.
bool pixel_inside(const Region& r, bool orthographic, double cam_x, uint32_t px, uint32_t py,
                  double margin) {
  const double scale = orthographic ? kOrthoPxPerUnit : kFocalPx / r.depth;
  const double left = kWidth / 2.0 + (r.x0 - cam_x) * scale;
  const double right = kWidth / 2.0 + (r.x1 - cam_x) * scale;
  const double top = kHeight / 2.0 - r.y1 * scale;
  const double bottom = kHeight / 2.0 - r.y0 * scale;
  return px >= left + margin && px + 1.0 <= right - margin && py >= top + margin &&
         py + 1.0 <= bottom - margin;
}

// The regions of motion_gltf_json at t = 1 and their motion at kFps, for the animations
// selected: per frame (1 / 4 s) A and C move +0.5 units in x, B -0.5 units in y, and with the
// camera's animation the camera +0.25 units in x. An image displacement of (+d, +e) pixels a
// frame (x right, y down) is X = -d, Y = +e, Z = -d, W = +e.
std::vector<Region> regions(bool orthographic, bool objects, bool camera) {
  const double cam = camera ? 0.25 : 0.0, obj = objects ? 0.5 : 0.0;
  auto px = [&](double units, double depth) {
    return float(units * (orthographic ? kOrthoPxPerUnit : kFocalPx / depth));
  };
  auto moving = [&](double dx_units, double dy_units, double depth) {
    // Image displacement: x right as world x relative to the camera, y down as -world y.
    const float d = px(dx_units - cam, depth), e = px(-dy_units, depth);
    return std::vector<float>{-d, e, -d, e};
  };
  std::vector<Region> out;
  auto add = [&](const char* name, double x0, double x1, double y0, double y1, double depth,
                 const std::vector<float>& m) {
    out.push_back({name, x0, x1, y0, y1, depth, {m[0], m[1], m[2], m[3]}});
  };
  // A and B rest where t = 1 puts them, with or without the objects' animation.
  add("A", -2, 0, 1, 3, 10, moving(obj, 0, 10));
  add("B", 1, 3, 0, 2, 12, moving(0, -obj, 12));
  // C: without the objects' animation its weight is the mesh's 0 (centred at (-2, -2)).
  add("C", objects ? -1 : -3, objects ? 1 : -1, -3, -1, 10, moving(obj, 0, 10));
  add("wall", -10, -4, -7, 7, 15, moving(0, 0, 15));
  return out;
}

struct Poses {
  std::shared_ptr<const Scene> previous, current, next;
};

Poses pose_scene(const std::string& json, std::vector<int> animations,
                 const Shutter& shutter = {}) {
  const std::string path = testing::test_path("motion.gltf");
  {
    std::ofstream out(path);
    out << json;
  }
  LoadOptions load;
  load.animations = std::move(animations);
  load.image_height = kHeight;
  const AnimatedScene animated(parse_gltf(path, nullptr, load), load);
  Poses p;
  p.previous = animated.pose(kTime - 1.0 / kFps);
  p.current = animated.pose(kTime, nullptr, shutter);
  p.next = animated.pose(kTime + 1.0 / kFps);
  return p;
}

RenderSettings settings_for(IntegratorType integrator) {
  RenderSettings settings;
  settings.width = kWidth;
  settings.height = kHeight;
  settings.seed = 11;
  settings.max_depth = 2;
  settings.integrator = integrator;
  return settings;
}

// The Motion and Depth rows of the whole image over the one-sample batch at sample 0.
struct Rows {
  std::vector<float> motion, depth;
};
Rows render_motion(const Scene& scene, const RenderSettings& settings,
                   const MotionPoses* poses) {
  TileBuffer tile;
  EXPECT_TRUE(render_rect(scene, settings, {0, 0, kWidth, kHeight}, 0, 1, &tile, nullptr,
                          channels::bit(channels::Id::Motion) |
                              channels::bit(channels::Id::Depth),
                          poses));
  return {tile.sum(channels::Id::Motion), tile.sum(channels::Id::Depth)};
}

// Every pixel inside a region (by `margin` pixels more than its samples' footprint) has the
// region's motion within float32 rounding; every pixel right of column 36 (nothing there)
// and every pixel whose camera ray missed has 0. Returns the pixels checked per region.
std::vector<int> check_rows(const Rows& rows, const std::vector<Region>& expected,
                            bool orthographic, double cam_x, double margin,
                            const std::string& what) {
  std::vector<int> counts(expected.size(), 0);
  for (uint32_t y = 0; y < kHeight; ++y)
    for (uint32_t x = 0; x < kWidth; ++x) {
      const size_t i = size_t(y) * kWidth + x;
      const float* m = &rows.motion[4 * i];
      if (x >= 36 || rows.depth[i] == 1e10f) {
        if (x >= 36) {
          EXPECT_EQ(rows.depth[i], 1e10f) << what << " pixel " << x << "," << y;
        }
        for (int c = 0; c < 4; ++c) {
          EXPECT_EQ(m[c], 0.f) << what << " miss " << x << "," << y << " component " << c;
        }
        continue;
      }
      for (size_t k = 0; k < expected.size(); ++k) {
        if (!pixel_inside(expected[k], orthographic, cam_x, x, y, margin)) continue;
        ++counts[k];
        for (int c = 0; c < 4; ++c) {
          EXPECT_NEAR(m[c], expected[k].motion[c], 1e-3f)
              << what << " " << expected[k].name << " pixel " << x << "," << y
              << " component " << c;
        }
      }
    }
  return counts;
}

class MotionRow : public ::testing::TestWithParam<bool> {};  // orthographic?

// Objects moving in front of a still camera: A and C (an instance and a morphed mesh) move
// right, B (deeper) down, the wall (world triangles) stays; for the path, direct and ao
// integrators alike.
TEST_P(MotionRow, MovingObjectsHaveTheirAnalyticPixelMotion) {
  const bool ortho = GetParam();
  const Poses p = pose_scene(motion_gltf_json(ortho), {0});
  const MotionPoses poses(*p.current, 0.f, *p.previous, *p.next, kWidth, kHeight);
  const std::vector<Region> expected = regions(ortho, true, false);
  for (IntegratorType integrator :
       {IntegratorType::Path, IntegratorType::Direct, IntegratorType::AmbientOcclusion}) {
    const Rows rows = render_motion(*p.current, settings_for(integrator), &poses);
    const std::vector<int> counts =
        check_rows(rows, expected, ortho, 0.0, 0.0, integrator_type_name(integrator));
    for (size_t k = 0; k < expected.size(); ++k)
      EXPECT_GE(counts[k], 4) << expected[k].name;
  }
  // Y = -(prev.y - cur.y): B moving down the image has Y, W > 0; A moving right X, Z < 0.
  EXPECT_GT(expected[1].motion[1], 1.f);
  EXPECT_LT(expected[0].motion[0], -1.f);
}

// A moving camera adds its own motion: with the camera sliding right every point slides left
// in the image, the static wall included, by focal length x 0.25 / depth pixels a frame.
TEST_P(MotionRow, AMovingCameraMovesEveryPoint) {
  const bool ortho = GetParam();
  const Poses p = pose_scene(motion_gltf_json(ortho), {});  // both animations
  const MotionPoses poses(*p.current, 0.f, *p.previous, *p.next, kWidth, kHeight);
  const std::vector<Region> expected = regions(ortho, true, true);
  const Rows rows = render_motion(*p.current, settings_for(IntegratorType::Path), &poses);
  // The camera is at x = 1 at t = 1.
  const std::vector<int> counts = check_rows(rows, expected, ortho, 1.0, 0.0, "camera");
  for (size_t k = 0; k < expected.size(); ++k) EXPECT_GE(counts[k], 4) << expected[k].name;
  EXPECT_GT(expected[3].motion[0], 0.f);  // the wall moves left: X = prev.x - cur.x > 0
}

// A still (no poses: what the farm passes for a task with animated = false) has 0 everywhere,
// and so has a pose whose neighbours are itself.
TEST_P(MotionRow, AStillHasNoMotion) {
  const bool ortho = GetParam();
  const Poses p = pose_scene(motion_gltf_json(ortho), {0});
  const Rows still = render_motion(*p.current, settings_for(IntegratorType::Path), nullptr);
  for (float v : still.motion) EXPECT_EQ(v, 0.f);
  const MotionPoses same(*p.current, 0.f, *p.current, *p.current, kWidth, kHeight);
  const Rows rows = render_motion(*p.current, settings_for(IntegratorType::Path), &same);
  int hits = 0;
  for (size_t i = 0; i < size_t(kWidth) * kHeight; ++i) {
    hits += rows.depth[i] != 1e10f;
    for (int c = 0; c < 4; ++c) EXPECT_EQ(rows.motion[4 * i + c], 0.f) << "pixel " << i;
  }
  EXPECT_GT(hits, 100);
}

// Motion blur: with the shutter open over [0, 0.5] frames after the frame's time, the first
// hit (found at the sample's time in the shutter) is followed from where it is at the frame's
// time, so a uniformly moving quad has the same motion as with the shutter closed (pixels
// inside it during the whole shutter: a margin of 1.2 pixels, A's and C's travel over it).
TEST_P(MotionRow, AnOpenShutterTakesThePointAtTheFramesTime) {
  const bool ortho = GetParam();
  const Shutter shutter{0.0, 0.5 / kFps};
  const Poses p = pose_scene(motion_gltf_json(ortho), {0}, shutter);
  ASSERT_TRUE(p.current->has_motion());
  EXPECT_EQ(frame_shutter_time(shutter), 0.f);
  EXPECT_EQ(frame_shutter_time(Shutter{-0.25, 0.25}), 0.5f);
  EXPECT_EQ(frame_shutter_time(Shutter{0.1, 0.3}), 0.f);
  EXPECT_EQ(frame_shutter_time(Shutter{-0.3, -0.1}), 1.f);
  const MotionPoses poses(*p.current, frame_shutter_time(shutter), *p.previous, *p.next,
                          kWidth, kHeight);
  const std::vector<Region> expected = regions(ortho, true, false);
  const Rows rows = render_motion(*p.current, settings_for(IntegratorType::Path), &poses);
  const std::vector<int> counts = check_rows(rows, expected, ortho, 0.0, 1.2, "shutter");
  for (size_t k = 0; k < expected.size(); ++k) EXPECT_GE(counts[k], 1) << expected[k].name;
}

INSTANTIATE_TEST_SUITE_P(Cameras, MotionRow, ::testing::Values(false, true),
                         [](const ::testing::TestParamInfo<bool>& param) {
                           return std::string(param.param ? "Orthographic" : "Perspective");
                         });

// An orthographic view (3 pixels a unit) of one morphed mesh of two 2 x 2 quads at z = 0, in
// this order: P (triangles 0 and 1) centred at (-4, 0) and Q (triangles 2 and 3) centred at
// (-1, 0); and a static wall (the world's triangles) x in [-8, -6], y in [-6, 6] at z = -5.
// Morph target 0 moves P's four vertices onto P's centre (zero area), target 1 moves Q by
// (2, 0, 0) a unit of weight. Over t = 0, 1, 1.25, 2 (LINEAR) the weights are (0, 0), (0, 1),
// (1, 1.25), (1, 2): at t = 1 P is whole and Q centred at (1, 0); Q moves +2 units/s in x
// throughout, and P, whole at the previous frame (0.75 s) and at t, is collapsed onto its
// centre at the next (1.25 s).
std::string collapsing_gltf_json() {
  Buffer b;
  const int quads_p = b.add({-5, -1, 0, -3, -1, 0, -3, 1, 0, -5, 1, 0,
                             -2, -1, 0, 0, -1, 0, 0, 1, 0, -2, 1, 0},
                            8, "VEC3");
  const int quads_i = b.add_indices({0, 1, 2, 0, 2, 3, 4, 5, 6, 4, 6, 7});
  const int collapse = b.add({1, 1, 0, -1, 1, 0, -1, -1, 0, 1, -1, 0,
                              0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0},
                             8, "VEC3");
  const int shift = b.add({0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0,
                           2, 0, 0, 2, 0, 0, 2, 0, 0, 2, 0, 0},
                          8, "VEC3");
  const int wall_p = b.add({-1, -1, 0, 1, -1, 0, 1, 1, 0, -1, 1, 0}, 4, "VEC3");
  const int wall_i = b.add_indices({0, 1, 2, 0, 2, 3});
  const int times = b.add({0, 1, 1.25, 2}, 4, "SCALAR");
  const int weights = b.add({0, 0, 0, 1, 1, 1.25, 1, 2}, 8, "SCALAR");
  return R"({"asset": {"version": "2.0"}, "scene": 0,
  "scenes": [{"nodes": [0, 1, 2]}],
  "cameras": [{"type": "orthographic", "orthographic": {"xmag": 8, "ymag": 6, "znear": 0.01,
               "zfar": 100}}],
  "materials": [{"pbrMetallicRoughness": {"baseColorFactor": [0.8, 0.8, 0.8, 1]},
                 "emissiveFactor": [1, 1, 1]}],
  "meshes": [{"primitives": [{"attributes": {"POSITION": )" + std::to_string(quads_p) +
         R"(}, "indices": )" + std::to_string(quads_i) + R"(, "material": 0,
               "targets": [{"POSITION": )" + std::to_string(collapse) + R"(},
                           {"POSITION": )" + std::to_string(shift) + R"(}]}],
              "weights": [0, 0]},
             {"primitives": [{"attributes": {"POSITION": )" + std::to_string(wall_p) +
         R"(}, "indices": )" + std::to_string(wall_i) + R"(, "material": 0}]}],
  "nodes": [{"name": "camera", "camera": 0, "translation": [0, 0, 10]},
            {"name": "PQ", "mesh": 0},
            {"name": "wall", "mesh": 1, "translation": [-7, 0, -5], "scale": [1, 6, 1]}],
  "animations": [{"name": "morph",
     "channels": [{"sampler": 0, "target": {"node": 1, "path": "weights"}}],
     "samplers": [{"input": )" + std::to_string(times) + R"(, "output": )" +
         std::to_string(weights) + R"(}]}],
  )" + b.json() + "}";
}

// The poses name a deformed mesh's triangles alike even where one is degenerate in a pose
// (the Scene keeps a pose's degenerate triangles, with a zero face normal, instead of dropping
// them: clean_mesh with drop false), so the Motion row follows each triangle by its index:
// Q, after P in the mesh, has its analytic motion (+0.5 units = 1.5 pixels right a frame: X =
// Z = -1.5, Y = W = 0) although P collapses at the next frame; P's points follow P's vertices,
// so each goes to P's centre at the next frame (raster (12, 18)): X = Y = 0, Z = cur.x - 12,
// W = -(cur.y - 18), cur somewhere in the pixel (one jittered sample). Were P's triangles
// dropped from the next pose, Q would be its triangles 0 and 1 there and Q's pixels 0.
TEST(MotionRowDeformed, ATriangleCollapsedInAnotherPoseKeepsTheOthersInPlace) {
  const Poses p = pose_scene(collapsing_gltf_json(), {});
  for (const Scene* s : {p.previous.get(), p.current.get(), p.next.get()}) {
    ASSERT_EQ(s->slot_mesh(1).size(), 4u);
  }
  const TriangleMesh& collapsed = p.next->slot_mesh(1);
  EXPECT_EQ(length(collapsed.face_normals[0]), 0.f);
  EXPECT_EQ(length(collapsed.face_normals[1]), 0.f);
  EXPECT_GT(length(collapsed.face_normals[2]), 0.5f);
  const MotionPoses poses(*p.current, 0.f, *p.previous, *p.next, kWidth, kHeight);
  const Rows rows = render_motion(*p.current, settings_for(IntegratorType::Path), &poses);
  const Region q{"Q", 0, 2, -1, 1, 10, {-1.5f, 0.f, -1.5f, 0.f}};
  const Region wall{"wall", -8, -6, -6, 6, 15, {0.f, 0.f, 0.f, 0.f}};
  const std::vector<int> counts = check_rows(rows, {q, wall}, true, 0.0, 0.0, "collapse");
  EXPECT_GE(counts[0], 16);
  EXPECT_GE(counts[1], 16);
  const Region p_region{"P", -5, -3, -1, 1, 10, {}};
  int p_pixels = 0;
  for (uint32_t y = 0; y < kHeight; ++y)
    for (uint32_t x = 0; x < kWidth; ++x) {
      if (!pixel_inside(p_region, true, 0.0, x, y, 0.0)) continue;
      ++p_pixels;
      const float* m = &rows.motion[4 * (size_t(y) * kWidth + x)];
      EXPECT_NEAR(m[0], 0.f, 1e-3f) << "P pixel " << x << "," << y;
      EXPECT_NEAR(m[1], 0.f, 1e-3f) << "P pixel " << x << "," << y;
      EXPECT_GE(m[2], float(x) - 12.f - 1e-3f) << "P pixel " << x << "," << y;
      EXPECT_LE(m[2], float(x) + 1.f - 12.f + 1e-3f) << "P pixel " << x << "," << y;
      EXPECT_GE(m[3], 18.f - float(y) - 1.f - 1e-3f) << "P pixel " << x << "," << y;
      EXPECT_LE(m[3], 18.f - float(y) + 1e-3f) << "P pixel " << x << "," << y;
    }
  EXPECT_EQ(p_pixels, 36);
}

// KHR_node_visibility animated: over t in [0, 2], with the orthographic camera at (0, 0, 10),
//   H (node 1): a 2 x 2 quad centred at (-4, 2), visible until t = 1.1 (STEP), so visible at
//     the previous frame and at t = 1 but hidden at the next (1.25 s): in that pose it has no
//     instance, and M's instance, after it, takes its slot;
//   M (node 2): the same quad sliding from (-3, -2) to (1, -2): +2 units/s in x;
//   HL (node 3): a LINES segment from (-7, -4.5) to (-5, -4.5), hidden as H is;
//   ML (node 4): a LINES segment, x in [-2, 2] at t = 1, y = 4.5 (pixel row 4), sliding as M.
std::string hiding_gltf_json() {
  Buffer b;
  const int quad_p = b.add({-1, -1, 0, 1, -1, 0, 1, 1, 0, -1, 1, 0}, 4, "VEC3");
  const int quad_i = b.add_indices({0, 1, 2, 0, 2, 3});
  const int line_p = b.add({-1, 0, 0, 1, 0, 0}, 2, "VEC3");
  const int times = b.add({0, 2}, 2, "SCALAR");
  const int m_moves = b.add({-3, -2, 0, 1, -2, 0}, 2, "VEC3");
  const int ml_moves = b.add({-2, 4.5f, 0, 2, 4.5f, 0}, 2, "VEC3");
  const int switch_times = b.add({0, 1.1f}, 2, "SCALAR");
  const size_t offset = b.bytes.size();
  b.bytes.push_back(1);
  b.bytes.push_back(0);
  const int visible = b.view(offset, 2, 5121, 2, "SCALAR");
  while (b.bytes.size() % 4) b.bytes.push_back(0);
  auto sampler = [](int input, int output, const char* interpolation) {
    return R"({"input": )" + std::to_string(input) + R"(, "output": )" +
           std::to_string(output) + R"(, "interpolation": ")" + interpolation + "\"}";
  };
  auto hide = [](int sampler_index, int node) {
    return R"({"sampler": )" + std::to_string(sampler_index) +
           R"(, "target": {"path": "pointer", "extensions": {"KHR_animation_pointer": )"
           R"({"pointer": "/nodes/)" + std::to_string(node) +
           R"(/extensions/KHR_node_visibility/visible"}}}})";
  };
  const std::string shown = R"("extensions": {"KHR_node_visibility": {"visible": true}})";
  return R"({"asset": {"version": "2.0"}, "scene": 0,
  "extensionsUsed": ["KHR_animation_pointer", "KHR_node_visibility"],
  "scenes": [{"nodes": [0, 1, 2, 3, 4]}],
  "cameras": [{"type": "orthographic", "orthographic": {"xmag": 8, "ymag": 6, "znear": 0.01,
               "zfar": 100}}],
  "materials": [{"pbrMetallicRoughness": {"baseColorFactor": [0.8, 0.8, 0.8, 1]},
                 "emissiveFactor": [1, 1, 1]}],
  "meshes": [{"primitives": [{"attributes": {"POSITION": )" + std::to_string(quad_p) +
         R"(}, "indices": )" + std::to_string(quad_i) + R"(, "material": 0}]},
             {"primitives": [{"attributes": {"POSITION": )" + std::to_string(line_p) +
         R"(}, "mode": 1, "material": 0}]}],
  "nodes": [{"name": "camera", "camera": 0, "translation": [0, 0, 10]},
            {"name": "H", "mesh": 0, "translation": [-4, 2, 0], )" + shown + R"(},
            {"name": "M", "mesh": 0, "translation": [-1, -2, 0]},
            {"name": "HL", "mesh": 1, "translation": [-6, -4.5, 0], )" + shown + R"(},
            {"name": "ML", "mesh": 1, "translation": [0, 4.5, 0], "scale": [2, 1, 1]}],
  "animations": [{"name": "hide and slide",
     "channels": [{"sampler": 0, "target": {"node": 2, "path": "translation"}},
                  {"sampler": 1, "target": {"node": 4, "path": "translation"}}, )" +
         hide(2, 1) + ", " + hide(2, 3) + R"(],
     "samplers": [)" + sampler(times, m_moves, "LINEAR") + ", " +
         sampler(times, ml_moves, "LINEAR") + ", " + sampler(switch_times, visible, "STEP") +
         R"(]}],
  )" + b.json() + "}";
}

// A node hidden in the pose after (or before) shifts the later instances' slots and thin
// triangles down in that pose; the Motion row maps them by node and occurrence (MotionPoses),
// so M and ML, after H and HL, have their analytic motion (+0.5 units = 1.5 pixels right a
// frame: X = Z = -1.5, Y = W = 0). H and HL, absent from the next pose, have motion 0 (the
// documented rule). Read by slot, M would be looked for at a slot the next pose has not (0)
// and H at M's (H's pixels M's motion plus the distance between them), and ML at thin
// triangles the next pose has not.
TEST(MotionRowVisibility, ANodeHiddenInAnotherPoseKeepsTheLaterOnesInPlace) {
  const Poses p = pose_scene(hiding_gltf_json(), {});
  ASSERT_EQ(p.previous->instance_count(), p.current->instance_count());
  // H and HL (an empty mesh of its own: lines only) have no instance in the next pose.
  ASSERT_EQ(p.next->instance_count() + 2, p.current->instance_count());
  const MotionPoses poses(*p.current, 0.f, *p.previous, *p.next, kWidth, kHeight);
  const Rows rows = render_motion(*p.current, settings_for(IntegratorType::Path), &poses);
  const Region m{"M", -2, 0, -3, -1, 10, {-1.5f, 0.f, -1.5f, 0.f}};
  const Region h{"H", -5, -3, 1, 3, 10, {0.f, 0.f, 0.f, 0.f}};
  const std::vector<int> counts = check_rows(rows, {m, h}, true, 0.0, 0.0, "hidden");
  EXPECT_EQ(counts[0], 36);
  EXPECT_EQ(counts[1], 36);
  // The lines: pixel rows 4 (ML, columns 18 to 29) and 31 (HL, columns 3 to 8), where hit.
  auto check_line = [&](const char* name, uint32_t row, uint32_t x0, uint32_t x1, float x) {
    int hits = 0;
    for (uint32_t col = x0 + 1; col < x1; ++col) {
      const size_t i = size_t(row) * kWidth + col;
      if (rows.depth[i] == 1e10f) continue;
      ++hits;
      const float expected[4] = {x, 0.f, x, 0.f};
      for (int c = 0; c < 4; ++c) {
        EXPECT_NEAR(rows.motion[4 * i + size_t(c)], expected[c], 1e-3f)
            << name << " pixel " << col << "," << row << " component " << c;
      }
    }
    EXPECT_GE(hits, 4) << name;
  };
  check_line("ML", 4, 18, 29, -1.5f);
  check_line("HL", 31, 3, 8, 0.f);
}

// Camera::project inverts the raster: the point at distance s along the ray through (px, py)
// projects back to (px, py); a point behind the camera (or behind its plane) does not project.
TEST(CameraProject, InvertsTheRasterAndRefusesPointsBehind) {
  for (bool ortho : {false, true}) {
    Camera camera;
    camera.position = Vec3(1.f, 2.f, 3.f);
    camera.forward = normalize(Vec3(0.3f, -0.2f, -1.f));
    camera.right = normalize(cross(camera.forward, Vec3(0.f, 1.f, 0.f)));
    camera.up = cross(camera.right, camera.forward);
    camera.orthographic = ortho;
    camera.xmag = 4.f;
    camera.ymag = 3.f;
    const Camera::Raster r = camera.raster(40, 30);
    for (float px : {0.f, 3.25f, 20.f, 39.5f})
      for (float py : {0.f, 7.75f, 29.f}) {
        const Vec3 p = r.origin(px, py) + r.direction(px, py) * 7.f;
        float x = -1.f, y = -1.f;
        ASSERT_TRUE(Camera::project(r, p, &x, &y));
        EXPECT_NEAR(x, px, 1e-3f);
        EXPECT_NEAR(y, py, 1e-3f);
      }
    float x, y;
    EXPECT_FALSE(Camera::project(r, camera.position - camera.forward, &x, &y));
    EXPECT_FALSE(Camera::project(r, camera.position + camera.right - camera.forward * 1e-3f,
                                 &x, &y));
  }
}

}  // namespace
}  // namespace rf
