#include "scene/lights.h"

#include <algorithm>
#include <cmath>

#include "sampling/sampling.h"
#include "scene/scene.h"

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

float PunctualLight::spot_falloff(float cos_angle) const {
  if (type != PunctualType::Spot) return 1.f;
  if (cos_angle <= cos_outer) return 0.f;
  if (cos_angle >= cos_inner) return 1.f;
  const float t = (cos_angle - cos_outer) / std::max(1e-6f, cos_inner - cos_outer);
  return t * t;
}

LightSet::LightSet(std::vector<Emitter> emitters, const std::vector<Material>& materials,
                   std::vector<PunctualLight> punctual, float scene_radius) {
  std::vector<double> weights;
  for (const Emitter& e : emitters) {
    const Vec3 L = materials[e.material].emission;
    const double power = kPi * double(e.area) * double(luminance(L));
    if (!(power > 0.0)) continue;
    emitters_.push_back(e);
    emission_.push_back(L);
    weights.push_back(power);
  }
  for (const PunctualLight& l : punctual) {
    const double I = std::max(0.f, luminance(l.intensity));
    double power = 0.0;
    switch (l.type) {
      case PunctualType::Point:
        power = 4.0 * kPi * I;
        break;
      case PunctualType::Spot:
        power = 2.0 * kPi * (1.0 - 0.5 * (double(l.cos_inner) + double(l.cos_outer))) * I;
        break;
      case PunctualType::Directional:
        power = kPi * double(scene_radius) * double(scene_radius) * I;
        break;
    }
    if (!(power > 0.0) || !std::isfinite(power)) continue;
    punctual_.push_back(l);
    weights.push_back(power);
  }
  for (double w : weights) total_power_ += w;
  if (weights.empty()) return;
  table_ = AliasTable(weights);
  for (size_t li = 0; li < emitters_.size(); ++li) {
    const Emitter& e = emitters_[li];
    if (pdf_area_by_slot_.size() <= e.slot) pdf_area_by_slot_.resize(e.slot + 1);
    std::vector<float>& v = pdf_area_by_slot_[e.slot];
    if (v.size() <= e.prim) v.resize(e.prim + 1, 0.f);
    v[e.prim] = float(table_.pmf(uint32_t(li)) / double(e.area));
    emitter_pdf_area_.push_back(v[e.prim]);
  }
}

size_t LightSet::memory_bytes() const {
  size_t n = emitters_.capacity() * sizeof(Emitter) +
             punctual_.capacity() * sizeof(PunctualLight) + emission_.capacity() * sizeof(Vec3) +
             table_.memory_bytes() + pdf_area_by_slot_.capacity() * sizeof(std::vector<float>) +
             emitter_pdf_area_.capacity() * sizeof(float);
  for (const std::vector<float>& v : pdf_area_by_slot_) n += v.capacity() * sizeof(float);
  return n;
}

LightSample LightSet::sample(float u_select, float u, float v) const {
  const uint32_t li = table_.sample(u_select);
  LightSample s;
  if (li >= emitters_.size()) {
    const uint32_t pi = li - uint32_t(emitters_.size());
    const PunctualLight& l = punctual_[pi];
    s.punctual = int(pi);
    s.p = l.type == PunctualType::Directional ? -l.direction : l.position;
    s.emission = l.intensity;
    s.pdf_area = float(table_.pmf(li));
    return s;
  }
  const Emitter& e = emitters_[li];
  const Point2 b = sample_triangle({u, v});
  s.p = e.p[0] * b.x + e.p[1] * b.y + e.p[2] * (1.f - b.x - b.y);
  s.n = e.ng;
  s.emission = emission_[li];
  s.pdf_area = emitter_pdf_area_[li];
  s.prim = e.prim;
  s.slot = e.slot;
  s.b1 = b.y;
  s.b2 = 1.f - b.x - b.y;
  return s;
}

}  // namespace rf
