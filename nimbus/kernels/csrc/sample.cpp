// CPU bilinear sampling of a one-channel map at pixel positions, as torch's grid_sample with
// align_corners=False and border padding (grid_sample.h), for GGS's per-Gaussian error
// (nimbus/methods/nimbusgs/ggs.py: sample_error).
//
// torch needs the visible Gaussians' centres gathered (index_select), normalised into a grid and
// sampled (grid_sample), three passes with their allocations; here each index is taken through all
// of it at once.  Same bits as that path where torch runs its vectorised (AVX2 / AVX-512) grid_sample,
// and the same bits on every CPU (grid_sample.h); points are independent, so any thread count too.
//
// Registered as torch.ops.nimbus_sample.bilinear_border; built into NimbusGS's extension with
// march.cpp by nimbus/kernels/march.py.

#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <c10/util/Exception.h>
#include <torch/library.h>

#include <cstdint>

#include "common.h"
#include "grid_sample.h"

namespace nimbus_sample {
namespace {

// Points per parallel chunk: a few microseconds of work each.
constexpr int64_t kGrain = 8192;

NIMBUS_INLINE void points(const float* map, int64_t W, int64_t H, const float* xy, const int64_t* index, int64_t b,
                          int64_t e, float* out) {
  for (int64_t j = b; j < e; ++j) {
    const float* p = xy + 2 * index[j];
    const float x = nimbus_grid_sample::location(p[0], W), y = nimbus_grid_sample::location(p[1], H);
    out[j] = nimbus_grid_sample::bilinear(map, W, H, x, y);
  }
}

#ifdef NIMBUS_HAS_AVX2_CLONE
// floor and fma as single instructions where the CPU has them (each exactly rounded either way: same bits).
__attribute__((target("avx2,fma"))) void points_avx2(const float* map, int64_t W, int64_t H, const float* xy,
                                                     const int64_t* index, int64_t b, int64_t e, float* out) {
  points(map, W, H, xy, index, b, e, out);
}
#endif

}  // namespace

// map [H, W] float32, xy [N, 2] float32 pixel positions (x, y), index [V] int64 rows of xy.  Returns [V].
at::Tensor bilinear_border(const at::Tensor& map, const at::Tensor& xy, const at::Tensor& index) {
  TORCH_CHECK(map.device().is_cpu() && map.scalar_type() == at::kFloat && map.is_contiguous() && map.dim() == 2 &&
                  map.size(0) > 0 && map.size(1) > 0,
              "bilinear_border: map must be a non-empty contiguous CPU float32 [H, W]");
  TORCH_CHECK(xy.device().is_cpu() && xy.scalar_type() == at::kFloat && xy.is_contiguous() && xy.dim() == 2 &&
                  xy.size(1) == 2,
              "bilinear_border: xy must be a contiguous CPU float32 [N, 2]");
  TORCH_CHECK(index.device().is_cpu() && index.scalar_type() == at::kLong && index.is_contiguous() &&
                  index.dim() == 1,
              "bilinear_border: index must be a contiguous CPU int64 [V]");
  const int64_t H = map.size(0), W = map.size(1), N = xy.size(0), V = index.size(0);
  const int64_t* idx = index.data_ptr<int64_t>();
  for (int64_t j = 0; j < V; ++j) TORCH_CHECK(idx[j] >= 0 && idx[j] < N, "bilinear_border: index out of range");
  at::Tensor out = at::empty({V}, map.options());
  const float* m = map.data_ptr<float>();
  const float* p = xy.data_ptr<float>();
  float* o = out.data_ptr<float>();
  at::parallel_for(0, V, kGrain, [&](int64_t b, int64_t e) {
#ifdef NIMBUS_HAS_AVX2_CLONE
    if (nimbus_grid_sample::cpu_has_avx2_fma()) return points_avx2(m, W, H, p, idx, b, e, o);
#endif
    points(m, W, H, p, idx, b, e, o);
  });
  return out;
}

}  // namespace nimbus_sample

TORCH_LIBRARY(nimbus_sample, m) {
  m.def("bilinear_border", &nimbus_sample::bilinear_border);
}
