// The glTF loader's animation, skins and morph targets (Loader, gltf_loader_internal.h; glTF
// 2.0, 3.11, 3.7.3, 3.7.2.2): the chosen animations' channels and samplers, read, checked and
// evaluated at the load's time (animation.h has the math), node poses and world matrices, skin
// joint matrices, morph target weights, and a deformed primitive's vertices.
#include "scene/gltf_loader_internal.h"

#include <algorithm>
#include <cmath>
#include <map>
#include <optional>
#include <string>
#include <vector>

namespace rf::gltf_detail {

// The animations' pose at options_.time (none without a time): every channel of the chosen
// animations, checked and evaluated: the four node paths of glTF 2.0, and
// KHR_animation_pointer's pointers (animation_pointer.h), whose node transforms join the
// pose and whose materials, lights, cameras and visibility evaluate_pointers writes. A path
// the renderer does not animate is ignored with a warning.
void Loader::evaluate_animations() {
  if (!options_.animated()) return;
  std::vector<int> chosen = options_.animations;
  if (chosen.empty())
    for (size_t a = 0; a < model_.animations.size(); ++a) chosen.push_back(int(a));
  std::vector<ChannelTrack> channels;
  for (const int a : chosen) {
    const std::string at = "animations[" + std::to_string(a) + "]";
    if (a < 0 || a >= int(model_.animations.size()))
      fail(at + ": no such animation (the scene has " +
           std::to_string(model_.animations.size()) + ")");
    const tinygltf::Animation& anim = model_.animations[size_t(a)];
    for (size_t k = 0; k < anim.channels.size(); ++k) {
      const tinygltf::AnimationChannel& ch = anim.channels[k];
      const std::string cw = at + ".channels[" + std::to_string(k) + "]";
      ChannelTrack track;
      const bool pointer = ch.target_path == "pointer";
      int n = ch.target_node;
      std::string node_at = cw + ".target.node";
      if (pointer) {
        // A node's transform or weights continue below; the rest is kept by pointer_channel.
        if (!pointer_channel(ch, a, cw, &track)) continue;
        n = track.node;
        node_at = cw + ".target.extensions.KHR_animation_pointer.pointer";
      } else if (ch.target_path == "translation") {
        track.path = AnimationPath::Translation;
      } else if (ch.target_path == "rotation") {
        track.path = AnimationPath::Rotation;
      } else if (ch.target_path == "scale") {
        track.path = AnimationPath::Scale;
      } else if (ch.target_path == "weights") {
        track.path = AnimationPath::Weights;
      } else {
        warn(cw + ".target.path: '" + ch.target_path +
             "' is not translation, rotation, scale, weights or pointer; channel ignored");
        continue;
      }
      if (n < 0 || n >= int(model_.nodes.size()))
        fail(node_at + ": refers to missing node " + std::to_string(n));
      const tinygltf::Node& node = model_.nodes[size_t(n)];
      if (!node.matrix.empty())
        fail(node_at + ": node " + std::to_string(n) +
             " has a 'matrix'; glTF 2.0 (3.11) allows animating only nodes whose transform "
             "is translation, rotation and scale");
      size_t components = track.path == AnimationPath::Rotation ? 4 : 3;
      if (track.path == AnimationPath::Weights) {
        components = node.mesh >= 0 && node.mesh < int(model_.meshes.size())
                         ? morph_target_count(node.mesh)
                         : 0;
        if (components == 0) {
          warn(cw + ": node " + std::to_string(n) +
               " has no mesh with morph targets; weights channel ignored");
          continue;
        }
      }
      if (ch.sampler < 0 || ch.sampler >= int(anim.samplers.size()))
        fail(cw + ".sampler: refers to missing sampler " + std::to_string(ch.sampler));
      track.node = n;
      // A pointer's output may be of any component type (KHR_animation_pointer: floats,
      // integers as their values, normalized integers dequantized).
      const bool weights = track.path == AnimationPath::Weights;
      track.track = pointer ? read_sampler_as(a, ch.sampler, Attribute::AnimationPointer,
                                              components, weights ? components : 1,
                                              track.path == AnimationPath::Rotation)
                            : read_sampler(a, ch.sampler, track.path, components);
      (weights ? weights_animated_ : trs_animated_).insert(track.node);
      channels.push_back(std::move(track));
    }
  }
  poses_ = evaluate_pose(channels, options_.time);
  evaluate_pointers(options_.time);
}

// A KHR_animation_pointer channel: true with *node_track's node and path set if it animates a
// node's translation, rotation, scale or weights (evaluate_animations reads it as a core
// channel); otherwise its track is kept for evaluate_pointers (materials, lights, cameras,
// visibility), or it is ignored with a warning, and false. A pointer to something the file
// does not have is refused naming the channel (the file is invalid).
bool Loader::pointer_channel(const tinygltf::AnimationChannel& ch, int a, const std::string& cw,
                             ChannelTrack* node_track) {
  const std::string at = cw + ".target.extensions.KHR_animation_pointer.pointer";
  const auto ext = ch.target_extensions.find("KHR_animation_pointer");
  if (ext == ch.target_extensions.end() || !ext->second.IsObject() ||
      !ext->second.Has("pointer") || !ext->second.Get("pointer").IsString())
    fail(at + ": a channel whose path is 'pointer' needs the pointer, a string");
  const std::string pointer = ext->second.Get("pointer").Get<std::string>();
  PointerTrack p;
  std::string why;
  bool missing = false;
  if (!resolve_pointer(model_, pointer, &p.target, &why, &missing)) {
    if (missing) fail(at + ": '" + pointer + "' " + why);
    warn(at + ": '" + pointer + "': " + why + "; channel ignored");
    return false;
  }
  using Kind = PointerTarget::Kind;
  switch (p.target.kind) {
    case Kind::NodeTranslation:
    case Kind::NodeRotation:
    case Kind::NodeScale:
    case Kind::NodeWeights:
      node_track->node = p.target.index;
      node_track->path = p.target.kind == Kind::NodeTranslation ? AnimationPath::Translation
                         : p.target.kind == Kind::NodeRotation  ? AnimationPath::Rotation
                         : p.target.kind == Kind::NodeScale     ? AnimationPath::Scale
                                                                : AnimationPath::Weights;
      return true;
    default:
      break;
  }
  const tinygltf::Animation& anim = model_.animations[size_t(a)];
  if (ch.sampler < 0 || ch.sampler >= int(anim.samplers.size()))
    fail(cw + ".sampler: refers to missing sampler " + std::to_string(ch.sampler));
  const Attribute kind = p.target.boolean ? Attribute::AnimationBool : Attribute::AnimationPointer;
  p.track = read_sampler_as(a, ch.sampler, kind, p.target.components, 1, false);
  if (p.target.boolean) {
    // KHR_animation_pointer: samplers of bool properties use STEP.
    if (p.track.interpolation != Interpolation::Step)
      fail("animations[" + std::to_string(a) + "].samplers[" + std::to_string(ch.sampler) +
           "].interpolation: '" + anim.samplers[size_t(ch.sampler)].interpolation +
           "' animates a bool (" + pointer + "), which KHR_animation_pointer steps: STEP");
    visibility_animated_.insert(p.target.index);
    visibility_tracks_.push_back(std::move(p));
  } else {
    pointer_tracks_.push_back(std::move(p));
  }
  return false;
}

// The pointer channels' values at `time` written into copies of the materials, lights and
// cameras they target (later channels over earlier ones), and node visibility at
// options_.visibility_time if set (a motion-blurred pose's steps share one visibility), else
// at `time`.
void Loader::evaluate_pointers(double time) {
  using Kind = PointerTarget::Kind;
  const tinygltf::Value* lights = nullptr;
  const auto lp = model_.extensions.find("KHR_lights_punctual");
  if (lp != model_.extensions.end() && lp->second.Has("lights") &&
      lp->second.Get("lights").IsArray())
    lights = &lp->second.Get("lights");
  for (const PointerTrack& p : pointer_tracks_) {
    const std::vector<double> v = evaluate_track(p.track, time);
    const size_t i = size_t(p.target.index);
    if (p.target.kind == Kind::Material) {
      auto it = animated_materials_.try_emplace(int(i), model_.materials[i]).first;
      apply_pointer(p.target, v.data(), &it->second);
    } else if (p.target.kind == Kind::Light && lights && i < lights->ArrayLen()) {
      auto it = animated_lights_.try_emplace(int(i), lights->Get(int(i))).first;
      apply_pointer(p.target, v.data(), &it->second);
    } else if (p.target.kind == Kind::Camera) {
      auto it = animated_cameras_.try_emplace(int(i), model_.cameras[i]).first;
      apply_pointer(p.target, v.data(), &it->second);
    }
  }
  const double vt = std::isnan(options_.visibility_time) ? time : options_.visibility_time;
  for (const PointerTrack& p : visibility_tracks_)
    visible_at_[p.target.index] = evaluate_track(p.track, vt)[0] != 0.0;
}

const tinygltf::Material& Loader::material_source(size_t i) const {
  const auto it = animated_materials_.find(int(i));
  return it == animated_materials_.end() ? model_.materials[i] : it->second;
}

const tinygltf::Value& Loader::light_source(size_t i, const tinygltf::Value& file) const {
  const auto it = animated_lights_.find(int(i));
  return it == animated_lights_.end() ? file : it->second;
}

const tinygltf::Camera& Loader::camera_source(size_t i) const {
  const auto it = animated_cameras_.find(int(i));
  return it == animated_cameras_.end() ? model_.cameras[i] : it->second;
}

// Sampler j of animation a as keyframes of `components` numbers (glTF 2.0, 3.11): float
// times that strictly increase, and one output element per keyframe (three with
// CUBICSPLINE: in-tangent, value, out-tangent), dequantized.
KeyframeTrack Loader::read_sampler(int a, int j, AnimationPath path, size_t components) {
  const Attribute kind = path == AnimationPath::Rotation  ? Attribute::AnimationRotation
                         : path == AnimationPath::Weights ? Attribute::AnimationWeights
                                                          : Attribute::AnimationVec3;
  // Weights outputs are scalars, `components` (the morph target count) per element.
  return read_sampler_as(a, j, kind, components,
                         path == AnimationPath::Weights ? components : 1,
                         path == AnimationPath::Rotation);
}

// read_sampler with the output accessor checked as `kind`, per_element of its elements to a
// keyframe's value (the morph target count for weights, else 1); `rotation`: the values are
// unit quaternions (slerp).
KeyframeTrack Loader::read_sampler_as(int a, int j, Attribute kind, size_t components,
                                      size_t per_element, bool rotation) {
  const tinygltf::AnimationSampler& s = model_.animations[size_t(a)].samplers[size_t(j)];
  const std::string sw =
      "animations[" + std::to_string(a) + "].samplers[" + std::to_string(j) + "]";
  KeyframeTrack track;
  track.components = components;
  track.rotation = rotation;
  if (!parse_interpolation(s.interpolation, &track.interpolation))
    fail(sw + ".interpolation: '" + s.interpolation + "' is not STEP, LINEAR or CUBICSPLINE");
  const View input = check_accessor(s.input, Attribute::AnimationInput, sw + ".input");
  const std::string in_at = sw + ".input (accessors[" + std::to_string(s.input) + "])";
  if (input.count == 0) fail(in_at + ": no keyframes");
  track.times.resize(input.count);
  for (size_t k = 0; k < input.count; ++k) {
    const double t = input.get(k, 0);
    if (!std::isfinite(t)) fail(in_at + ": keyframe time " + std::to_string(k) + " is not finite");
    if (k > 0 && !(t > track.times[k - 1]))
      fail(in_at + ": keyframe time " + std::to_string(k) + " (" + std::to_string(t) +
           ") is not greater than the one before it (" + std::to_string(track.times[k - 1]) +
           "); glTF 2.0 (3.11) requires strictly increasing times");
    track.times[k] = t;
  }
  const View output = check_accessor(s.output, kind, sw + ".output");
  const std::string out_at = sw + ".output (accessors[" + std::to_string(s.output) + "])";
  if (size_t(output.components) * per_element != components)
    fail(out_at + ": " + std::to_string(output.components) + " numbers per element, the " +
         "animated property has " + std::to_string(components / per_element));
  const size_t per_key = track.interpolation == Interpolation::CubicSpline ? 3 : 1;
  const size_t expected = input.count * per_key * per_element;
  if (output.count != expected)
    fail(out_at + ": " + std::to_string(output.count) + " elements, expected " +
         std::to_string(expected) + " (" + std::to_string(input.count) + " keyframes" +
         (per_key == 3 ? " x 3 for CUBICSPLINE" : "") +
         (per_element > 1 ? " x " + std::to_string(per_element) + " morph targets" : "") + ")");
  track.values.resize(input.count * per_key * components);
  const int nc = output.components;
  for (size_t e = 0; e < output.count; ++e)
    for (int c = 0; c < nc; ++c) {
      const double v = output.get(e, c);
      if (!std::isfinite(v)) fail(out_at + ": element " + std::to_string(e) + " is not finite");
      track.values[e * size_t(nc) + size_t(c)] = v;
    }
  return track;
}

const NodePose* Loader::pose_of(int node) const {
  if (poses_.empty()) return nullptr;
  const auto it = poses_.find(node);
  return it == poses_.end() ? nullptr : &it->second;
}

size_t Loader::morph_target_count(int mesh) const {
  size_t n = 0;
  for (const tinygltf::Primitive& prim : model_.meshes[size_t(mesh)].primitives)
    n = std::max(n, prim.targets.size());
  return n;
}

// A mesh node's morph target weights (3.7.2.2): animated, else the node's, else the mesh's
// (missing ones are 0).
const std::vector<double>& Loader::morph_weights(int index) const {
  const NodePose* pose = pose_of(index);
  if (pose && pose->has_weights) return pose->weights;
  const tinygltf::Node& node = model_.nodes[size_t(index)];
  if (!node.weights.empty()) return node.weights;
  return model_.meshes[size_t(node.mesh)].weights;
}

// Whether a node's mesh is skinned, or morphed by a weight other than 0: the node then has
// vertices of its own (flattened into the world mesh, never an instance of a shared mesh).
bool Loader::is_deformed(int index) const {
  const tinygltf::Node& node = model_.nodes[size_t(index)];
  if (node.mesh < 0 || node.mesh >= int(model_.meshes.size())) return false;
  if (node.skin >= 0) return true;
  if (morph_target_count(node.mesh) == 0) return false;
  const std::vector<double>& w = morph_weights(index);
  return std::any_of(w.begin(), w.end(), [](double x) { return x != 0.0; });
}

// A node's world matrix at the pose, as visit() composes it (parent * local from the root
// down), for nodes visit() may not have reached yet (joints) or at all.
Mat4 Loader::global_transform(int index) {
  std::vector<int> chain;
  for (int j = index; j >= 0 && !global_.count(j); j = parent_[size_t(j)]) chain.push_back(j);
  for (auto it = chain.rbegin(); it != chain.rend(); ++it) {
    const int j = *it, p = parent_[size_t(j)];
    const tinygltf::Node& node = model_.nodes[size_t(j)];
    const Mat4 parent = p >= 0 ? global_.at(p) : Mat4::identity();
    global_.emplace(j, parent * local_transform(node, "nodes[" + std::to_string(j) + "]" +
                                                          named(node.name),
                                                pose_of(j)));
  }
  return global_.at(index);
}

// Skin s's joint matrices (3.7.3): globalTransform(joints[j]) * inverseBindMatrices[j]
// (the identity without inverseBindMatrices). The skinned node's own transform is not used.
const std::vector<Mat4>& Loader::joint_matrices(int s) {
  const auto found = joint_matrices_.find(s);
  if (found != joint_matrices_.end()) return found->second;
  const tinygltf::Skin& skin = model_.skins[size_t(s)];
  const std::string at = "skins[" + std::to_string(s) + "]" + named(skin.name);
  std::optional<View> ibm;
  if (skin.inverseBindMatrices >= 0) {
    ibm = check_accessor(skin.inverseBindMatrices, Attribute::InverseBindMatrices,
                         at + ".inverseBindMatrices");
    if (ibm->count < skin.joints.size())
      fail("skins[" + std::to_string(s) + "].inverseBindMatrices (accessors[" +
           std::to_string(skin.inverseBindMatrices) + "]): " + std::to_string(ibm->count) +
           " matrices for " + std::to_string(skin.joints.size()) + " joints");
  }
  std::vector<Mat4> out;
  for (size_t k = 0; k < skin.joints.size(); ++k) {
    const int j = skin.joints[k];
    if (j < 0 || j >= int(model_.nodes.size()))
      fail("skins[" + std::to_string(s) + "].joints[" + std::to_string(k) +
           "]: refers to missing node " + std::to_string(j));
    Mat4 inverse_bind = Mat4::identity();
    if (ibm)
      for (int c = 0; c < 16; ++c) inverse_bind.m[size_t(c / 4)][size_t(c % 4)] = ibm->get(k, c);
    out.push_back(global_transform(j) * inverse_bind);
  }
  return joint_matrices_.emplace(s, std::move(out)).first->second;
}

Loader::Deformation Loader::deformation_of(int index, const std::string& where) {
  const tinygltf::Node& node = model_.nodes[size_t(index)];
  Deformation d;
  if (morph_target_count(node.mesh) > 0) {
    d.weights = morph_weights(index);
    if (std::all_of(d.weights.begin(), d.weights.end(), [](double w) { return w == 0.0; }))
      d.weights.clear();
  }
  if (node.skin >= 0) {
    if (node.skin >= int(model_.skins.size()))
      fail(where + ": 'skin' refers to missing skin " + std::to_string(node.skin));
    d.skin = node.skin;
    d.joint_matrices = joint_matrices(node.skin);
  }
  return d;
}

// The accessors a deformed primitive's vertices also depend on: primitives that share their
// vertex attributes but not these get vertices of their own.
void Loader::add_deformation_key(const tinygltf::Primitive& prim, VertexKey* key) {
  for (const auto& [name, accessor] : prim.attributes)
    if (name.rfind("JOINTS_", 0) == 0 || name.rfind("WEIGHTS_", 0) == 0)
      key->emplace(name, accessor);
  for (size_t t = 0; t < prim.targets.size(); ++t)
    for (const auto& [name, accessor] : prim.targets[t])
      key->emplace("targets[" + std::to_string(t) + "]." + name, accessor);
}

// A deformed primitive's vertices: the morph targets' POSITION and NORMAL displacements
// added with the weights (3.7.2.2), then the skin matrix sum_i w_i jointMatrix[j_i] over
// every JOINTS_n / WEIGHTS_n set (3.7.3.3), or world for an unskinned node; normals with
// the inverse transpose of that matrix.
Loader::PosedVertices Loader::pose_vertices(const tinygltf::Primitive& prim,
                                            const VertexAttributes& a, const Deformation& d,
                                            const Mat4& world, const std::string& where) {
  const size_t n = a.position.count;
  const View* nrm = a.normal ? &*a.normal : nullptr;
  std::vector<double> p(3 * n), nn(nrm ? 3 * n : 0);
  for (size_t vi = 0; vi < n; ++vi)
    for (int c = 0; c < 3; ++c) {
      p[3 * vi + size_t(c)] = a.position.get(vi, c);
      if (nrm) nn[3 * vi + size_t(c)] = nrm->get(vi, c);
    }
  for (size_t t = 0; t < prim.targets.size() && t < d.weights.size(); ++t) {
    const double w = d.weights[t];
    if (w == 0.0) continue;
    for (const auto& [name, accessor] : prim.targets[t]) {
      const bool position = name == "POSITION";
      if (!position && !(name == "NORMAL" && nrm)) continue;  // TANGENT etc.: not read
      const std::string tw = where + " targets[" + std::to_string(t) + "]." + name;
      const View v = check_accessor(
          accessor, position ? Attribute::MorphPosition : Attribute::MorphNormal, tw);
      if (v.count != n) fail(tw + ": count differs from POSITION's");
      std::vector<double>& dst = position ? p : nn;
      for (size_t vi = 0; vi < n; ++vi)
        for (int c = 0; c < 3; ++c) dst[3 * vi + size_t(c)] += w * v.get(vi, c);
    }
  }
  // The skin's influences: every JOINTS_n / WEIGHTS_n pair from n = 0 up.
  std::vector<std::pair<View, View>> sets;
  std::vector<int> joint_accessors;
  if (d.skin >= 0) {
    for (int set = 0;; ++set) {
      const std::string js = "JOINTS_" + std::to_string(set), ws = "WEIGHTS_" + std::to_string(set);
      const auto j = prim.attributes.find(js), w = prim.attributes.find(ws);
      if (j == prim.attributes.end() && w == prim.attributes.end()) break;
      if (j == prim.attributes.end() || w == prim.attributes.end())
        fail(where + ": " + (j == prim.attributes.end() ? ws + " without " + js
                                                        : js + " without " + ws));
      const View jv = check_accessor(j->second, Attribute::Joints, where + " " + js);
      const View wv = check_accessor(w->second, Attribute::Weights, where + " " + ws);
      if (jv.count != n || wv.count != n)
        fail(where + ": " + js + ", " + ws + " and POSITION counts differ");
      sets.push_back({jv, wv});
      joint_accessors.push_back(j->second);
    }
    if (sets.empty() && !warned_unskinned_) {
      warn(where + " (and possibly others): the node has a skin but the primitive no "
                   "JOINTS_0 and WEIGHTS_0; it is placed by its node, unskinned");
      warned_unskinned_ = true;
    }
  }
  PosedVertices out;
  out.positions.resize(n);
  if (nrm) out.normals.resize(n);
  if (!sets.empty()) out.mirrored.resize(n);
  const size_t joint_count = d.joint_matrices.size();
  std::vector<uint32_t> joints(4 * sets.size());
  std::vector<double> weights(4 * sets.size());
  for (size_t vi = 0; vi < n; ++vi) {
    Mat4 m = world;
    if (!sets.empty()) {
      for (size_t k = 0; k < sets.size(); ++k)
        for (int c = 0; c < 4; ++c) {
          const double j = sets[k].first.raw(vi, c);
          if (!(j < double(joint_count)))
            fail("accessors[" + std::to_string(joint_accessors[k]) + "] (" + where +
                 " JOINTS_" + std::to_string(k) + "): vertex " + std::to_string(vi) +
                 " refers to joint " + std::to_string(uint64_t(j)) + ", but skins[" +
                 std::to_string(d.skin) + "] has " + std::to_string(joint_count) + " joints");
          joints[4 * k + size_t(c)] = uint32_t(j);
          weights[4 * k + size_t(c)] = sets[k].second.get(vi, c);
        }
      m = blend_skin_matrix(d.joint_matrices, joints.data(), weights.data(), joints.size());
      out.mirrored[vi] = m.det3() < 0.0;
    }
    out.positions[vi] = transform_point(m, &p[3 * vi]);
    if (nrm) out.normals[vi] = transform_normal(m, &nn[3 * vi]);
  }
  return out;
}

}  // namespace rf::gltf_detail
