// Area lights: every triangle whose material emits. One is chosen with probability
// proportional to area x luminance(emission) by an alias table, then a point on it uniformly
// by area.
#pragma once

#include <cstdint>
#include <vector>

#include "vecmath.h"

namespace rf {

struct Triangle;
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

 private:
  std::vector<double> prob_;     // acceptance probability of column i
  std::vector<uint32_t> alias_;  // alternative index of column i
  std::vector<double> pmf_;      // normalized input weights
};

struct LightSample {
  Vec3 p;              // point on the light
  Vec3 n;              // unit front-face normal of the light at p
  Vec3 emission;       // radiance leaving the front face
  float pdf_area = 0;  // density per unit area, including the light-selection probability
  uint32_t prim = 0;
};

class LightSet {
 public:
  LightSet() = default;
  LightSet(const std::vector<Triangle>& triangles, const std::vector<Material>& materials);
  bool empty() const { return prims_.empty(); }
  size_t size() const { return prims_.size(); }
  // u_select chooses the triangle, (u, v) the point on it. Requires !empty().
  LightSample sample(float u_select, float u, float v) const;
  // Area density with which sample() produces a point on triangle prim (0 if not a light).
  float pdf_area(uint32_t prim) const {
    return prim < pdf_area_by_prim_.size() ? pdf_area_by_prim_[prim] : 0.f;
  }

 private:
  const std::vector<Triangle>* triangles_ = nullptr;
  const std::vector<Material>* materials_ = nullptr;
  std::vector<uint32_t> prims_;  // light index -> triangle index
  AliasTable table_;
  std::vector<float> pdf_area_by_prim_;
};

}  // namespace rf
