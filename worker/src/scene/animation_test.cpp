// glTF 2.0 animation (3.11, Appendix C), skins (3.7.3) and morph targets (3.7.2.2): the
// keyframe interpolations on their own, then through the loader (LoadOptions::time). Expected
// values are worked out here from the specification's formulas: a cubic polynomial that the
// Hermite spline reproduces exactly, rotations about one axis whose half-angle sines are
// known, skinned and morphed vertices computed by hand.
#include <gtest/gtest.h>

#include <cmath>
#include <string>
#include <vector>

#include "scene/animation.h"
#include "scene/scene.h"
#include "testing/test_scenes.h"

namespace rf {
namespace {

constexpr double kTol = 1e-12;

KeyframeTrack track(Interpolation interpolation, std::vector<double> times,
                    std::vector<double> values, size_t components, bool rotation = false) {
  KeyframeTrack t;
  t.interpolation = interpolation;
  t.times = std::move(times);
  t.values = std::move(values);
  t.components = components;
  t.rotation = rotation;
  return t;
}

// A rotation by angle about +z as a quaternion (x, y, z, w).
Quat about_z(double angle) { return {0.0, 0.0, std::sin(angle / 2.0), std::cos(angle / 2.0)}; }

void expect_quat(const std::vector<double>& got, const Quat& want, double tol = 1e-12) {
  ASSERT_EQ(got.size(), 4u);
  for (size_t i = 0; i < 4; ++i) EXPECT_NEAR(got[i], want[i], tol) << "component " << i;
}

TEST(AnimationSampler, ParsesTheThreeInterpolations) {
  Interpolation i = Interpolation::Linear;
  EXPECT_TRUE(parse_interpolation("STEP", &i));
  EXPECT_EQ(i, Interpolation::Step);
  EXPECT_TRUE(parse_interpolation("CUBICSPLINE", &i));
  EXPECT_EQ(i, Interpolation::CubicSpline);
  EXPECT_TRUE(parse_interpolation("LINEAR", &i));
  EXPECT_EQ(i, Interpolation::Linear);
  EXPECT_FALSE(parse_interpolation("linear", &i));
  EXPECT_FALSE(parse_interpolation("BEZIER", &i));
}

// STEP holds v_k on [t_k, t_k+1); outside the keys the nearest key's value.
TEST(AnimationSampler, StepHoldsEachValueUntilTheNextKey) {
  const KeyframeTrack t =
      track(Interpolation::Step, {1.0, 2.0, 3.0}, {10, 11, 12, 20, 21, 22, 30, 31, 32}, 3);
  const struct {
    double time, first;
  } cases[] = {{-5.0, 10}, {0.999, 10}, {1.0, 10}, {1.5, 10}, {1.999, 10}, {2.0, 20},
               {2.5, 20},  {3.0, 30},   {7.0, 30}};
  for (const auto& c : cases) {
    const std::vector<double> v = evaluate_track(t, c.time);
    EXPECT_EQ(v[0], c.first) << "t = " << c.time;
    EXPECT_EQ(v[2], c.first + 2) << "t = " << c.time;
  }
}

// LINEAR: (1 - s) v_k + s v_k+1 with s = (t - t_k) / (t_k+1 - t_k), clamped outside.
TEST(AnimationSampler, LinearInterpolatesAndClampsOutsideTheKeys) {
  const KeyframeTrack t = track(Interpolation::Linear, {1.0, 3.0, 4.0}, {0, 0, 0, 2, -4, 8,
                                                                         3, -4, 0}, 3);
  auto at = [&](double time) { return evaluate_track(t, time); };
  EXPECT_EQ(at(0.0), (std::vector<double>{0, 0, 0}));
  EXPECT_EQ(at(1.0), (std::vector<double>{0, 0, 0}));
  // t = 1.5: s = 0.25 of the way to (2, -4, 8).
  const std::vector<double> a = at(1.5);
  EXPECT_NEAR(a[0], 0.5, kTol);
  EXPECT_NEAR(a[1], -1.0, kTol);
  EXPECT_NEAR(a[2], 2.0, kTol);
  EXPECT_EQ(at(3.0), (std::vector<double>{2, -4, 8}));
  // t = 3.75: s = 0.75 from (2, -4, 8) to (3, -4, 0).
  const std::vector<double> b = at(3.75);
  EXPECT_NEAR(b[0], 2.75, kTol);
  EXPECT_NEAR(b[1], -4.0, kTol);
  EXPECT_NEAR(b[2], 2.0, kTol);
  EXPECT_EQ(at(4.0), (std::vector<double>{3, -4, 0}));
  EXPECT_EQ(at(100.0), (std::vector<double>{3, -4, 0}));
}

TEST(AnimationSampler, ASingleKeyframeIsConstant) {
  for (Interpolation i : {Interpolation::Step, Interpolation::Linear}) {
    const KeyframeTrack t = track(i, {2.0}, {1, 2, 3}, 3);
    for (double time : {-1.0, 2.0, 9.0}) EXPECT_EQ(evaluate_track(t, time), (std::vector<double>{1, 2, 3}));
  }
  // CUBICSPLINE: the value, not a tangent.
  const KeyframeTrack c = track(Interpolation::CubicSpline, {2.0}, {9, 9, 9, 1, 2, 3, 7, 7, 7}, 3);
  for (double time : {-1.0, 2.0, 9.0}) EXPECT_EQ(evaluate_track(c, time), (std::vector<double>{1, 2, 3}));
}

// Slerp between rotations about z by 0 and 90 degrees: at s the rotation by s * 90 degrees.
TEST(AnimationSampler, LinearRotationIsSlerp) {
  const Quat q0 = about_z(0.0), q1 = about_z(M_PI / 2.0);
  const KeyframeTrack t = track(Interpolation::Linear, {0.0, 1.0},
                                {q0[0], q0[1], q0[2], q0[3], q1[0], q1[1], q1[2], q1[3]}, 4, true);
  for (double s : {0.0, 0.25, 0.5, 0.8, 1.0})
    expect_quat(evaluate_track(t, s), about_z(s * M_PI / 2.0));
  // Plain linear interpolation would give the rotation by 45 degrees only at s = 0.5; slerp
  // has constant angular speed: at s = 0.25 the angle is 22.5 degrees (not atan(...)).
  const std::vector<double> q = evaluate_track(t, 0.25);
  EXPECT_NEAR(2.0 * std::atan2(q[2], q[3]), M_PI / 8.0, 1e-12);
}

// Rotations about z by 0 and 270 degrees: dot < 0, so slerp takes the shorter arc through
// -45 degrees (to -90 = 270), never through 135 degrees.
TEST(AnimationSampler, SlerpTakesTheShorterArc) {
  const Quat q0 = about_z(0.0), q1 = about_z(1.5 * M_PI);
  ASSERT_LT(q0[3] * q1[3] + q0[2] * q1[2], 0.0);
  const KeyframeTrack t = track(Interpolation::Linear, {0.0, 1.0},
                                {q0[0], q0[1], q0[2], q0[3], q1[0], q1[1], q1[2], q1[3]}, 4, true);
  expect_quat(evaluate_track(t, 0.5), about_z(-M_PI / 4.0));
  expect_quat(evaluate_track(t, 0.25), about_z(-M_PI / 8.0));
  // The same keys with q1 negated (the same rotation) interpolate identically.
  const KeyframeTrack u = track(Interpolation::Linear, {0.0, 1.0},
                                {q0[0], q0[1], q0[2], q0[3], -q1[0], -q1[1], -q1[2], -q1[3]}, 4,
                                true);
  expect_quat(evaluate_track(u, 0.5), about_z(-M_PI / 4.0));
}

// Quaternions closer than dot 0.9995: the normalized linear interpolation (Appendix C), within
// 1e-9 of the slerp there.
TEST(AnimationSampler, NearlyEqualRotationsInterpolateLinearly) {
  const Quat q0 = about_z(0.0), q1 = about_z(0.01);
  const Quat q = slerp(q0, q1, 0.5);
  const double lx = 0.5 * (q0[2] + q1[2]), lw = 0.5 * (q0[3] + q1[3]);
  const double n = std::sqrt(lx * lx + lw * lw);
  EXPECT_NEAR(q[2], lx / n, 1e-15);
  EXPECT_NEAR(q[3], lw / n, 1e-15);
  expect_quat(std::vector<double>(q.begin(), q.end()), about_z(0.005), 1e-9);
}

// Non-unit keys (dequantized normalized integers) are normalized.
TEST(AnimationSampler, RotationsAreNormalized) {
  const KeyframeTrack t = track(Interpolation::Step, {0.0}, {0, 0, 0, 2}, 4, true);
  expect_quat(evaluate_track(t, 0.0), {0, 0, 0, 1});
}

// f(t) = t^3 - 2 t^2 + 0.5 t + 1 is a cubic: the Hermite spline through its values with its
// derivatives f'(t) = 3t^2 - 4t + 0.5 as tangents (in-tangent a_k = out-tangent b_k = f'(t_k))
// reproduces it exactly, if and only if the tangents are scaled by the keyframe spacing td as
// Appendix C says (the spacings here differ: 1 and 1.5).
TEST(AnimationSampler, CubicSplineReproducesACubic) {
  auto f = [](double t) { return t * t * t - 2 * t * t + 0.5 * t + 1; };
  auto df = [](double t) { return 3 * t * t - 4 * t + 0.5; };
  const std::vector<double> times = {0.5, 1.5, 3.0};
  std::vector<double> values;
  for (double t : times) values.insert(values.end(), {df(t), f(t), df(t)});
  const KeyframeTrack c = track(Interpolation::CubicSpline, times, values, 1);
  for (double t : {0.5, 0.7, 1.0, 1.5, 1.51, 2.2, 2.9999})
    EXPECT_NEAR(evaluate_track(c, t)[0], f(t), 1e-12) << "t = " << t;
  // Outside: the first and last values (not the spline extended).
  EXPECT_EQ(evaluate_track(c, 0.0)[0], f(0.5));
  EXPECT_EQ(evaluate_track(c, 3.0)[0], f(3.0));
  EXPECT_EQ(evaluate_track(c, 5.0)[0], f(3.0));
}

// The four Hermite basis functions at s = 0.5 (1/2, 1/8, 1/2, -1/8), one component each.
TEST(AnimationSampler, CubicSplineBasisAtTheMidpoint) {
  // Key 0 at t = 0: a0 = 100 (unused), v0 = 1, b0 = 2; key 1 at t = 4: a1 = 3, v1 = 5.
  const KeyframeTrack c =
      track(Interpolation::CubicSpline, {0.0, 4.0}, {100, 1, 2, 3, 5, 200}, 1);
  // 0.5 * 1 + 4 * 0.125 * 2 + 0.5 * 5 + 4 * (-0.125) * 3 = 0.5 + 1 + 2.5 - 1.5.
  EXPECT_NEAR(evaluate_track(c, 2.0)[0], 2.5, kTol);
}

// A CUBICSPLINE rotation is normalized after the spline (glTF 2.0, Appendix C).
TEST(AnimationSampler, CubicSplineRotationIsNormalized) {
  const Quat q0 = about_z(0.0), q1 = about_z(M_PI / 2.0);
  std::vector<double> values;
  for (const Quat& q : {q0, q1}) {
    values.insert(values.end(), {0, 0, 0, 0});
    values.insert(values.end(), q.begin(), q.end());
    values.insert(values.end(), {0, 0, 0, 0});
  }
  const KeyframeTrack c = track(Interpolation::CubicSpline, {0.0, 1.0}, values, 4, true);
  // Zero tangents: at s = 0.5 the spline is (q0 + q1) / 2, normalized: the rotation by 45
  // degrees.
  expect_quat(evaluate_track(c, 0.5), about_z(M_PI / 4.0));
}

// Morph weights: several components per element, interpolated each.
TEST(AnimationSampler, WeightsInterpolateEveryTarget) {
  const KeyframeTrack t = track(Interpolation::Linear, {0.0, 2.0}, {0, 1, 0.5, 1, 0, 0.5}, 3);
  const std::vector<double> w = evaluate_track(t, 0.5);
  EXPECT_NEAR(w[0], 0.25, kTol);
  EXPECT_NEAR(w[1], 0.75, kTol);
  EXPECT_NEAR(w[2], 0.5, kTol);
}

TEST(AnimationPose, LaterChannelsOfTheSamePathWin) {
  ChannelTrack a{3, AnimationPath::Translation,
                 track(Interpolation::Step, {0.0}, {1, 2, 3}, 3)};
  ChannelTrack b{3, AnimationPath::Translation,
                 track(Interpolation::Step, {0.0}, {4, 5, 6}, 3)};
  ChannelTrack s{3, AnimationPath::Scale, track(Interpolation::Step, {0.0}, {2, 2, 2}, 3)};
  const std::map<int, NodePose> poses = evaluate_pose({a, b, s}, 0.0);
  ASSERT_EQ(poses.count(3), 1u);
  const NodePose& p = poses.at(3);
  EXPECT_TRUE(p.has_translation);
  EXPECT_TRUE(p.has_scale);
  EXPECT_FALSE(p.has_rotation);
  EXPECT_EQ(p.translation[0], 4.0);
  EXPECT_EQ(p.scale[2], 2.0);
}

// ---- Through the loader.

// Test buffers: views appended one after another (4-byte aligned).
struct Buffer {
  std::vector<unsigned char> bytes;
  std::vector<std::string> views;
  template <typename T>
  int add(const std::vector<T>& values) {
    while (bytes.size() % 4) bytes.push_back(0);
    const size_t offset = bytes.size();
    const auto* p = reinterpret_cast<const unsigned char*>(values.data());
    bytes.insert(bytes.end(), p, p + values.size() * sizeof(T));
    views.push_back(R"({"buffer": 0, "byteOffset": )" + std::to_string(offset) +
                    R"(, "byteLength": )" + std::to_string(values.size() * sizeof(T)) + "}");
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

std::string accessor(int view, int component_type, size_t count, const std::string& type,
                     bool normalized = false) {
  return R"({"bufferView": )" + std::to_string(view) + R"(, "componentType": )" +
         std::to_string(component_type) + R"(, "count": )" + std::to_string(count) +
         R"(, "type": ")" + type + "\"" + (normalized ? R"(, "normalized": true)" : "") + "}";
}

// A triangle (0,0,0), (1,0,0), (0,1,0) with +z normals on a node under a parent; the parent's
// rotation is animated LINEAR about z from 0 to 180 degrees over t in [0, 2], the child's
// translation STEP (0,0,0) then (0,0,5) from t = 1. Accessors: 0 positions, 1 normals,
// 2 rotation times, 3 rotations, 4 translations, 5 translation times.
std::string animated_triangle_json(const std::string& child_extra = "",
                                   const std::string& input_times = "") {
  Buffer b;
  const int pos = b.add(std::vector<float>{0, 0, 0, 1, 0, 0, 0, 1, 0});
  const int nrm = b.add(std::vector<float>{0, 0, 1, 0, 0, 1, 0, 0, 1});
  std::vector<float> times = {0.f, 2.f};
  if (input_times == "equal") times = {1.f, 1.f};
  const int tms = b.add(times);
  const int rot = b.add(std::vector<float>{0, 0, 0, 1, 0, 0, 1, 0});
  const int trn = b.add(std::vector<float>{0, 0, 0, 0, 0, 5});
  const int tms2 = b.add(std::vector<float>{0.f, 1.f});
  return R"({"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
  "nodes": [{"children": [1]}, {"mesh": 0)" + child_extra + R"(}],
  "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1}}]}],
  "animations": [{"channels": [{"sampler": 0, "target": {"node": 0, "path": "rotation"}},
                               {"sampler": 1, "target": {"node": 1, "path": "translation"}}],
                  "samplers": [{"input": 2, "output": 3},
                               {"input": 5, "output": 4, "interpolation": "STEP"}]}],
  "accessors": [)" + accessor(pos, 5126, 3, "VEC3") + ", " + accessor(nrm, 5126, 3, "VEC3") +
         ", " + accessor(tms, 5126, 2, "SCALAR") + ", " + accessor(rot, 5126, 2, "VEC4") + ", " +
         accessor(trn, 5126, 2, "VEC3") + ", " + accessor(tms2, 5126, 2, "SCALAR") + "], " +
         b.json() + "}";
}

SceneDescription load(const std::string& json, double time, std::vector<std::string>* warnings =
                                                                 nullptr) {
  LoadOptions options;
  options.time = time;
  return load_gltf_from_string(json, "", "anim.gltf", warnings, options);
}

std::string refusal(const std::string& json, double time, std::string* message = nullptr) {
  try {
    load(json, time);
  } catch (const SceneError& e) {
    if (message) *message = e.what();
    return e.path();
  }
  return "";
}

void expect_vec(Vec3 got, Vec3 want, float tol = 1e-6f) {
  EXPECT_NEAR(got.x, want.x, tol);
  EXPECT_NEAR(got.y, want.y, tol);
  EXPECT_NEAR(got.z, want.z, tol);
}

TEST(AnimationLoader, WithoutATimeTheNodesKeepTheirOwnTransforms) {
  const std::string json = animated_triangle_json();
  const SceneDescription still = load_gltf_from_string(json, "", "anim.gltf", nullptr);
  ASSERT_EQ(still.world.positions.size() >= 3, true);
  expect_vec(still.world.positions[1], {1, 0, 0}, 0.f);
  expect_vec(still.world.positions[2], {0, 1, 0}, 0.f);
}

// At t = 1 the parent has turned 90 degrees about z (slerp half way) and the child moved to
// z = 5 (STEP, exactly on its second key); at t = 0.5 45 degrees and z = 0; after the last key
// (t = 9) 180 degrees.
TEST(AnimationLoader, TheParentsRotationAndTheChildsTranslationPoseTheMesh) {
  const std::string json = animated_triangle_json();
  const SceneDescription at1 = load(json, 1.0);
  expect_vec(at1.world.positions[0], {0, 0, 5});
  expect_vec(at1.world.positions[1], {0, 1, 5});
  expect_vec(at1.world.positions[2], {-1, 0, 5});
  expect_vec(at1.world.normals[0], {0, 0, 1});
  const SceneDescription at05 = load(json, 0.5);
  const float c = float(std::cos(M_PI / 4.0));
  expect_vec(at05.world.positions[1], {c, c, 0});
  const SceneDescription at9 = load(json, 9.0);
  expect_vec(at9.world.positions[1], {-1, 0, 5});
  const SceneDescription before = load(json, -1.0);
  expect_vec(before.world.positions[1], {1, 0, 0});
}

TEST(AnimationLoader, OnlyTheChosenAnimationsApply) {
  const std::string json = animated_triangle_json();
  LoadOptions options;
  options.time = 1.0;
  options.animations = {1};
  std::string message;
  try {
    load_gltf_from_string(json, "", "anim.gltf", nullptr, options);
    ADD_FAILURE() << "animation 1 does not exist";
  } catch (const SceneError& e) {
    EXPECT_EQ(e.path(), "animations[1]");
  }
}

TEST(AnimationLoader, KeyframeTimesMustStrictlyIncrease) {
  std::string message;
  EXPECT_EQ(refusal(animated_triangle_json("", "equal"), 0.0, &message),
            "animations[0].samplers[0].input");
  EXPECT_NE(message.find("strictly increasing"), std::string::npos) << message;
}

TEST(AnimationLoader, ANodeWithAMatrixCannotBeAnimated) {
  std::string json = animated_triangle_json();
  json.replace(json.find(R"({"children": [1]})"), 17,
               R"({"children": [1], "matrix": [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1]})");
  EXPECT_EQ(refusal(json, 0.0), "animations[0].channels[0].target.node");
  // Without a time the animations are not read: the still loads as before.
  EXPECT_EQ(refusal(json, std::nan("")), "");
}

TEST(AnimationLoader, UnknownTargetPathsAreIgnoredWithAWarning) {
  std::string json = animated_triangle_json();
  json.replace(json.find(R"("path": "rotation")"), 18, R"("path": "orbit")");
  std::vector<std::string> warnings;
  const SceneDescription d = load(json, 1.0, &warnings);
  expect_vec(d.world.positions[1], {1, 0, 5});  // translated, not rotated
  bool warned = false;
  for (const std::string& w : warnings) warned = warned || w.find("'orbit'") != std::string::npos;
  EXPECT_TRUE(warned);
}

// A triangle skinned to two joints: vertex 0 fully on joint 0 (translated by
// (0, 0, 2) at t = 1), vertex 1 fully on joint 1 (static at the origin), vertex 2 half on
// each. The inverse bind matrix of joint 1 translates by (-1, 0, 0) and its node sits at
// (1, 0, 0): the bind pose. The skinned node itself is translated by (100, 0, 0), which the
// spec says is ignored.
std::string skinned_triangle_json(uint8_t joint2 = 1) {
  Buffer b;
  const int pos = b.add(std::vector<float>{0, 0, 0, 1, 0, 0, 0, 1, 0});
  const int jnt = b.add(std::vector<uint8_t>{0, 0, 0, 0, 1, 0, 0, 0, 0, joint2, 0, 0});
  const int wgt = b.add(std::vector<float>{1, 0, 0, 0, 1, 0, 0, 0, 0.5f, 0.5f, 0, 0});
  const int ibm = b.add(std::vector<float>{1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1,
                                           1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, -1, 0, 0, 1});
  const int tms = b.add(std::vector<float>{0.f, 1.f});
  const int trn = b.add(std::vector<float>{0, 0, 0, 0, 0, 2});
  return R"({"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0, 1, 2]}],
  "nodes": [{"mesh": 0, "skin": 0, "translation": [100, 0, 0]}, {}, {"translation": [1, 0, 0]}],
  "skins": [{"joints": [1, 2], "inverseBindMatrices": 3}],
  "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "JOINTS_0": 1, "WEIGHTS_0": 2}}]}],
  "animations": [{"channels": [{"sampler": 0, "target": {"node": 1, "path": "translation"}}],
                  "samplers": [{"input": 4, "output": 5}]}],
  "accessors": [)" + accessor(pos, 5126, 3, "VEC3") + ", " + accessor(jnt, 5121, 3, "VEC4") +
         ", " + accessor(wgt, 5126, 3, "VEC4") + ", " + accessor(ibm, 5126, 2, "MAT4") + ", " +
         accessor(tms, 5126, 2, "SCALAR") + ", " + accessor(trn, 5126, 2, "VEC3") + "], " +
         b.json() + "}";
}

