#include "scene/lights.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <map>
#include <numeric>
#include <utility>

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
  build_clusters(weights, materials);
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
             emitter_pdf_area_.capacity() * sizeof(float) +
             clusters_.capacity() * sizeof(LightCluster) +
             members_.capacity() * sizeof(uint32_t) + member_pmf_.capacity() * sizeof(float) +
             member_cdf_.capacity() * sizeof(float) +
             local_by_slot_.capacity() * sizeof(std::vector<Local>);
  for (const std::vector<float>& v : pdf_area_by_slot_) n += v.capacity() * sizeof(float);
  for (const std::vector<Local>& v : local_by_slot_) n += v.capacity() * sizeof(Local);
  return n;
}

LightSample LightSet::sample(float u_select, float u, float v) const {
  const uint32_t li = table_.sample(u_select);
  return sample_light(li, li < emitters_.size() ? emitter_pdf_area_[li] : float(table_.pmf(li)),
                      u, v);
}

LightSample LightSet::sample_in(uint32_t c, float u, float v) const {
  const LightCluster& k = clusters_[c];
  // The last light whose interval starts at or below u (lights of probability 0 have empty
  // intervals and are never chosen: the search skips to the next start above them).
  const auto first = member_cdf_.begin() + k.first, last = first + k.count;
  uint32_t i = uint32_t(std::upper_bound(first + 1, last, u) - first) - 1;
  uint32_t li = members_[k.first + i];
  while (!(member_pmf_[li] > 0.f) && i > 0) li = members_[k.first + --i];
  const float pmf = member_pmf_[li];
  const float rest = std::min(0.99999994f, std::max(0.f, (u - first[i]) / pmf));
  return sample_light(li, li < emitters_.size() ? pmf / emitters_[li].area : pmf, rest, v);
}

LightSample LightSet::sample_light(uint32_t li, float pdf, float u, float v) const {
  LightSample s;
  if (li >= emitters_.size()) {
    const uint32_t pi = li - uint32_t(emitters_.size());
    const PunctualLight& l = punctual_[pi];
    s.punctual = int(pi);
    s.p = l.type == PunctualType::Directional ? -l.direction : l.position;
    s.emission = l.intensity;
    s.pdf_area = pdf;
    return s;
  }
  const Emitter& e = emitters_[li];
  const Point2 b = sample_triangle({u, v});
  s.p = e.p[0] * b.x + e.p[1] * b.y + e.p[2] * (1.f - b.x - b.y);
  s.n = e.ng;
  s.emission = emission_[li];
  s.pdf_area = pdf;
  s.prim = e.prim;
  s.slot = e.slot;
  s.b1 = b.y;
  s.b2 = 1.f - b.x - b.y;
  return s;
}

namespace {

// One light's bounds while the clusters are built.
struct LightBounds {
  Vec3 lo, hi, centroid, normal;
  bool omni = false;  // emits in every direction (punctual, double-sided)
  bool infinite = false;
  double energy = 0.0;
};

}  // namespace

