// CPU alpha compositing of sorted, tiled 2D Gaussians: forward and backward.
//
// The contract (pixel-corner origin, rules, outputs) is documented in
// nimbus/kernels/raster.py; this file implements exactly that, for float32
// and float64, and is built on first use by torch.utils.cpp_extension.load.
//
// Layout of the work.  Each image tile is processed by one thread (tiles are
// handed out dynamically from an atomic counter, so heavy tiles do not stall a
// static partition).  Inside a tile the loop runs over the tile's Gaussians in
// depth order and, for each, over the pixels of its footprint box in blocks of
// kLanes horizontally adjacent pixels, with GCC/Clang vector extensions.  Blocks
// (and rows) where the Gaussian's alpha is below 1/255 for sure are culled with a
// scalar bound first.  Every pixel keeps its own transmittance, stop flag and
// contributor count and the rules are applied lane-wise with masks, so the result
// is that of a plain per-pixel loop.  The backward walks the same lists back to
// front, recovering T by division, and sums each Gaussian's gradient over the
// tile's pixels into a per-intersection slot (no two threads ever write the same
// slot); the slots are then summed per Gaussian in list order, so every output is
// bitwise identical whatever the thread count.
//
// Portability: built with generic x86-64 flags; on x86-64 with GCC the float32
// tile functions are also compiled for AVX2 and AVX-512 (x86-64-v4), and the
// best clone this CPU runs is used unless set_cpu_isa() (NIMBUS_CPU_ISA, applied
// by nimbus/kernels/raster.py) forces another, so every path can be tested on one
// machine.  There is no FMA contraction and no -ffast-math, and the clones run
// the same IEEE operations in the same order, so they give identical results.
// float32 uses a vectorisable exp (Cephes polynomial, ~1 ulp, in common.h); float64 uses
// std::exp (and exists for gradcheck and tests).
//
// Only light ATen headers are included (not torch/extension.h): the first build
// takes seconds instead of tens of seconds.  Ops are registered with
// TORCH_LIBRARY and called as torch.ops.nimbus_composite.*.

#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <c10/util/Exception.h>
#include <torch/library.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <memory>
#include <string>
#include <tuple>
#include <vector>

#include "common.h"

