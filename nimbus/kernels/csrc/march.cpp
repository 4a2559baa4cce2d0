// CPU ray march through a trilinear voxel extinction grid: optical depth per ray, forward and backward.
//
// The same mathematics as nimbus/methods/nimbusgs/scattering.py (march_reference with an
// ExtinctionGrid field).  Ray r has origin o, unit direction d and interval [t0, t1];
// its K samples sit at s_i = t0 + (i + 0.5) ds with ds = max(t1 - t0, 0) / K, and
//
//   n_i = (o + s_i d - lo) / (hi - lo) * 2 - 1                 grid_sample's align_corners=True frame
//   f_i = trilinear(features, (n_i + 1) / 2 * (size - 1))       only where every |n_i| <= 1
//   S   = ds * sum_i softplus(f_i)                             softplus with torch's threshold 20
//
// The caller scales S by the field's density scale (tau = S exp(log_scale)); T =
// exp(-tau) and the scattering weight 1 - T follow in torch.  Evaluating the K
// samples in one pass, without the [P, K, 3] point tensor and grid_sample's gathers
// and scatters, is what makes this faster than the torch path.  The sample position
// is computed as first + i * step in voxel units (the same point, rounded differently);
// float32 evaluates softplus and its derivative kLanes samples at a time with a
// polynomial exp and log1p (~1e-7 relative), float64 with std::exp / std::log1p.
// float32 runs an AVX2 clone where the CPU has AVX2: the same operations (no FMA
// contraction), so the same numbers as the generic code, in half the vector instructions.
// There the forward and the kept backward also locate a ray's samples kLanes at a time and
// the forward gathers their corners (the lane paths: locate's, interpolate's and scatter's
// operations lane by lane, the sums in sample order, so again the same numbers; 1.3x the
// forward's speed on the fast preset's march).
//
// Backward: dS/dfeatures only (the rays and their intervals are constants here; the
// Python wrapper uses the torch path when t0 / t1 need gradients).  A forward that will be
// differentiated (march_forward_keep) also returns each sample's softplus' [P, K] (0 outside
// the box), computed from the same exp as its softplus; march_backward_kept then only locates
// each sample and scatters, instead of gathering and evaluating it again.  The values and the
// order of the scatters are those of march_backward, so the gradient is the same bits.  The rays are split
// into parts by their number alone (kMaxParts, kMinRaysPerPart); each part scatters into its
// own grid and the grids are summed in part order, so the result is the same bits for any
// thread count.
//
// Registered as torch.ops.nimbus_march.*; built with airlight.cpp as NimbusGS's extension by
// nimbus/kernels/march.py (the shared vector helpers, exp and sigmoid are in common.h).

#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <ATen/ops/zeros.h>
#include <c10/util/Exception.h>
#include <torch/library.h>

#include "interrupt.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <memory>
#include <tuple>
#include <vector>

#include "medium.h"

#ifdef NIMBUS_HAS_AVX2_CLONE
#include <immintrin.h>
#endif

