// Warps from the unit square to sampling domains, as pure triples (Mitsuba's warp.h):
//   sample_X(u)   maps u in [0,1)^2 to the domain,
//   X_pdf(...)    density of sample_X with respect to the domain's measure (solid angle for
//                 directions, area of the reference domain for disk/triangle); 0 outside it,
//   invert_X(...) maps a point of the domain back to the u that produces it.
// Directions are in a local frame with the surface normal along +z.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include "math/vecmath.h"

namespace rf {

struct Point2 {
  float x = 0.f, y = 0.f;
};

// ---- Concentric disk (Shirley & Chiu 1997): square -> unit disk, area-preserving up to pi.
inline Point2 sample_concentric_disk(Point2 u) {
  const float a = 2.f * u.x - 1.f, b = 2.f * u.y - 1.f;
  if (a == 0.f && b == 0.f) return {0.f, 0.f};
  // Horizontal wedges: phi = (pi/4)(b/a), the point r (cos phi, sin phi) with r = a. Vertical
  // ones: phi = pi/2 - psi with psi = (pi/4)(a/b), so the point is r (sin psi, cos psi), r = b.
  // The wedge test is a coin flip for the branch predictor: the operands are selected without
  // a branch.
  const bool horizontal = std::fabs(a) > std::fabs(b);
  const float r = select_bits(horizontal, a, b);
  const float psi = (kPi / 4.f) * (select_bits(horizontal, b, a) / r);
  float s, c;
  sincos_quarter(psi, &s, &c);
  return {r * select_bits(horizontal, c, s), r * select_bits(horizontal, s, c)};
}
// Density per unit area of the disk: 1/pi inside, 0 outside.
inline float concentric_disk_pdf(Point2 p) { return p.x * p.x + p.y * p.y <= 1.f ? kInvPi : 0.f; }
inline Point2 invert_concentric_disk(Point2 p) {
  const float r = std::sqrt(p.x * p.x + p.y * p.y);
  float phi = std::atan2(p.y, p.x);
  if (phi < -kPi / 4.f) phi += 2.f * kPi;  // phi in [-pi/4, 7pi/4)
  float a, b;
  if (phi < kPi / 4.f) {  // right wedge: r = a > 0
    a = r;
    b = phi * a / (kPi / 4.f);
  } else if (phi < 3.f * kPi / 4.f) {  // top wedge: r = b > 0
    b = r;
    a = (kPi / 2.f - phi) * b / (kPi / 4.f);
  } else if (phi < 5.f * kPi / 4.f) {  // left wedge: r = a < 0, phi - pi = (pi/4)(b/a)
    a = -r;
    b = (phi - kPi) * a / (kPi / 4.f);
  } else {  // bottom wedge: r = b < 0, phi - pi = pi/2 - (pi/4)(a/b)
    b = -r;
    a = (kPi / 2.f - (phi - kPi)) * b / (kPi / 4.f);
  }
  return {(a + 1.f) * 0.5f, (b + 1.f) * 0.5f};
}

// ---- Cosine-weighted hemisphere (Malley's method: project the concentric disk up).
inline Vec3 sample_cosine_hemisphere(Point2 u) {
  const Point2 d = sample_concentric_disk(u);
  const float z = std::sqrt(std::max(0.f, 1.f - d.x * d.x - d.y * d.y));
  return {d.x, d.y, z};
}
// Solid-angle density cos(theta)/pi on the upper hemisphere; 0 below it (z <= 0).
inline float cosine_hemisphere_pdf(Vec3 w) { return w.z > 0.f ? w.z * kInvPi : 0.f; }
inline Point2 invert_cosine_hemisphere(Vec3 w) { return invert_concentric_disk({w.x, w.y}); }

// ---- Uniform sphere: z = 1 - 2 u0, phi = 2 pi u1 (Archimedes' hat-box theorem).
inline Vec3 sample_uniform_sphere(Point2 u) {
  const float z = 1.f - 2.f * u.x;
  const float r = std::sqrt(std::max(0.f, 1.f - z * z));
  const float phi = 2.f * kPi * u.y;
  return {r * std::cos(phi), r * std::sin(phi), z};
}
inline float uniform_sphere_pdf(Vec3 /*w*/) { return 1.f / (4.f * kPi); }
inline Point2 invert_uniform_sphere(Vec3 w) {
  float phi = std::atan2(w.y, w.x);
  if (phi < 0.f) phi += 2.f * kPi;
  return {(1.f - w.z) * 0.5f, phi / (2.f * kPi)};
}

// ---- Uniform hemisphere (z >= 0): z = u0, phi = 2 pi u1.
inline Vec3 sample_uniform_hemisphere(Point2 u) {
  const float z = u.x;
  const float r = std::sqrt(std::max(0.f, 1.f - z * z));
  const float phi = 2.f * kPi * u.y;
  return {r * std::cos(phi), r * std::sin(phi), z};
}
// 1/(2 pi) on the upper hemisphere, 0 below it.
inline float uniform_hemisphere_pdf(Vec3 w) { return w.z >= 0.f ? 1.f / (2.f * kPi) : 0.f; }
inline Point2 invert_uniform_hemisphere(Vec3 w) {
  float phi = std::atan2(w.y, w.x);
  if (phi < 0.f) phi += 2.f * kPi;
  return {w.z, phi / (2.f * kPi)};
}

// ---- Uniform triangle by area, square-root warp (Shirley): returns barycentrics (b0, b1) of
// vertices 0 and 1 (b2 = 1 - b0 - b1). The point is b0 p0 + b1 p1 + b2 p2.
inline Point2 sample_triangle(Point2 u) {
  const float su0 = std::sqrt(u.x);
  return {1.f - su0, u.y * su0};
}
// Density with respect to area of the reference triangle {b0, b1 >= 0, b0 + b1 <= 1}, whose
// area is 1/2: the constant 2 inside, 0 outside. Divide by 2 * world area for world density,
// i.e. the world-space area pdf is 1 / area.
inline float triangle_pdf(Point2 b) {
  return (b.x >= 0.f && b.y >= 0.f && b.x + b.y <= 1.f) ? 2.f : 0.f;
}
inline Point2 invert_triangle(Point2 b) {
  const float su0 = 1.f - b.x;
  return {su0 * su0, su0 > 0.f ? std::min(1.f, b.y / su0) : 0.f};
}

// ---- Multiple importance sampling: power heuristic with beta = 2 (Veach 1997, eq. 9.13) for
// one sample from each of two strategies with densities pdf_a (the one used) and pdf_b.
inline float power_heuristic(float pdf_a, float pdf_b) {
  const float a = pdf_a * pdf_a, b = pdf_b * pdf_b;
  if (a == 0.f) return 0.f;
  if (std::isinf(a)) return 1.f;
  return a / (a + b);
}

// ---- GGX (Trowbridge-Reitz) microfacet distribution, isotropic roughness alpha > 0, in the
// local frame of the (shading) normal. D is a density of microfacet normals per unit
// projected area: integral of D(m) m.z dm over the hemisphere = 1.
inline float ggx_d(Vec3 m, float alpha) {
  if (m.z <= 0.f) return 0.f;
  const float a2 = alpha * alpha;
  const float c2 = m.z * m.z;
  const float t = c2 * (a2 - 1.f) + 1.f;
  return a2 / (kPi * t * t);
}
// Smith Lambda of direction w (Heitz 2014, eq. 72): (-1 + sqrt(1 + alpha^2 tan^2)) / 2.
inline float ggx_lambda(Vec3 w, float alpha) {
  const float c2 = w.z * w.z;
  if (c2 <= 0.f) return 1e30f;
  const float t2 = std::max(0.f, 1.f - c2) / c2;
  return 0.5f * (-1.f + std::sqrt(1.f + alpha * alpha * t2));
}
inline float ggx_g1(Vec3 w, float alpha) { return 1.f / (1.f + ggx_lambda(w, alpha)); }
// Height-correlated Smith masking-shadowing G2 (Heitz 2014, eq. 99).
inline float ggx_g2(Vec3 wo, Vec3 wi, float alpha) {
  return 1.f / (1.f + ggx_lambda(wo, alpha) + ggx_lambda(wi, alpha));
}

namespace detail {
struct VndfFrame {
  Vec3 vh, t1, t2;
  float s;
};
inline VndfFrame vndf_frame(Vec3 wo, float alpha) {
  VndfFrame f;
  f.vh = normalize(Vec3(alpha * wo.x, alpha * wo.y, wo.z));
  const float lensq = f.vh.x * f.vh.x + f.vh.y * f.vh.y;
  f.t1 = lensq > 0.f ? Vec3(-f.vh.y, f.vh.x, 0.f) / std::sqrt(lensq) : Vec3(1.f, 0.f, 0.f);
  f.t2 = cross(f.vh, f.t1);
  f.s = 0.5f * (1.f + f.vh.z);
  return f;
}
}  // namespace detail

// ---- GGX visible normals (Heitz 2018, "Sampling the GGX Distribution of Visible Normals"):
// maps u to a microfacet normal m distributed as D_wo(m) = G1(wo) max(0, wo.m) D(m) / wo.z.
// Requires wo.z > 0 (unit, local frame).
// The first step, which depends on u alone: a uniform point of the unit disk in polar
// coordinates, r = sqrt(u.x), phi = 2 pi u.y.
inline Point2 sample_polar_disk(Point2 u) {
  const float r = std::sqrt(u.x);
  float s, c;
  sincos_turn(u.y, &s, &c);
  return {r * c, r * s};
}
// The rest, from the disk point d = sample_polar_disk(u).
inline Vec3 sample_ggx_vndf_from_disk(Vec3 wo, float alpha, Point2 d) {
  const detail::VndfFrame f = detail::vndf_frame(wo, alpha);
  const float p1 = d.x;
  const float p2 = (1.f - f.s) * std::sqrt(std::max(0.f, 1.f - p1 * p1)) + f.s * d.y;
  const Vec3 nh = f.t1 * p1 + f.t2 * p2 + f.vh * std::sqrt(std::max(0.f, 1.f - p1 * p1 - p2 * p2));
  return normalize(Vec3(alpha * nh.x, alpha * nh.y, std::max(1e-7f, nh.z)));
}
inline Vec3 sample_ggx_vndf(Vec3 wo, float alpha, Point2 u) {
  return sample_ggx_vndf_from_disk(wo, alpha, sample_polar_disk(u));
}
// The two warps of a BSDF sample's pair u that depend on u alone: the diffuse lobe's cosine
// direction and the GGX lobe's disk point. The packet tracer computes both for all its lanes
// at once (simd.h), before it knows which lobe each lane samples.
struct BsdfDisks {
  Vec3 cosine;   // sample_cosine_hemisphere(u)
  Point2 polar;  // sample_polar_disk(u)
};
inline BsdfDisks bsdf_disks(Point2 u) {
  return {sample_cosine_hemisphere(u), sample_polar_disk(u)};
}
// ---- Anisotropic GGX (KHR_materials_anisotropy; Heitz 2014 and 2018): alpha ax along the
// local x axis, ay along y. D(m) = 1 / (pi ax ay ((m.x/ax)^2 + (m.y/ay)^2 + m.z^2)^2),
// Lambda(w) = (-1 + sqrt(1 + (ax^2 w.x^2 + ay^2 w.y^2) / w.z^2)) / 2; with ax = ay they are
// ggx_d and ggx_lambda.
inline float ggx_d_aniso(Vec3 m, float ax, float ay) {
  if (m.z <= 0.f) return 0.f;
  const float x = m.x / ax, y = m.y / ay;
  const float t = x * x + y * y + m.z * m.z;
  return 1.f / (kPi * ax * ay * t * t);
}
inline float ggx_lambda_aniso(Vec3 w, float ax, float ay) {
  const float z2 = w.z * w.z;
  if (z2 <= 0.f) return 1e30f;
  return 0.5f * (-1.f + std::sqrt(1.f + (ax * ax * w.x * w.x + ay * ay * w.y * w.y) / z2));
}
// Visible normals of the anisotropic distribution: the isotropic construction in the space
// stretched by (ax, ay), from the disk point d = sample_polar_disk(u).
inline Vec3 sample_ggx_vndf_aniso_from_disk(Vec3 wo, float ax, float ay, Point2 d) {
  const Vec3 vh = normalize(Vec3(ax * wo.x, ay * wo.y, wo.z));
  const float lensq = vh.x * vh.x + vh.y * vh.y;
  const Vec3 t1 = lensq > 0.f ? Vec3(-vh.y, vh.x, 0.f) / std::sqrt(lensq) : Vec3(1.f, 0.f, 0.f);
  const Vec3 t2 = cross(vh, t1);
  const float s = 0.5f * (1.f + vh.z);
  const float p1 = d.x;
  const float p2 = (1.f - s) * std::sqrt(std::max(0.f, 1.f - p1 * p1)) + s * d.y;
  const Vec3 nh = t1 * p1 + t2 * p2 + vh * std::sqrt(std::max(0.f, 1.f - p1 * p1 - p2 * p2));
  return normalize(Vec3(ax * nh.x, ay * nh.y, std::max(1e-7f, nh.z)));
}
// Density of sample_ggx_vndf per unit solid angle of m.
inline float ggx_vndf_pdf(Vec3 wo, Vec3 m, float alpha) {
  if (wo.z <= 0.f) return 0.f;
  return ggx_g1(wo, alpha) * std::max(0.f, dot(wo, m)) * ggx_d(m, alpha) / wo.z;
}
inline Point2 invert_ggx_vndf(Vec3 wo, float alpha, Vec3 m) {
  const detail::VndfFrame f = detail::vndf_frame(wo, alpha);
  const Vec3 nh = normalize(Vec3(m.x / alpha, m.y / alpha, m.z));
  const float p1 = dot(nh, f.t1);
  const float p2w = dot(nh, f.t2);
  const float p2 = (p2w - (1.f - f.s) * std::sqrt(std::max(0.f, 1.f - p1 * p1))) / f.s;
  float phi = std::atan2(p2, p1);
  if (phi < 0.f) phi += 2.f * kPi;
  return {std::min(1.f, p1 * p1 + p2 * p2), phi / (2.f * kPi)};
}

// ---- Piecewise-constant 1D distribution on [0, 1) with n equal cells (pbrt's
// PiecewiseConstant1D). Weights >= 0; if all are 0 the distribution is uniform.
class Distribution1D {
 public:
  Distribution1D() = default;
  explicit Distribution1D(const std::vector<float>& weights) : func_(weights) {
    const size_t n = func_.size();
    cdf_.assign(n + 1, 0.0);
    for (size_t i = 0; i < n; ++i) {
      func_[i] = std::isfinite(func_[i]) ? std::max(0.f, func_[i]) : 0.f;
      cdf_[i + 1] = cdf_[i] + double(func_[i]) / double(n);
    }
    integral_ = cdf_[n];
    if (!(integral_ > 0.0)) {
      for (size_t i = 0; i < n; ++i) {
        func_[i] = 1.f;
        cdf_[i + 1] = double(i + 1) / double(n);
      }
      integral_ = 1.0;
    } else {
      for (size_t i = 1; i <= n; ++i) cdf_[i] /= integral_;
    }
    // guide_[j]: the index of the first cdf value above j / n (a merge of the two sorted
    // sequences).
    guide_.resize(n + 1);
    size_t r = 0;
    for (size_t j = 0; j <= n; ++j) {
      const double bound = double(j) / double(n);
      while (r < cdf_.size() && cdf_[r] <= bound) ++r;
      guide_[j] = uint32_t(r);
    }
  }
  size_t size() const { return func_.size(); }
  double integral() const { return integral_; }  // mean of the weights
  // x in [0, 1); *pdf = density at x (func / integral); *cell = the cell of x.
  float sample(float u, float* pdf, size_t* cell) const {
    const size_t n = func_.size();
    // Largest i with cdf[i] <= u: the first cdf value above u, searched between the first
    // ones above the bounds of u's n-th of [0, 1) (guide_), where a distribution's cells
    // are about as many as the cdf values a search meets: one or two steps instead of
    // log2(n), each a likely cache miss in a large environment map's rows. Where rounding
    // puts u outside its n-th, the whole search decides; the result is the whole search's.
    const double x_u = double(u);
    size_t i;
    const size_t j = x_u >= 0.0 ? std::min(n - 1, size_t(x_u * double(n))) : 0;
    const size_t lo = guide_[j], hi = guide_[j + 1];
    if ((lo == 0 || cdf_[lo - 1] <= x_u) && (hi == cdf_.size() || cdf_[hi] > x_u))
      i = size_t(std::upper_bound(cdf_.begin() + std::ptrdiff_t(lo),
                                  cdf_.begin() + std::ptrdiff_t(hi), x_u) -
                 cdf_.begin());
    else
      i = size_t(std::upper_bound(cdf_.begin(), cdf_.end(), x_u) - cdf_.begin());
    i = std::min(n - 1, i > 0 ? i - 1 : 0);
    while (i + 1 < n && func_[i] == 0.f) ++i;  // never land in an empty cell
    const double width = cdf_[i + 1] - cdf_[i];
    double du = width > 0.0 ? (double(u) - cdf_[i]) / width : 0.5;
    du = std::min(std::max(du, 0.0), 1.0);
    if (pdf) *pdf = float(double(func_[i]) / integral_);
    if (cell) *cell = i;
    const float x = float((double(i) + du) / double(n));
    return std::min(x, 0.99999994f);
  }
  float pdf(float x) const {
    const size_t n = func_.size();
    const size_t i = std::min(n - 1, size_t(std::max(0.f, x) * float(n)));
    return float(double(func_[i]) / integral_);
  }
  float invert(float x) const {
    const size_t n = func_.size();
    const size_t i = std::min(n - 1, size_t(std::max(0.f, x) * float(n)));
    const double frac = double(x) * double(n) - double(i);
    return float(cdf_[i] + frac * (cdf_[i + 1] - cdf_[i]));
  }
  float weight(size_t i) const { return func_[i]; }