namespace nimbus_composite {
namespace {

using namespace nimbus_simd;

// Rules of the contract.
constexpr double kMaxAlpha = 0.99;
constexpr double kMinAlpha = 1.0 / 255.0;
constexpr double kMinTransmittance = 1e-4;
constexpr double kMinOneMinusAlpha = 1e-6;
// exp(-sigma) is evaluated with sigma clamped to [0, kMaxSigma]: sigma < 0 is
// skipped anyway, and beyond kMaxSigma alpha < 1/255 for any opacity <= 1, so the
// clamp changes no decision while keeping exp finite and out of denormals.
constexpr double kMaxSigma = 80.0;
// The footprint box is computed for sigma <= log(255 * opacity) widened by these,
// and padded by a pixel, so rounding can never cut off a contributing pixel.
constexpr double kBoxRelMargin = 1e-3;
constexpr double kBoxAbsMargin = 1e-2;
// block_misses() culls with sigma > s * (1 + kCullErrorPerCondition * cond), cond =
// (a + c)^2 / det >= 4, and only conics with cond <= kMaxCullCondition.
constexpr double kCullErrorPerCondition = 1e-5;
constexpr double kMaxCullCondition = 1e5;
// Conics whose determinant is below this fraction of a*c are treated as
// degenerate: their footprint box is the whole image rather than an ellipse box
// computed with catastrophic cancellation.
constexpr double kMinRelativeDet = 1e-9;

// Per-intersection gradient slots: d means2d (2), d conics (3), d colors (3),
// d opacity, d depth, |d means2d| summed per pixel (2).
constexpr int kSlots = 12;

// The float32 tile clones.  Names as NIMBUS_CPU_ISA spells them (raster.py).
enum class Isa : int { kGeneric = 0, kAvx2 = 1, kAvx512 = 2 };
constexpr const char* kIsaNames[] = {"generic", "avx2", "avx512"};

// Whether this build has the clone and this CPU can run it.
bool isa_runs(Isa isa) {
  switch (isa) {
    case Isa::kGeneric:
      return true;
#ifdef NIMBUS_HAS_AVX2_CLONE
    case Isa::kAvx2:
      __builtin_cpu_init();
      return __builtin_cpu_supports("avx2");
#endif
#ifdef NIMBUS_HAS_AVX512_CLONE
    case Isa::kAvx512:
      __builtin_cpu_init();
      return __builtin_cpu_supports("x86-64-v4");
#endif
    default:
      return false;
  }
}

Isa best_isa() {
  for (Isa isa : {Isa::kAvx512, Isa::kAvx2}) {
    if (isa_runs(isa)) return isa;
  }
  return Isa::kGeneric;
}

// Read on every tile call (a relaxed load costs nothing next to a tile); -1 = not chosen yet.
std::atomic<int> g_isa{-1};

Isa active_isa() {
  int isa = g_isa.load(std::memory_order_relaxed);
  if (isa < 0) {
    isa = static_cast<int>(best_isa());
    g_isa.store(isa, std::memory_order_relaxed);
  }
  return static_cast<Isa>(isa);
}

// exp(x) for x in [-kMaxSigma, 0]: float32 by the Cephes polynomial (~1 ulp), float64 by std::exp.
NIMBUS_INLINE Vec<float> vexp(Vec<float> x) { return exp_cephes(x); }
NIMBUS_INLINE Vec<double> vexp(Vec<double> x) {
  Vec<double> y;
  for (int l = 0; l < kLanes; ++l) y[l] = std::exp(x[l]);
  return y;
}

// Footprint of one Gaussian: a box of inclusive pixel indices (empty when x0 > x1)
// and what Cull needs: the sigma above which alpha < 1/255 for sure (+inf: no
// culling), the row minimum of sigma (row_min * dy^2, at dx = vertex * dy) and
// 0.5 a, b, 0.5 c.  Floats keep the record small (it is read in random order); the
// cut's margin dwarfs their rounding.
struct Box {
  int32_t x0, x1, y0, y1;
  float cut, vertex, row_min, ha, b, hc;
};

template <typename S>
struct Inputs {
  const S* means;          // [M, 2]
  const S* conics;         // [M, 3]
  const S* colors;         // [M, 3]
  const S* opac;           // [M]
  const S* depths;         // [M]
  const int64_t* ids;      // [I]
  const int64_t* offsets;  // [T + 1]
  S bg[3];
  int64_t width, height, tile, tiles_x, tiles_y;
  int64_t blocks_x;  // vector blocks per tile row
  const Box* boxes;  // [M]
};

// Buffers kept per calling thread between calls, one per Tag: a fresh buffer of
// megabytes is usually a fresh mapping whose pages fault in again.  At 240 x 180 with 198k
// Gaussians (slots about 11 MB, boxes 8 MB) keeping them, with the backward's sums written
// straight into its outputs, made a backward about 16 % faster (docs/performance.md, round
// 10).  Grown when a call needs more, never shrunk; contents are unspecified.
template <typename T, int Tag>
T* kept_buffer(size_t n) {
  thread_local std::unique_ptr<T[]> buffer;
  thread_local size_t capacity = 0;
  if (n > capacity) {
    // The old buffer goes first (a lower peak); if new throws, the next call allocates again.
    buffer.reset();
    capacity = 0;
    buffer.reset(new T[n]);
    capacity = n;
  }
  return buffer.get();
}
enum KeptBufferTag : int { kBoxesTag, kSlotsTag };

// Footprint boxes of all Gaussians (computed in double).
template <typename S>
void footprints(const S* means, const S* conics, const S* opac, int64_t M, int64_t width,
                int64_t height, Box* boxes) {
  const float inf = std::numeric_limits<float>::infinity();
  const Box empty{1, 0, 1, 0, inf, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f};
  at::parallel_for(0, M, 2048, [&](int64_t begin, int64_t end) {
    for (int64_t g = begin; g < end; ++g) {
      const double mx = means[2 * g], my = means[2 * g + 1];
      const double a = conics[3 * g], b = conics[3 * g + 1], c = conics[3 * g + 2];
      const double o = opac[g];
      // alpha <= opacity, so a Gaussian below 1/255 (or carrying NaN/inf) contributes nothing.
      if (!(o >= kMinAlpha) || !std::isfinite(o) || !std::isfinite(mx) || !std::isfinite(my) ||
          !std::isfinite(a) || !std::isfinite(b) || !std::isfinite(c)) {
        boxes[g] = empty;
        continue;
      }
      const double det = a * c - b * b;
      Box box{0, static_cast<int32_t>(width - 1), 0, static_cast<int32_t>(height - 1),
              inf, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f};
      if (a > 0 && c > 0 && det > kMinRelativeDet * a * c) {
        // 0.5 d^T C d <= s  <=>  |dx| <= sqrt(2 s c / det), |dy| <= sqrt(2 s a / det).
        const double s = std::log(255.0 * o) * (1.0 + kBoxRelMargin) + kBoxAbsMargin;
        const double hx = std::sqrt(2.0 * s * c / det);
        const double hy = std::sqrt(2.0 * s * a / det);
        // Pixel u has its centre at u + 0.5.
        const double x0 = std::floor(mx - hx - 0.5) - 1.0;
        const double x1 = std::ceil(mx + hx - 0.5) + 1.0;
        const double y0 = std::floor(my - hy - 0.5) - 1.0;
        const double y1 = std::ceil(my + hy - 0.5) + 1.0;
        if (x0 > static_cast<double>(width - 1) || y0 > static_cast<double>(height - 1) || x1 < 0.0 ||
            y1 < 0.0) {
          box = empty;
        } else {
          box.x0 = static_cast<int32_t>(std::max(x0, 0.0));
          box.y0 = static_cast<int32_t>(std::max(y0, 0.0));
          box.x1 = static_cast<int32_t>(std::min(x1, static_cast<double>(width - 1)));
          box.y1 = static_cast<int32_t>(std::min(y1, static_cast<double>(height - 1)));
          // Float sigma carries an error up to a few ulp of its terms' magnitude, which is
          // at most (a + c)^2 / det times sigma: the cut is raised by far more than that,
          // and conics too ill-conditioned for it are not culled.
          const double cond = (a + c) * (a + c) / det;
          if (cond <= kMaxCullCondition) {
            box.cut = static_cast<float>(s * (1.0 + kCullErrorPerCondition * cond));
            box.vertex = static_cast<float>(-b / a);
            box.row_min = static_cast<float>(0.5 * det / a);
            box.ha = static_cast<float>(0.5 * a);
            box.b = static_cast<float>(b);
            box.hc = static_cast<float>(0.5 * c);
          }
        }
      }
      boxes[g] = box;
    }
  });
}

// Tile lists visit Gaussians in depth order, i.e. at random places in memory: their
// data is prefetched this many list entries ahead.
constexpr int64_t kPrefetch = 6;

template <typename S>
NIMBUS_INLINE void prefetch_gaussian(const Inputs<S>& in, int64_t g) {
  __builtin_prefetch(in.boxes + g);
  __builtin_prefetch(in.means + 2 * g);
  __builtin_prefetch(in.conics + 3 * g);
  __builtin_prefetch(in.colors + 3 * g);
  __builtin_prefetch(in.opac + g);
  __builtin_prefetch(in.depths + g);
}

// Below this many intersections the tiles run on the calling thread: waking the pool
// costs more than the work.
constexpr int64_t kMinParallelIsects = 4096;

// Runs fn(tile, scratch) for every tile, tiles handed out dynamically to the threads.
template <typename Scratch, typename Fn>
void for_each_tile(int64_t num_tiles, int64_t num_isects, int64_t blocks, const Fn& fn) {
  std::atomic<int64_t> next{0};
  const int64_t workers = num_isects < kMinParallelIsects
                              ? 1
                              : std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), num_tiles));
  auto work = [&](int64_t, int64_t) {
    Scratch scratch(blocks);
    for (int64_t t = next.fetch_add(1); t < num_tiles; t = next.fetch_add(1)) fn(t, scratch);
  };
  // parallel_for over a range of 1 would still wake the whole pool.
  if (workers == 1) {
    work(0, 1);
  } else {
    at::parallel_for(0, workers, 1, work);
  }
}

struct TileRect {
  int64_t x0, y0, w, h;
};