namespace nimbus_march {
namespace {

using namespace nimbus_simd;

// torch.nn.functional.softplus's default threshold: above it softplus(x) = x.
constexpr double kSoftplusThreshold = 20.0;
// Rays per part below which another part does not pay for its gradient grid.
constexpr int64_t kMinRaysPerPart = 2048;
// The backward's parts: min(kMaxParts, P / kMinRaysPerPart), fixed by P alone (threads share them out).
constexpr int64_t kMaxParts = 8;
// Rays per forward task.
constexpr int64_t kForwardGrain = 256;
// Samples marched between two polls for Ctrl-C (interrupt.h): about a millisecond of work, in whole rays (at
// least one), so a poll that does not ask Python (a clock read) is lost in the work however many samples a ray has.
constexpr int64_t kSamplesPerPoll = int64_t(1) << 18;
// Samples of a ray processed per block: features gathered first, then softplus in SIMD.
// A multiple of kLanes (the float blocks run in whole vectors).
constexpr int kChunk = 64;
// Voxels per task of the final gradient reduction.
constexpr int64_t kReduceGrain = 1 << 16;

template <typename T>
struct Grid {
  const T* f;           // [Z, Y, X]
  int64_t size[3];      // X, Y, Z (the order of the sample coordinates)
  int64_t stride[3];    // 1, X, X * Y
  T lo[3], hi[3];
};

// One sample's trilinear cell: base voxel offset and the fractions along x, y, z.
template <typename T>
struct Cell {
  int64_t base;
  T w[3];
};

// A ray in voxel coordinates (x = 0 .. size - 1 spans the box, as grid_sample's
// align_corners=True): sample i sits at first + i * step.
template <typename T>
struct VoxelRay {
  T first[3], step[3];
};

// (o + s d - lo) / (hi - lo) * 2 - 1 mapped by (n + 1) / 2 * (size - 1): the same point,
// rearranged so that a sample costs one multiply-add per axis.
template <typename T>
NIMBUS_INLINE VoxelRay<T> voxel_ray(const Grid<T>& g, const T* o, const T* d, T t0, T ds) {
  VoxelRay<T> v;
  for (int a = 0; a < 3; ++a) {
    const T k = T(g.size[a] - 1) / (g.hi[a] - g.lo[a]);
    v.first[a] = (o[a] - g.lo[a] + (t0 + T(0.5) * ds) * d[a]) * k;
    v.step[a] = ds * d[a] * k;
  }
  return v;
}

// The rays of one call (forward and backward read them alike): origin o [3], unit directions d [P, 3] and
// intervals [t0, t1] [P]; ray r is sampled at `samples` midpoints of step `step(r)`.
template <typename T>
struct Rays {
  const T* o;
  const T* d;
  const T* t0;
  const T* t1;
  int64_t samples;
  Rays(const at::Tensor& origin, const at::Tensor& dirs, const at::Tensor& t_start, const at::Tensor& t_end,
       int64_t samples_)
      : o(origin.data_ptr<T>()), d(dirs.data_ptr<T>()), t0(t_start.data_ptr<T>()), t1(t_end.data_ptr<T>()),
        samples(samples_) {}
  NIMBUS_INLINE T step(int64_t r) const { return std::max(t1[r] - t0[r], T(0)) / T(samples); }
  NIMBUS_INLINE VoxelRay<T> voxels(const Grid<T>& g, int64_t r, T ds) const { return voxel_ray(g, o, d + 3 * r, t0[r], ds); }
};

// Locates sample i of the ray; false when it lies outside the box.
template <typename T>
NIMBUS_INLINE bool locate(const Grid<T>& g, const VoxelRay<T>& ray, int64_t i, Cell<T>& c) {
  c.base = 0;
  for (int a = 0; a < 3; ++a) {
    const T x = ray.first[a] + T(i) * ray.step[a];
    const T top = T(g.size[a] - 1);
    if (!(x >= T(0) && x <= top)) return false;  // also rejects NaN, as the torch mask does
    // grid_sample's weights: at the upper face x0 = size - 2 with fraction 1 equals x0 = size - 1 with 0.
    const int64_t x0 = std::min<int64_t>(static_cast<int64_t>(x), g.size[a] - 2);
    c.w[a] = x - T(x0);
    c.base += x0 * g.stride[a];
  }
  return true;
}

template <typename T>
NIMBUS_INLINE T interpolate(const Grid<T>& g, const Cell<T>& c) {
  const T* v = g.f + c.base;
  const int64_t sx = g.stride[0], sy = g.stride[1], sz = g.stride[2];
  const T wx = c.w[0], wy = c.w[1], wz = c.w[2];
  const T ux = T(1) - wx, uy = T(1) - wy, uz = T(1) - wz;
  return uz * (uy * (ux * v[0] + wx * v[sx]) + wy * (ux * v[sy] + wx * v[sy + sx])) +
         wz * (uy * (ux * v[sz] + wx * v[sz + sx]) + wy * (ux * v[sz + sy] + wx * v[sz + sy + sx]));
}

template <typename T>
NIMBUS_INLINE void scatter(const Grid<T>& g, const Cell<T>& c, T value, T* out) {
  T* v = out + c.base;
  const int64_t sx = g.stride[0], sy = g.stride[1], sz = g.stride[2];
  const T wx = c.w[0], wy = c.w[1], wz = c.w[2];
  const T ux = T(1) - wx, uy = T(1) - wy, uz = T(1) - wz;
  const T a0 = uz * uy * value, a1 = uz * wy * value, a2 = wz * uy * value, a3 = wz * wy * value;
  v[0] += ux * a0;
  v[sx] += wx * a0;
  v[sy] += ux * a1;
  v[sy + sx] += wx * a1;
  v[sz] += ux * a2;
  v[sz + sx] += wx * a2;
  v[sz + sy] += ux * a3;
  v[sz + sy + sx] += wx * a3;
}

// softplus and its derivative (as torch's softplus_backward computes it) over a block
// of n feature values, in place.  float32 runs kLanes at a time with a polynomial exp
// and log1p (below); float64 (gradcheck, tests) calls std::exp / std::log1p.
// With d, softplus' goes there too, from the same exp (the numbers softplus_grad_block gives).
NIMBUS_INLINE void softplus_block(double* x, int n, double* d = nullptr) {
  for (int j = 0; j < n; ++j) {
    const bool above = x[j] > kSoftplusThreshold;
    const double z = std::exp(x[j]);
    if (d) d[j] = above ? 1.0 : z / (z + 1.0);
    x[j] = above ? x[j] : std::log1p(z);
  }
}
NIMBUS_INLINE void softplus_grad_block(double* x, int n) {
  for (int j = 0; j < n; ++j) {
    const double z = std::exp(x[j]);
    x[j] = x[j] > kSoftplusThreshold ? 1.0 : z / (z + 1.0);
  }
}

using VecF = Vec<float>;
using VecI = Mask<float>;

// log1p(u) for u in [0, 1] as 2 atanh(s), s = u / (2 + u) <= 1/3: the odd series to s^13
// (next term < 2^-26 relative), accurate in relative terms however small u is.
NIMBUS_INLINE VecF log1p_unit(VecF u) {
  const VecF s = u / (u + 2.0f);
  const VecF s2 = s * s;
  VecF p = splat(1.0f / 13.0f);
  p = p * s2 + 1.0f / 11.0f;
  p = p * s2 + 1.0f / 9.0f;
  p = p * s2 + 1.0f / 7.0f;
  p = p * s2 + 1.0f / 5.0f;
  p = p * s2 + 1.0f / 3.0f;
  return 2.0f * (s + s * s2 * p);
}

// softplus(x) = max(x, 0) + log1p(exp(-|x|)); x above the threshold is kept as it is.  With d,
// softplus' = sigmoid goes there too, from the same e = exp(-|x|) (medium.h's sigmoid, and
// softplus_grad_block's numbers).
NIMBUS_INLINE void softplus_block(float* x, int n, float* d = nullptr) {
  for (int j = 0; j < n; j += kLanes) {
    const VecF v = load<VecF>(x + j);
    const VecF a = select(v < 0.0f, -v, v);
    const VecF e = exp_nonpositive(-a);
    const VecF sp = select(v > 0.0f, v, splat(0.0f)) + log1p_unit(e);
    if (d) {
      const VecF sig = select(v >= 0.0f, splat(1.0f), e) / (e + 1.0f);
      store(d + j, select(v > float(kSoftplusThreshold), splat(1.0f), sig));
    }
    store(x + j, select(v > float(kSoftplusThreshold), v, sp));
  }
}

// softplus' = sigmoid (common.h), 1 above the threshold.
NIMBUS_INLINE void softplus_grad_block(float* x, int n) {
  for (int j = 0; j < n; j += kLanes) {
    const VecF v = load<VecF>(x + j);
    store(x + j, select(v > float(kSoftplusThreshold), splat(1.0f), sigmoid(v)));
  }
}

template <typename T>
Grid<T> make_grid(const at::Tensor& features, const at::Tensor& lo, const at::Tensor& hi) {
  Grid<T> g{};
  g.f = features.data_ptr<T>();
  g.size[0] = features.size(2);
  g.size[1] = features.size(1);
  g.size[2] = features.size(0);
  g.stride[0] = 1;
  g.stride[1] = g.size[0];
  g.stride[2] = g.size[0] * g.size[1];
  const T* l = lo.data_ptr<T>();
  const T* h = hi.data_ptr<T>();
  for (int a = 0; a < 3; ++a) {
    g.lo[a] = l[a];
    g.hi[a] = h[a];
  }
  return g;
}

// S[r] for rays b .. e - 1; with D (not null), each sample's softplus' in D[r * K + i] (0 outside the box).
template <typename T>
NIMBUS_INLINE void forward_rays(const Grid<T>& g, const Rays<T>& rays, int64_t b, int64_t e, T* S, T* D) {
  Cell<T> c;
  T f[kChunk], fd[kChunk];
  int idx[kChunk];
  const int64_t K = rays.samples;
  for (int64_t r = b; r < e; ++r) {
    const T ds = rays.step(r);
    T acc = 0;
    const VoxelRay<T> ray = rays.voxels(g, r, ds);
    T* dr = D ? D + r * K : nullptr;
    if (dr) std::fill(dr, dr + K, T(0));
    for (int64_t i0 = 0; i0 < K; i0 += kChunk) {
      int n = 0;
      for (int64_t i = i0; i < std::min<int64_t>(K, i0 + kChunk); ++i) {
        if (locate(g, ray, i, c)) {
          idx[n] = static_cast<int>(i - i0);
          f[n++] = interpolate(g, c);
        }
      }
      std::fill(f + n, f + kChunk, T(0));  // whole vectors: no uninitialised lanes
      if (dr) {
        softplus_block(f, n, fd);
        for (int j = 0; j < n; ++j) dr[i0 + idx[j]] = fd[j];
      } else {
        softplus_block(f, n);
      }
      for (int j = 0; j < n; ++j) acc += f[j];
    }
    S[r] = acc * ds;
  }
}

// dS/dfeatures of rays b .. e - 1 (weighted by gS) added to acc, in ray order.
template <typename T>
NIMBUS_INLINE void backward_rays(const Grid<T>& g, const Rays<T>& rays, const T* gS, int64_t b, int64_t e, T* acc) {
  Cell<T> cells[kChunk];
  T f[kChunk];
  for (int64_t r = b; r < e; ++r) {
    const T ds = rays.step(r);
    const T coef = gS[r] * ds;
    if (coef == T(0)) continue;
    const VoxelRay<T> ray = rays.voxels(g, r, ds);
    for (int64_t i0 = 0; i0 < rays.samples; i0 += kChunk) {
      int n = 0;
      for (int64_t i = i0; i < std::min<int64_t>(rays.samples, i0 + kChunk); ++i) {
        if (locate(g, ray, i, cells[n])) {
          f[n] = interpolate(g, cells[n]);
          ++n;
        }
      }
      std::fill(f + n, f + kChunk, T(0));
      softplus_grad_block(f, n);
      for (int j = 0; j < n; ++j) scatter(g, cells[j], coef * f[j], acc);
    }
  }
}

// The same sums as backward_rays, with each sample's softplus' read from the forward's D [P, K].
template <typename T>
NIMBUS_INLINE void backward_rays_kept(const Grid<T>& g, const Rays<T>& rays, const T* gS, const T* D, int64_t b,
                                      int64_t e, T* acc) {
  Cell<T> c;
  const int64_t K = rays.samples;
  for (int64_t r = b; r < e; ++r) {
    const T ds = rays.step(r);
    const T coef = gS[r] * ds;
    if (coef == T(0)) continue;
    const VoxelRay<T> ray = rays.voxels(g, r, ds);
    const T* dr = D + r * K;
    for (int64_t i = 0; i < K; ++i) {
      if (locate(g, ray, i, c)) scatter(g, c, coef * dr[i], acc);
    }
  }
}

// Backward with the forward's softplus' (D) when given, else evaluating every sample again.
template <typename T>
NIMBUS_INLINE void backward_any(const Grid<T>& g, const Rays<T>& rays, const T* gS, const T* D, int64_t b, int64_t e,
                                T* acc) {
  if (D) {
    backward_rays_kept(g, rays, gS, D, b, e, acc);
  } else {
    backward_rays(g, rays, gS, b, e, acc);
  }
}

// Whether the float32 AVX2 paths locate kLanes samples at a time (forward_rays_gather, backward_rays_kept_gather)
// rather than one (the AVX2 clones of forward_rays, backward_rays_kept): the same numbers either way; the switch
// (march_set_lane_paths) lets the tests compare the two.
std::atomic<bool> g_lane_paths{true};

// The lane paths index the grid with int32 and count samples in float: a grid of < 2^31 voxels, < 2^24 samples.
template <typename T>
bool lane_paths_fit(const Grid<T>& g, int64_t samples) {
  return g_lane_paths.load(std::memory_order_relaxed) && g.size[0] * g.size[1] * g.size[2] < (int64_t(1) << 31) &&
         samples < (int64_t(1) << 24);
}

#ifdef NIMBUS_HAS_AVX2_CLONE
// Locates kLanes samples of a ray at once (i = first + lane, the lanes from `count` on are not samples): the
// base voxel and the fractions, with locate's operations lane by lane; `inside` is -1 where locate is true
// (the base is 0 elsewhere, a voxel that is safe to read).
struct VecCells {
  VecI inside, base;
  VecF w[3];
};
// The grid's bounds per axis as vectors (the largest voxel coordinate, the last cell's base, the stride), built
// once per call of a lane path.
struct LaneGrid {
  VecF top[3];
  VecI last[3], stride[3];
  NIMBUS_TARGET_AVX2 explicit LaneGrid(const Grid<float>& g) {
    for (int a = 0; a < 3; ++a) {
      top[a] = splat(float(g.size[a] - 1));
      last[a] = splat_int<float>(g.size[a] - 2);
      stride[a] = splat_int<float>(g.stride[a]);
    }
  }
};
NIMBUS_TARGET_AVX2 NIMBUS_INLINE VecCells locate_lanes(const LaneGrid& lg, const VoxelRay<float>& ray, int64_t first,
                                                       int count) {
  VecCells c;
  const VecF lane = iota<float>();
  const VecF fi = lane + float(first);  // float(i), exactly (i < 2^24)
  c.inside = __builtin_convertvector(lane, VecI) < count;
  c.base = splat_int<float>(0);
  for (int a = 0; a < 3; ++a) {
    VecF x = ray.first[a] + fi * ray.step[a];
    const VecI in_axis = (x >= 0.0f) & (x <= lg.top[a]);
    c.inside &= in_axis;
    x = select(in_axis, x, splat(0.0f));
    VecI x0 = __builtin_convertvector(x, VecI);
    x0 = select(x0 > lg.last[a], lg.last[a], x0);
    c.w[a] = x - __builtin_convertvector(x0, VecF);
    c.base += x0 * lg.stride[a];
  }
  c.base = select(c.inside != 0, c.base, splat_int<float>(0));
  return c;
}

// float32 forward with AVX2: a ray's samples kLanes at a time, located and interpolated lane by lane with
// locate's and interpolate's operations in their order (so the same numbers as the scalar code), the eight
// corners read with gathers.  Invalid samples (outside the box, or past the ray's last) get 0 and add
// nothing; the valid ones are summed in sample order, as forward_rays sums them.
NIMBUS_TARGET_AVX2 void forward_rays_gather(const Grid<float>& g, const Rays<float>& rays, int64_t b, int64_t e,
                                            float* S, float* D) {
  const int64_t K = rays.samples;
  alignas(32) float f[kChunk], fd[kChunk];
  alignas(32) int32_t ok[kChunk];
  const LaneGrid lg(g);
  const int32_t sx = int32_t(g.stride[0]), sy = int32_t(g.stride[1]), sz = int32_t(g.stride[2]);
  for (int64_t r = b; r < e; ++r) {
    const float ds = rays.step(r);
    float acc = 0;
    const VoxelRay<float> ray = rays.voxels(g, r, ds);
    float* dr = D ? D + r * K : nullptr;
    for (int64_t i0 = 0; i0 < K; i0 += kChunk) {
      const int m = int(std::min<int64_t>(kChunk, K - i0));
      for (int j = 0; j < m; j += kLanes) {
        const VecCells c = locate_lanes(lg, ray, i0 + j, m - j);
        const __m256i idx = (__m256i)c.base;
#define NIMBUS_AT(off) ((VecF)_mm256_i32gather_ps(g.f + (off), idx, 4))
        const VecF wx = c.w[0], wy = c.w[1], wz = c.w[2];
        const VecF ux = 1.0f - wx, uy = 1.0f - wy, uz = 1.0f - wz;
        const VecF v = uz * (uy * (ux * NIMBUS_AT(0) + wx * NIMBUS_AT(sx)) +
                             wy * (ux * NIMBUS_AT(sy) + wx * NIMBUS_AT(sy + sx))) +
                       wz * (uy * (ux * NIMBUS_AT(sz) + wx * NIMBUS_AT(sz + sx)) +
                             wy * (ux * NIMBUS_AT(sz + sy) + wx * NIMBUS_AT(sz + sy + sx)));
#undef NIMBUS_AT
        store(f + j, select(c.inside != 0, v, splat(0.0f)));
        store(ok + j, c.inside);
      }
      const int mv = (m + kLanes - 1) / kLanes * kLanes;
      if (dr) {
        softplus_block(f, mv, fd);
        for (int j = 0; j < m; ++j) dr[i0 + j] = ok[j] ? fd[j] : 0.0f;
      } else {
        softplus_block(f, mv);
      }
      for (int j = 0; j < m; ++j) {
        if (ok[j]) acc += f[j];
      }
    }
    S[r] = acc * ds;
  }
}

// backward_rays_kept with AVX2: the samples located and their eight corner values computed kLanes at a time
// (scatter's products, lane by lane), then added to the grid sample by sample, in backward_rays_kept's order.
NIMBUS_TARGET_AVX2 void backward_rays_kept_gather(const Grid<float>& g, const Rays<float>& rays, const float* gS,
                                                  const float* D, int64_t b, int64_t e, float* acc) {
  const int64_t K = rays.samples;
  const LaneGrid lg(g);
  const int64_t sx = g.stride[0], sy = g.stride[1], sz = g.stride[2];
  const int64_t off[8] = {0, sx, sy, sy + sx, sz, sz + sx, sz + sy, sz + sy + sx};
  alignas(32) float part[8][kLanes];
  alignas(32) int32_t ok[kLanes], base[kLanes];
  for (int64_t r = b; r < e; ++r) {
    const float ds = rays.step(r);
    const float coef = gS[r] * ds;
    if (coef == 0.0f) continue;
    const VoxelRay<float> ray = rays.voxels(g, r, ds);
    const float* dr = D + r * K;
    for (int64_t i0 = 0; i0 < K; i0 += kLanes) {
      const int m = int(std::min<int64_t>(kLanes, K - i0));
      const VecCells c = locate_lanes(lg, ray, i0, m);
      float vals[kLanes] = {};
      std::copy(dr + i0, dr + i0 + m, vals);
      const VecF value = coef * load<VecF>(vals);
      const VecF wx = c.w[0], wy = c.w[1], wz = c.w[2];
      const VecF ux = 1.0f - wx, uy = 1.0f - wy, uz = 1.0f - wz;
      const VecF a0 = uz * uy * value, a1 = uz * wy * value, a2 = wz * uy * value, a3 = wz * wy * value;
      store(part[0], ux * a0), store(part[1], wx * a0), store(part[2], ux * a1), store(part[3], wx * a1);
      store(part[4], ux * a2), store(part[5], wx * a2), store(part[6], ux * a3), store(part[7], wx * a3);
      store(ok, c.inside), store(base, c.base);
      for (int j = 0; j < m; ++j) {
        if (!ok[j]) continue;
        float* v = acc + base[j];
        for (int k = 0; k < 8; ++k) v[off[k]] += part[k][j];
      }
    }
  }
}
#endif

// float32 runs the AVX2 clone where the CPU has it: the same operations (no FMA contraction), wider.
void forward_rays_generic(const Grid<float>& g, const Rays<float>& rays, int64_t b, int64_t e, float* S, float* D) {
  forward_rays(g, rays, b, e, S, D);
}
void backward_rays_generic(const Grid<float>& g, const Rays<float>& rays, const float* gS, const float* D, int64_t b,
                           int64_t e, float* acc) {
  backward_any(g, rays, gS, D, b, e, acc);
}
#ifdef NIMBUS_HAS_AVX2_CLONE
NIMBUS_TARGET_AVX2 void forward_rays_avx2(const Grid<float>& g, const Rays<float>& rays, int64_t b, int64_t e,
                                          float* S, float* D) {
  forward_rays(g, rays, b, e, S, D);
}
NIMBUS_TARGET_AVX2 void backward_rays_avx2(const Grid<float>& g, const Rays<float>& rays, const float* gS,
                                           const float* D, int64_t b, int64_t e, float* acc) {
  backward_any(g, rays, gS, D, b, e, acc);
}
#endif

void run_forward(const Grid<float>& g, const Rays<float>& rays, int64_t b, int64_t e, float* S, float* D) {
#ifdef NIMBUS_HAS_AVX2_CLONE
  if (cpu_has_avx2() && lane_paths_fit(g, rays.samples)) return forward_rays_gather(g, rays, b, e, S, D);
  if (cpu_has_avx2()) return forward_rays_avx2(g, rays, b, e, S, D);
#endif
  forward_rays_generic(g, rays, b, e, S, D);
}
void run_forward(const Grid<double>& g, const Rays<double>& rays, int64_t b, int64_t e, double* S, double* D) {
  forward_rays(g, rays, b, e, S, D);
}
void run_backward(const Grid<float>& g, const Rays<float>& rays, const float* gS, const float* D, int64_t b, int64_t e,
                  float* acc) {
#ifdef NIMBUS_HAS_AVX2_CLONE
  if (cpu_has_avx2() && D && lane_paths_fit(g, rays.samples)) {
    return backward_rays_kept_gather(g, rays, gS, D, b, e, acc);
  }
  if (cpu_has_avx2()) return backward_rays_avx2(g, rays, gS, D, b, e, acc);
#endif
  backward_rays_generic(g, rays, gS, D, b, e, acc);
}
void run_backward(const Grid<double>& g, const Rays<double>& rays, const double* gS, const double* D, int64_t b,
                  int64_t e, double* acc) {
  backward_any(g, rays, gS, D, b, e, acc);
}

void check_inputs(const at::Tensor& features, const at::Tensor& origin, const at::Tensor& dirs,
                  const at::Tensor& t_start, const at::Tensor& t_end, const at::Tensor& lo, const at::Tensor& hi,
                  int64_t samples) {
  TORCH_CHECK(features.dim() == 3 && features.size(0) >= 2 && features.size(1) >= 2 && features.size(2) >= 2,
              "features must be [Z, Y, X] with every side >= 2");
  TORCH_CHECK(origin.numel() == 3 && lo.numel() == 3 && hi.numel() == 3, "origin, lo and hi must have 3 elements");
  TORCH_CHECK(dirs.dim() == 2 && dirs.size(1) == 3, "dirs must be [P, 3]");
  const int64_t P = dirs.size(0);
  TORCH_CHECK(t_start.numel() == P && t_end.numel() == P, "t_start and t_end must have P elements");
  TORCH_CHECK(samples >= 1, "samples must be >= 1");
  for (const at::Tensor* t : {&features, &origin, &dirs, &t_start, &t_end, &lo, &hi}) {
    TORCH_CHECK(t->device().is_cpu(), "march kernel: CPU tensors expected");
    TORCH_CHECK(t->scalar_type() == features.scalar_type(), "march kernel: all tensors must share one dtype");
    TORCH_CHECK(t->is_contiguous(), "march kernel: contiguous tensors expected");
  }
}

// S [P], and with keep the samples' softplus' D [P, K] (an undefined tensor without).
std::tuple<at::Tensor, at::Tensor> forward_impl(const at::Tensor& features, const at::Tensor& origin,
                                                const at::Tensor& dirs, const at::Tensor& t_start,
                                                const at::Tensor& t_end, const at::Tensor& lo, const at::Tensor& hi,
                                                int64_t samples, bool keep) {
  check_inputs(features, origin, dirs, t_start, t_end, lo, hi, samples);
  const int64_t P = dirs.size(0);
  at::Tensor out = at::empty({P}, dirs.options());
  at::Tensor kept = keep ? at::empty({P, samples}, dirs.options()) : at::Tensor();
  AT_DISPATCH_FLOATING_TYPES(features.scalar_type(), "march_forward", [&] {
    using T = scalar_t;
    const Grid<T> g = make_grid<T>(features, lo, hi);
    const Rays<T> rays(origin, dirs, t_start, t_end, samples);
    T* S = out.data_ptr<T>();
    T* D = keep ? kept.data_ptr<T>() : nullptr;
    nimbus_interrupt::Interrupt interrupt;
    const int64_t block = std::max<int64_t>(1, kSamplesPerPoll / samples);
    at::parallel_for(0, P, kForwardGrain, [&](int64_t b, int64_t e) {
      for (int64_t r = b; r < e && !interrupt.stop(); r += block) {
        run_forward(g, rays, r, std::min(e, r + block), S, D);
      }
    });
  });
  return {out, kept};
}

at::Tensor march_forward(const at::Tensor& features, const at::Tensor& origin, const at::Tensor& dirs,
                         const at::Tensor& t_start, const at::Tensor& t_end, const at::Tensor& lo,
                         const at::Tensor& hi, int64_t samples) {
  return std::get<0>(forward_impl(features, origin, dirs, t_start, t_end, lo, hi, samples, false));
}

// (S [P], D [P, K]): the forward of a march that will be differentiated with march_backward_kept.
std::tuple<at::Tensor, at::Tensor> march_forward_keep(const at::Tensor& features, const at::Tensor& origin,
                                                      const at::Tensor& dirs, const at::Tensor& t_start,
                                                      const at::Tensor& t_end, const at::Tensor& lo,
                                                      const at::Tensor& hi, int64_t samples) {
  return forward_impl(features, origin, dirs, t_start, t_end, lo, hi, samples, true);
}

// dS/dfeatures weighted by grad_out; with kept (march_forward_keep's D) defined, no sample is evaluated again.
at::Tensor backward_impl(const at::Tensor& features, const at::Tensor& origin, const at::Tensor& dirs,
                         const at::Tensor& t_start, const at::Tensor& t_end, const at::Tensor& lo,
                         const at::Tensor& hi, int64_t samples, const at::Tensor& kept, const at::Tensor& grad_out) {
  check_inputs(features, origin, dirs, t_start, t_end, lo, hi, samples);
  const int64_t P = dirs.size(0);
  TORCH_CHECK(grad_out.numel() == P && grad_out.is_contiguous() && grad_out.scalar_type() == features.scalar_type(),
              "grad_out must be a contiguous [P] tensor of the features' dtype");
  if (kept.defined()) {
    TORCH_CHECK(kept.numel() == P * samples && kept.is_contiguous() && kept.device().is_cpu() &&
                    kept.scalar_type() == features.scalar_type(),
                "kept must be march_forward_keep's contiguous [P, samples] tensor of the features' dtype");
  }
  at::Tensor grad = at::zeros(features.sizes(), features.options());
  const int64_t V = features.numel();
  const int64_t parts = std::max<int64_t>(1, std::min<int64_t>(kMaxParts, P / kMinRaysPerPart));
  AT_DISPATCH_FLOATING_TYPES(features.scalar_type(), "march_backward", [&] {
    using T = scalar_t;
    const Grid<T> g = make_grid<T>(features, lo, hi);
    const Rays<T> rays(origin, dirs, t_start, t_end, samples);
    const T* gS = grad_out.data_ptr<T>();
    const T* D = kept.defined() ? kept.data_ptr<T>() : nullptr;
    T* out = grad.data_ptr<T>();
    // Part 0 writes into the result; the others into their own grids, zeroed by their owner.
    std::unique_ptr<T[]> extra(parts > 1 ? new T[(parts - 1) * V] : nullptr);
    nimbus_interrupt::Interrupt interrupt;
    const int64_t block = std::max<int64_t>(1, kSamplesPerPoll / samples);
    auto work = [&](int64_t wb, int64_t we) {
      for (int64_t w = wb; w < we; ++w) {
        T* acc = w == 0 ? out : extra.get() + (w - 1) * V;
        if (w > 0) std::fill(acc, acc + V, T(0));
        // In ray order, block by block: the same sums as one call over the part.
        const int64_t end = P * (w + 1) / parts;
        for (int64_t r = P * w / parts; r < end && !interrupt.stop(); r += block) {
          run_backward(g, rays, gS, D, r, std::min(end, r + block), acc);
        }
      }
    };
    if (parts == 1) {
      work(0, 1);  // parallel_for over a range of 1 would still wake the whole pool
    } else {
      at::parallel_for(0, parts, 1, work);
      at::parallel_for(0, V, kReduceGrain, [&](int64_t b, int64_t e) {
        for (int64_t w = 1; w < parts; ++w) {
          const T* src = extra.get() + (w - 1) * V;
          for (int64_t v = b; v < e; ++v) out[v] += src[v];
        }
      });
    }
  });
  return grad;
}

at::Tensor march_backward(const at::Tensor& features, const at::Tensor& origin, const at::Tensor& dirs,
                          const at::Tensor& t_start, const at::Tensor& t_end, const at::Tensor& lo,
                          const at::Tensor& hi, int64_t samples, const at::Tensor& grad_out) {
  return backward_impl(features, origin, dirs, t_start, t_end, lo, hi, samples, at::Tensor(), grad_out);
}

at::Tensor march_backward_kept(const at::Tensor& features, const at::Tensor& origin, const at::Tensor& dirs,
                               const at::Tensor& t_start, const at::Tensor& t_end, const at::Tensor& lo,
                               const at::Tensor& hi, int64_t samples, const at::Tensor& kept,
                               const at::Tensor& grad_out) {
  return backward_impl(features, origin, dirs, t_start, t_end, lo, hi, samples, kept, grad_out);
}

// ---------------------------------------------------------------------------------------------
// L_TV of the grid (ExtinctionGrid.tv without its scale): sum over the axes of mean |forward
// difference| of softplus(features), and its gradient.  torch evaluates it as a dozen passes over
// the grid (softplus, three diffs, abs, means and their backward); here one pass computes
// softplus and softplus' and one more the sums (or the gradient).  Per-slice partial sums are
// added in slice order, so the value is the same bits for any thread count; each voxel's gradient
// is computed from its neighbours alone.  |x|'s derivative at 0 is 0, as torch's.

// softplus and softplus' of n values, any n, through softplus_block in whole chunks.
template <typename T>
NIMBUS_INLINE void softplus_values(const T* f, T* sp, T* sig, int64_t n) {
  T x[kChunk], d[kChunk];
  for (int64_t i0 = 0; i0 < n; i0 += kChunk) {
    const int m = static_cast<int>(std::min<int64_t>(kChunk, n - i0));
    std::copy(f + i0, f + i0 + m, x);
    std::fill(x + m, x + kChunk, T(0));
    softplus_block(x, m, d);
    std::copy(x, x + m, sp + i0);
    std::copy(d, d + m, sig + i0);
  }
}
void softplus_values_generic(const float* f, float* sp, float* sig, int64_t n) { softplus_values(f, sp, sig, n); }
#ifdef NIMBUS_HAS_AVX2_CLONE
NIMBUS_TARGET_AVX2 void softplus_values_avx2(const float* f, float* sp, float* sig, int64_t n) {
  softplus_values(f, sp, sig, n);
}
#endif
void run_softplus(const float* f, float* sp, float* sig, int64_t n) {
#ifdef NIMBUS_HAS_AVX2_CLONE
  if (cpu_has_avx2()) return softplus_values_avx2(f, sp, sig, n);
#endif
  softplus_values_generic(f, sp, sig, n);
}
void run_softplus(const double* f, double* sp, double* sig, int64_t n) { softplus_values(f, sp, sig, n); }

struct TVShape {
  int64_t Z, Y, X;
  int64_t slice() const { return Y * X; }
};

TVShape tv_shape(const at::Tensor& features) {
  TORCH_CHECK(features.dim() == 3 && features.size(0) >= 2 && features.size(1) >= 2 && features.size(2) >= 2,
              "features must be [Z, Y, X] with every side >= 2");
  TORCH_CHECK(features.device().is_cpu() && features.is_contiguous(), "grid TV: a contiguous CPU tensor expected");
  return TVShape{features.size(0), features.size(1), features.size(2)};
}

// softplus (sp) and softplus' (sig) of every voxel, slices in parallel.
template <typename T>
void softplus_grid(const T* f, T* sp, T* sig, const TVShape& s) {
  at::parallel_for(0, s.Z, 1, [&](int64_t b, int64_t e) {
    run_softplus(f + b * s.slice(), sp + b * s.slice(), sig + b * s.slice(), (e - b) * s.slice());
  });
}

// sum |b[i] - a[i]| over n values, in kLanes running sums (vectorised; a fixed order) added in lane order.
template <typename T>
NIMBUS_INLINE T abs_diff_sum(const T* a, const T* b, int64_t n) {
  T acc[kLanes] = {};
  int64_t i = 0;
  for (; i + kLanes <= n; i += kLanes) {
    for (int l = 0; l < kLanes; ++l) acc[l] += std::abs(b[i + l] - a[i + l]);
  }
  T sum = 0;
  for (int l = 0; l < kLanes; ++l) sum += acc[l];
  for (; i < n; ++i) sum += std::abs(b[i] - a[i]);
  return sum;
}

// The x, y and z (to the next slice) sums of slice z.
template <typename T>
NIMBUS_INLINE void tv_slice_sums(const T* sp, const TVShape& s, int64_t z, T* out) {
  const T* a = sp + z * s.slice();
  T sx = 0;
  for (int64_t y = 0; y < s.Y; ++y) sx += abs_diff_sum(a + y * s.X, a + y * s.X + 1, s.X - 1);
  out[0] = sx;
  out[1] = abs_diff_sum(a, a + s.X, (s.Y - 1) * s.X);
  out[2] = z + 1 < s.Z ? abs_diff_sum(a, a + s.slice(), s.slice()) : T(0);
}

template <typename T>
NIMBUS_INLINE T sgn(T v) {
  return (v > T(0) ? T(1) : T(0)) - (v < T(0) ? T(1) : T(0));
}

// The gradient of slice z (w: the three axes' weights, grad / count); t is scratch of X values.
template <typename T>
NIMBUS_INLINE void tv_slice_grad(const T* sp, const T* sig, const TVShape& s, int64_t z, const T* w, T* t, T* out) {
  const int64_t X = s.X, S = s.slice();
  const T* a = sp + z * S;
  T* o = out + z * S;
  for (int64_t y = 0; y < s.Y; ++y) {  // x: o[x] = t[x - 1] - t[x], t[x] = w sgn(a[x + 1] - a[x])
    const T* row = a + y * X;
    T* orow = o + y * X;
    for (int64_t x = 0; x + 1 < X; ++x) t[x] = w[0] * sgn(row[x + 1] - row[x]);
    orow[0] = -t[0];
    for (int64_t x = 1; x + 1 < X; ++x) orow[x] = t[x - 1] - t[x];
    orow[X - 1] = t[X - 2];
  }
  for (int64_t y = 0; y + 1 < s.Y; ++y) {  // y: the difference between rows y and y + 1
    const T* r0 = a + y * X;
    T* o0 = o + y * X;
    for (int64_t x = 0; x < X; ++x) {
      const T d = w[1] * sgn(r0[x + X] - r0[x]);
      o0[x] -= d;
      o0[x + X] += d;
    }
  }
  if (z > 0) {
    for (int64_t v = 0; v < S; ++v) o[v] += w[2] * sgn(a[v] - a[v - S]);
  }
  if (z + 1 < s.Z) {
    for (int64_t v = 0; v < S; ++v) o[v] -= w[2] * sgn(a[v + S] - a[v]);
  }
  for (int64_t v = 0; v < S; ++v) o[v] *= sig[z * S + v];
}

void tv_slice_sums_generic(const float* sp, const TVShape& s, int64_t z, float* out) { tv_slice_sums(sp, s, z, out); }
void tv_slice_grad_generic(const float* sp, const float* sig, const TVShape& s, int64_t z, const float* w, float* t,
                           float* out) {
  tv_slice_grad(sp, sig, s, z, w, t, out);
}
#ifdef NIMBUS_HAS_AVX2_CLONE
NIMBUS_TARGET_AVX2 void tv_slice_sums_avx2(const float* sp, const TVShape& s, int64_t z, float* out) {
  tv_slice_sums(sp, s, z, out);
}
NIMBUS_TARGET_AVX2 void tv_slice_grad_avx2(const float* sp, const float* sig, const TVShape& s, int64_t z,
                                           const float* w, float* t, float* out) {
  tv_slice_grad(sp, sig, s, z, w, t, out);
}
#endif
void run_tv_sums(const float* sp, const TVShape& s, int64_t z, float* out) {
#ifdef NIMBUS_HAS_AVX2_CLONE
  if (cpu_has_avx2()) return tv_slice_sums_avx2(sp, s, z, out);
#endif
  tv_slice_sums_generic(sp, s, z, out);
}
void run_tv_sums(const double* sp, const TVShape& s, int64_t z, double* out) { tv_slice_sums(sp, s, z, out); }
void run_tv_grad(const float* sp, const float* sig, const TVShape& s, int64_t z, const float* w, float* t, float* out) {
#ifdef NIMBUS_HAS_AVX2_CLONE
  if (cpu_has_avx2()) return tv_slice_grad_avx2(sp, sig, s, z, w, t, out);
#endif
  tv_slice_grad_generic(sp, sig, s, z, w, t, out);
}
void run_tv_grad(const double* sp, const double* sig, const TVShape& s, int64_t z, const double* w, double* t,
                 double* out) {
  tv_slice_grad(sp, sig, s, z, w, t, out);
}

// (the sum over the axes of mean |forward difference of softplus(features)| (0-d), softplus(features),
// softplus'(features)): the last two for grid_tv_backward.
std::tuple<at::Tensor, at::Tensor, at::Tensor> grid_tv(const at::Tensor& features) {
  const TVShape s = tv_shape(features);
  at::Tensor out = at::empty({}, features.options());
  at::Tensor sp = at::empty(features.sizes(), features.options());
  at::Tensor sig = at::empty_like(sp);
  AT_DISPATCH_FLOATING_TYPES(features.scalar_type(), "grid_tv", [&] {
    using T = scalar_t;
    T* a = sp.data_ptr<T>();
    softplus_grid(features.data_ptr<T>(), a, sig.data_ptr<T>(), s);
    std::vector<T> part(3 * s.Z);  // per slice: the x, y and z sums
    at::parallel_for(0, s.Z, 1, [&](int64_t b, int64_t e) {
      for (int64_t z = b; z < e; ++z) run_tv_sums(a, s, z, part.data() + 3 * z);
    });
    T sx = 0, sy = 0, sz = 0;
    for (int64_t z = 0; z < s.Z; ++z) sx += part[3 * z], sy += part[3 * z + 1], sz += part[3 * z + 2];
    const T nx = T(s.Z * s.Y * (s.X - 1)), ny = T(s.Z * (s.Y - 1) * s.X), nz = T((s.Z - 1) * s.Y * s.X);
    out.fill_(sx / nx + sy / ny + sz / nz);
  });
  return {out, sp, sig};
}

// d grid_tv / d features times grad (a 0-d tensor), from grid_tv's softplus and softplus'.
at::Tensor grid_tv_backward(const at::Tensor& sp, const at::Tensor& sig, const at::Tensor& grad) {
  const TVShape s = tv_shape(sp);
  TORCH_CHECK(grad.numel() == 1, "grad must hold one value");
  TORCH_CHECK(sig.sizes() == sp.sizes() && sig.is_contiguous() && sig.scalar_type() == sp.scalar_type(),
              "sig must be grid_tv's softplus' of the same grid");
  at::Tensor out = at::empty(sp.sizes(), sp.options());
  AT_DISPATCH_FLOATING_TYPES(sp.scalar_type(), "grid_tv_backward", [&] {
    using T = scalar_t;
    const T g = grad.to(sp.scalar_type()).item<T>();
    const T w[3] = {g / T(s.Z * s.Y * (s.X - 1)), g / T(s.Z * (s.Y - 1) * s.X), g / T((s.Z - 1) * s.Y * s.X)};
    T* o = out.data_ptr<T>();
    const T *a = sp.data_ptr<T>(), *d = sig.data_ptr<T>();
    at::parallel_for(0, s.Z, 1, [&](int64_t b, int64_t e) {
      std::vector<T> t(s.X);
      for (int64_t z = b; z < e; ++z) run_tv_grad(a, d, s, z, w, t.data(), o);
    });
  });
  return out;
}

}  // namespace
}  // namespace nimbus_march

namespace nimbus_march {
namespace {
// Turns the lane paths on or off (tests); returns the previous setting.
bool march_set_lane_paths(bool enabled) { return g_lane_paths.exchange(enabled); }
}  // namespace
}  // namespace nimbus_march

TORCH_LIBRARY(nimbus_march, m) {
  m.def("march_set_lane_paths", &nimbus_march::march_set_lane_paths);
  m.def("march_forward", &nimbus_march::march_forward);
  m.def("march_backward", &nimbus_march::march_backward);
  m.def("march_forward_keep", &nimbus_march::march_forward_keep);
  m.def("march_backward_kept", &nimbus_march::march_backward_kept);
  m.def("grid_tv", &nimbus_march::grid_tv);
  m.def("grid_tv_backward", &nimbus_march::grid_tv_backward);
}
