// glTF 2.0 animation, skins and morph targets, evaluated at one time: keyframe samplers (3.11
// and Appendix C: STEP, LINEAR with slerp for rotations, CUBICSPLINE), the node poses their
// channels give, the skin matrices of vertices (3.7.3) and morph target sums (3.7.2.2). The
// glTF loader reads the file's accessors into these types (gltf_animation.cpp) and applies the
// pose where it flattens the node hierarchy (gltf_loader.cpp); nothing here reads a file.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <map>
#include <string>
#include <vector>

#include "math/vecmath.h"

namespace rf {

// An animation sampler's interpolation (glTF 2.0, 3.11.2.1).
enum class Interpolation { Step, Linear, CubicSpline };
// "STEP", "LINEAR", "CUBICSPLINE" (the glTF names); false for anything else.
bool parse_interpolation(const std::string& name, Interpolation* out);

// What a channel animates: a node's translation, rotation, scale or morph target weights.
enum class AnimationPath { Translation, Rotation, Scale, Weights };

// One sampler's keyframes: times (seconds, strictly increasing, at least one) and values,
// `components` numbers per element (3 for translation and scale, 4 for rotation quaternions
// (x, y, z, w), the morph target count for weights). STEP and LINEAR tracks have one element
// per keyframe; CUBICSPLINE tracks three, in-tangent a_k, value v_k and out-tangent b_k.
struct KeyframeTrack {
  Interpolation interpolation = Interpolation::Linear;
  std::vector<double> times;
  std::vector<double> values;
  size_t components = 0;
  // The values are unit quaternions: LINEAR slerps them (the shorter arc), every result is
  // normalized.
  bool rotation = false;
};

// The track's value at time t (glTF 2.0, Appendix C), components numbers into out. Before the
// first keyframe it is the first value, after the last the last one; a single keyframe is a
// constant. Between keyframes t_k <= t < t_k+1, with td = t_k+1 - t_k and s = (t - t_k) / td:
// STEP v_k; LINEAR (1 - s) v_k + s v_k+1, or slerp(v_k, v_k+1, s) for rotations; CUBICSPLINE
// the Hermite spline (2s^3 - 3s^2 + 1) v_k + td (s^3 - 2s^2 + s) b_k + (-2s^3 + 3s^2) v_k+1
// + td (s^3 - s^2) a_k+1.
void evaluate_track(const KeyframeTrack& track, double t, double* out);
std::vector<double> evaluate_track(const KeyframeTrack& track, double t);

using Quat = std::array<double, 4>;  // (x, y, z, w)
// q / |q| (q itself if it is 0).
Quat normalize_quat(const Quat& q);
// Appendix C's slerp of unit quaternions: b is negated when dot(a, b) < 0 (the shorter arc),
// nearly equal ones (dot > 0.9995) are interpolated linearly; the result is normalized.
Quat slerp(const Quat& a, Quat b, double s);

// What the animations make of one node at a time: the paths they animate, which replace the
// node's own translation, rotation, scale or (mesh) weights.
struct NodePose {
  bool has_translation = false, has_rotation = false, has_scale = false, has_weights = false;
  std::array<double, 3> translation{{0.0, 0.0, 0.0}};
  Quat rotation{{0.0, 0.0, 0.0, 1.0}};
  std::array<double, 3> scale{{1.0, 1.0, 1.0}};
  std::vector<double> weights;
};

// One channel of an animation: the node and path it animates and its sampler's keyframes.
struct ChannelTrack {
  int node = -1;
  AnimationPath path = AnimationPath::Translation;
  KeyframeTrack track;
};

// The poses the channels give at time t, per animated node. Channels are applied in order: a
// later channel of the same node and path replaces an earlier one.
std::map<int, NodePose> evaluate_pose(const std::vector<ChannelTrack>& channels, double t);

// The skin matrix of a vertex (glTF 2.0, 3.7.3.3): sum_i weight_i joint_matrix[joint_i], where
// joint_matrix[j] = globalTransform(joints[j]) * inverseBindMatrix[j]; n influences.
Mat4 blend_skin_matrix(const std::vector<Mat4>& joint_matrices, const uint32_t* joints,
                       const double* weights, size_t n);

// m applied to the point p (3 numbers; the bottom row of m is not used) and to the normal n
// (with m's inverse transpose up to scale, Mat4::normal_matrix; not normalized).
Vec3 transform_point(const Mat4& m, const double* p);
Vec3 transform_normal(const Mat4& m, const double* n);

// How the loader splits an animated scene into what a time changes and what it does not
// (LoadOptions::layout; AnimatedScene, animated_scene.h, builds on it). A node "moves" if a
// chosen animation targets the translation, rotation or scale of it or of a node on its path
// to the root. A mesh node whose deformation varies (a skin with a moving joint, a weights
// channel on the node, or a morphed node that moves) gets a mesh of its own, in world space,
// placed at the identity; the mesh of a moving node is kept in its own space (once per glTF
// mesh) and placed by an instance at the node's world matrix; everything else is flattened
// or instanced as in a still. The description lists every mesh in both modes, with the same
// numbering and the same instances; each mode fills only its own meshes, the others stay
// empty.
struct AnimatedLayout {
  // In. false: the static part (the world triangles and the meshes of moving and shared
  // nodes; deformed meshes empty). true: one time's pose (only the deformed meshes, camera,
  // lights and instances; no world triangles, no textures).
  bool pose_only = false;
  // Out, per mesh of the description: whether it is a varying deformed mesh.
  std::vector<char> deformed_mesh;
  // Out: the mesh nodes that move rigidly and those deformed per time.
  uint32_t moving_nodes = 0, deformed_nodes = 0;
};

// A loaded scene's pose, filled by the loader when LoadOptions::pose_report is set (the
// `renderfarm-worker pose` command): every node's world matrix, the node of the camera, and
// where each mesh node's vertices went.
struct PoseReport {
  std::vector<Mat4> node_world;  // per glTF node (nodes outside the scene: from their roots)
  int camera_node = -1;          // the node whose camera the scene renders through, or -1
  // The vertices of a mesh node: positions [first_vertex, first_vertex + count) of the
  // world mesh (instance -1) or of SceneDescription::meshes[mesh_slot] placed by instance
  // `instance` (an index into SceneDescription::instances).
  struct Range {
    int node = -1, mesh = -1;
    int instance = -1, mesh_slot = -1;
    uint32_t first_vertex = 0, count = 0;
    bool skinned = false, morphed = false;
  };
  std::vector<Range> ranges;
};

}  // namespace rf