inline TileRect tile_rect(int64_t t, int64_t tiles_x, int64_t tile, int64_t width, int64_t height) {
  const int64_t x0 = (t % tiles_x) * tile, y0 = (t / tiles_x) * tile;
  return {x0, y0, std::min(tile, width - x0), std::min(tile, height - y0)};
}

// The part of a Gaussian's box inside a tile, as rows [y0, y1] (image rows) and
// vector blocks [b0, b1] of the tile row; empty when y0 > y1 or b0 > b1.
struct Span {
  int64_t y0, y1, b0, b1;
};

inline Span span_in_tile(const Box& box, const TileRect& R) {
  const int64_t x0 = std::max<int64_t>(box.x0, R.x0), x1 = std::min<int64_t>(box.x1, R.x0 + R.w - 1);
  const int64_t y0 = std::max<int64_t>(box.y0, R.y0), y1 = std::min<int64_t>(box.y1, R.y0 + R.h - 1);
  if (x0 > x1) return {1, 0, 1, 0};
  return {y0, y1, (x0 - R.x0) / kLanes, (x1 - R.x0) / kLanes};
}

// Per-Gaussian constants of block_misses(), in the kernel's precision.
template <typename S>
struct Cull {
  S cut, vertex, row_min, ha, b, hc;
  explicit Cull(const Box& box)
      : cut(box.cut), vertex(box.vertex), row_min(box.row_min), ha(box.ha), b(box.b), hc(box.hc) {}
  // Whether sigma > cut on the whole row (dy = row centre - mean y).
  NIMBUS_INLINE bool row_misses(S dy) const { return row_min * dy * dy > cut; }
  // Whether sigma > cut on all of the segment dx in [dx0, dx0 + kLanes - 1] of a row:
  // sigma is a parabola in dx with its vertex at vertex * dy, so its minimum on the
  // segment is at the vertex clamped to the segment.  The cut is far enough above
  // log(255 opacity) that float rounding cannot make this skip a contributing pixel.
  NIMBUS_INLINE bool block_misses(S dx0, S dy) const {
    const S dx = std::min(std::max(vertex * dy, dx0), dx0 + S(kLanes - 1));
    return (ha * dx + b * dy) * dx + hc * dy * dy > cut;
  }
};

// Pixel-centre x minus mean x for the lanes of block b: (float(u) + 0.5) - mean_x.
template <typename S>
NIMBUS_INLINE Vec<S> lane_dx(const TileRect& R, int64_t b, S mx) {
  return (splat(static_cast<S>(R.x0 + b * kLanes)) + iota<S>() + S(0.5)) - mx;
}

// sigma = 0.5 (a dx^2 + c dy^2) + b dx dy on one pixel row, factored as
// (0.5 a dx + b dy) dx + 0.5 c dy^2 with the row's constants hoisted.  The forward and
// the backward both use this, so they agree bit for bit on every skip decision.
template <typename S>
struct RowSigma {
  S ha, bdy, hcdy2;
  NIMBUS_INLINE RowSigma(S a, S b, S c, S dy) : ha(S(0.5) * a), bdy(b * dy), hcdy2(S(0.5) * c * dy * dy) {}
  NIMBUS_INLINE Vec<S> operator()(Vec<S> dx) const { return (ha * dx + bdy) * dx + hcdy2; }
};

// Lanes that map to no pixel (past the tile's or the image's right edge).
template <typename S>
NIMBUS_INLINE Mask<S> outside_lanes(const TileRect& R, int64_t b) {
  return iota<S>() + static_cast<S>(b * kLanes) >= static_cast<S>(R.w);
}

template <typename S>
struct ForwardScratch {
  // Per pixel (kLanes per block): transmittance, colour and depth sums, contributor
  // count, stopped flag (-1); per block, the number of live pixels (to skip dead blocks).
  using Int = typename VecTypes<S>::Int;
  std::vector<S> T, r, g, b, d;
  std::vector<Int> last, done;
  std::vector<int32_t> live;
  explicit ForwardScratch(int64_t blocks)
      : T(blocks * kLanes), r(blocks * kLanes), g(blocks * kLanes), b(blocks * kLanes),
        d(blocks * kLanes), last(blocks * kLanes), done(blocks * kLanes), live(blocks) {}
};

template <typename S>
struct ForwardOut {
  S *rgb, *depth, *alpha, *t_final;
  int32_t* last;
};

// Stopped pixels are counted every kRecount list entries rather than per block: the
// count only serves to skip dead blocks and to end a saturated tile early.
constexpr int64_t kRecount = 8;

