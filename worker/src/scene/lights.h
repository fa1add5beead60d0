// Lights of a scene: emissive triangles (area lights) and KHR_lights_punctual lights.
//
// The renderer selects a light per shading point (select / sample_in): the lights are grouped
// into at most kMaxClusters clusters (an emissive mesh per material, split by position when it
// has many triangles; each punctual light alone, many of them split by position), each with a
// bounding sphere, a cone bounding its emitters' normals and its energy. At a shading point o
// with geometric normal ng a cluster's importance estimates the irradiance it sends to o,
// energy * cos-bound at o * cos-bound at the light / distance^2 (Conty & Kulla's light-tree
// importance, one level), and is 0 only where no light of the cluster can contribute to light
// sampling at o (wholly below ng's plane, or every emitter facing away). A cluster is chosen
// with probability proportional to its importance (and the environment's, a constant the
// caller adds), then a light inside it by power (its cumulative distribution), then (area
// lights) a point uniformly by area. One number makes every choice, rescaled to [0, 1) within
// the interval each choice took, and then places the point with the light sample's second
// number: a stratified pair stays stratified over every light (sample_in). The environment is
// a job setting, not part of the scene: see render/light_sampling.cpp.
//
// sample() and pdf_area() are the older global choice by power alone (one alias table over
// every light), kept for tools and tests.
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
  // The glTF node that carries it (its index in "nodes"; ~0u, kNoNode, for none): the light
  // groups attribute its light samples to that node's group (render/light_groups.h).
  uint32_t node = ~0u;
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

// The bounds of a cluster of lights, for its importance at a shading point.
struct LightCluster {
  Vec3 center;               // bounding sphere (radius 0: a point light)
  float radius = 0.f;
  Vec3 axis{0.f, 0.f, 1.f};  // cone around every emitter's front normal
  float cos_spread = -1.f, sin_spread = 0.f;  // its half-angle; cos -1: any direction
  float energy = 0.f;        // sum of luminance(L) * area, or of luminance(I) (punctual)
  bool infinite = false;     // directional lights: `axis` is the direction light travels in
  uint32_t first = 0, count = 0;  // its lights: members_[first, first + count)
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

  // ---- Per-shading-point selection.
  static constexpr uint32_t kMaxClusters = 40;
  uint32_t cluster_count() const { return uint32_t(clusters_.size()); }
  const LightCluster& cluster(uint32_t c) const { return clusters_[c]; }
  // Light i of the clusters' list (LightCluster::first, count): an index into emitters()
  // below emitter_count(), else emitter_count() + an index into punctual().
  uint32_t member(uint32_t i) const { return members_[i]; }
  const std::vector<Emitter>& emitters() const { return emitters_; }
  // Importance of cluster c at point o with geometric normal ng (unit): >= 0, and 0 only if
  // no light of c can send light to o from above ng's plane (where light sampling looks).
  float importance(uint32_t c, Vec3 o, Vec3 ng) const;
  // The importance of every cluster at (o, ng) into w[0, cluster_count()); their sum.
  float importances(Vec3 o, Vec3 ng, float* w) const;
  // Light sample of a light of cluster c chosen by power with u, the point on it from (u', v)
  // where u' is u rescaled to [0, 1) within the chosen light's interval of the cluster's
  // cumulative distribution (its lights in the order of members_). A stratified (u, v) set
  // therefore stays stratified over each light and across them: the two triangles of a quad
  // light share one well-spread point set instead of each getting a random half of it.
  // pdf_area is the probability within the cluster (divided by the area for area lights).
  LightSample sample_in(uint32_t c, float u, float v) const;
  // For triangle prim of slot: its cluster and its area density within it (0: not a light).
  float pdf_area_in_cluster(uint32_t slot, uint32_t prim, uint32_t* cluster) const {
    if (slot >= local_by_slot_.size()) return 0.f;
    const std::vector<Local>& v = local_by_slot_[slot];
    if (prim >= v.size()) return 0.f;
    *cluster = v[prim].cluster;
    return v[prim].pdf_area;
  }
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
  // Per-shading-point selection: the clusters, their lights (indices into emitters_ then
  // punctual_, as table_'s) and, per entry of members_, the cluster's cumulative probability
  // of the lights before it (its lights by power).
  struct Local {
    float pdf_area = 0.f;
    uint32_t cluster = 0;
  };
  void build_clusters(const std::vector<double>& power, const std::vector<Material>& materials);
  LightSample sample_light(uint32_t li, float pdf, float u, float v) const;
  std::vector<LightCluster> clusters_;
  std::vector<uint32_t> members_;
  std::vector<float> member_cdf_;
  std::vector<float> member_pmf_;  // by light index: its probability within its cluster
  std::vector<std::vector<Local>> local_by_slot_;
};

}  // namespace rf
