// CPU view-consistency excess of NimbusGS's particulate layer (nimbus/methods/nimbusgs/particulate.py).
//
// For each pixel i of a view with a rendered surface (depth d_i along its camera-frame ray r_i):
//
//   world  = R^T (r_i d_i - t)                        the surface point, world frame
//   p_k    = R_k world + t_k                          in neighbour k's camera frame
//   (u, v) = (fx_k p_x / z + cx_k, fy_k p_y / z + cy_k),  z = max(p_z, 1e-9)
//   ok_k   = valid_i, p_z > 1e-6, (u, v) inside the neighbour's image, the neighbour's own surface there
//            (nearest pixel) valid and not in front of the point by more than OCCLUSION_TOLERANCE
//   s_k    = the neighbour's maximum-filtered intensity at (u, v), bilinear, where ok_k (else NaN)
//   out_i  = lum_i - nanmedian_k(s_k)                  (NaN when no neighbour counts)
//
// torch computes the same with some thirty passes over [K, H W] tensors (three grid_samples per
// neighbour, a nanmedian over the stacked samples); here each pixel goes through every neighbour
// at once.  The result is the same bit for bit: every float32 operation is the one torch performs
// on that element, in its order, grid_sample's included (grid_sample.h: its border-padded bilinear
// arithmetic, with the fused multiply-adds of torch's vectorised kernel; nearest: round half to even), and
// the median is a selection (the lower middle of the counted samples, as torch.nanmedian).  So this kernel
// gives the same bits on every CPU, and equals torch's where torch runs its AVX2 or
// AVX-512 kernels.  Pixels are independent: the same bits for any thread count.
//
// Registered as torch.ops.nimbus_consistency.excess; built into NimbusGS's extension with
// march.cpp by nimbus/kernels/march.py.

#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <c10/util/Exception.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include "common.h"
#include "grid_sample.h"