template <typename S>
NIMBUS_INLINE void forward_tile_impl(const Inputs<S>& in, int64_t t, ForwardScratch<S>& s,
                                     const ForwardOut<S>& out) {
  using V = Vec<S>;
  using I = Mask<S>;
  const TileRect R = tile_rect(t, in.tiles_x, in.tile, in.width, in.height);
  const int64_t nb = in.blocks_x, blocks = R.h * nb;
  S* __restrict T = s.T.data();
  S* __restrict cr_sum = s.r.data();
  S* __restrict cg_sum = s.g.data();
  S* __restrict cb_sum = s.b.data();
  S* __restrict d_sum = s.d.data();
  auto* __restrict last = s.last.data();
  auto* __restrict done = s.done.data();
  int32_t* __restrict live = s.live.data();

  for (int64_t y = 0; y < R.h; ++y) {
    for (int64_t b = 0; b < nb; ++b) {
      const int64_t o = (y * nb + b) * kLanes;
      store(T + o, splat(S(1)));
      store(cr_sum + o, V{});
      store(cg_sum + o, V{});
      store(cb_sum + o, V{});
      store(d_sum + o, V{});
      store(last + o, I{});
      store(done + o, outside_lanes<S>(R, b));
    }
  }
  auto recount = [&]() {
    int64_t n = 0;
    for (int64_t q = 0; q < blocks; ++q) {
      int32_t c = 0;
      for (int l = 0; l < kLanes; ++l) c += done[q * kLanes + l] == 0;
      live[q] = c;
      n += c;
    }
    return n;
  };
  int64_t remaining = recount();

  const S max_alpha = static_cast<S>(kMaxAlpha);
  const S min_alpha = static_cast<S>(kMinAlpha);
  const S min_T = static_cast<S>(kMinTransmittance);
  const S max_sigma = static_cast<S>(kMaxSigma);
  I stopped = I{};  // lanes stopped since the last recount (any block)

  const int64_t begin = in.offsets[t], end = in.offsets[t + 1];
  for (int64_t k = begin; k < end; ++k) {
    if (k + kPrefetch < end) prefetch_gaussian(in, in.ids[k + kPrefetch]);
    if ((k - begin) % kRecount == kRecount - 1) {
      bool any = false;
      for (int l = 0; l < kLanes; ++l) any |= stopped[l] != 0;
      if (any) {
        remaining = recount();
        stopped = I{};
        if (remaining == 0) break;
      }
    }
    const int64_t gi = in.ids[k];
    const Span sp = span_in_tile(in.boxes[gi], R);
    if (sp.y0 > sp.y1 || sp.b0 > sp.b1) continue;
    const S mx = in.means[2 * gi], my = in.means[2 * gi + 1];
    const S ca = in.conics[3 * gi], cb = in.conics[3 * gi + 1], cc = in.conics[3 * gi + 2];
    const S op = in.opac[gi];
    const S cr = in.colors[3 * gi], cg = in.colors[3 * gi + 1], cbl = in.colors[3 * gi + 2];
    const S z = in.depths[gi];
    const I count = splat_int<S>(k - begin + 1);
    const Cull<S> cull(in.boxes[gi]);
    for (int64_t y = sp.y0; y <= sp.y1; ++y) {
      const S dy = (static_cast<S>(y) + S(0.5)) - my;
      if (cull.row_misses(dy)) continue;
      const RowSigma<S> row_sigma(ca, cb, cc, dy);
      for (int64_t b = sp.b0; b <= sp.b1; ++b) {
        const int64_t q = (y - R.y0) * nb + b, o = q * kLanes;
        if (live[q] == 0) continue;
        if (cull.block_misses(static_cast<S>(R.x0 + b * kLanes) + S(0.5) - mx, dy)) continue;
        const V dx = lane_dx(R, b, mx);
        const V sigma = row_sigma(dx);
        const V e = vexp(-vmin(vmax(sigma, V{}), splat(max_sigma)));
        const V a = vmin(op * e, splat(max_alpha));
        const V Ti = load<V>(T + o);
        const V Tn = Ti * (S(1) - a);
        const I dn = load<I>(done + o);
        const I ok = (dn == 0) & (sigma >= S(0)) & (a >= min_alpha);
        const I stop = ok & (Tn < min_T);
        const I take = ok & ~stop;
        const V w = a * Ti;
        const V r0 = load<V>(cr_sum + o), g0 = load<V>(cg_sum + o), b0 = load<V>(cb_sum + o);
        const V d0 = load<V>(d_sum + o);
        store(cr_sum + o, take ? r0 + cr * w : r0);
        store(cg_sum + o, take ? g0 + cg * w : g0);
        store(cb_sum + o, take ? b0 + cbl * w : b0);
        store(d_sum + o, take ? d0 + z * w : d0);
        store(T + o, take ? Tn : Ti);
        store(last + o, take ? count : load<I>(last + o));
        store(done + o, dn | stop);
        stopped |= stop;
      }
    }
  }

  for (int64_t y = 0; y < R.h; ++y) {
    for (int64_t x = 0; x < R.w; ++x) {
      const int64_t i = (y * nb + x / kLanes) * kLanes + x % kLanes;
      const int64_t p = (R.y0 + y) * in.width + (R.x0 + x);
      const S Tf = T[i];
      out.rgb[3 * p] = cr_sum[i] + Tf * in.bg[0];
      out.rgb[3 * p + 1] = cg_sum[i] + Tf * in.bg[1];
      out.rgb[3 * p + 2] = cb_sum[i] + Tf * in.bg[2];
      out.depth[p] = d_sum[i];
      out.alpha[p] = S(1) - Tf;
      out.t_final[p] = Tf;
      out.last[p] = static_cast<int32_t>(last[i]);
    }
  }
}

void forward_tile_generic(const Inputs<float>& in, int64_t t, ForwardScratch<float>& s,
                          const ForwardOut<float>& out) {
  forward_tile_impl(in, t, s, out);
}
#ifdef NIMBUS_HAS_AVX2_CLONE
NIMBUS_TARGET_AVX2 void forward_tile_avx2(const Inputs<float>& in, int64_t t, ForwardScratch<float>& s,
                                          const ForwardOut<float>& out) {
  forward_tile_impl(in, t, s, out);
}
#endif
#ifdef NIMBUS_HAS_AVX512_CLONE
NIMBUS_TARGET_AVX512 void forward_tile_avx512(const Inputs<float>& in, int64_t t, ForwardScratch<float>& s,
                                              const ForwardOut<float>& out) {
  forward_tile_impl(in, t, s, out);
}
#endif
void forward_tile(const Inputs<float>& in, int64_t t, ForwardScratch<float>& s,
                  const ForwardOut<float>& out) {
  switch (active_isa()) {
#ifdef NIMBUS_HAS_AVX512_CLONE
    case Isa::kAvx512:
      return forward_tile_avx512(in, t, s, out);
#endif
#ifdef NIMBUS_HAS_AVX2_CLONE
    case Isa::kAvx2:
      return forward_tile_avx2(in, t, s, out);
#endif
    default:
      return forward_tile_generic(in, t, s, out);
  }
}
void forward_tile(const Inputs<double>& in, int64_t t, ForwardScratch<double>& s,
                  const ForwardOut<double>& out) {
  forward_tile_impl(in, t, s, out);
}

template <typename S>
struct BackwardScratch {
  // Per pixel: transmittance in front of the current Gaussian, the loss-weighted
  // colour+depth of everything behind it (R), the constant final-T term (K), the
  // output gradients and the contributor count; per block the largest count.
  using Int = typename VecTypes<S>::Int;
  std::vector<S> T, R, K, gr, gg, gb, gd;
  std::vector<Int> last;
  std::vector<int32_t> max_last;
  explicit BackwardScratch(int64_t blocks)
      : T(blocks * kLanes), R(blocks * kLanes), K(blocks * kLanes), gr(blocks * kLanes),
        gg(blocks * kLanes), gb(blocks * kLanes), gd(blocks * kLanes), last(blocks * kLanes),
        max_last(blocks) {}
};

