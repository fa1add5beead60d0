// Small 3-vector and 4x4 matrix types for the renderer. Geometry is float (what Embree uses);
// accumulation happens in double elsewhere.
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <cstring>

namespace rf {

constexpr float kPi = 3.14159265358979323846f;
constexpr float kInvPi = 0.31830988618379067154f;

struct Vec3 {
  float x = 0.f, y = 0.f, z = 0.f;
  Vec3() = default;
  constexpr Vec3(float x_, float y_, float z_) : x(x_), y(y_), z(z_) {}
  float operator[](int i) const { return i == 0 ? x : (i == 1 ? y : z); }
  float& operator[](int i) { return i == 0 ? x : (i == 1 ? y : z); }
};

inline Vec3 operator+(Vec3 a, Vec3 b) { return {a.x + b.x, a.y + b.y, a.z + b.z}; }
inline Vec3 operator-(Vec3 a, Vec3 b) { return {a.x - b.x, a.y - b.y, a.z - b.z}; }
inline Vec3 operator-(Vec3 a) { return {-a.x, -a.y, -a.z}; }
inline Vec3 operator*(Vec3 a, Vec3 b) { return {a.x * b.x, a.y * b.y, a.z * b.z}; }
inline Vec3 operator*(Vec3 a, float s) { return {a.x * s, a.y * s, a.z * s}; }
inline Vec3 operator*(float s, Vec3 a) { return a * s; }
inline Vec3 operator/(Vec3 a, float s) { return a * (1.f / s); }
inline Vec3& operator+=(Vec3& a, Vec3 b) { return a = a + b; }
inline Vec3& operator*=(Vec3& a, Vec3 b) { return a = a * b; }
inline Vec3& operator*=(Vec3& a, float s) { return a = a * s; }

inline float dot(Vec3 a, Vec3 b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
inline Vec3 cross(Vec3 a, Vec3 b) {
  return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}
inline float length(Vec3 a) { return std::sqrt(dot(a, a)); }
inline Vec3 normalize(Vec3 a) { return a / length(a); }
inline float max_component(Vec3 a) { return std::max(a.x, std::max(a.y, a.z)); }
inline float max_abs_component(Vec3 a) {
  return std::max(std::fabs(a.x), std::max(std::fabs(a.y), std::fabs(a.z)));
}
inline Vec3 vmin(Vec3 a, Vec3 b) {
  return {std::min(a.x, b.x), std::min(a.y, b.y), std::min(a.z, b.z)};
}
inline Vec3 vmax(Vec3 a, Vec3 b) {
  return {std::max(a.x, b.x), std::max(a.y, b.y), std::max(a.z, b.z)};
}
inline bool is_zero(Vec3 a) { return a.x == 0.f && a.y == 0.f && a.z == 0.f; }
inline bool is_finite(Vec3 a) {
  return std::isfinite(a.x) && std::isfinite(a.y) && std::isfinite(a.z);
}
// c ? a : b through bit masks: compilers keep a float ?: as a branch when they judge it
// predictable, and a branch on random data mispredicts half the time.
inline float select_bits(bool c, float a, float b) {
  uint32_t ua, ub;
  std::memcpy(&ua, &a, sizeof ua);
  std::memcpy(&ub, &b, sizeof ub);
  const uint32_t mask = 0u - uint32_t(c);
  const uint32_t r = (ua & mask) | (ub & ~mask);
  float out;
  std::memcpy(&out, &r, sizeof out);
  return out;
}

// sin x and cos x for |x| <= pi/4 (a little beyond is fine): the minimax polynomials of
// Cephes' single-precision sinf/cosf (S. L. Moshier), a few 1e-8 from the true values there.
// T is float or a float vector type (simd.h): one definition, so a SIMD lane rounds exactly as
// the scalar code. The samplers need no range reduction beyond what sincos_turn does, and
// libm's sincosf, a call per sample, cost about 5% of a Cornell box render.
template <typename T>
inline void sincos_quarter(T x, T* s, T* c) {
  const T z = x * x;
  *s = x + x * z * ((-1.9515295891e-4f * z + 8.3321608736e-3f) * z - 1.6666654611e-1f);
  *c = 1.f - 0.5f * z +
       z * z * ((2.443315711809948e-5f * z - 1.388731625493765e-3f) * z + 4.166664568298827e-2f);
}
// sin and cos of 2 pi u for u in [0, 1]: u = q / 4 + t with q the nearest quarter turn, so
// 2 pi u = q pi / 2 + 2 pi t with |2 pi t| <= pi / 4 (t = u - q / 4 is exact), and the quarter
// turns only swap and negate the kernel's values.
inline void sincos_turn(float u, float* s, float* c) {
  const int32_t q = int32_t(4.f * u + 0.5f);
  float ks, kc;
  sincos_quarter((u - float(q) * 0.25f) * (2.f * kPi), &ks, &kc);
  const bool odd = q & 1, negate = q & 2;
  const float sin_q = select_bits(odd, kc, ks), cos_q = select_bits(odd, -ks, kc);
  *s = select_bits(negate, -sin_q, sin_q);
  *c = select_bits(negate, -cos_q, cos_q);
}

// Rec. 709 luminance, the Y the protocol's luminance_m2 is defined on.
inline float luminance(Vec3 c) { return 0.2126f * c.x + 0.7152f * c.y + 0.0722f * c.z; }

// Orthonormal basis around a unit vector n (Duff et al. 2017, "Building an Orthonormal Basis,
// Revisited"); local z maps to n.
struct Frame {
  Vec3 s, t, n;
  explicit Frame(Vec3 n_) : n(n_) {
    const float sign = std::copysign(1.f, n.z);
    const float a = -1.f / (sign + n.z);
    const float b = n.x * n.y * a;
    s = {1.f + sign * n.x * n.x * a, sign * b, -sign * n.x};
    t = {b, sign + n.y * n.y * a, -n.y};
  }
  // The frame around n whose s is `tangent` made orthogonal to n (tangent must not be
  // parallel to n), t = cross(n, s): right-handed like the one above.
  Frame(Vec3 n_, Vec3 tangent) : n(n_) {
    s = normalize(tangent - n * dot(n, tangent));
    t = cross(n, s);
  }
  Vec3 to_world(Vec3 v) const { return s * v.x + t * v.y + n * v.z; }
  Vec3 to_local(Vec3 v) const { return {dot(v, s), dot(v, t), dot(v, n)}; }
};

// Column-major 4x4 matrix (glTF's storage order): m[col][row].
struct Mat4 {
  std::array<std::array<double, 4>, 4> m{};
  static Mat4 identity() {
    Mat4 r;
    for (int i = 0; i < 4; ++i) r.m[i][i] = 1.0;
    return r;
  }
  Mat4 operator*(const Mat4& b) const {
    Mat4 r;
    for (int c = 0; c < 4; ++c)
      for (int rr = 0; rr < 4; ++rr) {
        double s = 0.0;
        for (int k = 0; k < 4; ++k) s += m[k][rr] * b.m[c][k];
        r.m[c][rr] = s;
      }
    return r;
  }
  Vec3 transform_point(Vec3 p) const {
    double out[3];
    for (int r = 0; r < 3; ++r)
      out[r] = m[0][r] * p.x + m[1][r] * p.y + m[2][r] * p.z + m[3][r];
    return {float(out[0]), float(out[1]), float(out[2])};
  }
  Vec3 transform_vector(Vec3 v) const {
    double out[3];
    for (int r = 0; r < 3; ++r) out[r] = m[0][r] * v.x + m[1][r] * v.y + m[2][r] * v.z;
    return {float(out[0]), float(out[1]), float(out[2])};
  }
  // Normals transform with the inverse transpose of the upper 3x3; the cofactor matrix equals
  // det * inverse-transpose, and the normal is renormalized anyway, so the cofactors suffice
  // (and stay defined for singular matrices, where we then get a zero vector). nm[r][c] =
  // sign(det) cofactor(r, c): the sign keeps the normal's side under mirroring transforms.
  void normal_matrix(double nm[3][3]) const {
    auto a = [&](int r, int c) { return m[size_t(c)][size_t(r)]; };
    const double sign = det3() < 0.0 ? -1.0 : 1.0;
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c) {
        const int r1 = (r + 1) % 3, r2 = (r + 2) % 3, c1 = (c + 1) % 3, c2 = (c + 2) % 3;
        nm[r][c] = sign * (a(r1, c1) * a(r2, c2) - a(r1, c2) * a(r2, c1));
      }
  }
  Vec3 transform_normal(Vec3 n) const {
    double nm[3][3];
    normal_matrix(nm);
    double out[3];
    for (int r = 0; r < 3; ++r) out[r] = nm[r][0] * n.x + nm[r][1] * n.y + nm[r][2] * n.z;
    return {float(out[0]), float(out[1]), float(out[2])};
  }
  double det3() const {
    auto a = [&](int r, int c) { return m[c][r]; };
    return a(0, 0) * (a(1, 1) * a(2, 2) - a(1, 2) * a(2, 1)) -
           a(0, 1) * (a(1, 0) * a(2, 2) - a(1, 2) * a(2, 0)) +
           a(0, 2) * (a(1, 0) * a(2, 1) - a(1, 1) * a(2, 0));
  }
};

// A Mat4's affine part in float, with its normal matrix and handedness computed once: what a
// hit inside an instance needs per query (Mat4's double arithmetic, with the cofactors and the
// determinant recomputed per call, cost about as much as the rest of the hit record).
struct Affine3f {
  float m[3][4] = {};  // m[row][col]; column 3 is the translation
  float n[3][3] = {};  // Mat4::normal_matrix / its largest entry: normals, up to length,
                       // side kept
  bool mirror = false;  // det < 0: the transform flips handedness
  static Affine3f from(const Mat4& a) {
    Affine3f x;
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 4; ++c) x.m[r][c] = float(a.m[size_t(c)][size_t(r)]);
    // The normal matrix scaled in double to a largest entry of 1 before it becomes float:
    // normals need only its direction, and a tiny or huge scale must not underflow or
    // overflow the float entries.
    double nm[3][3];
    a.normal_matrix(nm);
    double top = 0.0;
    for (const auto& row : nm)
      for (double v : row) top = std::max(top, std::fabs(v));
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c) x.n[r][c] = top > 0.0 ? float(nm[r][c] / top) : 0.f;
    x.mirror = a.det3() < 0.0;
    return x;
  }
  Vec3 vector(Vec3 v) const {
    return {m[0][0] * v.x + m[0][1] * v.y + m[0][2] * v.z,
            m[1][0] * v.x + m[1][1] * v.y + m[1][2] * v.z,
            m[2][0] * v.x + m[2][1] * v.y + m[2][2] * v.z};
  }
  Vec3 point(Vec3 p) const { return vector(p) + Vec3(m[0][3], m[1][3], m[2][3]); }
  Vec3 normal(Vec3 v) const {
    return {n[0][0] * v.x + n[0][1] * v.y + n[0][2] * v.z,
            n[1][0] * v.x + n[1][1] * v.y + n[1][2] * v.z,
            n[2][0] * v.x + n[2][1] * v.y + n[2][2] * v.z};
  }
};

}  // namespace rf