TEST(AnimationLoader, SkinnedVerticesFollowTheirJoints) {
  const std::string json = skinned_triangle_json();
  // Rest (no time): the bind pose, the node's own translation ignored.
  const SceneDescription rest = load_gltf_from_string(json, "", "skin.gltf", nullptr);
  expect_vec(rest.world.positions[0], {0, 0, 0});
  expect_vec(rest.world.positions[1], {1, 0, 0});
  expect_vec(rest.world.positions[2], {0, 1, 0});
  // t = 0.5: joint 0 at (0, 0, 1); vertex 2 = 0.5 (v + (0,0,1)) + 0.5 v.
  const SceneDescription half = load(json, 0.5);
  expect_vec(half.world.positions[0], {0, 0, 1});
  expect_vec(half.world.positions[1], {1, 0, 0});
  expect_vec(half.world.positions[2], {0, 1, 0.5f});
}

TEST(AnimationLoader, JointIndicesOutsideTheSkinAreRefused) {
  std::string message;
  EXPECT_EQ(refusal(skinned_triangle_json(2), 0.0, &message), "accessors[1]");
  EXPECT_NE(message.find("joint 2"), std::string::npos) << message;
}

// A quad with one morph target moving vertex 2 by (0, 0, 1) and another moving every vertex
// by (1, 0, 0): weights 0.5 and 0.25 (mesh.weights) give vertex 2 + (0.25, 0, 0.5). Two nodes
// use the mesh: morphed, each gets vertices of its own (no instances).
TEST(AnimationLoader, MorphTargetsAddTheirWeightedDisplacements) {
  Buffer b;
  const int pos = b.add(std::vector<float>{-1, -1, 0, 1, -1, 0, 1, 1, 0, -1, 1, 0});
  const int t0 = b.add(std::vector<float>{0, 0, 0, 0, 0, 0, 0, 0, 1, 0, 0, 0});
  const int t1 = b.add(std::vector<float>{1, 0, 0, 1, 0, 0, 1, 0, 0, 1, 0, 0});
  const int idx = b.add(std::vector<uint16_t>{0, 1, 2, 0, 2, 3});
  const std::string json = R"({"asset": {"version": "2.0"}, "scene": 0,
  "scenes": [{"nodes": [0, 1]}], "nodes": [{"mesh": 0}, {"mesh": 0, "translation": [0, 0, 10]}],
  "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 3,
                              "targets": [{"POSITION": 1}, {"POSITION": 2}]}],
              "weights": [0.5, 0.25]}],
  "accessors": [)" + accessor(pos, 5126, 4, "VEC3") + ", " + accessor(t0, 5126, 4, "VEC3") +
                           ", " + accessor(t1, 5126, 4, "VEC3") + ", " +
                           accessor(idx, 5123, 6, "SCALAR") + "], " + b.json() + "}";
  std::vector<std::string> warnings;
  const SceneDescription d = load_gltf_from_string(json, "", "morph.gltf", &warnings);
  for (const std::string& w : warnings) ADD_FAILURE() << "unexpected warning: " << w;
  EXPECT_TRUE(d.instances.empty());
  ASSERT_EQ(d.world.positions.size() >= 8, true);
  expect_vec(d.world.positions[0], {-0.75f, -1, 0});
  expect_vec(d.world.positions[2], {1.25f, 1, 0.5f});
  expect_vec(d.world.positions[6], {1.25f, 1, 10.5f});
}

