#include "lights.h"

#include <algorithm>
#include <cmath>

#include "sampling.h"
#include "scene.h"

namespace rf {

AliasTable::AliasTable(const std::vector<double>& weights) {
  double total = 0.0;
  for (double w : weights) total += std::max(0.0, w);
  if (!(total > 0.0) || !std::isfinite(total)) return;
  const size_t n = weights.size();
  pmf_.resize(n);
  prob_.assign(n, 1.0);
  alias_.resize(n);
  for (size_t i = 0; i < n; ++i) {
    pmf_[i] = std::max(0.0, weights[i]) / total;
    alias_[i] = uint32_t(i);
  }
  // Vose's algorithm: scaled probabilities n * p_i; pair each "small" column (< 1) with a
  // "large" one (>= 1) that donates the remainder.
  std::vector<double> scaled(n);
  std::vector<uint32_t> small, large;
  for (size_t i = 0; i < n; ++i) {
    scaled[i] = pmf_[i] * double(n);
    (scaled[i] < 1.0 ? small : large).push_back(uint32_t(i));
  }
  while (!small.empty() && !large.empty()) {
    const uint32_t s = small.back(), l = large.back();
    small.pop_back();
    large.pop_back();
    prob_[s] = scaled[s];
    alias_[s] = l;
    scaled[l] = (scaled[l] + scaled[s]) - 1.0;
    (scaled[l] < 1.0 ? small : large).push_back(l);
  }
  // Leftovers are 1 up to rounding.
  for (uint32_t i : large) prob_[i] = 1.0;
  for (uint32_t i : small) prob_[i] = 1.0;
}

uint32_t AliasTable::sample(float u, double* pmf) const {
  const size_t n = prob_.size();
  const double scaled = double(u) * double(n);
  const uint32_t column = uint32_t(std::min<double>(double(n - 1), std::floor(scaled)));
  // The fractional part is a fresh uniform variate for the accept/alias decision.
  const double remainder = scaled - double(column);
  const uint32_t i = remainder < prob_[column] ? column : alias_[column];
  if (pmf) *pmf = pmf_[i];
  return i;
}

LightSet::LightSet(const std::vector<Triangle>& triangles, const std::vector<Material>& materials)
    : triangles_(&triangles), materials_(&materials) {
  std::vector<double> weights;
  for (uint32_t i = 0; i < triangles.size(); ++i) {
    const Triangle& tri = triangles[i];
    const Vec3 e = materials[tri.material].emission;
    const double power = double(tri.area) * double(luminance(e));
    if (power > 0.0) {
      prims_.push_back(i);
      weights.push_back(power);
    }
  }
  if (prims_.empty()) return;
  table_ = AliasTable(weights);
  pdf_area_by_prim_.assign(triangles.size(), 0.f);
  for (uint32_t li = 0; li < prims_.size(); ++li) {
    const Triangle& tri = triangles[prims_[li]];
    pdf_area_by_prim_[prims_[li]] = float(table_.pmf(li) / double(tri.area));
  }
}

LightSample LightSet::sample(float u_select, float u, float v) const {
  const uint32_t li = table_.sample(u_select);
  const uint32_t prim = prims_[li];
  const Triangle& tri = (*triangles_)[prim];
  const Point2 b = sample_triangle({u, v});
  LightSample s;
  s.p = tri.p[0] * b.x + tri.p[1] * b.y + tri.p[2] * (1.f - b.x - b.y);
  s.n = tri.ng;
  s.emission = (*materials_)[tri.material].emission;
  s.pdf_area = pdf_area_by_prim_[prim];
  s.prim = prim;
  return s;
}

}  // namespace rf