template <typename S>
struct BackwardIn {
  const S *t_final, *g_rgb, *g_depth, *g_alpha;
  const int32_t* last;
};

template <typename S>
NIMBUS_INLINE void backward_tile_impl(const Inputs<S>& in, int64_t t, BackwardScratch<S>& s,
                                      const BackwardIn<S>& bin, S* slots, int32_t* tile_count) {
  using V = Vec<S>;
  using I = Mask<S>;
  const TileRect Rc = tile_rect(t, in.tiles_x, in.tile, in.width, in.height);
  const int64_t nb = in.blocks_x, n = Rc.h * nb * kLanes;
  S* __restrict T = s.T.data();
  S* __restrict Rs = s.R.data();
  S* __restrict K = s.K.data();
  S* __restrict gr_p = s.gr.data();
  S* __restrict gg_p = s.gg.data();
  S* __restrict gb_p = s.gb.data();
  S* __restrict gd_p = s.gd.data();
  auto* __restrict last = s.last.data();
  int32_t* __restrict max_last = s.max_last.data();

  // Lanes without a pixel keep last = 0 and so never take part.
  std::fill_n(T, n, S(0));
  std::fill_n(Rs, n, S(0));
  std::fill_n(K, n, S(0));
  std::fill_n(gr_p, n, S(0));
  std::fill_n(gg_p, n, S(0));
  std::fill_n(gb_p, n, S(0));
  std::fill_n(gd_p, n, S(0));
  std::fill_n(last, n, 0);
  int32_t kmax = 0;
  for (int64_t y = 0; y < Rc.h; ++y) {
    for (int64_t x = 0; x < Rc.w; ++x) {
      const int64_t i = (y * nb + x / kLanes) * kLanes + x % kLanes;
      const int64_t p = (Rc.y0 + y) * in.width + (Rc.x0 + x);
      const S Tf = bin.t_final[p];
      const S gr = bin.g_rgb[3 * p], gg = bin.g_rgb[3 * p + 1], gb = bin.g_rgb[3 * p + 2];
      T[i] = Tf;
      gr_p[i] = gr;
      gg_p[i] = gg;
      gb_p[i] = gb;
      gd_p[i] = bin.g_depth[p];
      // d rgb / d alpha_k carries -T_final * bg / (1 - alpha_k) and d alpha_out / d alpha_k
      // is +T_final / (1 - alpha_k): K collects both numerators.
      K[i] = Tf * (bin.g_alpha[p] - (gr * in.bg[0] + gg * in.bg[1] + gb * in.bg[2]));
      last[i] = bin.last[p];
      kmax = std::max(kmax, bin.last[p]);
    }
  }
  for (int64_t q = 0; q < Rc.h * nb; ++q) {
    int32_t m = 0;
    for (int l = 0; l < kLanes; ++l) m = std::max(m, static_cast<int32_t>(last[q * kLanes + l]));
    max_last[q] = m;
  }
  // A count beyond the tile's list cannot come from the forward; clamping it keeps a
  // corrupted `last` from reading past the list.
  kmax = static_cast<int32_t>(std::min<int64_t>(kmax, in.offsets[t + 1] - in.offsets[t]));
  tile_count[t] = kmax;
  const S max_alpha = static_cast<S>(kMaxAlpha);
  const S min_alpha = static_cast<S>(kMinAlpha);
  const S min_om = static_cast<S>(kMinOneMinusAlpha);
  const S max_sigma = static_cast<S>(kMaxSigma);

  const int64_t begin = in.offsets[t];
  for (int32_t local = kmax - 1; local >= 0; --local) {
    const int64_t k = begin + local;
    if (local >= kPrefetch) prefetch_gaussian(in, in.ids[k - kPrefetch]);
    const int64_t gi = in.ids[k];
    const Span sp = span_in_tile(in.boxes[gi], Rc);
    V acc[kSlots] = {};
    if (sp.y0 <= sp.y1 && sp.b0 <= sp.b1) {
      const S mx = in.means[2 * gi], my = in.means[2 * gi + 1];
      const S ca = in.conics[3 * gi], cb = in.conics[3 * gi + 1], cc = in.conics[3 * gi + 2];
      const S op = in.opac[gi];
      const S cr = in.colors[3 * gi], cg = in.colors[3 * gi + 1], cbl = in.colors[3 * gi + 2];
      const S z = in.depths[gi];
      const I local_v = splat_int<S>(local);
      const Cull<S> cull(in.boxes[gi]);
      for (int64_t y = sp.y0; y <= sp.y1; ++y) {
        const S dy = (static_cast<S>(y) + S(0.5)) - my;
        if (cull.row_misses(dy)) continue;
        const RowSigma<S> row_sigma(ca, cb, cc, dy);
        const S hdy2 = S(0.5) * dy * dy, cbdy = cb * dy, ccdy = cc * dy;
        for (int64_t b = sp.b0; b <= sp.b1; ++b) {
          const int64_t q = (y - Rc.y0) * nb + b, o = q * kLanes;
          if (max_last[q] <= local) continue;
          if (cull.block_misses(static_cast<S>(Rc.x0 + b * kLanes) + S(0.5) - mx, dy)) continue;
          // Same arithmetic as the forward, so the same Gaussians are skipped.
          const V dx = lane_dx(Rc, b, mx);
          const V sigma = row_sigma(dx);
          const V e = vexp(-vmin(vmax(sigma, V{}), splat(max_sigma)));
          const V raw = op * e;
          const V a = vmin(raw, splat(max_alpha));
          const I ok = (local_v < load<I>(last + o)) & (sigma >= S(0)) & (a >= min_alpha);
          const V inv_om = S(1) / vmax(S(1) - a, splat(min_om));
          const V T0 = load<V>(T + o), R0 = load<V>(Rs + o);
          const V Tk = T0 * inv_om;
          const V w = ok ? a * Tk : V{};
          const V gr = load<V>(gr_p + o), gg = load<V>(gg_p + o), gb = load<V>(gb_p + o);
          const V gd = load<V>(gd_p + o);
          acc[5] += gr * w;
          acc[6] += gg * w;
          acc[7] += gb * w;
          acc[9] += gd * w;
          const V v = gr * cr + gg * cg + gb * cbl + gd * z;
          const V d_alpha = v * Tk - (R0 - load<V>(K + o)) * inv_om;
          store(Rs + o, ok ? R0 + v * w : R0);
          store(T + o, ok ? Tk : T0);
          // Where alpha is clamped at 0.99 it does not depend on opacity or sigma.
          const V da = (ok & (raw <= max_alpha)) ? d_alpha : V{};
          acc[8] += da * e;
          const V d_sigma = -da * a;
          const V ds_dx = d_sigma * dx;
          acc[2] += S(0.5) * ds_dx * dx;
          acc[3] += ds_dx * dy;
          acc[4] += d_sigma * hdy2;
          // dx = px - mx, so d sigma / d mx = -(a dx + b dy).
          const V gmx = -(ca * ds_dx + cbdy * d_sigma);
          const V gmy = -(cb * ds_dx + ccdy * d_sigma);
          acc[0] += gmx;
          acc[1] += gmy;
          acc[10] += gmx < S(0) ? -gmx : gmx;
          acc[11] += gmy < S(0) ? -gmy : gmy;
        }
      }
    }
    S* slot = slots + k * kSlots;
    for (int j = 0; j < kSlots; ++j) slot[j] = hsum(acc[j]);
  }
}

