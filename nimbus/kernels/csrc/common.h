// What the compiled kernels share: the per-ISA clone and always-inline macros, kLanes-wide
// vector types (GCC/Clang vector extensions) with their small helpers, and the float32
// Cephes exp polynomial.  Included by composite.cpp (the rasterizer extension) and
// march.cpp (NimbusGS's march extension); each extension is built by nimbus/kernels/extension.py
// with the same flags (no -ffast-math, no FMA contraction), so the operations below run
// exactly as written wherever they are inlined.

#pragma once

#include <cstdint>
#include <cstring>

// Explicit per-ISA clones instead of target_clones: an ifunc picks its clone once,
// at load, from the CPU alone, so the other paths could never run on this machine.
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#define NIMBUS_HAS_AVX2_CLONE 1
#define NIMBUS_TARGET_AVX2 __attribute__((target("avx2")))
#if __GNUC__ >= 12
#define NIMBUS_HAS_AVX512_CLONE 1
#define NIMBUS_TARGET_AVX512 __attribute__((target("arch=x86-64-v4")))
#endif
#endif
#define NIMBUS_INLINE inline __attribute__((always_inline))

namespace nimbus_simd {
// Internal linkage, as when each .cpp defined its own copies: GCC then compiles the kernels to
// the same instructions as before the header existed (with external linkage it schedules and
// allocates registers differently in the tile clones).
namespace {

// Values per vector: 8 float32 lanes fill one AVX2 register.
constexpr int kLanes = 8;

template <typename S>
struct VecTypes;
template <>
struct VecTypes<float> {
  typedef float V __attribute__((vector_size(kLanes * sizeof(float))));
  typedef int32_t I __attribute__((vector_size(kLanes * sizeof(float))));
  typedef int32_t Int;
};
template <>
struct VecTypes<double> {
  typedef double V __attribute__((vector_size(kLanes * sizeof(double))));
  typedef int64_t I __attribute__((vector_size(kLanes * sizeof(double))));
  typedef int64_t Int;
};
// kLanes values of S, and the same-width integers that comparisons return (-1 = true).
template <typename S>
using Vec = typename VecTypes<S>::V;
template <typename S>
using Mask = typename VecTypes<S>::I;

template <typename S>
NIMBUS_INLINE Vec<S> splat(S x) {
  return Vec<S>{} + x;
}
template <typename S>
NIMBUS_INLINE Mask<S> splat_int(int64_t x) {
  return Mask<S>{} + static_cast<typename VecTypes<S>::Int>(x);
}
template <typename S>
NIMBUS_INLINE Vec<S> iota() {
  Vec<S> v;
  for (int l = 0; l < kLanes; ++l) v[l] = static_cast<S>(l);
  return v;
}
// Lane-wise mask ? a : b.
template <typename M, typename V>
NIMBUS_INLINE V select(M mask, V a, V b) {
  return mask ? a : b;
}
template <typename V>
NIMBUS_INLINE V vmin(V a, V b) {
  return b < a ? b : a;
}
template <typename V>
NIMBUS_INLINE V vmax(V a, V b) {
  return a < b ? b : a;
}
// Lane sum by a fixed pairwise tree (deterministic): halves, then quarters, then pairs.
template <typename V>
NIMBUS_INLINE auto hsum(V v) {
  static_assert(kLanes == 8, "hsum is written for 8 lanes");
  return ((v[0] + v[4]) + (v[2] + v[6])) + ((v[1] + v[5]) + (v[3] + v[7]));
}

// Data is kept in plain scalar arrays and moved to and from vectors with memcpy
// (unaligned loads and stores): containers do not honour the over-alignment of vector types.
template <typename V, typename P>
NIMBUS_INLINE V load(const P* p) {
  V x;
  std::memcpy(&x, p, sizeof(V));
  return x;
}
template <typename V, typename P>
NIMBUS_INLINE void store(P* p, const V& x) {
  std::memcpy(p, &x, sizeof(V));
}

// exp(x) for x in [-87, 0] (2^n must stay a normal number; callers clamp or bound x).
NIMBUS_INLINE Vec<float> exp_cephes(Vec<float> x) {
  // Cephes expf: x = n ln2 + r, |r| <= ln2 / 2, exp(r) by a degree-6 polynomial,
  // 2^n through the exponent bits.  n is rounded with the 1.5 * 2^23 trick.
  const Vec<float> n = (x * 1.44269504088896341f + 12582912.0f) - 12582912.0f;
  Vec<float> r = x - n * 0.693359375f;
  r = r - n * -2.12194440e-4f;
  Vec<float> p = splat(1.9875691500e-4f);
  p = p * r + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  p = p * r * r + r + 1.0f;
  const Mask<float> bits = (__builtin_convertvector(n, Mask<float>) + 127) << 23;
  Vec<float> scale;
  std::memcpy(&scale, &bits, sizeof(scale));
  return p * scale;
}

}  // namespace
}  // namespace nimbus_simd
