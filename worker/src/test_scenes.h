// Scenes built by the tests (not part of the worker binary).
#pragma once

#include <string>

#include "scene.h"

namespace rf {
namespace testing {

// Two triangles p0 p1 p2 and p0 p2 p3 (front face = counter-clockwise as listed).
void add_quad(SceneDescription* desc, Vec3 p0, Vec3 p1, Vec3 p2, Vec3 p3, uint32_t material);

// A Lambertian square of albedo rho (side 4, centered at the origin in z = 0, facing +z) under
// a one-sided emissive a x b rectangle of radiance L centered above the origin at height c and
// facing down; camera at `eye` looking at the origin with field of view yfov.
SceneDescription plane_under_emitter(float rho, float L, float a, float b, float c, Vec3 eye,
                                     float yfov);

// A small glTF 2.0 scene as JSON text with its buffer as a base64 data: URI: an indexed
// (uint16) floor quad, a non-indexed emissive quad (emissiveStrength 4) under a translated and
// scaled parent node, a camera on a rotated node, and a LINES primitive that must be skipped.
std::string small_gltf_json();

// Camera looking from eye to target with +Y-ish up.
Camera look_at(Vec3 eye, Vec3 target, float yfov);

}  // namespace testing
}  // namespace rf