void backward_tile_generic(const Inputs<float>& in, int64_t t, BackwardScratch<float>& s,
                           const BackwardIn<float>& bin, float* slots, int32_t* tile_count) {
  backward_tile_impl(in, t, s, bin, slots, tile_count);
}
#ifdef NIMBUS_HAS_AVX2_CLONE
NIMBUS_TARGET_AVX2 void backward_tile_avx2(const Inputs<float>& in, int64_t t, BackwardScratch<float>& s,
                                           const BackwardIn<float>& bin, float* slots,
                                           int32_t* tile_count) {
  backward_tile_impl(in, t, s, bin, slots, tile_count);
}
#endif
#ifdef NIMBUS_HAS_AVX512_CLONE
NIMBUS_TARGET_AVX512 void backward_tile_avx512(const Inputs<float>& in, int64_t t, BackwardScratch<float>& s,
                                               const BackwardIn<float>& bin, float* slots,
                                               int32_t* tile_count) {
  backward_tile_impl(in, t, s, bin, slots, tile_count);
}
#endif
void backward_tile(const Inputs<float>& in, int64_t t, BackwardScratch<float>& s,
                   const BackwardIn<float>& bin, float* slots, int32_t* tile_count) {
  switch (active_isa()) {
#ifdef NIMBUS_HAS_AVX512_CLONE
    case Isa::kAvx512:
      return backward_tile_avx512(in, t, s, bin, slots, tile_count);
#endif
#ifdef NIMBUS_HAS_AVX2_CLONE
    case Isa::kAvx2:
      return backward_tile_avx2(in, t, s, bin, slots, tile_count);
#endif
    default:
      return backward_tile_generic(in, t, s, bin, slots, tile_count);
  }
}
void backward_tile(const Inputs<double>& in, int64_t t, BackwardScratch<double>& s,
                   const BackwardIn<double>& bin, double* slots, int32_t* tile_count) {
  backward_tile_impl(in, t, s, bin, slots, tile_count);
}

// Ids per task of the index check: below this the pool is not woken.
constexpr int64_t kMinCheckGrain = 1 << 16;

void check_inputs(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& colors,
                  const at::Tensor& opacities, const at::Tensor& depths, const at::Tensor& isect_ids,
                  const at::Tensor& tile_offsets, int64_t width, int64_t height, int64_t tile_size,
                  const at::Tensor& background) {
  const int64_t M = means2d.size(0);
  TORCH_CHECK(width > 0 && height > 0 && tile_size > 0, "width, height and tile_size must be positive");
  TORCH_CHECK(width < (int64_t(1) << 24) && height < (int64_t(1) << 24), "image too large");
  const auto dtype = means2d.scalar_type();
  for (const at::Tensor* x : {&means2d, &conics, &colors, &opacities, &depths, &background}) {
    TORCH_CHECK(x->device().is_cpu(), "composite kernel: tensors must be on the CPU");
    TORCH_CHECK(x->scalar_type() == dtype, "composite kernel: all float inputs must share one dtype");
    TORCH_CHECK(x->is_contiguous(), "composite kernel: inputs must be contiguous");
  }
  TORCH_CHECK(means2d.dim() == 2 && means2d.size(1) == 2, "means2d must be [M, 2]");
  TORCH_CHECK(conics.dim() == 2 && conics.size(0) == M && conics.size(1) == 3, "conics must be [M, 3]");
  TORCH_CHECK(colors.dim() == 2 && colors.size(0) == M && colors.size(1) == 3, "colors must be [M, 3]");
  TORCH_CHECK(opacities.dim() == 1 && opacities.size(0) == M, "opacities must be [M]");
  TORCH_CHECK(depths.dim() == 1 && depths.size(0) == M, "depths must be [M]");
  TORCH_CHECK(background.dim() == 1 && background.size(0) == 3, "background must be [3]");
  TORCH_CHECK(isect_ids.scalar_type() == at::kLong && isect_ids.dim() == 1 && isect_ids.is_contiguous() &&
                  isect_ids.device().is_cpu(),
              "isect_ids must be a contiguous CPU int64 [I] tensor");
  TORCH_CHECK(tile_offsets.scalar_type() == at::kLong && tile_offsets.dim() == 1 &&
                  tile_offsets.is_contiguous() && tile_offsets.device().is_cpu(),
              "tile_offsets must be a contiguous CPU int64 [T + 1] tensor");
  const int64_t tiles = ((width + tile_size - 1) / tile_size) * ((height + tile_size - 1) / tile_size);
  TORCH_CHECK(tile_offsets.size(0) == tiles + 1, "tile_offsets must have tiles_x * tiles_y + 1 = ",
              tiles + 1, " entries, got ", tile_offsets.size(0));
  // Out-of-range indices would read or write out of bounds: check them all (O(I + T)).
  const int64_t I = isect_ids.size(0);
  const int64_t* off = tile_offsets.data_ptr<int64_t>();
  TORCH_CHECK(off[0] >= 0 && off[tiles] <= I, "tile_offsets must lie in [0, I]");
  for (int64_t t = 0; t < tiles; ++t) {
    TORCH_CHECK(off[t] <= off[t + 1], "tile_offsets must be non-decreasing");
  }
  // The forward and the backward each check every id: in parallel, and only a failed check
  // looks for the first bad one (the error names it) serially.
  const int64_t* ids = isect_ids.data_ptr<int64_t>();
  std::atomic<bool> bad{false};
  at::parallel_for(0, I, kMinCheckGrain, [&](int64_t b, int64_t e) {
    bool any = false;
    for (int64_t k = b; k < e; ++k) any |= ids[k] < 0 || ids[k] >= M;
    if (any) bad.store(true, std::memory_order_relaxed);
  });
  if (!bad.load()) return;
  for (int64_t k = 0; k < I; ++k) {
    TORCH_CHECK(ids[k] >= 0 && ids[k] < M, "isect_ids[", k, "] = ", ids[k], " is not in [0, ", M, ")");
  }
}

