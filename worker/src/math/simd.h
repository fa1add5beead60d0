// 4-lane float vectors for the renderer's packet-wide arithmetic (GCC/Clang vector extensions:
// SSE on x86-64, NEON on ARM). Every helper rounds each lane exactly as the scalar expression
// it is named after, so that SIMD code written in the scalar code's order of operations gives
// its results bit for bit.
#pragma once

#include <cmath>
#include <cstdint>

#include "math/vecmath.h"

namespace rf {

typedef float F32x4 __attribute__((vector_size(16)));
typedef int32_t I32x4 __attribute__((vector_size(16)));

inline F32x4 load4(const float* p) {
  F32x4 v;
  __builtin_memcpy(&v, p, sizeof v);
  return v;
}
inline void store4(float* p, F32x4 v) { __builtin_memcpy(p, &v, sizeof v); }
inline I32x4 load4(const int32_t* p) {
  I32x4 v;
  __builtin_memcpy(&v, p, sizeof v);
  return v;
}
inline void store4(int32_t* p, I32x4 v) { __builtin_memcpy(p, &v, sizeof v); }
inline F32x4 splat4(float x) { return F32x4{x, x, x, x}; }
// The lane-wise std::min(a, b) = b < a ? b : a and std::max(a, b) = a < b ? b : a.
inline F32x4 min4(F32x4 a, F32x4 b) { return b < a ? b : a; }
inline F32x4 max4(F32x4 a, F32x4 b) { return a < b ? b : a; }
// mask ? a : b lane by lane (mask lanes all ones or all zeros, as comparisons give).
inline F32x4 select4(I32x4 mask, F32x4 a, F32x4 b) { return mask ? a : b; }
// Lane i of the mask of the low four bits of `bits`.
inline I32x4 lane_mask4(uint32_t bits) {
  return I32x4{-int32_t(bits & 1u), -int32_t((bits >> 1) & 1u), -int32_t((bits >> 2) & 1u),
               -int32_t((bits >> 3) & 1u)};
}
// Correctly rounded square root, as std::sqrt.
inline F32x4 sqrt4(F32x4 v) {
#if defined(__SSE__)
  return __builtin_ia32_sqrtps(v);
#else
  return F32x4{std::sqrt(v[0]), std::sqrt(v[1]), std::sqrt(v[2]), std::sqrt(v[3])};
#endif
}
// Dot product in vecmath.h's order: a.x * b.x + a.y * b.y + a.z * b.z.
inline F32x4 dot4(F32x4 ax, F32x4 ay, F32x4 az, F32x4 bx, F32x4 by, F32x4 bz) {
  return ax * bx + ay * by + az * bz;
}
// normalize(v) = v * (1 / sqrt(dot(v, v))), lane-wise.
inline void normalize4(F32x4& x, F32x4& y, F32x4& z) {
  const F32x4 inv = 1.f / sqrt4(dot4(x, y, z, x, y, z));
  x = x * inv;
  y = y * inv;
  z = z * inv;
}

// |v| lane-wise (the sign bit cleared, as std::fabs).
inline F32x4 abs4(F32x4 v) { return F32x4(I32x4(v) & 0x7fffffff); }

// sincos_turn (vecmath.h) lane-wise: sin and cos of 2 pi u, u in [0, 1].
inline void sincos_turn4(F32x4 u, F32x4* s, F32x4* c) {
  const I32x4 q = __builtin_convertvector(4.f * u + 0.5f, I32x4);  // truncates, as int32_t()
  F32x4 ks, kc;
  sincos_quarter((u - __builtin_convertvector(q, F32x4) * 0.25f) * (2.f * kPi), &ks, &kc);
  const I32x4 odd = (q & 1) != 0, negate = (q & 2) != 0;
  const F32x4 sin_q = odd ? kc : ks, cos_q = odd ? -ks : kc;
  *s = negate ? -sin_q : sin_q;
  *c = negate ? -cos_q : cos_q;
}

// sample_polar_disk (sampling.h) lane-wise.
inline void sample_polar_disk4(F32x4 ux, F32x4 uy, F32x4* x, F32x4* y) {
  const F32x4 r = sqrt4(ux);
  F32x4 s, c;
  sincos_turn4(uy, &s, &c);
  *x = r * c;
  *y = r * s;
}

// sample_cosine_hemisphere (sampling.h) lane-wise, through its concentric disk.
inline void sample_cosine_hemisphere4(F32x4 ux, F32x4 uy, F32x4* x, F32x4* y, F32x4* z) {
  const F32x4 zero = splat4(0.f);
  const F32x4 a = 2.f * ux - 1.f, b = 2.f * uy - 1.f;
  const I32x4 horizontal = abs4(a) > abs4(b);
  const F32x4 r = horizontal ? a : b;
  const F32x4 psi = (kPi / 4.f) * ((horizontal ? b : a) / r);
  F32x4 s, c;
  sincos_quarter(psi, &s, &c);
  // The centre (a = b = 0, where psi is 0/0) maps to the centre.
  const I32x4 centre = (a == zero) & (b == zero);
  *x = centre ? zero : r * (horizontal ? c : s);
  *y = centre ? zero : r * (horizontal ? s : c);
  *z = sqrt4(max4(zero, 1.f - *x * *x - *y * *y));
}

}  // namespace rf