namespace nimbus_consistency {
namespace {

using nimbus_grid_sample::bilinear;
#ifdef NIMBUS_HAS_AVX2_CLONE
using nimbus_grid_sample::cpu_has_avx2_fma;
#endif
using nimbus_grid_sample::location;

// Pixels per parallel chunk: a few microseconds of work each.
constexpr int64_t kGrain = 2048;
// Most neighbours the median's stack buffer holds (consistency_neighbours is small; more are refused).
constexpr int64_t kMaxNeighbours = 64;

struct Neighbour {
  float R[9];  // row-major R_k
  float t[3];
  float fx, fy, cx, cy;
  int64_t cam_w, cam_h;  // the camera's size (bounds of u, v)
  int64_t W, H;          // its maps' size (grid_sample's normalisation)
  const float* depth;    // [H, W]
  const float* valid;    // [H, W], > 0 where its surface is valid
  const float* bright;   // [H, W]
};

NIMBUS_INLINE float excess_pixel(float lum, const float* ray, float depth, bool valid, const float* R, const float* t,
                   const std::vector<Neighbour>& nbs) {
  const float nan = std::numeric_limits<float>::quiet_NaN();
  float samples[kMaxNeighbours];
  int64_t count = 0;
  if (valid) {
    // p_cam - t, then R^T as _rotate's three broadcast products summed left to right.
    const float q0 = ray[0] * depth - t[0];
    const float q1 = ray[1] * depth - t[1];
    const float q2 = ray[2] * depth - t[2];
    float world[3];
    for (int j = 0; j < 3; ++j) world[j] = q0 * R[0 * 3 + j] + q1 * R[1 * 3 + j] + q2 * R[2 * 3 + j];
    for (const Neighbour& nb : nbs) {
      float p[3];
      for (int j = 0; j < 3; ++j) {
        p[j] = world[0] * nb.R[j * 3 + 0] + world[1] * nb.R[j * 3 + 1] + world[2] * nb.R[j * 3 + 2];
        p[j] = p[j] + nb.t[j];
      }
      const float z = p[2];
      const float zs = std::max(z, 1e-9f);
      const float u = nb.fx * p[0] / zs + nb.cx;
      const float v = nb.fy * p[1] / zs + nb.cy;
      if (!(z > 1e-6f && u >= 0.0f && u < static_cast<float>(nb.cam_w) && v >= 0.0f &&
            v < static_cast<float>(nb.cam_h)))
        continue;
      const float x = location(u, nb.W);
      const float y = location(v, nb.H);
      // Nearest: the neighbour's surface and whether it is valid there.
      const int64_t xi = static_cast<int64_t>(std::nearbyint(x));
      const int64_t yi = static_cast<int64_t>(std::nearbyint(y));
      const int64_t at = yi * nb.W + xi;
      if (!(nb.valid[at] > 0.0f) || !(z <= nb.depth[at] * 1.05f)) continue;
      const float value = bilinear(nb.bright, nb.W, nb.H, x, y);  // as grid_sample's bilinear forward
      if (std::isnan(value)) continue;  // nanmedian skips it
      samples[count++] = value;
    }
  }
  if (count == 0) return lum - nan;
  const int64_t mid = (count - 1) / 2;
  std::nth_element(samples, samples + mid, samples + count);
  return lum - samples[mid];
}

void pixels(const float* L, const float* ry, const float* d, const float* vd, const float* pose,
            const std::vector<Neighbour>& nbs, int64_t b, int64_t e, float* o) {
  for (int64_t i = b; i < e; ++i) o[i] = excess_pixel(L[i], ry + 3 * i, d[i], vd[i] > 0.0f, pose, pose + 9, nbs);
}

#ifdef NIMBUS_HAS_AVX2_CLONE
// The same operations where the CPU has AVX2 and FMA: floor, nearbyint and fma become single
// instructions instead of libm calls (each is exactly rounded either way, so the bits do not change).
__attribute__((target("avx2,fma"))) void pixels_avx2(const float* L, const float* ry, const float* d,
                                                     const float* vd, const float* pose,
                                                     const std::vector<Neighbour>& nbs, int64_t b, int64_t e,
                                                     float* o) {
  for (int64_t i = b; i < e; ++i) o[i] = excess_pixel(L[i], ry + 3 * i, d[i], vd[i] > 0.0f, pose, pose + 9, nbs);
}
#endif

void check_map(const at::Tensor& t, const char* what) {
  TORCH_CHECK(t.device().is_cpu() && t.scalar_type() == at::kFloat && t.is_contiguous() && t.dim() == 2,
              "consistency excess: ", what, " must be contiguous CPU float32 [H, W]");
}

}  // namespace

// lum [P], rays [P, 3], depth [P], valid [P] (float, > 0 where valid), pose [12] (R row-major, t), and per
// neighbour k: poses [K, 12], intrinsics [K, 4] (fx, fy, cx, cy), sizes [K, 2] (the camera's width, height,
// int64), and its depth / valid / bright maps [H_k, W_k].  Returns the excess [P].
at::Tensor excess(const at::Tensor& lum, const at::Tensor& rays, const at::Tensor& depth, const at::Tensor& valid,
                  const at::Tensor& pose, const at::Tensor& poses, const at::Tensor& intrinsics,
                  const at::Tensor& sizes, at::TensorList depths, at::TensorList valids, at::TensorList brights) {
  const int64_t P = lum.numel();
  const int64_t K = poses.size(0);
  for (const at::Tensor* t : {&lum, &rays, &depth, &valid, &pose, &poses, &intrinsics})
    TORCH_CHECK(t->device().is_cpu() && t->scalar_type() == at::kFloat && t->is_contiguous(),
                "consistency excess: every input must be a contiguous CPU float32 tensor");
  TORCH_CHECK(rays.numel() == 3 * P && depth.numel() == P && valid.numel() == P && pose.numel() == 12,
              "consistency excess: lum, rays, depth, valid and pose do not match");
  TORCH_CHECK(K <= kMaxNeighbours, "consistency excess: at most ", kMaxNeighbours, " neighbours");
  TORCH_CHECK(poses.numel() == 12 * K && intrinsics.numel() == 4 * K && sizes.numel() == 2 * K &&
                  sizes.scalar_type() == at::kLong && sizes.is_contiguous() &&
                  static_cast<int64_t>(depths.size()) == K && static_cast<int64_t>(valids.size()) == K &&
                  static_cast<int64_t>(brights.size()) == K,
              "consistency excess: the neighbours' inputs do not match");
  std::vector<Neighbour> nbs(K);
  const float* pp = poses.data_ptr<float>();
  const float* kp = intrinsics.data_ptr<float>();
  const int64_t* sp = sizes.data_ptr<int64_t>();
  for (int64_t k = 0; k < K; ++k) {
    Neighbour& nb = nbs[k];
    std::copy(pp + 12 * k, pp + 12 * k + 9, nb.R);
    std::copy(pp + 12 * k + 9, pp + 12 * k + 12, nb.t);
    nb.fx = kp[4 * k];
    nb.fy = kp[4 * k + 1];
    nb.cx = kp[4 * k + 2];
    nb.cy = kp[4 * k + 3];
    nb.cam_w = sp[2 * k];
    nb.cam_h = sp[2 * k + 1];
    check_map(depths[k], "a neighbour's depth");
    check_map(valids[k], "a neighbour's valid map");
    check_map(brights[k], "a neighbour's intensity");
    nb.H = depths[k].size(0);
    nb.W = depths[k].size(1);
    TORCH_CHECK(valids[k].sizes() == depths[k].sizes() && brights[k].sizes() == depths[k].sizes(),
                "consistency excess: a neighbour's maps differ in size");
    TORCH_CHECK(nb.H > 0 && nb.W > 0, "consistency excess: a neighbour's maps are empty");
    nb.depth = depths[k].data_ptr<float>();
    nb.valid = valids[k].data_ptr<float>();
    nb.bright = brights[k].data_ptr<float>();
  }
  at::Tensor out = at::empty({P}, lum.options());
  const float* L = lum.data_ptr<float>();
  const float* ry = rays.data_ptr<float>();
  const float* d = depth.data_ptr<float>();
  const float* vd = valid.data_ptr<float>();
  const float* pz = pose.data_ptr<float>();
  float* o = out.data_ptr<float>();
  at::parallel_for(0, P, kGrain, [&](int64_t b, int64_t e) {
#ifdef NIMBUS_HAS_AVX2_CLONE
    if (cpu_has_avx2_fma()) return pixels_avx2(L, ry, d, vd, pz, nbs, b, e, o);
#endif
    pixels(L, ry, d, vd, pz, nbs, b, e, o);
  });
  return out;
}

}  // namespace nimbus_consistency

TORCH_LIBRARY(nimbus_consistency, m) {
  m.def("excess", &nimbus_consistency::excess);
}