 private:
  std::vector<float> func_;
  std::vector<double> cdf_;
  std::vector<uint32_t> guide_;  // n + 1 entries: the first cdf index above j / n
  double integral_ = 0.0;
};

// ---- Piecewise-constant 2D distribution on [0, 1)^2 over an nu x nv grid (row-major
// weights[v * nu + u]): the row v by its marginal, then u by the row's conditional.
class Distribution2D {
 public:
  Distribution2D() = default;
  Distribution2D(const std::vector<float>& weights, size_t nu, size_t nv) {
    std::vector<float> marginal(nv);
    rows_.reserve(nv);
    for (size_t v = 0; v < nv; ++v) {
      rows_.emplace_back(std::vector<float>(weights.begin() + std::ptrdiff_t(v * nu),
                                            weights.begin() + std::ptrdiff_t((v + 1) * nu)));
      // An all-zero row became uniform inside Distribution1D; its marginal weight stays 0.
      double sum = 0.0;
      for (size_t u = 0; u < nu; ++u) sum += std::max(0.f, weights[v * nu + u]);
      marginal[v] = float(sum / double(nu));
    }
    marginal_ = Distribution1D(marginal);
  }
  // Density with respect to area of [0, 1)^2.
  Point2 sample(Point2 u, float* pdf) const {
    float pv = 0.f, pu = 0.f;
    size_t row = 0;
    const float y = marginal_.sample(u.y, &pv, &row);
    const float x = rows_[row].sample(u.x, &pu, nullptr);
    if (pdf) *pdf = pv * pu;
    return {x, y};
  }
  float pdf(Point2 p) const {
    const size_t nv = rows_.size();
    const size_t row = std::min(nv - 1, size_t(std::max(0.f, p.y) * float(nv)));
    return marginal_.pdf(p.y) * rows_[row].pdf(p.x);
  }
  Point2 invert(Point2 p) const {
    const size_t nv = rows_.size();
    const size_t row = std::min(nv - 1, size_t(std::max(0.f, p.y) * float(nv)));
    return {rows_[row].invert(p.x), marginal_.invert(p.y)};
  }
  bool empty() const { return rows_.empty(); }

 private:
  std::vector<Distribution1D> rows_;
  Distribution1D marginal_;
};

}  // namespace rf
