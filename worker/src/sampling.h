// Warps from the unit square to sampling domains, as pure triples (Mitsuba's warp.h):
//   sample_X(u)   maps u in [0,1)^2 to the domain,
//   X_pdf(...)    density of sample_X with respect to the domain's measure (solid angle for
//                 directions, area of the reference domain for disk/triangle); 0 outside it,
//   invert_X(...) maps a point of the domain back to the u that produces it.
// Directions are in a local frame with the surface normal along +z.
#pragma once

#include <algorithm>
#include <cmath>

#include "vecmath.h"

namespace rf {

struct Point2 {
  float x = 0.f, y = 0.f;
};

// ---- Concentric disk (Shirley & Chiu 1997): square -> unit disk, area-preserving up to pi.
inline Point2 sample_concentric_disk(Point2 u) {
  const float a = 2.f * u.x - 1.f, b = 2.f * u.y - 1.f;
  if (a == 0.f && b == 0.f) return {0.f, 0.f};
  float r, phi;
  if (std::fabs(a) > std::fabs(b)) {
    r = a;
    phi = (kPi / 4.f) * (b / a);
  } else {
    r = b;
    phi = (kPi / 2.f) - (kPi / 4.f) * (a / b);
  }
  return {r * std::cos(phi), r * std::sin(phi)};
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

}  // namespace rf
