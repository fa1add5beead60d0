// KHR_animation_pointer: animation channels that target any mutable property of the glTF
// object model by a JSON pointer (RFC 6901), e.g. "/materials/0/pbrMetallicRoughness/
// baseColorFactor". This file resolves a pointer to what it animates and writes an animated
// value into the tinygltf object it belongs to (a copy the loader keeps for one time), so the
// loader reads an animated material, light or camera exactly as it reads a still one: the same
// defaults, checks and clamping (a value out of range at some time is refused or clamped
// naming its glTF path, as the same value in the file would be).
//
// What a pointer may animate here (the glTF 2.0 Asset Object Model's mutable properties that
// the renderer reads):
// - /nodes/N/translation, rotation, scale, weights: as the core channel paths (motion blur
//   included);
// - /nodes/N/extensions/KHR_node_visibility/visible (bool: STEP, unsigned byte 0 or not);
// - /materials/N/...: pbrMetallicRoughness/baseColorFactor, metallicFactor, roughnessFactor,
//   emissiveFactor, alphaCutoff, normalTexture/scale, occlusionTexture/strength, every
//   property of a material extension (its factors, colours, ior, thicknesses, ...), and
//   extensions/KHR_texture_transform/offset, rotation, scale of any texture reference;
// - /extensions/KHR_lights_punctual/lights/N/color, intensity, range, spot/innerConeAngle,
//   spot/outerConeAngle;
// - /cameras/N/perspective/yfov, aspectRatio, znear, zfar and orthographic/xmag, ymag, znear,
//   zfar.
#pragma once

#include <cstddef>
#include <string>
#include <vector>

namespace tinygltf {
struct Material;
class Value;
struct Camera;
class Model;
}  // namespace tinygltf

namespace rf {

struct PointerTarget {
  enum class Kind { NodeTranslation, NodeRotation, NodeScale, NodeWeights, NodeVisible,
                    Material, Light, Camera };
  Kind kind = Kind::Material;
  int index = -1;  // the node, material, light or camera
  // The reference tokens after the object (e.g. {"pbrMetallicRoughness", "baseColorFactor"}),
  // unescaped (~1 is '/', ~0 is '~').
  std::vector<std::string> path;
  // Numbers per keyframe the output accessor gives (for weights: the morph target count,
  // filled by the loader), and whether the property is a bool (STEP only).
  size_t components = 1;
  bool boolean = false;
};

// Resolves `pointer` against the document. Returns false with *why set when the pointer does
// not name an animatable property the renderer reads ("is not animatable here": the channel is
// then ignored with a warning) or names something the document does not have (*missing set:
// the file is invalid, and the loader refuses it naming the channel).
bool resolve_pointer(const tinygltf::Model& model, const std::string& pointer,
                     PointerTarget* out, std::string* why, bool* missing);

// Write the value v (target.components numbers) at the target's path into the object, creating
// the member where the extension text gives it a default (the enclosing object exists: the
// resolution checked it).
void apply_pointer(const PointerTarget& target, const double* v, tinygltf::Material* m);
// A light: its object in extensions.KHR_lights_punctual.lights, as the loader reads it.
void apply_pointer(const PointerTarget& target, const double* v, tinygltf::Value* light);
void apply_pointer(const PointerTarget& target, const double* v, tinygltf::Camera* c);

}  // namespace rf