template <typename scalar_t>
Inputs<scalar_t> make_inputs(const at::Tensor& means2d, const at::Tensor& conics,
                             const at::Tensor& colors, const at::Tensor& opacities,
                             const at::Tensor& depths, const at::Tensor& isect_ids,
                             const at::Tensor& tile_offsets, int64_t width, int64_t height,
                             int64_t tile_size, const at::Tensor& background) {
  Inputs<scalar_t> in{};
  in.means = means2d.data_ptr<scalar_t>();
  in.conics = conics.data_ptr<scalar_t>();
  in.colors = colors.data_ptr<scalar_t>();
  in.opac = opacities.data_ptr<scalar_t>();
  in.depths = depths.data_ptr<scalar_t>();
  in.ids = isect_ids.data_ptr<int64_t>();
  in.offsets = tile_offsets.data_ptr<int64_t>();
  const scalar_t* bg = background.data_ptr<scalar_t>();
  in.bg[0] = bg[0];
  in.bg[1] = bg[1];
  in.bg[2] = bg[2];
  in.width = width;
  in.height = height;
  in.tile = tile_size;
  in.tiles_x = (width + tile_size - 1) / tile_size;
  in.tiles_y = (height + tile_size - 1) / tile_size;
  in.blocks_x = (tile_size + kLanes - 1) / kLanes;
  const int64_t M = means2d.size(0);
  // Every box is written below, so the buffer is not cleared first.
  Box* boxes = kept_buffer<Box, kBoxesTag>(static_cast<size_t>(M));
  footprints(in.means, in.conics, in.opac, M, width, height, boxes);
  in.boxes = boxes;
  return in;
}

// Returns rgb [H, W, 3], depth [H, W], alpha [H, W], final transmittance [H, W]
// and the contributor count per pixel [H, W] int32 (the last two feed the backward).
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> composite_forward(
    const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& colors,
    const at::Tensor& opacities, const at::Tensor& depths, const at::Tensor& isect_ids,
    const at::Tensor& tile_offsets, int64_t width, int64_t height, int64_t tile_size,
    const at::Tensor& background) {
  check_inputs(means2d, conics, colors, opacities, depths, isect_ids, tile_offsets, width, height,
               tile_size, background);
  const auto opts = means2d.options();
  at::Tensor rgb = at::empty({height, width, 3}, opts);
  at::Tensor depth = at::empty({height, width}, opts);
  at::Tensor alpha = at::empty({height, width}, opts);
  at::Tensor t_final = at::empty({height, width}, opts);
  at::Tensor last = at::empty({height, width}, opts.dtype(at::kInt));
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "composite_forward", [&] {
    const Inputs<scalar_t> in = make_inputs<scalar_t>(means2d, conics, colors, opacities, depths,
                                                      isect_ids, tile_offsets, width, height,
                                                      tile_size, background);
    const ForwardOut<scalar_t> out{rgb.data_ptr<scalar_t>(), depth.data_ptr<scalar_t>(),
                                   alpha.data_ptr<scalar_t>(), t_final.data_ptr<scalar_t>(),
                                   last.data_ptr<int32_t>()};
    for_each_tile<ForwardScratch<scalar_t>>(
        in.tiles_x * in.tiles_y, isect_ids.size(0), tile_size * in.blocks_x,
        [&](int64_t t, ForwardScratch<scalar_t>& s) { forward_tile(in, t, s, out); });
  });
  return {rgb, depth, alpha, t_final, last};
}

