// What NimbusGS's kernels (march.cpp, airlight.cpp) add to common.h: the AVX2-clone CPU check,
// a non-overflowing exp for x <= 0 and a sigmoid on it.  Kept out of common.h so the rasterizer
// (composite.cpp), which needs none of it, compiles from exactly the header it was tuned with
// (GCC's scheduling of its tile clones moves with what else the header defines).

#pragma once

#include "common.h"

namespace nimbus_simd {
namespace {
#ifdef NIMBUS_HAS_AVX2_CLONE
// Whether this CPU runs the AVX2 clones (asked once).
inline bool cpu_has_avx2() {
  static const bool yes = (__builtin_cpu_init(), __builtin_cpu_supports("avx2"));
  return yes;
}
#endif

// exp(x) for x <= 0: exp_cephes with x clamped at -87 so 2^n stays a normal number (exp(-87) ~ 1.6e-38
// is 0 next to any value that matters where this is used: softplus, sigmoid).
NIMBUS_INLINE Vec<float> exp_nonpositive(Vec<float> x) { return exp_cephes(select(x < -87.0f, splat(-87.0f), x)); }

// sigmoid(x) = 1 / (1 + e) for x >= 0, e / (1 + e) below, with e = exp(-|x|) (never overflows).
NIMBUS_INLINE Vec<float> sigmoid(Vec<float> v) {
  const Vec<float> a = select(v < 0.0f, -v, v);
  const Vec<float> e = exp_nonpositive(-a);
  return select(v >= 0.0f, splat(1.0f), e) / (e + 1.0f);
}

}  // namespace
}  // namespace nimbus_simd
