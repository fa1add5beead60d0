// Lights of a scene: emissive triangles (area lights) and KHR_lights_punctual lights. One is
// chosen with probability proportional to its power by an alias table, then (area lights) a
// point on it uniformly by area. The environment is a job setting, not part of the scene: the
// integrator selects it against this set by power (see render/light_sampling.cpp).
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "math/vecmath.h"

namespace rf {

struct Material;

// Walker/Vose alias table: O(1) sampling of a discrete distribution.
class AliasTable {
 public:
  AliasTable() = default;
  // weights >= 0, not all zero (otherwise the table is empty and size() is 0).
  explicit AliasTable(const std::vector<double>& weights);
  size_t size() const { return prob_.size(); }
  // Maps u in [0,1) to an index; *pmf receives its probability.
  uint32_t sample(float u, double* pmf = nullptr) const;
  double pmf(uint32_t i) const { return pmf_[i]; }
  size_t memory_bytes() const {
    return (prob_.capacity() + pmf_.capacity()) * sizeof(double) +
           alias_.capacity() * sizeof(uint32_t);
  }

 private:
  std::vector<double> prob_;     // acceptance probability of column i
  std::vector<uint32_t> alias_;  // alternative index of column i
  std::vector<double> pmf_;      // normalized input weights
};

// KHR_lights_punctual. glTF's photometric units are used as the renderer's radiance scale,
// consistently with emissive materials (whose emission is in nits, cd/m^2): intensity (cd) is
// the intensity of point and spot lights and (lux) the irradiance of directional lights,
// times the light's color.
enum class PunctualType { Point, Spot, Directional };
struct PunctualLight {
  PunctualType type = PunctualType::Point;
  Vec3 position;                 // point and spot
  Vec3 direction{0.f, 0.f, -1.f};  // unit direction the light travels (node's local -Z)
  Vec3 intensity{1.f, 1.f, 1.f};
  float cos_inner = 1.f, cos_outer = 0.f;  // spot cone (glTF innerConeAngle/outerConeAngle)
  // Spot falloff, glTF's recommended implementation:
  // clamp((cos - cos_outer) / (cos_inner - cos_outer), 0, 1)^2; 1 for other types.
  float spot_falloff(float cos_angle) const;
};

// An emissive triangle in world space: the triangle `prim` of geometry slot `slot` (0 = the
// world mesh, 1 + i = instance i).
struct Emitter {
  Vec3 p[3];
  Vec3 ng;  // unit front normal
  float area = 0.f;
  uint32_t slot = 0, prim = 0, material = 0;
};

struct LightSample {
  Vec3 p;              // point on the light (area, point, spot) or -direction (directional)
  Vec3 n;              // unit front-face normal of an area light at p
  Vec3 emission;       // area lights: emitted radiance factor (before textures); punctual:
                       // intensity (W/sr, already including the spot falloff is the caller's
                       // job) or irradiance (directional)
  float pdf_area = 0;  // area lights: density per unit area including the selection
                       // probability; punctual lights: the selection probability
  uint32_t prim = 0, slot = 0;
  float b1 = 0.f, b2 = 0.f;  // barycentrics of vertices 1 and 2 of the point
  int punctual = -1;         // index of the punctual light, -1 for an area light
};

// Every light of a scene (emissive triangles and punctual lights), selected with
// probability proportional to its power by one alias table:
//   triangle: pi * area * luminance(emission),  point: 4 pi * luminance(I),
//   spot: 2 pi (1 - (cos_inner + cos_outer) / 2) * luminance(I),
//   directional: pi R^2 * luminance(E) with R the scene's bounding radius.
class LightSet {
 public:
  LightSet() = default;
  LightSet(std::vector<Emitter> emitters, const std::vector<Material>& materials,
           std::vector<PunctualLight> punctual, float scene_radius);
  bool empty() const { return table_.size() == 0; }
  size_t size() const { return table_.size(); }
  size_t emitter_count() const { return emitters_.size(); }
  double total_power() const { return total_power_; }
  // u_select chooses the light, (u, v) the point on an area light. Requires !empty().
  LightSample sample(float u_select, float u, float v) const;
  // Area density with which sample() produces a point on triangle prim of slot (0 if that
  // triangle is not a light).
  float pdf_area(uint32_t slot, uint32_t prim) const {
    if (slot >= pdf_area_by_slot_.size()) return 0.f;
    const std::vector<float>& v = pdf_area_by_slot_[slot];
    return prim < v.size() ? v[prim] : 0.f;
  }
  float pdf_area(uint32_t prim) const { return pdf_area(0, prim); }
  const std::vector<PunctualLight>& punctual() const { return punctual_; }
  // Bytes held by the tables.
  size_t memory_bytes() const;

 private:
  std::vector<Emitter> emitters_;
  std::vector<PunctualLight> punctual_;
  std::vector<Vec3> emission_;  // per emitter
  AliasTable table_;  // emitters first, then punctual lights
  std::vector<std::vector<float>> pdf_area_by_slot_;
  // pdf_area of each emitter (the same floats as pdf_area_by_slot_): sample() reads it with
  // one load instead of a slot lookup or a division.
  std::vector<float> emitter_pdf_area_;
  double total_power_ = 0.0;
};

}  // namespace rf
