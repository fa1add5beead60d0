// 4-lane float vectors for the renderer's packet-wide arithmetic (GCC/Clang vector extensions:
// SSE on x86-64, NEON on ARM). Every helper rounds each lane exactly as the scalar expression
// it is named after, so that SIMD code written in the scalar code's order of operations gives
// its results bit for bit.
#pragma once

#include <cmath>
#include <cstdint>

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

}  // namespace rf