void LightSet::build_clusters(const std::vector<double>& power,
                              const std::vector<Material>& materials) {
  const uint32_t n = uint32_t(power.size());
  std::vector<LightBounds> b(n);
  for (uint32_t li = 0; li < n; ++li) {
    LightBounds& x = b[li];
    if (li < emitters_.size()) {
      const Emitter& e = emitters_[li];
      x.lo = vmin(vmin(e.p[0], e.p[1]), e.p[2]);
      x.hi = vmax(vmax(e.p[0], e.p[1]), e.p[2]);
      x.centroid = (e.p[0] + e.p[1] + e.p[2]) * (1.f / 3.f);
      x.normal = e.ng;
      x.omni = materials[e.material].double_sided;
      x.energy = power[li] / kPi;  // area * luminance(L)
    } else {
      const PunctualLight& l = punctual_[li - emitters_.size()];
      x.infinite = l.type == PunctualType::Directional;
      x.lo = x.hi = x.centroid = l.position;
      x.normal = l.direction;
      x.omni = true;
      x.energy = std::max(0.f, luminance(l.intensity));  // intensity, or irradiance
    }
  }
  // The first groups: an emissive mesh per (slot, material); each punctual light alone, or all
  // but the directional ones in one group (split below) when there are many; each directional
  // light alone, or all in one when there are many.
  struct Group {
    std::vector<uint32_t> lights;
    bool infinite = false, split_points = false;
  };
  std::vector<Group> groups;
  std::map<std::pair<uint32_t, uint32_t>, size_t> by_mesh;
  for (uint32_t li = 0; li < uint32_t(emitters_.size()); ++li) {
    const auto key = std::make_pair(emitters_[li].slot, emitters_[li].material);
    auto it = by_mesh.find(key);
    if (it == by_mesh.end()) {
      it = by_mesh.emplace(key, groups.size()).first;
      groups.emplace_back();
    }
    groups[it->second].lights.push_back(li);
  }
  std::vector<uint32_t> points, distant;
  for (uint32_t li = uint32_t(emitters_.size()); li < n; ++li)
    (b[li].infinite ? distant : points).push_back(li);
  constexpr size_t kFewPoints = 16, kFewDistant = 4, kLeafTriangles = 16;
  if (points.size() <= kFewPoints) {
    for (uint32_t li : points) groups.push_back({{li}, false, false});
  } else {
    groups.push_back({points, false, true});
  }
  if (distant.size() <= kFewDistant) {
    for (uint32_t li : distant) groups.push_back({{li}, true, false});
  } else {
    groups.push_back({distant, true, false});
  }
  const auto bounds_of = [&b](const std::vector<uint32_t>& lights, Vec3* lo, Vec3* hi) {
    const float inf = std::numeric_limits<float>::infinity();
    *lo = Vec3(inf, inf, inf);
    *hi = -*lo;
    for (uint32_t li : lights) {
      *lo = vmin(*lo, b[li].lo);
      *hi = vmax(*hi, b[li].hi);
    }
  };
  // Split the widest splittable group at the median of its lights' centroids along its widest
  // axis until there are kMaxClusters groups (or nothing is left to split).
  while (groups.size() < kMaxClusters) {
    int widest = -1;
    float widest_extent = -1.f;
    for (size_t g = 0; g < groups.size(); ++g) {
      const Group& gr = groups[g];
      if (gr.infinite || gr.lights.size() <= (gr.split_points ? 1 : kLeafTriangles)) continue;
      Vec3 lo, hi;
      bounds_of(gr.lights, &lo, &hi);
      const float extent = length(hi - lo);
      if (extent > widest_extent) {
        widest_extent = extent;
        widest = int(g);
      }
    }
    if (widest < 0) break;
    Group& gr = groups[size_t(widest)];
    Vec3 lo, hi;
    bounds_of(gr.lights, &lo, &hi);
    const Vec3 ext = hi - lo;
    const int axis = ext.x >= ext.y && ext.x >= ext.z ? 0 : (ext.y >= ext.z ? 1 : 2);
    const auto coord = [&b, axis](uint32_t li) {
      return axis == 0 ? b[li].centroid.x : axis == 1 ? b[li].centroid.y : b[li].centroid.z;
    };
    std::vector<uint32_t>& v = gr.lights;
    const size_t mid = v.size() / 2;
    std::nth_element(v.begin(), v.begin() + long(mid), v.end(), [&](uint32_t a, uint32_t c) {
      const float ca = coord(a), cc = coord(c);
      return ca < cc || (ca == cc && a < c);
    });
    Group upper{std::vector<uint32_t>(v.begin() + long(mid), v.end()), false, gr.split_points};
    v.resize(mid);
    std::sort(v.begin(), v.end());
    std::sort(upper.lights.begin(), upper.lights.end());
    groups.push_back(std::move(upper));
  }
  // The clusters: bounds, normal cone, energy; the distribution of each one's lights.
  member_pmf_.assign(n, 0.f);
  for (const Group& gr : groups) {
    LightCluster k;
    k.first = uint32_t(members_.size());
    k.count = uint32_t(gr.lights.size());
    k.infinite = gr.infinite;
    std::vector<double> w;
    double energy = 0.0;
    for (uint32_t li : gr.lights) {
      members_.push_back(li);
      w.push_back(power[li]);
      energy += b[li].energy;
    }
    k.energy = float(energy);
    if (gr.infinite) {
      // One directional light: its direction; several: no direction (importance = energy).
      k.axis = b[gr.lights[0]].normal;
      k.cos_spread = gr.lights.size() == 1 ? 1.f : -1.f;
    } else {
      Vec3 lo, hi;
      bounds_of(gr.lights, &lo, &hi);
      k.center = (lo + hi) * 0.5f;
      // Half the diagonal, a little more so that rounding leaves every point inside.
      k.radius = 0.5f * length(hi - lo) * (1.f + 1e-5f) + 1e-7f * length(k.center);
      bool omni = false;
      Vec3 sum;
      for (uint32_t li : gr.lights) {
        omni = omni || b[li].omni;
        sum = sum + b[li].normal;
      }
      const float len = length(sum);
      if (!omni && len > 1e-6f) {
        k.axis = sum / len;
        float c = 1.f;
        for (uint32_t li : gr.lights) c = std::min(c, dot(k.axis, b[li].normal));
        // Rounding margin: the cone may be a little wider, never narrower.
        c = std::max(-1.f, c - 1e-4f);
        if (c > -0.999f) {
          k.cos_spread = c;
          k.sin_spread = std::sqrt(std::max(0.f, 1.f - c * c));
        }
      }
    }
    double sum = 0.0;
    for (double x : w) sum += x;
    double below = 0.0;
    for (uint32_t i = 0; i < k.count; ++i) {
      member_pmf_[gr.lights[i]] = float(w[i] / sum);
      member_cdf_.push_back(float(below / sum));
      below += w[i];
    }
    clusters_.push_back(k);
  }
  for (size_t c = 0; c < clusters_.size(); ++c) {
    const LightCluster& k = clusters_[c];
    for (uint32_t i = k.first; i < k.first + k.count; ++i) {
      const uint32_t li = members_[i];
      if (li >= emitters_.size()) continue;
      const Emitter& e = emitters_[li];
      if (local_by_slot_.size() <= e.slot) local_by_slot_.resize(e.slot + 1);
      std::vector<Local>& v = local_by_slot_[e.slot];
      if (v.size() <= e.prim) v.resize(e.prim + 1);
      v[e.prim] = {member_pmf_[li] / e.area, uint32_t(c)};
    }
  }
}