// With weights all 0 the morphed geometry is the base one: a mesh two nodes use stays one
// shared mesh placed by two instances (as before morph targets applied), and the pose report
// says where each node's vertices are.
TEST(AnimationLoader, ZeroWeightsKeepASharedMeshInstanced) {
  Buffer b;
  const int pos = b.add(std::vector<float>{0, 0, 0, 1, 0, 0, 0, 1, 0});
  const int tgt = b.add(std::vector<float>{0, 0, 1, 0, 0, 1, 0, 0, 1});
  const std::string json = R"({"asset": {"version": "2.0"}, "scene": 0,
  "scenes": [{"nodes": [0, 1, 2]}],
  "nodes": [{"mesh": 0}, {"mesh": 0, "translation": [0, 0, 3]}, {"mesh": 0, "weights": [1]}],
  "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "targets": [{"POSITION": 1}]}],
              "weights": [0]}],
  "accessors": [)" + accessor(pos, 5126, 3, "VEC3") + ", " + accessor(tgt, 5126, 3, "VEC3") +
                           "], " + b.json() + "}";
  PoseReport report;
  LoadOptions options;
  options.pose_report = &report;
  const SceneDescription d = load_gltf_from_string(json, "", "shared.gltf", nullptr, options);
  ASSERT_EQ(d.instances.size(), 2u);
  ASSERT_EQ(d.meshes.size(), 1u);
  expect_vec(d.meshes[0].geometry.positions[1], {1, 0, 0}, 0.f);
  // Node 2's weight 1 moves its own copy by the target: (1, 0, 1).
  ASSERT_EQ(report.ranges.size(), 3u);
  const PoseReport::Range& own = report.ranges[2];
  EXPECT_EQ(own.node, 2);
  EXPECT_EQ(own.instance, -1);
  EXPECT_TRUE(own.morphed);
  ASSERT_EQ(own.count, 3u);
  expect_vec(d.world.positions[own.first_vertex + 1], {1, 0, 1});
  EXPECT_EQ(report.ranges[1].instance, 1);
  EXPECT_EQ(report.ranges[1].mesh_slot, 0);
  ASSERT_EQ(report.node_world.size(), 3u);
  EXPECT_EQ(report.node_world[1].m[3][2], 3.0);
}

}  // namespace
}  // namespace rf
