// torch's grid_sample (2-D, one channel, align_corners=False, padding_mode="border") at one point, with the
// float32 arithmetic of torch's vectorised CPU kernel, for the kernels that replace a grid_sample call
// (consistency.cpp, sample.cpp) and must give its bits.
//
// The Python side normalises a pixel coordinate as u / size * 2 - 1.  torch then unnormalises it as
// (g + 1) * size / 2 - 0.5, clamps it to [0, size - 1] (NaN to 0), and takes the bilinear sum
// nw + ne + sw + se of the four corners, a corner past the last row or column reading 0.  Its vectorised
// kernels (AVX2, AVX-512) are compiled with FMA contraction: the unnormalisation and the weighted sum are
// fused multiply-adds (measured: 25 % of bilinear samples differ in the last bit otherwise).  They are
// written here as std::fma (exactly rounded on every CPU) and everything else without contraction
// (-ffp-contract=off), so these functions give the same bits on every CPU, and equal torch's where torch
// runs its AVX2 or AVX-512 kernels.  The kernels also build an AVX2+FMA clone of their loops, where floor and fma
// are single instructions instead of libm calls (each exactly rounded either way: the same bits), chosen at run time
// by cpu_has_avx2_fma().

#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>

#include "common.h"

namespace nimbus_grid_sample {

#ifdef NIMBUS_HAS_AVX2_CLONE
inline bool cpu_has_avx2_fma() {
  static const bool yes = (__builtin_cpu_init(), __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma"));
  return yes;
}
#endif

// The sampling location along one axis of ``size`` pixels for the pixel coordinate ``coord``.
inline __attribute__((always_inline)) float location(float coord, int64_t size) {
  const float g = coord / static_cast<float>(size) * 2.0f - 1.0f;  // the Python side's u / w * 2 - 1
  float x = std::fma(g + 1.0f, static_cast<float>(size) / 2, -0.5f);
  const float hi = static_cast<float>(size - 1);
  x = std::isnan(x) ? 0.0f : std::max(x, 0.0f);  // clamp_min(Vec(0), x): NaN goes to 0
  return std::min(x, hi);
}

// The bilinear value of ``map`` [H, W] (row-major) at the location (x, y) from location().
inline __attribute__((always_inline)) float bilinear(const float* map, int64_t W, int64_t H, float x, float y) {
  const float x_w = std::floor(x), y_n = std::floor(y);
  const float w = x - x_w, e = 1.0f - w, n = y - y_n, s = 1.0f - n;
  const float nw = s * e, ne = s * w, sw = n * e, se = n * w;
  const int64_t ix = static_cast<int64_t>(x_w), iy = static_cast<int64_t>(y_n);
  const bool east = ix + 1 < W, south = iy + 1 < H;
  const float* row = map + iy * W;
  const float nw_val = row[ix];
  const float ne_val = east ? row[ix + 1] : 0.0f;
  const float sw_val = south ? row[W + ix] : 0.0f;
  const float se_val = east && south ? row[W + ix + 1] : 0.0f;
  return std::fma(se_val, se, std::fma(sw_val, sw, std::fma(ne_val, ne, nw_val * nw)));
}

}  // namespace nimbus_grid_sample