// Returns the gradients w.r.t. means2d [M, 2], conics [M, 3], colors [M, 3],
// opacities [M], depths [M], and the per-Gaussian sum over pixels of
// |d loss / d means2d| [M, 2] (for densification).  The background gradient is
// sum(grad_rgb * t_final) and is left to the caller.
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> composite_backward(
    const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& colors,
    const at::Tensor& opacities, const at::Tensor& depths, const at::Tensor& isect_ids,
    const at::Tensor& tile_offsets, int64_t width, int64_t height, int64_t tile_size,
    const at::Tensor& background, const at::Tensor& t_final, const at::Tensor& last,
    const at::Tensor& grad_rgb, const at::Tensor& grad_depth, const at::Tensor& grad_alpha) {
  check_inputs(means2d, conics, colors, opacities, depths, isect_ids, tile_offsets, width, height,
               tile_size, background);
  const auto dtype = means2d.scalar_type();
  TORCH_CHECK(t_final.scalar_type() == dtype && t_final.is_contiguous() &&
                  t_final.sizes() == at::IntArrayRef({height, width}),
              "t_final must be a contiguous [H, W] tensor of the inputs' dtype");
  TORCH_CHECK(last.scalar_type() == at::kInt && last.is_contiguous() &&
                  last.sizes() == at::IntArrayRef({height, width}),
              "last must be a contiguous [H, W] int32 tensor");
  TORCH_CHECK(grad_rgb.scalar_type() == dtype && grad_rgb.is_contiguous() &&
                  grad_rgb.sizes() == at::IntArrayRef({height, width, 3}),
              "grad_rgb must be a contiguous [H, W, 3] tensor of the inputs' dtype");
  TORCH_CHECK(grad_depth.scalar_type() == dtype && grad_depth.is_contiguous() &&
                  grad_depth.sizes() == at::IntArrayRef({height, width}),
              "grad_depth must be a contiguous [H, W] tensor of the inputs' dtype");
  TORCH_CHECK(grad_alpha.scalar_type() == dtype && grad_alpha.is_contiguous() &&
                  grad_alpha.sizes() == at::IntArrayRef({height, width}),
              "grad_alpha must be a contiguous [H, W] tensor of the inputs' dtype");
  const int64_t M = means2d.size(0);
  const auto opts = means2d.options();
  at::Tensor g_means = at::empty({M, 2}, opts);
  at::Tensor g_conics = at::empty({M, 3}, opts);
  at::Tensor g_colors = at::empty({M, 3}, opts);
  at::Tensor g_opac = at::empty({M}, opts);
  at::Tensor g_depths = at::empty({M}, opts);
  at::Tensor g_abs = at::empty({M, 2}, opts);
  AT_DISPATCH_FLOATING_TYPES(dtype, "composite_backward", [&] {
    const Inputs<scalar_t> in = make_inputs<scalar_t>(means2d, conics, colors, opacities, depths,
                                                      isect_ids, tile_offsets, width, height,
                                                      tile_size, background);
    const int64_t tiles = in.tiles_x * in.tiles_y;
    // Every slot read back below is written by its tile (up to the tile's largest
    // contributor count), so the buffer is left uninitialised.
    scalar_t* slots = kept_buffer<scalar_t, kSlotsTag>(static_cast<size_t>(isect_ids.size(0)) * kSlots);
    std::vector<int32_t> tile_count(tiles, 0);
    const BackwardIn<scalar_t> bin{t_final.data_ptr<scalar_t>(), grad_rgb.data_ptr<scalar_t>(),
                                   grad_depth.data_ptr<scalar_t>(), grad_alpha.data_ptr<scalar_t>(),
                                   last.data_ptr<int32_t>()};
    for_each_tile<BackwardScratch<scalar_t>>(
        tiles, isect_ids.size(0), tile_size * in.blocks_x, [&](int64_t t, BackwardScratch<scalar_t>& s) {
          backward_tile(in, t, s, bin, slots, tile_count.data());
        });

    // Sum the slots per Gaussian, tiles in order (deterministic), straight into the
    // outputs; each task owns a range of Gaussians (and zeroes its rows: no serial memset
    // of M rows) and skims the whole list, so no two tasks write one row.
    const int64_t* ids = in.ids;
    const int64_t* off = in.offsets;
    const scalar_t* sl = slots;
    scalar_t* gm = g_means.data_ptr<scalar_t>();
    scalar_t* gc = g_conics.data_ptr<scalar_t>();
    scalar_t* gcol = g_colors.data_ptr<scalar_t>();
    scalar_t* go = g_opac.data_ptr<scalar_t>();
    scalar_t* gz = g_depths.data_ptr<scalar_t>();
    scalar_t* ga = g_abs.data_ptr<scalar_t>();
    const int64_t parts = std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), M / 1024));
    auto sum_part = [&](int64_t pb, int64_t pe) {
      const int64_t g0 = M * pb / parts, g1 = M * pe / parts;
      std::fill(gm + 2 * g0, gm + 2 * g1, scalar_t(0));
      std::fill(gc + 3 * g0, gc + 3 * g1, scalar_t(0));
      std::fill(gcol + 3 * g0, gcol + 3 * g1, scalar_t(0));
      std::fill(go + g0, go + g1, scalar_t(0));
      std::fill(gz + g0, gz + g1, scalar_t(0));
      std::fill(ga + 2 * g0, ga + 2 * g1, scalar_t(0));
      for (int64_t t = 0; t < tiles; ++t) {
        const int64_t end = off[t] + tile_count[t];
        for (int64_t k = off[t]; k < end; ++k) {
          const int64_t g = ids[k];
          if (g < g0 || g >= g1) continue;
          const scalar_t* src = sl + k * kSlots;
          gm[2 * g] += src[0];
          gm[2 * g + 1] += src[1];
          gc[3 * g] += src[2];
          gc[3 * g + 1] += src[3];
          gc[3 * g + 2] += src[4];
          gcol[3 * g] += src[5];
          gcol[3 * g + 1] += src[6];
          gcol[3 * g + 2] += src[7];
          go[g] += src[8];
          gz[g] += src[9];
          ga[2 * g] += src[10];
          ga[2 * g + 1] += src[11];
        }
      }
    };
    if (parts == 1) {
      sum_part(0, 1);
    } else {
      at::parallel_for(0, parts, 1, sum_part);
    }
  });
  return {g_means, g_conics, g_colors, g_opac, g_depths, g_abs};
}

// The clone the float32 tile functions use now ("generic", "avx2" or "avx512").
std::string cpu_isa() { return kIsaNames[static_cast<int>(active_isa())]; }

// The clones this build has and this CPU runs, slowest first.
std::vector<std::string> cpu_isas() {
  std::vector<std::string> out;
  for (Isa isa : {Isa::kGeneric, Isa::kAvx2, Isa::kAvx512}) {
    if (isa_runs(isa)) out.push_back(kIsaNames[static_cast<int>(isa)]);
  }
  return out;
}

// Forces a clone by name ("auto": the best this CPU runs) and returns the one now in use.
// A clone the CPU cannot run is refused: it would die of an illegal instruction.
std::string set_cpu_isa(const std::string& name) {
  Isa want = best_isa();
  if (name != "auto") {
    int found = -1;
    for (int i = 0; i < 3; ++i) {
      if (name == kIsaNames[i]) found = i;
    }
    TORCH_CHECK(found >= 0, "unknown ISA '", name, "'; use auto, generic, avx2 or avx512");
    want = static_cast<Isa>(found);
    TORCH_CHECK(isa_runs(want), "this build or CPU cannot run the ", name, " clone");
  }
  g_isa.store(static_cast<int>(want), std::memory_order_relaxed);
  return cpu_isa();
}

}  // namespace

// The clone in use, for the other kernels of this library (project.cpp): 0 generic, 1 AVX2, 2 AVX-512.
int active_isa_index() { return static_cast<int>(active_isa()); }

}  // namespace nimbus_composite

TORCH_LIBRARY(nimbus_composite, m) {
  m.def("composite_forward", &nimbus_composite::composite_forward);
  m.def("composite_backward", &nimbus_composite::composite_backward);
  m.def("cpu_isa", &nimbus_composite::cpu_isa);
  m.def("cpu_isas", &nimbus_composite::cpu_isas);
  m.def("set_cpu_isa", &nimbus_composite::set_cpu_isa);
}