float LightSet::importance(uint32_t c, Vec3 o, Vec3 ng) const {
  const LightCluster& k = clusters_[c];
  // A bound that is not 0 is kept at least this large: the importance is an estimate, and a
  // light near a grazing bound may still contribute more than the bound's cosine says.
  constexpr float kFloor = 1e-3f;
  if (k.infinite) {
    if (k.cos_spread < 0.f) return k.energy;
    // Light sampling keeps a directional light where dot(-direction, ng) > 0.
    const float ci = dot(-k.axis, ng);
    return ci > 0.f ? k.energy * std::max(ci, kFloor) : 0.f;
  }
  const Vec3 v = k.center - o;
  const float d2 = dot(v, v);
  const float r = k.radius, r2 = r * r;
  const float d = std::sqrt(d2);
  // Wholly below the plane of ng (with a margin for rounding): light sampling drops it.
  const float vn = dot(ng, v);
  if (vn + r < -1e-4f * (d + r)) return 0.f;
  float cos_i = 1.f, cos_o = 1.f;
  if (d2 > r2) {
    const float sin_u = r / d, cos_u = std::sqrt(std::max(0.f, 1.f - sin_u * sin_u));
    // At the shading point: cos(max(0, theta_i - theta_u)), theta_i the angle between ng and
    // the centre's direction, theta_u the bounding sphere's half angle.
    const float ci = vn / d;
    if (ci < cos_u) {
      const float si = std::sqrt(std::max(0.f, 1.f - ci * ci));
      cos_i = std::max(kFloor, ci * cos_u + si * sin_u);
    }
    // At the lights: cos(max(0, theta - theta_spread - theta_u)), theta the angle between
    // the cone's axis and the direction from the centre to o; 0 past 90 degrees (every
    // emitter faces away from o).
    if (k.cos_spread > -1.f) {
      const float cos_a = k.cos_spread * cos_u - k.sin_spread * sin_u;
      const float sin_a = k.sin_spread * cos_u + k.cos_spread * sin_u;
      const float co = -dot(k.axis, v) / d;
      if (sin_a >= 0.f && co < cos_a) {
        const float so = std::sqrt(std::max(0.f, 1.f - co * co));
        const float c_bound = co * cos_a + so * sin_a;
        if (c_bound < -1e-3f) return 0.f;
        cos_o = std::max(kFloor, c_bound);
      }
    }
  }
  return k.energy * cos_i * cos_o / std::max(d2, std::max(r2, 1e-12f));
}

float LightSet::importances(Vec3 o, Vec3 ng, float* w) const {
  float total = 0.f;
  for (uint32_t c = 0; c < uint32_t(clusters_.size()); ++c) {
    w[c] = importance(c, o, ng);
    total += w[c];
  }
  return total;
}

}  // namespace rf
